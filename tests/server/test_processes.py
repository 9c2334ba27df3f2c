"""`jitdyn serve --processes 2`: several processes on one port share the registry, the index and
the data folder; a killed serving process loses its sessions' leases, and its parent recovers them
and starts a new process in its place. Also what sharing one index needs: migrations that servers
starting together do not race, and models that open on a server whose data folder lacks them."""

from __future__ import annotations

import contextlib
import os
import re
import secrets
import signal
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import _serve
import numpy as np
import pytest

from jitdyn.client import Client, FrameData, SessionOptions, TickResult
from jitdyn.storage.db import open_index
from jitdyn.v1 import session_pb2

INLINE = """<mujoco model="slider"><worldbody><body><joint name="s" type="slide" axis="1 0 0"/>
<geom type="box" size="0.1 0.1 0.1" mass="2"/></body></worldbody></mujoco>"""


class Serve(_serve.Serve):
    """`jitdyn serve --processes N` as a user runs it."""

    def __init__(self, data: Path, *, processes: int, extra: tuple[str, ...] = ()) -> None:
        super().__init__(data, "--processes", str(processes), *extra)
        match = re.search(r"listening on \S+ \(plaintext(?:, (\d+) processes)?\)", "".join(self.lines))
        assert match is not None and int(match.group(1) or 1) == processes, "".join(self.lines)

    def children(self) -> list[int]:
        found = []
        for entry in os.listdir("/proc"):
            if entry.isdigit():
                try:
                    stat = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()
                except OSError:
                    continue
                if int(stat[1]) == self.process.pid:
                    found.append(int(entry))
        return found

    def stop(self) -> str:  # type: ignore[override]  # the whole output, for the tests to read
        super().stop()
        return "".join(self.lines)


@pytest.fixture()
def serve(tmp_path: Path) -> Iterator[Serve]:
    server = Serve(tmp_path / "data", processes=2)
    try:
        yield server
    finally:
        if server.process.poll() is None:
            server.stop()


def _serving_children(server: Serve, expected: int) -> list[int]:
    """The serving processes (multiprocessing's spawned children, not its resource tracker)."""
    deadline = time.monotonic() + 60
    serving: list[int] = []
    while time.monotonic() < deadline:
        serving = []
        for pid in server.children():
            try:
                cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
            except OSError:
                continue
            if b"spawn_main" in cmdline and b"resource_tracker" not in cmdline:
                serving.append(pid)
        if len(serving) == expected:
            return serving
        time.sleep(0.2)
    raise AssertionError(f"expected {expected} serving processes, found {serving}")


def test_a_second_server_on_a_served_port_refuses_to_start(serve: Serve, tmp_path: Path) -> None:
    """SO_REUSEPORT is shared by a server's own processes only: a second `jitdyn serve` on the
    address says so in one line, exits 1 and creates nothing, whatever its process count."""
    for processes in ("2", "1"):
        data = tmp_path / f"second-{processes}"
        second = subprocess.run(
            [
                sys.executable,
                "-m",
                "jitdyn.cli",
                "serve",
                "--address",
                serve.address,
                "--data",
                str(data),
                "--processes",
                processes,
            ],
            check=False,  # the refusal's exit status is asserted below
            capture_output=True,
            text=True,
            timeout=60,
            env=dict(os.environ, JITDYN_SECRET=secrets.token_hex(32)),
        )
        assert second.returncode == 1, second.stdout + second.stderr
        lines = second.stderr.strip().splitlines()
        assert len(lines) == 1 and f"cannot listen on {serve.address}: the address is in use" in lines[0], (
            lines
        )
        assert not data.exists(), f"a refused server created {data}"


def test_a_model_registered_through_one_process_opens_through_all(serve: Serve) -> None:
    assert len(_serving_children(serve, 2)) == 2
    with Client(serve.address) as client:
        model, created = client.register_model(name="slider", mjcf=INLINE)
        assert created

    def open_and_step(i: int) -> float:
        # A new connection each: the kernel spreads connections over the processes.
        with (
            Client(serve.address) as client,
            client.open_session(
                SessionOptions(model_id=model.id, dt=0.01, measured=("qpos", "qvel", "qacc"))
            ) as session,
        ):
            answer = session.send_frame(FrameData(seq=0, t=0.0, qpos=[0.1 * i], qvel=[0.0], qacc=[3.0]))
            assert isinstance(answer, TickResult)
            return float(answer.qfrc_inverse[0])

    with ThreadPoolExecutor(8) as pool:
        forces = list(pool.map(open_and_step, range(16)))
    np.testing.assert_allclose(forces, 6.0)  # 2 kg at 3 m/s^2, whichever process answered


def test_a_killed_process_is_recovered_and_replaced(serve: Serve) -> None:
    children = _serving_children(serve, 2)
    client = Client(serve.address, timeout=30)
    sessions = []
    for _ in range(4):
        session = Client(serve.address, timeout=30).open_session(
            SessionOptions(model_name="pendulum_1", dt=0.05)
        )
        for k in range(20):
            assert isinstance(
                session.send_frame(FrameData(seq=k, t=k * 0.05, qpos=[0.2], qvel=[0.0])), TickResult
            )
        sessions.append(session)
    time.sleep(0.1)  # a group commit after the last frame
    ids = [s.opened.session_id for s in sessions]
    for pid in children:
        os.kill(pid, signal.SIGKILL)
    for s in sessions:
        s.cancel()
    # The parent recovers every session the dead processes held and starts new ones.
    deadline = time.monotonic() + 60
    statuses: list[str] = []
    while time.monotonic() < deadline:
        try:
            statuses = [session_pb2.SessionStatus.Name(client.get_session(i).status) for i in ids]
        except Exception:  # noqa: BLE001 - the new processes are starting
            time.sleep(0.3)
            continue
        if all(status == "SESSION_STATUS_RECOVERED" for status in statuses):
            break
        time.sleep(0.3)
    assert statuses == ["SESSION_STATUS_RECOVERED"] * 4
    replaced = _serving_children(serve, 2)
    assert not set(replaced) & set(children)
    with client.open_session(SessionOptions(model_name="pendulum_1", dt=0.05)) as session:
        assert isinstance(session.send_frame(FrameData(seq=0, t=0.0, qpos=[0.2], qvel=[0.0])), TickResult)
    client.close()
    log = serve.stop()
    assert "exited (code -9); recovering its sessions and restarting it" in log, log


@pytest.mark.postgres
def test_servers_starting_together_on_one_postgresql_index_do_not_race(tmp_path: Path) -> None:
    import sqlalchemy as sa

    schema = f"race_{secrets.token_hex(4)}"
    url = "postgresql+psycopg://postgres@127.0.0.1:5432/test"
    try:
        with ThreadPoolExecutor(4) as pool:
            engines = list(pool.map(lambda _: open_index(url, schema=schema), range(4)))
        with engines[0].connect() as conn:
            versions = conn.execute(sa.text(f'SELECT count(*) FROM "{schema}".alembic_version')).scalar()
        assert versions == 1
    finally:
        engine = sa.create_engine(url)
        with engine.begin() as conn:
            conn.execute(sa.text(f'DROP SCHEMA IF EXISTS "{schema}" CASCADE'))
        engine.dispose()
        for e in locals().get("engines", []):
            e.dispose()


def test_sqlite_migrations_of_processes_starting_together_do_not_race(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'index.sqlite'}"
    code = f"from jitdyn.storage.db import open_index; open_index({url!r}).dispose(); print('ok')"
    runs = [
        subprocess.Popen(
            [sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        for _ in range(4)
    ]
    outputs = [r.communicate(timeout=120) for r in runs]
    assert [r.returncode for r in runs] == [0] * 4, outputs


def test_a_model_missing_from_the_data_folder_comes_from_the_index(tmp_path: Path) -> None:
    """Two servers sharing an index, each with its own data folder (two hosts, in effect): a model
    registered through the first opens on the second, its content fetched from the index into the
    second's folder."""
    index = ("--index", f"sqlite:///{tmp_path / 'shared-index.sqlite'}")
    first, second = tmp_path / "a", tmp_path / "b"
    server = Serve(first, processes=1, extra=index)
    try:
        with Client(server.address) as client:
            model, _ = client.register_model(name="slider", mjcf=INLINE)
    finally:
        server.stop()
    blob = f"models/{model.id.split(':', 1)[1]}.zip"
    assert not (second / blob).exists()
    server = Serve(second, processes=1, extra=index)
    try:
        with Client(server.address) as client:
            session = client.open_session(SessionOptions(model_id=model.id, dt=0.01))
            session.close()
    finally:
        server.stop()
    assert (second / blob).read_bytes() == (first / blob).read_bytes()


def _open_sessions_by_process(metrics_port: int) -> dict[str, float]:
    import urllib.request

    scraped = urllib.request.urlopen(f"http://127.0.0.1:{metrics_port}/metrics", timeout=10).read().decode()
    return {
        process: float(value)
        for process, value in re.findall(
            r'^jitdyn_open_sessions\{process="(\d+)"\} (\S+)$', scraped, re.MULTILINE
        )
    }


@pytest.mark.parametrize("per_session", [True, False])
def test_one_client_s_sessions_spread_over_the_processes(tmp_path: Path, per_session: bool) -> None:
    """The kernel spreads connections, not streams, over the processes: a client's sessions reach
    both only when each has its own connection (the client's default)."""
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        metrics_port = int(sock.getsockname()[1])
    server = Serve(tmp_path / "data", processes=2, extra=("--metrics-address", f"127.0.0.1:{metrics_port}"))
    try:
        with Client(server.address, connection_per_session=per_session) as client:
            sessions = [
                client.open_session(SessionOptions(model_name="pendulum_1", dt=0.05)) for _ in range(12)
            ]
            by_process = _open_sessions_by_process(metrics_port)
            for session in sessions:
                session.close()
        assert sum(by_process.values()) == 12, by_process
        serving = [p for p, n in by_process.items() if n > 0]
        # 12 connections hashed over 2 processes all land on one with probability 2^-11.
        assert len(serving) == (2 if per_session else 1), by_process
    finally:
        server.stop()


@pytest.mark.parametrize("processes", [1, 2])
def test_metrics_on_port_0_announce_the_port_and_show_an_idle_server(tmp_path: Path, processes: int) -> None:
    """`--metrics-address HOST:0` serves on a free port and says which; before any session, the
    open-sessions gauge is there at 0 (a dashboard sees an idle server, not a missing one)."""
    server = Serve(tmp_path / "data", processes=processes, extra=("--metrics-address", "127.0.0.1:0"))
    try:
        deadline = time.monotonic() + 60
        while not any("metrics on" in line for line in server.lines) and time.monotonic() < deadline:
            time.sleep(0.05)
        announced = re.search(r"metrics on http://(127\.0\.0\.1:(\d+))/metrics", "".join(server.lines))
        assert announced and int(announced.group(2)) != 0, server.lines
        scraped = urllib.request.urlopen(f"http://{announced.group(1)}/metrics", timeout=10).read().decode()
        assert re.search(r"^jitdyn_open_sessions\{.*\} 0\.0$", scraped, re.MULTILINE), scraped[:2000]
    finally:
        server.stop()


def _thread_nices(pid: int) -> set[int]:
    """The nice value of every thread of process `pid` (field 19 of /proc/PID/task/TID/stat)."""
    nices = set()
    for tid in os.listdir(f"/proc/{pid}/task"):
        with contextlib.suppress(OSError):
            nices.add(int(Path(f"/proc/{pid}/task/{tid}/stat").read_text().rsplit(")", 1)[1].split()[16]))
    return nices


@pytest.mark.parametrize("processes", [1, 2])
def test_every_thread_of_the_serving_processes_runs_at_the_priority_asked_for(
    tmp_path: Path, processes: int
) -> None:
    """--nice 7 (raising it needs no privilege): every thread of every serving process, those
    started once it serves included."""
    server = Serve(tmp_path / "data", processes=processes, extra=("--nice", "7"))
    try:
        with Client(server.address, timeout=30) as client:  # a session starts the threads of work
            options = SessionOptions(model_name="pendulum_1", dt=0.025, clock="LOCKSTEP", scenario="PASSIVE")
            with client.open_session(options) as session:
                assert isinstance(
                    session.send_frame(FrameData(seq=0, t=0.0, qpos=[0.3], qvel=[0.0])), TickResult
                )
                serving = [server.process.pid] if processes == 1 else _serving_children(server, processes)
                assert [_thread_nices(pid) for pid in serving] == [{7}] * processes
    finally:
        server.stop()


def test_without_the_right_to_lower_its_priority_the_server_says_so_and_serves(tmp_path: Path) -> None:
    """The default --nice -10 needs CAP_SYS_NICE; a server without it (setpriv drops it when the test
    runs as root) warns in one line and serves at the priority it was started with."""
    drop = ("setpriv", "--inh-caps=-sys_nice", "--bounding-set=-sys_nice") if os.geteuid() == 0 else ()
    server = _serve.Serve(tmp_path / "data", "--processes", "1", prefix=drop)
    try:
        assert _thread_nices(server.process.pid) == {os.getpriority(os.PRIO_PROCESS, 0)}, server.lines
    finally:
        server.stop()
    warnings = [line for line in server.lines if "CAP_SYS_NICE" in line]
    assert len(warnings) == 1 and re.search(
        r"the serving processes run at nice -?\d+, not --nice -10: lowering it needs CAP_SYS_NICE",
        warnings[0],
    ), server.lines


def test_verbose_serving_processes_log_every_refused_open(tmp_path: Path) -> None:
    """`jitdyn serve --verbose --processes 2` logs each refused open, as the SDK's message for a
    refusal a balancer hid tells its user to look for: the serving processes used to log at WARNING
    whatever the flag, so nothing was logged (4 opens of a missing model, 0 lines)."""
    from jitdyn.errors import NotFound

    server = Serve(tmp_path / "data", processes=2, extra=("--verbose",))
    try:
        for _ in range(4):  # the kernel spreads connections over both processes
            with Client(server.address, timeout=30) as client, pytest.raises(NotFound):
                client.open_session(SessionOptions(model_name="no_such_model", dt=0.05))
        deadline = time.monotonic() + 5
        while "".join(server.lines).count("an open was refused") < 4 and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        output = server.stop()
    refused = re.findall(
        r"INFO \[process \d\] \S+: an open was refused: NOT_FOUND: no model is named", output
    )
    assert len(refused) == 4, output
    assert "alembic" not in output  # its per-start migration notes stay out of -v
