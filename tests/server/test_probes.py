"""The kubelet's probes are answered off the event loop (`jitdyn serve --health-address`,
server/transport/probes.py): a real server, `serve()` itself in a process of its own, whose loop is
held for seconds, as a long computation on it would hold it, still answers liveness and readiness
within the probes' timeout, while its sessions' port cannot. Liveness fails only for a loop silent
past the hang limit (shortened here to 1 s), and comes back when the loop does."""

from __future__ import annotations

import os
import re
import secrets
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

SESSION_SERVICE = "jitdyn.v1.DynamicsService"
PROBE_TIMEOUT = 1.0  # s, shorter than any timeoutSeconds of deploy/kubernetes/deployment.yaml
HOLD = 3.0  # s the loop is held

# serve() as `jitdyn serve` runs it, with SIGUSR1 holding its loop for HOLD seconds.
_SERVER = """
import asyncio, signal, sys, time
from pathlib import Path
import jitdyn.server.transport.app as app

data, health_address, hung_after, hold = sys.argv[1], sys.argv[2], float(sys.argv[3]), float(sys.argv[4])
app.LOOP_HUNG_AFTER = hung_after

async def main() -> None:
    asyncio.get_running_loop().add_signal_handler(signal.SIGUSR1, time.sleep, hold)
    config = app.ServerConfig(
        address="127.0.0.1:0", data_root=Path(data), health_address=health_address, workers=1
    )
    await app.serve(config, announce=lambda line: print(line, flush=True))

asyncio.run(main())
"""


@dataclass
class Server:
    process: subprocess.Popen[str]
    address: str
    probes: str
    lines: list[str]


@contextmanager
def _server(tmp_path: Path, *, hung_after: float) -> Iterator[Server]:
    env = dict(os.environ, JITDYN_SECRET=secrets.token_hex(32), PYTHONUNBUFFERED="1")
    process = subprocess.Popen(
        [sys.executable, "-c", _SERVER, str(tmp_path / "data"), "127.0.0.1:0", str(hung_after), str(HOLD)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )
    assert process.stdout is not None
    lines: list[str] = []
    found: dict[str, str] = {}
    reader: threading.Thread | None = None
    try:
        for line in process.stdout:
            lines.append(line)
            if match := re.search(r"listening on (127\.0\.0\.1:\d+)", line):
                found["address"] = match.group(1)
            if match := re.search(r"health probes on (127\.0\.0\.1:\d+)", line):
                found["probes"] = match.group(1)
                break
        else:
            raise RuntimeError("the server did not start:\n" + "".join(lines))
        # Read on as it comes: a full pipe would block the server's next line, and its loop.
        reader = threading.Thread(target=lambda: lines.extend(process.stdout or ()), daemon=True)
        reader.start()
        yield Server(process, found["address"], found["probes"], lines)
    finally:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=60)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=10)
        if reader is not None:
            reader.join(timeout=10)
        process.stdout.close()


def _check(address: str, service: str) -> tuple[str, float]:
    """A probe as the kubelet's `grpc:` probe asks it: the status's name (or the RPC's failure),
    and how long the answer took."""
    started = time.monotonic()
    with grpc.insecure_channel(address) as channel:
        try:
            answer = health_pb2_grpc.HealthStub(channel).Check(
                health_pb2.HealthCheckRequest(service=service), timeout=PROBE_TIMEOUT
            )
        except grpc.RpcError as error:
            return error.code().name, time.monotonic() - started
    return health_pb2.HealthCheckResponse.ServingStatus.Name(answer.status), time.monotonic() - started


def _while_held(server: Server) -> tuple[list[tuple[str, float]], list[tuple[str, float]], str]:
    """The loop held: liveness and readiness asked every 0.1 s for HOLD - 0.5 s, and the sessions'
    port's own health once."""
    server.process.send_signal(signal.SIGUSR1)
    time.sleep(0.2)
    main_port = _check(server.address, SESSION_SERVICE)[0]
    liveness, readiness = [], []
    end = time.monotonic() + HOLD - 0.5 - PROBE_TIMEOUT
    while time.monotonic() < end:
        liveness.append(_check(server.probes, ""))
        readiness.append(_check(server.probes, SESSION_SERVICE))
        time.sleep(0.1)
    return liveness, readiness, main_port


def test_a_server_whose_loop_is_held_answers_its_probes_on_time(tmp_path: Path) -> None:
    with _server(tmp_path, hung_after=30.0) as server:
        assert _check(server.probes, "")[0] == "SERVING"
        assert _check(server.probes, SESSION_SERVICE)[0] == "SERVING"
        liveness, readiness, main_port = _while_held(server)
    slowest = max(seconds for _, seconds in liveness + readiness)
    print(
        f"loop held {HOLD} s: {len(liveness)} liveness and readiness checks, slowest {1e3 * slowest:.1f} ms"
    )
    # The loop really was held: its own port's health did not answer within the probe's timeout.
    assert main_port == "DEADLINE_EXCEEDED", main_port
    assert {status for status, _ in liveness} == {"SERVING"}, liveness
    assert {status for status, _ in readiness} == {"SERVING"}, readiness
    assert len(liveness) >= 5 and slowest < 0.5 * PROBE_TIMEOUT


# 9 s: runs with the slow tests (pytest -m slow), to keep CI under 20 minutes.
@pytest.mark.slow
def test_liveness_fails_for_a_loop_silent_past_the_hang_limit_and_recovers(tmp_path: Path) -> None:
    hung_after = 1.0
    with _server(tmp_path, hung_after=hung_after) as server:
        liveness, _, _ = _while_held(server)
        time.sleep(HOLD)  # the loop runs again
        after = _check(server.probes, "")[0]
    statuses = [status for status, _ in liveness]
    print(f"loop held {HOLD} s, hang limit {hung_after} s: liveness {statuses}")
    assert "NOT_SERVING" in statuses, statuses
    assert all(seconds < PROBE_TIMEOUT for _, seconds in liveness)
    assert after == "SERVING"


def test_with_several_processes_the_supervising_one_answers_the_probes(tmp_path: Path) -> None:
    from .test_processes import Serve

    server = Serve(tmp_path / "data", processes=2, extra=("--health-address", "127.0.0.1:0"))
    try:
        deadline = time.monotonic() + 30
        while not (match := re.search(r"health probes on (127\.0\.0\.1:\d+)", "".join(server.lines))):
            assert time.monotonic() < deadline, server.lines
            time.sleep(0.05)
        probes = match.group(1)
        assert _check(probes, "")[0] == "SERVING"
        assert _check(probes, SESSION_SERVICE)[0] == "SERVING"
    finally:
        server.stop()


def test_a_busy_health_port_stops_the_start_in_one_line_before_anything_is_made(tmp_path: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        busy = f"127.0.0.1:{taken.getsockname()[1]}"
        env = dict(os.environ, JITDYN_SECRET=secrets.token_hex(32))
        for processes in ("1", "2"):
            done = subprocess.run(
                [
                    *(sys.executable, "-m", "jitdyn.cli", "serve", "--address=127.0.0.1:0"),
                    f"--data={tmp_path / 'data'}",
                    f"--processes={processes}",
                    f"--health-address={busy}",
                ],
                env=env,
                capture_output=True,
                text=True,
                timeout=120,
                check=False,
            )
            assert done.returncode == 1, done.stdout + done.stderr
            assert (done.stdout + done.stderr).splitlines() == [
                (
                    f"jitdyn serve: FailedPrecondition: cannot serve health probes on {busy}: the address "
                    "is in use or not an address of this machine; choose another with --health-address "
                    "HOST:PORT"
                )
            ]
            assert not (tmp_path / "data").exists()
