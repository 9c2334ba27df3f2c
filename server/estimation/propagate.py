"""Batched propagation of a set of sigma points through MuJoCo, one call per filter step.

filterpy's UnscentedKalmanFilter calls its process model once per sigma point from a Python loop;
jitdyn's filter instead hands the whole set (nsigma, nx) to a `Propagator`, which steps every point
`nstep` physics steps on the shared `WorkerPool`, by `mujoco.rollout` or by threads looping
`mj_step` (server/estimation/pool.py). Both give the same numbers to the last bit::

    model = process_model(model, scenario="PASSIVE")
    propagate = Propagator(model, pool=pool, nsigma=5, nstep=5, inputs=Inputs.NONE)
    out = propagate(qpos, qvel, act=np.zeros(model.na))      # out.qpos (5, nq), out.qvel (5, nv)
"""

from __future__ import annotations

import copy
import enum
import time
from dataclasses import dataclass
from typing import Final

import mujoco
import mujoco.batch
import numpy as np

from jitdyn.errors import InvalidArgument
from jitdyn.server.estimation.pool import MIN_CHUNK_SECONDS, Backend, WorkerPool
from jitdyn.vocabulary import Scenario

__all__ = ["Inputs", "Propagated", "Propagator", "process_model", "step_seconds"]

_FULL: Final = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)
_CTRL: Final = int(mujoco.mjtState.mjSTATE_CTRL)
_QFRC: Final = int(mujoco.mjtState.mjSTATE_QFRC_APPLIED)
_INTEGRATION: Final = int(mujoco.mjtState.mjSTATE_INTEGRATION)
_PRICED_STEPS: Final = 8
_OTHER_COUNTS_KEPT: Final = 8  # buffers kept for step counts other than the tick's


class Inputs(enum.Enum):
    """What acts on the sigma points besides the model's own forces, held over the propagation."""

    NONE = 0  # PASSIVE: ctrl and qfrc_applied are zero
    CTRL = _CTRL  # CONTROLLED: the tick's control
    QFRC = _QFRC  # EXTERNAL: the restored generalized force, as qfrc_applied; DRIVEN: each
    # sigma point's own estimated force (and its rate), as qfrc_applied


def process_model(model: mujoco.MjModel, *, scenario: Scenario | str) -> mujoco.MjModel:
    """A private copy of `model` set up as the filter's process model.

    - Warm start off: the constraint solver then starts from the unconstrained acceleration every
      step, so a step is a pure function of (qpos, qvel, act, ctrl, qfrc_applied), with no hidden
      state carried in an MjData: back-ends, the reference loop and a timewarp replay agree
      exactly. Without constraints this changes nothing.
    - Auto-reset off: a sigma point that blows up stays non-finite, where MuJoCo would silently put
      it back at qpos0; the filter's divergence guard sees it.
    - Sensors off: the filter never reads them.
    - EXTERNAL and DRIVEN: actuation off. The restored (or estimated) force is everything mj_inverse says acted, actuators
      included; muscles' passive and active forces must not act a second time on top of it.
      Tendons that then do nothing (no stiffness, damping, friction, limit, armature or equality
      constraint: they only routed muscles) lose their wrap paths, so MuJoCo stops computing their
      lengths: the same states, bit for bit, in a third less time on myoHand.
    - Contacts off when no two geoms can ever touch (no pair of contype and conaffinity bits that
      match, no explicit pair, no flex): the collision pass would find nothing, and on myoElbow
      (whose geoms all have conaffinity 0) it was a fifth of every step. The same states, bit
      for bit.
    """
    private = copy.deepcopy(model)
    flags = (
        mujoco.mjtDisableBit.mjDSBL_WARMSTART
        | mujoco.mjtDisableBit.mjDSBL_AUTORESET
        | mujoco.mjtDisableBit.mjDSBL_SENSOR
    )
    if scenario in (Scenario.EXTERNAL, Scenario.DRIVEN):
        flags |= mujoco.mjtDisableBit.mjDSBL_ACTUATION
        private.tendon_num[_inert_tendons(private)] = 0
    if not _can_collide(private):
        flags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    private.opt.disableflags |= int(flags)
    return private


def _can_collide(model: mujoco.MjModel) -> bool:
    """Whether MuJoCo's collision pass could ever find a contact: an explicit pair, a flex, or two
    geoms whose contype and conaffinity share a bit (geoms of one body included: conservative)."""
    if model.npair or model.nflex:
        return True
    match = (model.geom_contype[:, None] & model.geom_conaffinity[None, :]) != 0
    np.fill_diagonal(match, False)
    return bool(match.any())


def _inert_tendons(model: mujoco.MjModel) -> np.ndarray:
    """(ntendon,) bool: tendons with no force of their own, which only actuators could use."""
    inert = (
        (model.tendon_stiffness == 0)
        & (model.tendon_damping == 0)
        & (model.tendon_frictionloss == 0)
        & (model.tendon_limited == 0)
        & (model.tendon_armature == 0)
    )
    for i in range(model.neq):
        if int(model.eq_type[i]) == int(mujoco.mjtEq.mjEQ_TENDON):
            inert[model.eq_obj1id[i]] = False
            if model.eq_obj2id[i] >= 0:
                inert[model.eq_obj2id[i]] = False
    return np.asarray(inert)


@dataclass(frozen=True)
class Propagated:
    """The sigma points after propagation; views into the propagator's buffers, valid until its
    next call.

    qpos (nsigma, nq), qvel (nsigma, nv), act (nsigma, na), qacc (nsigma, nv): the acceleration
    MuJoCo computed in the last physics step (None unless the propagator was asked for it).
    """

    qpos: np.ndarray
    qvel: np.ndarray
    act: np.ndarray
    qacc: np.ndarray | None


def _state_slices(model: mujoco.MjModel, spec: int = _FULL) -> dict[str, slice]:
    """Where each component (qpos, qvel, act, ...) sits in a state vector of `spec` (components
    are laid out in bit order)."""
    slices: dict[str, slice] = {}
    start = 0
    for bit in range(int(mujoco.mjtState.mjNSTATE)):
        component = 1 << bit
        if not component & spec:
            continue
        size = mujoco.mj_stateSize(model, component)
        slices[mujoco.mjtState(component).name.removeprefix("mjSTATE_").lower()] = slice(start, start + size)
        start += size
    return slices


def _full_columns(model: mujoco.MjModel) -> slice | np.ndarray:
    """The columns of an mjSTATE_INTEGRATION row that make up its mjSTATE_FULLPHYSICS vector: a
    slice when they are contiguous (no plugin state), which copies faster than an index array."""
    integration = _state_slices(model, _INTEGRATION)
    columns = np.concatenate(
        [np.arange(integration[name].start, integration[name].stop) for name in _state_slices(model)]
    ).astype(np.intp)
    if columns.size and np.array_equal(columns, np.arange(columns[0], columns[0] + columns.size)):
        return slice(int(columns[0]), int(columns[0]) + columns.size)
    return columns


def step_seconds(model: mujoco.MjModel, data: mujoco.MjData, *, steps: int = _PRICED_STEPS) -> float:
    """A price of one mj_step of `model` (s): the best of three runs of `steps` steps from its
    reference pose, in this thread's CPU time. Not the wall clock: estimators are built and
    sessions priced while other sessions tick, and every mj_step gives up the GIL, so a wall-clock
    price counted the waits to get it back (31 ms "per tick" for a 0.4 ms pendulum_3 cycle under
    load; an inflated price here split pendulum_3's 13 sigma points across two threads, a hand-off
    per predict). The best of three: a first run on a cold cache priced the biped's tick 1.7x its
    usual. `data` is left at the reference pose."""
    mujoco.mj_resetData(model, data)
    mujoco.mj_forward(model, data)
    best = float("inf")
    for _ in range(3):
        start = time.thread_time()
        for _ in range(steps):
            mujoco.mj_step(model, data)
        best = min(best, (time.thread_time() - start) / steps)
    mujoco.mj_resetData(model, data)
    return best


class _LastStep:
    """One worker's batch for the last physics step of its rows of a sigma set."""

    def __init__(self, model: mujoco.MjModel, nsigma: int) -> None:
        self._batch = mujoco.batch.Batch(model, nsim=nsigma, nthread=1)
        self._columns = _full_columns(model)
        self._ctrl = self._batch.bind("ctrl")
        self._qfrc = self._batch.bind("qfrc_applied")
        self._qacc = self._batch.bind("qacc")
        self._ids = np.arange(nsigma, dtype=np.int32)

    def step(
        self, before: np.ndarray, buffers: _Buffers, lo: int, hi: int, *, ctrl: np.ndarray, qfrc: np.ndarray
    ) -> None:
        """Rows [lo, hi) of `before` (nsigma, nstate) one step on; into buffers.final and .qacc."""
        state = self._batch.state
        state[lo:hi, self._columns] = before[lo:hi]
        self._ctrl[lo:hi] = ctrl
        self._qfrc[lo:hi] = qfrc
        self._batch.step(ids=self._ids[lo:hi], nstep=1)
        buffers.final[lo:hi] = state[lo:hi, self._columns]
        buffers.qacc[lo:hi] = self._qacc[lo:hi]


class _Buffers:
    """Preallocated arrays for one step count. `rolled`: the steps the rollout takes (all of them,
    or all but the last, which a batch then steps to read its qacc)."""

    def __init__(self, *, nsigma: int, nstep: int, rolled: int, nstate: int, ncontrol: int, nv: int) -> None:
        self.nstep = nstep
        self.rolled = rolled
        self.trajectory = np.zeros((nsigma, rolled, nstate)) if rolled else None
        self.control = np.zeros((nsigma, rolled, ncontrol)) if rolled and ncontrol else None
        if self.trajectory is not None and rolled == nstep:
            self.final = self.trajectory[:, -1, :]
        else:
            self.final = np.zeros((nsigma, nstate))
        self.qacc = np.zeros((nsigma, nv))


class Propagator:
    """Steps `nsigma` states `nstep` physics steps in one batched call on the shared pool.

    One per estimator: it owns one MjData per worker of the pool and every buffer, allocated here
    and reused. Call it from one thread at a time (an estimator is driven by one session).
    min_chunk_seconds: the least physics worth handing to another worker (0: split across every
    worker whatever the work, which the tests use to exercise the threads).
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        *,
        pool: WorkerPool,
        nsigma: int,
        nstep: int,
        inputs: Inputs,
        want_qacc: bool = False,
        min_chunk_seconds: float = MIN_CHUNK_SECONDS,
    ) -> None:
        if nsigma < 1:
            raise InvalidArgument(f"nsigma must be >= 1, got {nsigma}")
        if nstep < 1:
            raise InvalidArgument(f"nstep must be >= 1, got {nstep}")
        self._model = model
        self._pool = pool
        self._nsigma = nsigma
        self._nstep = nstep
        self._inputs = inputs
        self._want_qacc = want_qacc
        self._rollout = pool.backend is Backend.ROLLOUT
        self._data = [mujoco.MjData(model) for _ in range(pool.workers)]
        self._slices = _state_slices(model)
        self._nstate = mujoco.mj_stateSize(model, _FULL)
        self._ncontrol = mujoco.mj_stateSize(model, inputs.value) if inputs is not Inputs.NONE else 0
        # time = 0, and the history and plugin state of a fresh MjData, for every sigma point.
        template = np.zeros(self._nstate)
        mujoco.mj_getState(model, self._data[0], template, _FULL)
        self._initial = np.tile(template, (nsigma, 1))
        self._models = [model] * nsigma
        self._ctrl = np.zeros(model.nu)
        self._qfrc = np.zeros(model.nv)
        self._buffers = {nstep: self._new_buffers(nstep)}
        self._step_seconds = step_seconds(model, self._data[0])
        self._min_chunk_seconds = min_chunk_seconds
        # ROLLOUT and qacc wanted: per worker, a batch of the model on that worker's thread
        # (nthread=1 starts no thread of its own) takes the last step of its rows and reports the
        # qacc of it; see _run_rollout.
        self._batches = [_LastStep(model, nsigma) for _ in self._data] if self._rollout and want_qacc else []

    @property
    def nsigma(self) -> int:
        return self._nsigma

    @property
    def model(self) -> mujoco.MjModel:
        return self._model

    def _new_buffers(self, nstep: int) -> _Buffers:
        rolled = 0
        if self._rollout:
            rolled = nstep - 1 if self._want_qacc else nstep
        return _Buffers(
            nsigma=self._nsigma,
            nstep=nstep,
            rolled=rolled,
            nstate=self._nstate,
            ncontrol=self._ncontrol,
            nv=self._model.nv,
        )

    def _buffers_for(self, nstep: int) -> _Buffers:
        buffers = self._buffers.get(nstep)
        if buffers is None:
            # An extrapolation horizon or a glance a few ticks ahead: keep the tick's buffers and a
            # few other counts.
            if len(self._buffers) > _OTHER_COUNTS_KEPT:
                self._buffers = {self._nstep: self._buffers[self._nstep]}
            buffers = self._buffers[nstep] = self._new_buffers(nstep)
        return buffers

    def __call__(
        self,
        qpos: np.ndarray,
        qvel: np.ndarray,
        *,
        act: np.ndarray,
        ctrl: np.ndarray | None = None,
        qfrc: np.ndarray | None = None,
        qfrc_rate: np.ndarray | None = None,
        nstep: int | None = None,
    ) -> Propagated:
        """Step every sigma point.

        qpos (count, nq), qvel (count, nv), count <= nsigma; act (na,), the same for every point;
        ctrl (nu,) for Inputs.CTRL, qfrc (nv,) for Inputs.QFRC, held over all steps; or qfrc
        (count, nv), one force per point, and then optionally qfrc_rate (count, nv, per second):
        physics step s (from 0) of point i then acts with qfrc[i] + (s + 1/2) h qfrc_rate[i], the
        midpoint of a force that ramps (h: the timestep). nstep defaults to the propagator's own
        (buffers for another count are made on first use and kept). Returns (count, ...) views.
        """
        nstep = self._nstep if nstep is None else nstep
        if nstep < 1:
            raise InvalidArgument(f"nstep must be >= 1, got {nstep}")
        count = qpos.shape[0]
        if not 1 <= count <= self._nsigma:
            raise InvalidArgument(f"qpos must have 1 to {self._nsigma} rows, got {count}")
        buffers = self._buffers_for(nstep)
        # Only as many workers as the work is worth (server/estimation/pool.py, MIN_CHUNK_SECONDS).
        work = count * nstep * self._step_seconds
        chunks = int(work / self._min_chunk_seconds) if self._min_chunk_seconds > 0 else count
        s = self._slices
        self._initial[:count, s["qpos"]] = qpos
        self._initial[:count, s["qvel"]] = qvel
        self._initial[:count, s["act"]] = act
        self._ctrl[:] = ctrl if self._inputs is Inputs.CTRL and ctrl is not None else 0.0
        rows: np.ndarray | None = None
        if self._inputs is Inputs.QFRC and qfrc is not None and np.ndim(qfrc) == 2:
            rows = self._row_forces(np.asarray(qfrc), qfrc_rate, count, nstep)
            self._qfrc[:] = 0.0
        else:
            self._qfrc[:] = qfrc if self._inputs is Inputs.QFRC and qfrc is not None else 0.0
        if rows is not None and not self._rollout:
            self._pool.run_chunks(
                lambda worker, lo, hi: self._run_rows(buffers, rows, worker, lo, hi), count, chunks=chunks
            )
        elif self._rollout:
            self._run_rollout(buffers, count, chunks, rows=rows)
        else:
            self._pool.run_chunks(
                lambda worker, lo, hi: self._run_chunk(buffers, worker, lo, hi), count, chunks=chunks
            )
        final = buffers.final[:count]
        return Propagated(
            qpos=final[:, s["qpos"]],
            qvel=final[:, s["qvel"]],
            act=final[:, s["act"]],
            qacc=buffers.qacc[:count] if self._want_qacc else None,
        )

    def _row_forces(self, qfrc: np.ndarray, rate: np.ndarray | None, count: int, nstep: int) -> np.ndarray:
        """(count, nstep, nv): the force of every point at every physics step."""
        nv = self._model.nv
        if qfrc.shape != (count, nv):
            raise InvalidArgument(f"qfrc must have shape ({count}, {nv}) or ({nv},), got {qfrc.shape}")
        forces = np.repeat(qfrc[:, None, :], nstep, axis=1)
        if rate is not None:
            if rate.shape != (count, nv):
                raise InvalidArgument(f"qfrc_rate must have shape ({count}, {nv}), got {rate.shape}")
            h = float(self._model.opt.timestep)
            forces += ((np.arange(nstep) + 0.5) * h)[None, :, None] * rate[:, None, :]
        return forces

    def _run_rows(self, buffers: _Buffers, forces: np.ndarray, worker: int, lo: int, hi: int) -> None:
        """Per-point forces (DRIVEN): one worker's rows on its MjData, step by step when the force
        ramps. mj_step releases the GIL, so workers run in parallel."""
        m, d = self._model, self._data[worker]
        d.ctrl[:] = 0.0
        initial, final, nstep = self._initial, buffers.final, buffers.nstep
        constant = bool(np.all(forces[:, :1] == forces))
        for i in range(lo, hi):
            mujoco.mj_setState(m, d, initial[i], _FULL)
            if constant:
                d.qfrc_applied[:] = forces[i, 0]
                mujoco.mj_step(m, d, nstep)
            else:
                for s in range(nstep):
                    d.qfrc_applied[:] = forces[i, s]
                    mujoco.mj_step(m, d)
            mujoco.mj_getState(m, d, final[i], _FULL)

    def _run_chunk(self, buffers: _Buffers, worker: int, lo: int, hi: int) -> None:
        """THREADS back-end: one worker's share, on its own MjData (mj_step releases the GIL)."""
        m, d = self._model, self._data[worker]
        # Inputs are not changed by mj_step: set them once per chunk (rollout sets them every step,
        # to the same values).
        d.ctrl[:] = self._ctrl
        d.qfrc_applied[:] = self._qfrc
        initial, final, qacc, nstep = self._initial, buffers.final, buffers.qacc, buffers.nstep
        for i in range(lo, hi):
            mujoco.mj_setState(m, d, initial[i], _FULL)
            mujoco.mj_step(m, d, nstep)
            mujoco.mj_getState(m, d, final[i], _FULL)
            if self._want_qacc:
                qacc[i] = d.qacc

    def _run_rollout(
        self, buffers: _Buffers, count: int, chunks: int, *, rows: np.ndarray | None = None
    ) -> None:
        """ROLLOUT back-end: each worker's rows in one call into C++ (server/estimation/pool.py).
        rows (count, nstep, nv): per-point, per-step forces (DRIVEN), else the held inputs."""
        control = buffers.control
        if control is not None:
            if rows is not None:
                if self._want_qacc:
                    raise InvalidArgument("per-point forces cannot be combined with want_qacc")
                control[:count] = rows
            else:
                control[:count] = self._ctrl if self._inputs is Inputs.CTRL else self._qfrc
        trajectory = buffers.trajectory
        then = None
        if self._want_qacc:
            # A rollout returns states, not accelerations; and the qacc MuJoCo leaves after a step
            # depends on the integrator (Euler: the one at the state before the step; RK4: its
            # last stage's). So each worker takes the last step of its rows with a batch, which
            # reports it as mj_step does.
            before = trajectory[:, -1, :] if trajectory is not None else self._initial

            def then(worker: int, lo: int, hi: int) -> None:
                self._batches[worker].step(before, buffers, lo, hi, ctrl=self._ctrl, qfrc=self._qfrc)

        # Leading rows of C-contiguous buffers are C-contiguous: the unchecked call accepts them.
        self._pool.rollout(
            self._models[:count],
            self._data,
            nstep=buffers.rolled,
            control_spec=self._inputs.value,
            initial_state=self._initial[:count],
            control=None if control is None else control[:count],
            state=None if trajectory is None else trajectory[:count],
            chunks=chunks,
            then=then,
        )
