"""The one bounded pool of workers that propagates the sigma points of every session.

A server makes one `WorkerPool(workers)` and hands it to every estimator; whatever the number of
sessions, at most `workers` threads run MuJoCo for them at a time. Two back-ends do the stepping
(server/estimation/propagate.py uses them; benchmarks/ukf_cycle.py measures both)::

    with WorkerPool(2) as pool:                       # Backend.ROLLOUT, the default
        estimator = make_estimator(model, config, pool=pool)

- `Backend.ROLLOUT`: one persistent `mujoco.rollout.Rollout` per worker steps that worker's share
  of a sigma set in C++, without the GIL and without Python per point or per step.
- `Backend.THREADS`: each worker loops `mj_step` over its share on its own MjData, from Python
  (mj_step releases the GIL while it runs).

Either way a call is cut into up to `workers` contiguous chunks; the calling thread steps the
first itself and `workers - 1` pool threads the others, so a call wakes at most `workers - 1`
threads and the caller never sleeps while there is work. (A single Rollout with its own C++ pool
of `workers` threads was measured slower inside a filter cycle: it wakes every thread, and the
caller, on every call.) A call also says how many chunks its work is worth (server/estimation/propagate.py:
about MIN_CHUNK_SECONDS of physics each): a small sigma set stays on the calling thread.

Propagations are serialised by one lock: a call gets every worker, and sessions queue behind it.
That is what keeps the bound. BLAS (numpy's and scipy's OpenBLAS) runs single-threaded in a
process that has a pool: the filters' matrices are tens of rows, and OpenBLAS's own threads, which
spin after every call, fought the pool's for the cores (myoHand's DRIVEN cycle on a busy machine:
a mean of 5.5 ms and ticks of 70 ms, against 2.1 ms and at most 7 ms single-threaded).
"""

from __future__ import annotations

import enum
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Final

import mujoco
import mujoco.rollout
import numpy as np
import scipy.linalg  # noqa: F401  (its OpenBLAS is loaded, so that the limit below reaches it)
from threadpoolctl import ThreadpoolController

from jitdyn.errors import FailedPrecondition, InvalidArgument
from jitdyn.lifecycle import Closeable
from jitdyn.mujoco_log import counting, current_counter

__all__ = ["DEFAULT_BACKEND", "MAX_WORKERS", "MIN_CHUNK_SECONDS", "Backend", "WorkerPool"]


class Backend(enum.StrEnum):
    """How a sigma set is stepped: see the module docstring."""

    ROLLOUT = "ROLLOUT"
    THREADS = "THREADS"


# Measured in benchmarks/ukf_cycle.py (numbers in benchmarks/RESULTS.md, "## UKF cycle").
DEFAULT_BACKEND: Final = Backend.ROLLOUT

# More workers than this is a configuration mistake on any machine we run on.
MAX_WORKERS: Final = 256

# A chunk handed to another thread should carry at least this much work (seconds): waking a
# thread and waiting for it costs tens of microseconds, and far more when the other cores are
# busy with other work.
MIN_CHUNK_SECONDS: Final = 200e-6


_blas_limited = False
_blas_lock = threading.Lock()


def _single_threaded_blas() -> None:
    """Every BLAS loaded in this process runs on its caller's thread (once per process)."""
    global _blas_limited
    with _blas_lock:
        if not _blas_limited:
            ThreadpoolController().limit(limits=1, user_api="blas")
            _blas_limited = True


class WorkerPool(Closeable):
    """`workers` threads shared by all sessions. A context manager; `close()` is safe twice.

    Estimators never call the pool's methods themselves; server/estimation/propagate.py does.
    Making one leaves BLAS single-threaded in the process (see the module docstring).
    """

    def __init__(self, workers: int, *, backend: Backend | str = DEFAULT_BACKEND) -> None:
        if isinstance(workers, bool) or not isinstance(workers, int) or not 1 <= workers <= MAX_WORKERS:
            raise InvalidArgument(f"workers must be an integer in [1, {MAX_WORKERS}], got {workers!r}")
        try:
            self._backend = Backend(backend)
        except ValueError:
            raise InvalidArgument(
                f"backend must be one of {[b.value for b in Backend]}, got {backend!r}"
            ) from None
        _single_threaded_blas()
        self._workers = workers
        self._lock = threading.Lock()
        self._closed = False
        # nthread=0: each Rollout runs on the thread that calls it, the caller or a pool thread.
        self._rollouts = (
            [mujoco.rollout.Rollout(nthread=0) for _ in range(workers)]
            if self._backend is Backend.ROLLOUT
            else []
        )
        self._executor = (
            ThreadPoolExecutor(max_workers=workers - 1, thread_name_prefix="jitdyn-sigma")
            if workers > 1
            else None
        )

    @property
    def workers(self) -> int:
        """How many threads step MuJoCo at most, for all sessions together."""
        return self._workers

    @property
    def backend(self) -> Backend:
        return self._backend

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Stop the threads. Safe to call twice; using the pool afterwards raises FailedPrecondition."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            for rollout in self._rollouts:
                rollout.close()
            self._rollouts = []
            if self._executor is not None:
                self._executor.shutdown(wait=True)
                self._executor = None

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"WorkerPool(workers={self._workers}, backend={self._backend.value}, {state})"

    def _check_open(self) -> None:
        if self._closed:
            raise FailedPrecondition("the worker pool is closed")

    def rollout(
        self,
        models: list[mujoco.MjModel],
        data: list[mujoco.MjData],
        *,
        nstep: int,
        control_spec: int,
        initial_state: np.ndarray,
        control: np.ndarray | None,
        state: np.ndarray | None,
        chunks: int,
        then: Callable[[int, int, int], None] | None = None,
    ) -> None:
        """`Rollout.rollout` with checks skipped, each worker on its share of the rows.

        models: the model nbatch times (the unchecked call wants one per rollout); data: one
        MjData per worker; initial_state (nbatch, nstate); control (nbatch, nstep, ncontrol) or
        None; state, the output, (nbatch, nstep, nstate), all C-contiguous (None when nstep is 0);
        chunks: how many workers the work is worth; then(worker, start, stop): more work on the
        same rows, run by the same worker after its rollout.
        """
        if self._backend is not Backend.ROLLOUT:
            raise FailedPrecondition(f"the pool's backend is {self._backend.value}, not ROLLOUT")

        def work(worker: int, lo: int, hi: int) -> None:
            if nstep > 0 and state is not None:
                # Leading-axis slices of C-contiguous arrays are C-contiguous, as the call needs.
                self._rollouts[worker].rollout(
                    models[lo:hi],
                    [data[worker]],
                    initial_state[lo:hi],
                    None if control is None else control[lo:hi],
                    control_spec=control_spec,
                    skip_checks=True,
                    nstep=nstep,
                    initial_warmstart=None,
                    state=state[lo:hi],
                    sensordata=None,
                    chunk_size=None,
                )
            if then is not None:
                then(worker, lo, hi)

        self._run(work, initial_state.shape[0], chunks)

    def run_chunks(self, work: Callable[[int, int, int], None], count: int, *, chunks: int) -> None:
        """THREADS: call work(worker, start, stop) over [0, count) in up to `chunks` even chunks.

        Worker 0's chunk runs on the calling thread, the others on the pool's threads; returns
        when all are done and re-raises the first exception.
        """
        if self._backend is not Backend.THREADS:
            raise FailedPrecondition(f"the pool's backend is {self._backend.value}, not THREADS")
        self._run(work, count, chunks)

    def _run(self, work: Callable[[int, int, int], None], count: int, chunks: int) -> None:
        with self._lock:
            self._check_open()
            nchunk = max(1, min(chunks, self._workers, count))
            bounds = [i * count // nchunk for i in range(nchunk + 1)]  # even, contiguous
            futures: list[Future[None]] = []
            if nchunk > 1 and self._executor is not None:
                # MuJoCo's warnings on the pool's threads count for the caller's session too.
                counter = current_counter()

                def counted(i: int, lo: int, hi: int) -> None:
                    with counting(counter):
                        work(i, lo, hi)

                futures = [
                    self._executor.submit(counted, i, bounds[i], bounds[i + 1]) for i in range(1, nchunk)
                ]
            try:
                work(0, bounds[0], bounds[1])
            finally:
                # Wait for every chunk even when ours failed: they write into the caller's buffers.
                for future in futures:
                    future.exception()
            for future in futures:
                future.result()
