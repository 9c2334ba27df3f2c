"""A client's own start-up is not load (server/runtime/clients.py): the process at the other end of
a loopback connection is found with its start and CPU, and a real `jitdyn serve` admits clients
that spent every core of the machine starting up just before they opened."""

from __future__ import annotations

import asyncio
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from _serve import Serve

from jitdyn.server.runtime.clients import ClientStart, LocalClients, client_start

# Burns `BURN` s of its own CPU, connects to the port it is given, says so, and waits to be told.
_CONNECTOR = textwrap.dedent(
    """
    import socket, sys, time
    until = time.process_time() + float(sys.argv[3])
    while time.process_time() < until:
        pass
    sockets = [socket.create_connection((sys.argv[1], int(sys.argv[2]))) for _ in range(int(sys.argv[4]))]
    print("connected", flush=True)
    sys.stdin.readline()
    """
)


@pytest.mark.parametrize("host", ["127.0.0.1", "::1"])
def test_the_process_at_the_other_end_of_a_loopback_connection_is_found(host: str) -> None:
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    try:
        listener = socket.socket(family, socket.SOCK_STREAM)
        listener.bind((host, 0))
    except OSError:
        pytest.skip(f"no {host} on this machine")
    listener.listen()
    port = listener.getsockname()[1]
    before = time.monotonic()
    with subprocess.Popen(
        [sys.executable, "-c", _CONNECTOR, host, str(port), "0.3", "1"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    ) as child:
        _check_found(child, listener, host, before)


def _check_found(child: subprocess.Popen[str], listener: socket.socket, host: str, before: float) -> None:
    try:
        connection, address = listener.accept()
        assert child.stdout is not None and child.stdout.readline() == "connected\n"
        peer = f"ipv6:[{address[0]}]:{address[1]}" if ":" in host else f"ipv4:{host}:{address[1]}"
        found = client_start(peer)
        assert found is not None, peer
        assert found.pid == child.pid
        assert found.cpu >= 0.3  # its start-up: the burn, the interpreter's own start
        # Its start is read from /proc to a clock tick (10 ms), on the monotonic clock.
        assert before - 0.05 <= found.started <= found.opened <= time.monotonic()
        connection.close()
    finally:
        child.kill()
        listener.close()


def test_a_process_is_told_once_whatever_its_connections() -> None:
    """A client's second connection comes after its start-up: what it spent since is load."""
    listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    port = listener.getsockname()[1]
    told: list[ClientStart] = []
    clients = LocalClients(told.append, needed=lambda: True)
    with subprocess.Popen(
        [sys.executable, "-c", _CONNECTOR, "127.0.0.1", str(port), "0.1", "2"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    ) as child:
        try:
            accepted = [listener.accept() for _ in range(2)]
            assert child.stdout is not None and child.stdout.readline() == "connected\n"
            peers = [f"ipv4:127.0.0.1:{peer_port}" for _, (_, peer_port) in accepted]

            async def opens() -> None:  # three opens on each connection at once
                await asyncio.gather(*(clients.look(peer) for peer in peers for _ in range(3)))

            asyncio.run(opens())
            assert [start.pid for start in told] == [child.pid]
            assert not clients.wanted(peers[0]) and not clients.wanted(peers[1])
            for connection, _ in accepted:
                connection.close()
        finally:
            child.kill()
            listener.close()


def test_each_connection_is_looked_for_once_only_while_the_machine_is_short_and_at_a_bounded_rate() -> None:
    told: list[ClientStart] = []
    short = [False]
    clients = LocalClients(told.append, needed=lambda: short[0])
    peers = [f"ipv4:192.0.2.7:{40000 + i}" for i in range(LocalClients.LOOKUPS_PER_SECOND + 5)]
    assert not clients.wanted(peers[0])  # the machine has CPU to spare: not worth a lookup
    short[0] = True
    assert clients.wanted(peers[0])
    while int(time.monotonic() + 0.2) != int(time.monotonic()):
        time.sleep(0.05)  # all the lookups below within one second
    for peer in peers:
        clients.note(peer)
    assert not told  # none of them is on this machine
    looked = [p for p in peers if not clients.wanted(p)]
    assert len(looked) == len(peers)  # each was looked for, or this second's lookups are spent
    time.sleep(1.0)
    assert [p for p in peers if clients.wanted(p)] == peers[LocalClients.LOOKUPS_PER_SECOND :]


def test_a_peer_that_is_not_on_this_machine_or_not_tcp_is_not_a_local_client() -> None:
    assert client_start("ipv4:192.0.2.7:40000") is None  # TEST-NET-1: no socket of this machine
    assert client_start("unix:/tmp/jitdyn.sock") is None
    assert client_start("ipv4:not-an-address:1") is None
    assert client_start("") is None


def test_a_start_up_counts_in_a_window_by_its_share_of_it() -> None:
    start = ClientStart(pid=1, started=10.0, opened=14.0, cpu=2.0)  # half a core for 4 s
    assert start.within(12.0, 14.0) == pytest.approx(1.0)
    assert start.within(13.0, 20.0) == pytest.approx(0.5)
    assert start.within(14.0, 16.0) == 0.0  # after its first open: load like any other
    assert start.within(0.0, 10.0) == 0.0
    assert ClientStart(pid=1, started=5.0, opened=5.0, cpu=0.2).within(4.0, 6.0) == 0.0


# Burns `BURN` s of CPU (a client's imports, its trajectory, its model's compile), then opens a
# pendulum_1 REALTIME session at 20 Hz, runs 20 ticks and prints "ran", or prints the refusal.
_CLIENT = textwrap.dedent(
    """
    import sys, time
    until = time.process_time() + float(sys.argv[2])
    while time.process_time() < until:
        pass
    from jitdyn.client import Client, FrameData, SessionOptions
    from jitdyn.errors import ResourceExhausted
    options = SessionOptions(model_name="pendulum_1", dt=0.05, clock="REALTIME", scenario="PASSIVE")
    with Client(sys.argv[1], timeout=30) as client:
        try:
            with client.open_session(options) as session:
                for k in range(20):
                    time.sleep(max(0.0, k * 0.05 - session.now()))
                    session.send(FrameData(seq=k, t=k * 0.05, qpos=[0.3], qvel=[0.0]))
                    session.poll()
        except ResourceExhausted as error:
            print(error, flush=True)
            raise SystemExit(0)
    print("ran", flush=True)
    """
)


# A wall-clock promise: it runs first in the suite (docs/decisions/0010-timing-tests-first.md).
@pytest.mark.timing
def test_clients_that_took_every_core_starting_up_are_admitted(tmp_path: Path) -> None:
    """Two clients each burn 3 s of CPU starting up, the machine's two cores full, then open: every
    window the server measured before their opens was full of them. Counted as load, they were
    refused ("this machine has 0.03 of its 2 cores free"); not counted, both run."""
    server = Serve(tmp_path / "data", "--processes", "1")
    try:
        time.sleep(2.5)  # a window of the idle machine
        clients = [
            subprocess.Popen(
                [sys.executable, "-c", _CLIENT, server.address, "3.0"], stdout=subprocess.PIPE, text=True
            )
            for _ in range(2)
        ]
        said = [client.communicate(timeout=60)[0].strip() for client in clients]
    finally:
        server.stop()
    assert said == ["ran", "ran"], (said, "".join(server.lines[-20:]))
