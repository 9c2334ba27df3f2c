"""kill -9 of a real server process mid-session loses no frame the client saw as durable; the next
start recovers the session to Parquet and marks it RECOVERED. Then the `jitdyn sessions` commands
read what was recovered."""

from __future__ import annotations

import os
import re
import secrets
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from jitdyn.client import Client, FrameData, SessionOptions, TickResult


class ServerProcess:
    """`jitdyn serve` in a child process on a loopback port 0."""

    def __init__(self, data: Path, env: dict[str, str], *, processes: int = 1) -> None:
        self.process = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "jitdyn.cli",
                "serve",
                "--address",
                "127.0.0.1:0",
                "--data",
                str(data),
                "--workers",
                "1",
                "--processes",
                str(processes),
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env=env,
        )
        self.lines: list[str] = []
        deadline = time.monotonic() + 120
        assert self.process.stdout is not None
        while time.monotonic() < deadline:
            line = self.process.stdout.readline()
            if not line:
                raise RuntimeError("the server exited early:\n" + "".join(self.lines))
            self.lines.append(line)
            match = re.search(r"listening on (127\.0\.0\.1:\d+)", line)
            if match:
                self.address = match.group(1)
                return
        raise RuntimeError("the server did not say where it listens:\n" + "".join(self.lines))

    def kill(self) -> None:
        """SIGKILL: no shutdown, no flush, no Parquet footer."""
        self.process.kill()
        self.process.wait(timeout=30)
        assert self.process.stdout is not None
        self.process.stdout.close()

    def stop(self) -> str:
        self.process.send_signal(signal.SIGTERM)
        out, _ = self.process.communicate(timeout=60)
        return "".join(self.lines) + out


@pytest.fixture()
def env(tmp_path: Path) -> Iterator[dict[str, str]]:
    environ = dict(os.environ)
    environ["JITDYN_SECRET"] = secrets.token_hex(32)
    environ.pop("JITDYN_INDEX_URL", None)
    yield environ


def _truth(ticks: int) -> list[tuple[np.ndarray, np.ndarray]]:
    t = np.arange(ticks) * 0.05
    return [
        (
            np.array([0.3 * np.cos(x), 0.1 * np.sin(x), 0.0]),
            np.array([-0.3 * np.sin(x), 0.1 * np.cos(x), 0.0]),
        )
        for x in t
    ]


# Two processes (13 s) run with the slow tests (pytest -m slow), to keep CI under 20 minutes.
@pytest.mark.parametrize("processes", [1, pytest.param(2, marks=pytest.mark.slow)])
def test_kill_9_loses_no_durable_frame(tmp_path: Path, env: dict[str, str], processes: int) -> None:
    # With several processes, kill -9 of `jitdyn serve` takes its serving processes with it.
    data = tmp_path / "data"
    server = ServerProcess(data, env, processes=processes)
    durable = -1
    truth = _truth(400)
    try:
        client = Client(server.address, timeout=30)
        session = client.open_session(
            SessionOptions(model_name="pendulum_3", dt=0.05, subject_id="patient-4711")
        )
        session_id = session.opened.session_id
        for k, (q, v) in enumerate(truth):
            answer = (
                session.skip(k)
                if k % 7 == 3
                else session.send_frame(FrameData(seq=k, t=k * 0.05, qpos=q, qvel=v))
            )
            assert isinstance(answer, TickResult)
            if answer.durable_seq is not None:
                durable = max(durable, answer.durable_seq)
        time.sleep(0.05)  # a group commit or two after the last frame
        answer = session.send_frame(FrameData(seq=400, t=20.0, qpos=truth[0][0], qvel=truth[0][1]))
        assert isinstance(answer, TickResult) and answer.durable_seq is not None
        durable = max(durable, answer.durable_seq)
    finally:
        server.kill()
    session.cancel()
    client.close()
    assert durable >= 300, f"durable_seq lagged far behind: {durable}"

    restarted = ServerProcess(data, env, processes=processes)
    log = restarted.stop()
    assert "recovered 1 unfinished session" in log, log
    files = list((data / "frames").rglob(f"{session_id}.parquet"))
    assert len(files) == 1
    rows = pq.read_table(files[0]).to_pylist()
    stored = {r["seq"]: r for r in rows if r["kind"] == "result"}
    assert set(range(durable + 1)) <= set(stored), sorted(set(range(durable + 1)) - set(stored))[:10]
    for k in range(durable + 1):
        assert stored[k]["source"] == ("PREDICTED" if k % 7 == 3 else "MEASURED")
        if k % 7 != 3:
            np.testing.assert_array_equal(stored[k]["frame_qpos"], truth[k][0])

    # The recovered session, through the command line.
    cli = [sys.executable, "-m", "jitdyn.cli", "sessions", "--data", str(data)]
    listing = subprocess.run([*cli, "list"], capture_output=True, text=True, env=env, check=True).stdout
    assert session_id in listing and "RECOVERED" in listing
    count = subprocess.run(
        [
            *cli,
            "query",
            f"SELECT count(*) AS n FROM frames WHERE session_id = '{session_id}' AND kind = 'result'",
        ],
        capture_output=True,
        text=True,
        env=env,
        check=True,
    ).stdout
    assert str(len(stored)) in count
    sto = tmp_path / "session.sto"
    subprocess.run(
        [*cli, "export", session_id, "--format", "sto", "--out", str(sto)],
        capture_output=True,
        text=True,
        env=env,
        check=True,
    )
    header = sto.read_text().splitlines()
    assert "inDegrees=no" in header and "endheader" in header
    # Nothing identifies the subject anywhere under the data folder.
    for path in data.rglob("*"):
        if path.is_file():
            assert b"patient-4711" not in path.read_bytes(), path
