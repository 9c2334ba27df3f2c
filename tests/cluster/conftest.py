"""Fixtures of the cluster suite: a PostgreSQL database of the run's own, three replicas of
`jitdyn serve` on 127.0.0.2-4 sharing it (each its own data folder), HAProxy in front of them,
moto's S3 server, and factories for the replicas, balancers and namespaced hosts a test kills or
cuts off. Each fixture skips, saying why, where this machine lacks what it starts. Helpers live in
_cluster.py, importable from the tests as `_cluster`."""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))

from _cluster import Balancer, MotoS3, NetnsHost, Replica, Unavailable, postgres_database, tool

REPLICA_HOSTS = ("127.0.0.2", "127.0.0.3", "127.0.0.4")
SPARE_HOST = "127.0.0.9"


# The run's shared fleet (the three replicas, the spare and their balancer) stops after this folder's
# last test, not at the end of the run: idle, it still takes about a fifth of a core (health checks
# every 200 ms, metrics) from every test after it, and several of those read the machine's idle CPU.
_FLEET: list[Callable[[], None]] = []


def pytest_runtest_teardown(item: pytest.Item, nextitem: pytest.Item | None) -> None:
    here = Path(__file__).parent
    if _FLEET and not any(Path(later.path).is_relative_to(here) for later in _items_after(item)):
        while _FLEET:
            _FLEET.pop()()


def _items_after(item: pytest.Item) -> list[pytest.Item]:
    items = item.session.items
    return items[items.index(item) + 1 :]


@pytest.fixture(scope="session")
def index_url() -> Iterator[str]:
    """A fresh PostgreSQL database for this run, dropped at its end."""
    try:
        database = postgres_database()
        url = database.__enter__()
    except Unavailable as reason:
        pytest.skip(str(reason))
    try:
        yield url
    finally:
        database.__exit__(None, None, None)


@pytest.fixture(scope="session")
def _replica_processes(index_url: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[list[Replica]]:
    """Every session-scoped replica, started together (as a deployment rolls out, and because each
    takes seconds to start): the three of `replicas`, then `spare_replica`."""
    root = tmp_path_factory.mktemp("replicas")
    names = [*(f"r{n}" for n in range(1, len(REPLICA_HOSTS) + 1)), "spare"]
    with ExitStack() as stack, ThreadPoolExecutor(len(names)) as pool:
        futures = [
            pool.submit(Replica.start, name, host=host, data=root / name, index_url=index_url)
            for name, host in zip(names, (*REPLICA_HOSTS, SPARE_HOST), strict=True)
        ]
        started = []
        for future in futures:
            try:
                started.append(stack.enter_context(future.result()))
            except Unavailable as reason:
                pytest.skip(str(reason))
        _FLEET.append(stack.close)
        yield started


@pytest.fixture(scope="session")
def replicas(_replica_processes: list[Replica]) -> list[Replica]:
    """Three replicas, one per loopback address, sharing the run's PostgreSQL index."""
    return _replica_processes[: len(REPLICA_HOSTS)]


@pytest.fixture(scope="session")
def spare_replica(_replica_processes: list[Replica]) -> Replica:
    """A fourth replica on the same index, behind no session-scoped balancer: one test may kill it."""
    return _replica_processes[-1]


def _haproxy_or_skip() -> None:
    try:
        tool("haproxy")
    except Unavailable as reason:
        pytest.skip(f"{reason} (apt-get install -y haproxy)")


@pytest.fixture(scope="session")
def balancer(replicas: list[Replica], tmp_path_factory: pytest.TempPathFactory) -> Iterator[Balancer]:
    """HAProxy with deploy/haproxy/haproxy.cfg over the three replicas, every one UP."""
    _haproxy_or_skip()
    with Balancer.start(replicas, workdir=tmp_path_factory.mktemp("haproxy")) as running:
        _FLEET.append(running.close)
        yield running


@pytest.fixture()
def start_replica(index_url: str, tmp_path: Path) -> Iterator[Callable[..., Replica]]:
    """Starts a replica of the test's own on `host` (stopped after it): one a test may kill."""
    with ExitStack() as stack:

        def start(name: str, host: str, **options: object) -> Replica:
            options.setdefault("data", tmp_path / name)
            options.setdefault("index_url", index_url)
            replica = Replica.start(name, host=host, **options)  # type: ignore[arg-type]
            return stack.enter_context(replica)

        yield start


@pytest.fixture()
def start_balancer(tmp_path: Path) -> Iterator[Callable[[Sequence[Replica]], Balancer]]:
    """Starts HAProxy of the test's own over the given replicas (stopped after it)."""
    _haproxy_or_skip()
    with ExitStack() as stack:
        started: list[Balancer] = []

        def start(over: Sequence[Replica]) -> Balancer:
            balancer = Balancer.start(over, workdir=tmp_path / f"haproxy{len(started)}")
            started.append(stack.enter_context(balancer))
            return balancer

        yield start


@pytest.fixture(scope="session")
def moto_s3(tmp_path_factory: pytest.TempPathFactory) -> Iterator[MotoS3]:
    """moto's S3 server on a free loopback port."""
    try:
        server = MotoS3.start(workdir=tmp_path_factory.mktemp("moto"))
    except Unavailable as reason:
        pytest.skip(f"{reason} (pip install 'moto[server]', in the dev extra)")
    with server:
        yield server


@pytest.fixture()
def netns_host() -> Iterator[NetnsHost]:
    """A network namespace of the test's own, joined to this one by a veth pair."""
    try:
        host = NetnsHost()
    except Unavailable as reason:
        pytest.skip(str(reason))
    with host:
        yield host
