"""`python -m jitdyn.compliance` against a real `jitdyn serve` with API keys of two tenants, run as
a user runs it (its own process), every case: jitdyn keeps its own contract."""

from __future__ import annotations

import os
import re
import secrets
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from jitdyn.compliance.run import ordered

KEY = "compliance-" + secrets.token_hex(12)
OTHER_KEY = "other-tenant-" + secrets.token_hex(12)
# The REALTIME cases a loaded machine may not admit (RESOURCE_EXHAUSTED, which the contract allows).
REALTIME_CASES = {"late.realtime", "realtime.sequence", "clock.sync"}


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """`jitdyn serve` on a free loopback port with two tenants' API keys; its address."""
    folder = tmp_path_factory.mktemp("serve")
    keys = folder / "api-keys"
    keys.write_text(f"{KEY} lab\n{OTHER_KEY} other\n")
    keys.chmod(0o600)
    env = {k: v for k, v in os.environ.items() if not k.startswith("JITDYN_")}
    env["JITDYN_SECRET"] = secrets.token_hex(32)
    process = subprocess.Popen(
        [sys.executable, "-m", "jitdyn.cli", "serve", "--address", "127.0.0.1:0", "--data", str(folder / "data"),
         "--api-keys", str(keys), "--processes", "1", "--nice", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )  # fmt: skip
    assert process.stdout is not None
    address = None
    for line in process.stdout:
        match = re.search(r"listening on (127\.0\.0\.1:\d+)", line)
        if match:
            address = match.group(1)
            break
    assert address is not None, "jitdyn serve did not say where it listens"
    # Drain what it logs: a full pipe would block its event loop.
    drain = threading.Thread(target=process.stdout.read, daemon=True)
    drain.start()
    try:
        yield address
    finally:
        process.send_signal(signal.SIGTERM)
        process.wait(timeout=60)
        drain.join(timeout=10)
        process.stdout.close()


def suite(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "jitdyn.compliance", *args],
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )


def rows(stdout: str) -> dict[str, tuple[str, str]]:
    """The table's rows: case -> (result, note)."""
    found = {}
    for line in stdout.splitlines():
        parts = line.split(maxsplit=3)
        if len(parts) >= 3 and parts[1] in ("PASS", "FAIL", "SKIP"):
            found[parts[0]] = (parts[1], parts[3] if len(parts) > 3 else "")
    return found


def test_jitdyn_passes_every_case(server: str) -> None:
    result = suite("--server", server, "--api-key", KEY, "--other-api-key", OTHER_KEY, "-q")
    table = rows(result.stdout)
    assert list(table) == [c.name for c in ordered()], result.stdout
    for name, (outcome, note) in table.items():
        if name in REALTIME_CASES and outcome == "SKIP":
            assert note.startswith("not admitted: the server refused a 20 Hz REALTIME session"), note
            continue
        assert outcome == "PASS", f"{name}: {outcome} {note}"
    assert result.returncode == 0, result.stdout + result.stderr
    assert table["late.lockstep"][1] in ("CORRECTED", "TOO_OLD")
    assert re.search(r"^\d+ passed, 0 failed, \d+ skipped$", result.stdout, re.MULTILINE)
    provoked = re.search(r"^statuses provoked: (.*)$", result.stdout, re.MULTILINE)
    assert provoked is not None
    assert {
        "OK",
        "INVALID_ARGUMENT",
        "NOT_FOUND",
        "FAILED_PRECONDITION",
        "RESOURCE_EXHAUSTED",
        "UNAUTHENTICATED",
        "DEADLINE_EXCEEDED",
        "CANCELLED",
    } <= set(provoked.group(1).split(", "))


def test_chosen_cases_run_alone_and_a_failure_exits_1(server: str) -> None:
    chosen = suite("--server", server, "--api-key", KEY, "--case", "frame.", "open.order", "-q")
    assert chosen.returncode == 0, chosen.stdout + chosen.stderr
    assert list(rows(chosen.stdout)) == [
        "open.order",
        "frame.measured",
        "frame.shape",
        "frame.not_finite",
        "frame.checksum",
    ]
    # Without its key every call of the keyed server is refused: the suite says so and exits 1.
    keyless = suite("--server", server, "--case", "models.get")
    assert keyless.returncode == 1
    outcome, note = rows(keyless.stdout)["models.get"]
    assert (outcome, note.split(":")[0]) == ("FAIL", "unexpected UNAUTHENTICATED")
    assert "FAIL models.get" in keyless.stderr  # progress, as each case ends


@pytest.mark.slow  # 11 s of timeouts against an absent server
def test_usage_errors_and_an_absent_server_are_one_line(tmp_path: Path) -> None:
    unknown = suite("--server", "127.0.0.1:1", "--case", "frame.nope")
    assert unknown.returncode == 2
    assert unknown.stderr.splitlines()[-1].startswith(
        "python -m jitdyn.compliance: error: no case named frame.nope; the cases: register.content_id, "
    )
    with socket.socket() as closed:
        closed.bind(("127.0.0.1", 0))
        port = closed.getsockname()[1]
    absent = suite("--server", f"127.0.0.1:{port}")
    assert absent.returncode == 1
    assert (
        absent.stderr.strip() == f"jitdyn.compliance: no gRPC server answers at 127.0.0.1:{port} within 10 s"
    )
    listed = suite("--list")
    assert listed.returncode == 0
    assert [line.split()[0] for line in listed.stdout.splitlines()] == [c.name for c in ordered()]
