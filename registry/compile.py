"""Compiling an untrusted MJCF from memory, within the registry's limits.

    model = compile_model(mjcf, {"meshes/arm.stl": data}, limits=DEFAULT_LIMITS)

    with ModelCompiler(limits=limits) as compiler:      # reuses its worker processes
        model = compiler.compile(mjcf, assets)

Sizes are checked first, then every file reference (registry.references), so MuJoCo only ever reads
the request's assets. MuJoCo then compiles in a worker process: a compile that runs over
`compile_timeout` cannot be interrupted inside MuJoCo, but its process can be killed. Workers start
once (a fresh interpreter, not a fork: the gRPC server has threads) and are reused, so a compile
pays only for sending the model to the worker and its compiled form (MJB) back.
"""

from __future__ import annotations

import logging
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Mapping
from multiprocessing.connection import Connection
from pathlib import Path

import mujoco

from jitdyn.errors import InvalidArgument, ResourceExhausted
from jitdyn.lifecycle import Closeable
from jitdyn.registry.limits import DEFAULT_LIMITS, RegistryLimits
from jitdyn.registry.references import check_asset_names, check_model

__all__ = ["ModelCompiler", "check_request", "compile_model"]

_log = logging.getLogger(__name__)

# A worker imports MuJoCo before it answers; on a loaded 2-core machine that can take seconds.
_STARTUP_TIMEOUT = 120.0


def check_request(mjcf: str, assets: Mapping[str, bytes], *, limits: RegistryLimits) -> None:
    """The checks that need no parsing: types, sizes and asset names."""
    if not isinstance(mjcf, str):
        raise InvalidArgument(f"mjcf must be a string of MJCF (XML), got {type(mjcf).__name__}")
    if not mjcf.strip():
        raise InvalidArgument("mjcf is empty; expected the MJCF (XML) text of a model")
    limits.check("max_mjcf_bytes", "the MJCF", len(mjcf.encode("utf-8")), " bytes")
    if not isinstance(assets, Mapping):
        raise InvalidArgument(f"assets must map names to bytes, got {type(assets).__name__}")
    limits.check("max_assets", "the number of assets", len(assets))
    check_asset_names(assets)
    limits.check(
        "max_asset_bytes", "the assets' total size", sum(len(data) for data in assets.values()), " bytes"
    )


_WORKER = Path(__file__).with_name("compile_worker.py")


class _Worker:
    """One compile process (registry/compile_worker.py) and the parent's end of its socket."""

    def __init__(self, *, memory: int = 0) -> None:
        parent, child = socket.socketpair()
        self.expired = False
        try:
            # Run by path, not by module name: the worker needs MuJoCo only, whatever sys.path is.
            self.process = subprocess.Popen(
                [sys.executable, str(_WORKER), str(child.fileno()), str(memory)],
                pass_fds=(child.fileno(),),
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
            )
        finally:
            child.close()
        self.connection = Connection(parent.detach())
        if not self.connection.poll(_STARTUP_TIMEOUT):
            self.kill()
            raise RuntimeError(f"the MuJoCo compile worker did not start within {_STARTUP_TIMEOUT:g} s")
        self.connection.recv_bytes()

    def compile(
        self, mjcf: str, assets: dict[str, bytes], *, timeout: float, max_bytes: int
    ) -> mujoco.MjModel:
        # The limit covers the whole exchange (sending the job, compiling, sending the model back):
        # a timer kills the worker when it runs out, which ends any read or write here at once.
        timer = threading.Timer(timeout, self._expire)
        timer.daemon = True
        timer.start()
        try:
            self.connection.send((mjcf, assets, max_bytes))
            answer = self.connection.recv_bytes()
        except (EOFError, OSError):
            self.kill()
            if self.expired:
                raise ResourceExhausted(
                    f"compiling the model took longer than the limit of {timeout:g} s "
                    "(registry setting compile_timeout, --compile-timeout)"
                ) from None
            code = self.process.returncode
            if code == -signal.SIGKILL:
                raise ResourceExhausted(
                    "the MuJoCo compiler was killed while compiling the model (most likely out of memory)"
                ) from None
            raise InvalidArgument(f"MuJoCo's compiler crashed on the model (exit code {code})") from None
        finally:
            timer.cancel()
        kind, body = answer[:1], answer[1:]
        if kind == b"E":
            raise InvalidArgument(f"MuJoCo could not compile the model: {body.decode('utf-8').strip()}")
        if kind == b"B":
            raise ResourceExhausted(
                f"the compiled model needs {int(body)} bytes, over the limit of {max_bytes} bytes "
                "(registry setting max_compiled_bytes, --max-compiled-bytes)"
            )
        if kind == b"O":
            self.kill()  # its heap may be fragmented up to the limit; start afresh
            raise ResourceExhausted(
                "compiling the model ran out of the compile worker's memory limit "
                "(registry setting compile_memory_bytes, --compile-memory-bytes)"
            )
        return mujoco.MjModel.from_binary_path("model.mjb", {"model.mjb": body})

    def _expire(self) -> None:
        self.expired = True
        if self.process.poll() is None:
            self.process.kill()

    def alive(self) -> bool:
        return self.process.poll() is None

    def kill(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
        self.process.wait()
        self.connection.close()

    def stop(self) -> None:
        try:
            self.connection.send(None)
            self.process.wait(timeout=5)
        except (OSError, subprocess.TimeoutExpired):
            pass
        self.kill()


class ModelCompiler(Closeable):
    """Compiles models in up to `workers` reusable worker processes; thread-safe.

    Each compile checks the request against `limits` first. Workers start on first use; `close()`
    (safe to call twice) stops them.
    """

    def __init__(self, *, limits: RegistryLimits = DEFAULT_LIMITS, workers: int = 1) -> None:
        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
            raise ValueError(f"workers must be a positive integer, got {workers!r}")
        self._limits = limits
        self._slots = threading.BoundedSemaphore(workers)
        self._lock = threading.Lock()
        self._idle: list[_Worker] = []
        self._busy: set[_Worker] = set()
        self._closed = False

    @property
    def limits(self) -> RegistryLimits:
        return self._limits

    def compile(self, mjcf: str, assets: Mapping[str, bytes]) -> mujoco.MjModel:
        """The compiled model; see `compile_model` for what is checked and raised."""
        check_request(mjcf, assets, limits=self._limits)
        checked = check_model(mjcf, assets, max_documents=self._limits.max_assets)
        with self._slots:
            worker = self._acquire()
            try:
                model = worker.compile(
                    checked.mjcf,
                    checked.assets,
                    timeout=self._limits.compile_timeout,
                    max_bytes=self._limits.max_compiled_bytes,
                )
            finally:
                self._release(worker)
        self._limits.check("max_nv", "the model's number of degrees of freedom (nv)", model.nv)
        return model

    def _acquire(self) -> _Worker:
        with self._lock:
            if self._closed:
                raise RuntimeError("the ModelCompiler is closed")
            while self._idle:
                worker = self._idle.pop()
                if worker.alive():
                    self._busy.add(worker)
                    return worker
                worker.kill()
        worker = _Worker(memory=self._limits.compile_memory_bytes)
        with self._lock:
            self._busy.add(worker)
        return worker

    def _release(self, worker: _Worker) -> None:
        with self._lock:
            self._busy.discard(worker)
            if not self._closed and worker.alive():
                self._idle.append(worker)
                return
        worker.stop()

    def close(self) -> None:
        """Stop the idle workers now and the busy ones when their compile ends; safe twice."""
        with self._lock:
            self._closed = True
            idle, self._idle = self._idle, []
        for worker in idle:
            worker.stop()

    def __del__(self) -> None:
        if not getattr(self, "_closed", True):
            _log.debug("ModelCompiler garbage-collected without close()")
            self.close()


def compile_model(
    mjcf: str, assets: Mapping[str, bytes], *, limits: RegistryLimits = DEFAULT_LIMITS
) -> mujoco.MjModel:
    """Compile an untrusted MJCF with its assets, from memory only.

    Starts a worker process for this one compile (about a second); reuse a `ModelCompiler` to
    compile several.

    Raises:
      InvalidArgument: bad types, asset names, XML, a file reference that is not an asset, or
        MuJoCo's compile error (its message included).
      ResourceExhausted: over a limit of `limits`: MJCF size, asset count or size, compile time, nv.
    """
    with ModelCompiler(limits=limits) as compiler:
        return compiler.compile(mjcf, assets)
