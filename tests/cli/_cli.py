"""The command line as a user runs it, for the cli tests: `jitdyn ARGS` in a fresh process."""

from __future__ import annotations

import contextlib
import os
import re
import secrets
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq


def jitdyn(
    *args: str, cwd: Path | None = None, env: dict[str, str] | None = None, preamble: str = ""
) -> subprocess.CompletedProcess[str]:
    """`jitdyn ARGS` in a fresh process, no JITDYN_* setting but a secret and `env`; `preamble`
    runs first (to hide an installed extra, say)."""
    environ = {k: v for k, v in os.environ.items() if not k.startswith("JITDYN_")}
    environ.update(JITDYN_SECRET=secrets.token_hex(32), **(env or {}))
    code = f"import sys\n{preamble}\nfrom jitdyn.cli import main\nsys.exit(main(sys.argv[1:]))"
    return subprocess.run(
        [sys.executable, "-c", code, *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=environ,
        timeout=300,
        check=False,
    )


def listed(table: str) -> list[dict[str, str]]:
    """The rows of `jitdyn sessions list`'s table (a header, a rule, the rows) by column header."""
    lines = table.splitlines()
    spans, start = [], 0
    for dashes in lines[1].split("  "):
        spans.append((start, start + len(dashes)))
        start += len(dashes) + 2
    headers = [lines[0][a:b].strip() for a, b in spans]
    return [{h: line[a:b].strip() for h, (a, b) in zip(headers, spans, strict=True)} for line in lines[2:]]


def one_line_error(result: subprocess.CompletedProcess[str], code: int) -> str:
    """The one `jitdyn ...` line a failed command prints on stderr, with no traceback."""
    assert result.returncode == code, result.stdout + result.stderr
    assert "Traceback" not in result.stderr, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.startswith("jitdyn")]
    assert len(lines) == 1, result.stderr
    return lines[0]


@contextlib.contextmanager
def serving(*args: str, data: Path, env: dict[str, str] | None = None) -> Iterator[str]:
    """`jitdyn serve ARGS` on a free loopback port, one process; yields its address."""
    environ = {k: v for k, v in os.environ.items() if not k.startswith("JITDYN_")}
    environ.update(JITDYN_SECRET=secrets.token_hex(32), **(env or {}))
    command = [sys.executable, "-m", "jitdyn.cli", "serve", "--address", "127.0.0.1:0", "--processes", "1"]
    process = subprocess.Popen(
        [*command, "--workers", "1", "--data", str(data), *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=environ,
    )
    try:
        assert process.stdout is not None
        first = process.stdout.readline()
        listening = re.match(r"jitdyn listening on (\S+) ", first)
        assert listening, first + (process.stderr.read() if process.stderr else "")
        yield listening.group(1)
    finally:
        process.send_signal(signal.SIGINT)
        process.communicate(timeout=30)


def ok(result: subprocess.CompletedProcess[str]) -> str:
    assert result.returncode == 0, result.stdout + result.stderr
    assert "Traceback" not in result.stderr, result.stderr
    return result.stdout


def stored_frames(stdout: str, data: Path) -> tuple[np.ndarray, np.ndarray]:
    """(seqs, frame_qpos) of the frames the server received, from the Parquet the summary names
    in its data folder."""
    path = re.search(r"^stored: (\S+\.parquet) \(in the data folder of the server", stdout, re.MULTILINE)
    assert path, stdout
    table = pq.read_table(data / path.group(1)).to_pydict()
    rows = [
        (seq, qpos)
        for seq, qpos, received in zip(
            table["seq"], table["frame_qpos"], table["frame_received"], strict=True
        )
        if received and qpos
    ]
    seqs = sorted({seq for seq, _ in rows})
    by_seq = dict(rows)
    return np.array(seqs), np.array([by_seq[seq] for seq in seqs])
