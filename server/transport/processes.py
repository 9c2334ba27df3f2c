"""`jitdyn serve --processes N`: N server processes on one port, gRPC's documented pattern for
using every core from Python (each process its own event loop, GIL and worker pool; the kernel
spreads connections over them with SO_REUSEPORT).

    run_processes(config, processes=2, announce=print)    # blocks until SIGINT or SIGTERM

The parent does what must happen once, before any child serves: it migrates the index, recovers
sessions a dead server left open and registers the built-in models; it reserves the port; then it
starts the children and waits. The children share the data folder, the registry and the index. A
session's log is flock'ed by the process writing it, so its lock is the lease a killed process
loses: when a child dies, the parent recovers that child's sessions (only unlocked logs are
touched) and starts a new child in its place.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import ctypes.util
import dataclasses
import logging
import multiprocessing as mp
import os
import queue
import shutil
import signal
import socket
import tempfile
import time
from collections.abc import Callable, Iterator
from multiprocessing.process import BaseProcess
from typing import Any

from grpc_health.v1 import health_pb2
from prometheus_client import multiprocess as prometheus_multiprocess

from jitdyn.errors import FailedPrecondition, InvalidArgument
from jitdyn.server.estimation.config import Engine
from jitdyn.server.runtime.priority import prioritise
from jitdyn.server.transport.app import SERVICE_NAMES, ServerConfig, prepare_data, serve
from jitdyn.server.transport.metrics import MULTIPROCESS_ENV, serve_metrics
from jitdyn.server.transport.probes import Probes
from jitdyn.storage.root import normalise_root_uri

__all__ = ["run_processes"]

_log = logging.getLogger(__name__)

_READY_TIMEOUT = 120.0  # s: a child compiles the built-ins' cache lazily, so starting is quick


@contextlib.contextmanager
def _reserved_port(address: str) -> Iterator[int]:
    """Bind `address` with SO_REUSEPORT without listening, so that port 0 becomes one concrete port
    every child can bind too, and no other program takes it meanwhile."""
    host, _, port = address.rpartition(":")
    host = host.strip("[]")
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    busy = FailedPrecondition(
        f"cannot listen on {address}: the address is in use (another jitdyn serve?) or not an "
        "address of this machine; choose another with --address HOST:PORT (port 0 picks a free one)"
    )
    if int(port):
        # SO_REUSEPORT would let this server join a port another one (of the same user) already
        # serves, and take half of its new sessions into another data folder: a bind without it
        # fails while anyone listens there, so the port is ours alone before our children share it.
        with socket.socket(family, socket.SOCK_STREAM) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # TIME_WAIT is no owner
            try:
                probe.bind((host, int(port)))
            except OSError:
                raise busy from None
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        try:
            sock.bind((host, int(port)))
        except OSError:
            raise busy from None
        yield sock.getsockname()[1]
    finally:
        sock.close()


def _die_with_parent() -> None:
    """Linux: SIGKILL this process when its parent dies, so that `kill -9` of `jitdyn serve` ends
    every serving process (their logs' locks go with them and the next start recovers the
    sessions) instead of leaving orphans serving a port nobody supervises."""
    libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
    pr_set_pdeathsig = 1
    libc.prctl(pr_set_pdeathsig, signal.SIGKILL)


def _child(config: ServerConfig, index: int, ready: Any, parent: int, log_level: int) -> None:
    """One serving process (spawned): serve until SIGTERM, reporting readiness to the parent, logging
    at `log_level` as the parent does (`jitdyn -v serve`: INFO, every refused open among it)."""
    _die_with_parent()
    if os.getppid() != parent:  # the parent died before the line above took effect
        return
    logging.basicConfig(level=log_level, format=f"%(levelname)s [process {index}] %(name)s: %(message)s")
    # Alembic says which migrations it checked at every start of the index: noise for `-v`.
    logging.getLogger("alembic").setLevel(logging.WARNING)

    def announce(line: str) -> None:
        if line.startswith("jitdyn listening"):
            ready.put(("ready", index))

    try:
        asyncio.run(serve(config, announce=announce, process_index=index))
    except Exception as exc:  # reported to the parent, which says it in one line
        ready.put(("failed", f"process {index}: {type(exc).__name__}: {exc}"))
        raise


class _Children:
    """The serving processes of one `jitdyn serve --processes N`: started, awaited, restarted."""

    def __init__(self, config: ServerConfig, *, metrics_dir: str) -> None:
        self._config = config
        self._metrics_dir = metrics_dir
        self._context = mp.get_context("spawn")
        self._ready = self._context.Queue()
        self._children: dict[int, BaseProcess] = {}
        self.stopping = False
        # The serving processes log as `jitdyn serve` was told to: before, they logged at WARNING
        # whatever -v said, so no refused open was logged with the default two processes.
        self._log_level = logging.getLogger().getEffectiveLevel()

    def on_signal(self, signum: int, _frame: object) -> None:
        self.stopping = True

    def start(self, index: int) -> None:
        child = self._context.Process(
            target=_child,
            args=(self._config, index, self._ready, os.getpid(), self._log_level),
            name=f"jitdyn-serve-{index}",
            daemon=False,
        )
        child.start()
        self._children[index] = child

    def start_all(self, processes: int) -> None:
        """Start `processes` children and wait until each serves (or a signal stops the wait);
        InvalidArgument when one fails, exits or takes longer than _READY_TIMEOUT."""
        for index in range(processes):
            self.start(index)
        waiting = set(range(processes))
        deadline = time.monotonic() + _READY_TIMEOUT
        while waiting and not self.stopping:
            try:
                kind, detail = self._ready.get(timeout=0.2)
            except queue.Empty:
                pass
            else:
                if kind == "failed":
                    raise InvalidArgument(str(detail))
                waiting.discard(detail)
            if time.monotonic() > deadline:
                raise InvalidArgument(
                    f"{len(waiting)} server process(es) did not start within {_READY_TIMEOUT:g} s"
                )
            dead = [i for i in waiting if not self._children[i].is_alive()]
            if dead:
                raise InvalidArgument(
                    f"server process {dead[0]} exited while starting (see its messages above)"
                )

    def supervise(self) -> None:
        """Until a signal: a child that dies has its sessions recovered and is started again."""
        while not self.stopping:
            time.sleep(0.2)
            for index, child in list(self._children.items()):
                if not child.is_alive() and not self.stopping:
                    _log.warning(
                        "server process %d exited (code %s); recovering its sessions and restarting it",
                        index,
                        child.exitcode,
                    )
                    with contextlib.suppress(Exception):
                        prepare_data(self._config, recover_only=True)
                    if child.pid is not None:
                        prometheus_multiprocess.mark_process_dead(child.pid, self._metrics_dir)  # type: ignore[no-untyped-call]
                    self.start(index)

    def stop(self) -> None:
        """SIGTERM to every child (each shuts down gracefully), SIGKILL to those still alive after
        the shutdown grace."""
        for child in self._children.values():
            if child.is_alive():
                child.terminate()
        for child in self._children.values():
            child.join(timeout=self._config.shutdown_grace + 30)
            if child.is_alive():
                child.kill()


def _announce_start(
    config: ServerConfig,
    *,
    port: int,
    processes: int,
    index_url: str,
    served: dict[str, str],
    announce: Callable[[str], None],
) -> None:
    host = config.address.rpartition(":")[0]
    announce(
        f"jitdyn listening on {host}:{port} ({'TLS' if config.tls_cert else 'plaintext'}, {processes} processes)"
    )
    announce(f"data in {config.data_root} (index: {index_url})")
    if config.data_root_uri is not None:
        announce(f"finished sessions go to the data root {normalise_root_uri(config.data_root_uri)}")
    if "metrics" in served:
        announce(f"metrics on http://{served['metrics']}/metrics")
    if "probes" in served:
        announce(f"health probes on {served['probes']} (plaintext gRPC health, from the supervising process)")
    if config.engine != Engine.NATIVE:
        announce(
            "the UKF runs on the python engine (--engine python): the numpy reference of the "
            "native one, 1.3-3.5x its CPU per filter cycle; fewer sessions fit"
        )


def _set_ready(probes: Probes | None, ready: bool) -> None:
    """The sessions' services in the probes' health: the children's port is served or not."""
    status = health_pb2.HealthCheckResponse.SERVING if ready else health_pb2.HealthCheckResponse.NOT_SERVING
    if probes is not None:
        for name in SERVICE_NAMES:
            probes.set(name, status)


def run_processes(config: ServerConfig, *, processes: int, announce: Callable[[str], None] = print) -> None:
    """Serve `config` from `processes` processes until SIGINT or SIGTERM. With --health-address,
    this supervising process answers the probes: alive while it supervises (it restarts a child
    that dies), ready while every child serves."""
    if processes < 1:
        raise InvalidArgument(f"--processes must be at least 1, got {processes}")
    # The ports first: a busy one must leave nothing created on disk.
    with _reserved_port(config.address) as port:
        probes = Probes.bind(config.health_address) if config.health_address else None
        try:
            data_root, index_url = prepare_data(config)
        except BaseException:
            if probes is not None:
                probes.stop()
            raise
        metrics_dir = tempfile.mkdtemp(prefix="jitdyn-metrics-")
        os.environ[MULTIPROCESS_ENV] = metrics_dir  # inherited by the children, before they import metrics
        served: dict[str, str] = {}
        if config.metrics_address:
            served["metrics"] = serve_metrics(config.metrics_address)
        if config.nice is not None:  # the children inherit it
            prioritise(config.nice)
        child_config = dataclasses.replace(
            config,
            address=f"{config.address.rpartition(':')[0]}:{port}",
            data_root=data_root,
            startup_tasks=False,
            reuse_port=True,
            nice=None,
            health_address=None,
        )
        children = _Children(child_config, metrics_dir=metrics_dir)
        previous = {s: signal.signal(s, children.on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            children.start_all(processes)
            if children.stopping:
                return
            if probes is not None:  # answering once every child serves
                probes.start(alive=lambda: True)
                _set_ready(probes, True)
                served["probes"] = probes.address
            _announce_start(
                child_config,
                port=port,
                processes=processes,
                index_url=index_url,
                served=served,
                announce=announce,
            )
            children.supervise()
            _set_ready(probes, False)
            announce("jitdyn shutting down: open sessions are being stored")
        finally:
            children.stop()
            if probes is not None:
                probes.stop()
            for s, handler in previous.items():
                signal.signal(s, handler)
            shutil.rmtree(metrics_dir, ignore_errors=True)
            os.environ.pop(MULTIPROCESS_ENV, None)
