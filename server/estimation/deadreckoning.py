"""The dead-reckoning extrapolators of distributed interactive simulation (IEEE 1278.1), behind the
same `Estimator` protocol as the UKF, as baselines for the experiments.

Each frame re-anchors the extrapolation; ticks without one extrapolate from the anchor over the
time since it, in generalized coordinates (quaternions of ball and free joints move by
mj_integratePos):

- STATIC: the last measured state is held (q, qd and qdd as measured).
- CONSTANT_VELOCITY and CONSTANT_ACCELERATION: as estimation/extrapolators.py moves q and qd.

Channels a client does not measure come from the last two frames as DIS does: qd0 from the
difference of positions, qdd0 from the difference of velocities, over the time between the frames
(zero until there are two). No covariance, no NIS, no divergence guard: nothing can diverge.

Unlike DIS's entities, the server's joints have ranges: an extrapolation stops a limited hinge or
slide joint at its range, where it then rests (qd and qdd 0), and never carries one further out than
its frame had it (docs/decisions/0215-dead-reckoning-within-the-joints-ranges.md).

    estimator = DeadReckoning(model, config)          # config.estimator = "CONSTANT_VELOCITY"
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from jitdyn.errors import FailedPrecondition, InvalidArgument
from jitdyn.server.estimation.config import EstimatorConfig, check_against_model
from jitdyn.server.estimation.extrapolators import mean_velocity, velocity
from jitdyn.server.estimation.interface import Estimate, Measurement, check_measurement, read_only
from jitdyn.server.estimation.layout import derivative_order
from jitdyn.vocabulary import EstimatorKind

__all__ = ["DeadReckoning"]


@dataclass(frozen=True)
class _Anchor:
    """The state a frame fixed (read-only arrays): qpos (nq,), qvel (nv,), qacc (nv,)."""

    qpos: np.ndarray
    qvel: np.ndarray
    qacc: np.ndarray


def _ranges(model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The limited hinge and slide joints: their qpos addresses (k,), dof addresses (k,), and lower
    and upper bounds (k,) (rad or m)."""
    scalar = np.isin(model.jnt_type, [int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)])
    limited = scalar & model.jnt_limited.astype(bool)
    low, high = model.jnt_range[limited].T
    return model.jnt_qposadr[limited].copy(), model.jnt_dofadr[limited].copy(), low.copy(), high.copy()


@dataclass(frozen=True)
class _Snapshot:
    owner: int
    anchor: _Anchor | None
    elapsed: int  # ticks since the anchor


class DeadReckoning:
    """An IEEE 1278 extrapolator (see the module docstring). Implements `Estimator`."""

    def __init__(self, model: mujoco.MjModel, config: EstimatorConfig) -> None:
        if config.estimator in (EstimatorKind.UKF, EstimatorKind.EKF):
            raise InvalidArgument(
                f"config.estimator must be a dead-reckoning estimator, got {config.estimator}"
            )
        check_against_model(model, config)
        self._model = model
        self._config = config
        self._kind = EstimatorKind(config.estimator)
        self._order = derivative_order(config.scenario)
        self._nq, self._nv = int(model.nq), int(model.nv)
        self._qadr, self._dadr, self._low, self._high = _ranges(model)
        self._anchor: _Anchor | None = None
        self._elapsed = 0

    @property
    def config(self) -> EstimatorConfig:
        return self._config

    @property
    def state_dimension(self) -> int:
        return self._order * self._nv

    @property
    def state_size(self) -> int:
        return self._nq + (self._order - 1) * self._nv

    def initialise(self, m: Measurement) -> None:
        m = check_measurement(m, self._model, self._config.measured)
        zeros = read_only(np.zeros(self._nv))
        self._anchor = _Anchor(
            qpos=m.qpos,
            qvel=m.qvel if m.qvel is not None else zeros,
            qacc=m.qacc if m.qacc is not None else zeros,
        )
        self._elapsed = 0

    def predict(self, *, ctrl: np.ndarray | None) -> Estimate:
        anchor = self._require_anchor("predict")
        self._elapsed += 1
        return self._at(anchor, self._elapsed * self._config.dt)

    def advance(self, *, ctrl: np.ndarray | None) -> None:
        self._require_anchor("advance")
        self._elapsed += 1

    def step(self, *, ctrl: np.ndarray | None, m: Measurement) -> Estimate:
        self.advance(ctrl=ctrl)
        return self.update(m)

    def update(self, m: Measurement) -> Estimate:
        anchor = self._require_anchor("update")
        m = check_measurement(m, self._model, self._config.measured)
        gap = self._elapsed * self._config.dt
        if m.qvel is not None:
            qvel = m.qvel
        elif gap > 0.0:
            qvel = np.empty(self._nv)
            mujoco.mj_differentiatePos(self._model, qvel, gap, anchor.qpos, m.qpos)
            qvel = read_only(qvel)
        else:
            qvel = anchor.qvel
        if m.qacc is not None:
            qacc = m.qacc
        elif gap > 0.0:
            qacc = read_only((qvel - anchor.qvel) / gap)
        else:
            qacc = anchor.qacc
        self._anchor = _Anchor(qpos=m.qpos, qvel=qvel, qacc=qacc)
        self._elapsed = 0
        return self._at(self._anchor, 0.0)

    def extrapolate(self, seconds: float) -> Estimate:
        anchor = self._require_anchor("extrapolate")
        if (
            isinstance(seconds, bool)
            or not isinstance(seconds, (int, float))
            or not 0.0 <= seconds < float("inf")
        ):
            raise InvalidArgument(f"seconds must be finite and >= 0, got {seconds!r}")
        return self._at(anchor, self._elapsed * self._config.dt + seconds)

    def glance(self, seconds: float) -> Estimate:
        return self.extrapolate(seconds)  # already a closed form

    def snapshot(self) -> _Snapshot:
        return _Snapshot(owner=id(self), anchor=self._anchor, elapsed=self._elapsed)

    def restore(self, snap: object) -> None:
        if not isinstance(snap, _Snapshot) or snap.owner != id(self):
            raise InvalidArgument(f"snap must be a snapshot of this estimator, got {type(snap).__name__}")
        self._anchor = snap.anchor
        self._elapsed = snap.elapsed

    def _require_anchor(self, what: str) -> _Anchor:
        if self._anchor is None:
            raise FailedPrecondition(
                f"{what} needs an initialised estimator: call initialise() with the first frame"
            )
        return self._anchor

    def _at(self, anchor: _Anchor, t: float) -> Estimate:
        """The extrapolation t seconds after the anchor."""
        qpos = anchor.qpos.copy()
        kind = self._kind
        # STATIC reports the qdd measured (the state held as it came); CONSTANT_VELOCITY none.
        qacc = np.zeros(self._nv) if kind == EstimatorKind.CONSTANT_VELOCITY else anchor.qacc
        if kind == EstimatorKind.STATIC or t == 0.0:
            qvel = anchor.qvel
        else:
            mujoco.mj_integratePos(self._model, qpos, mean_velocity(kind, anchor.qvel, anchor.qacc, t), t)
            qvel = velocity(kind, anchor.qvel, anchor.qacc, t)
            qacc = self._within_ranges(anchor, qpos, qvel, qacc)
        parts = [qpos, qvel] + ([qacc] if self._order == 3 else [])
        return Estimate(
            qpos=read_only(qpos),
            qvel=read_only(qvel),
            qacc=read_only(qacc),
            state=read_only(np.concatenate(parts)),
            covariance=None,
            nis=None,
            reinitialised=False,
        )

    def _within_ranges(
        self, anchor: _Anchor, qpos: np.ndarray, qvel: np.ndarray, qacc: np.ndarray
    ) -> np.ndarray:
        """Stops the limited joints of an extrapolation (qpos (nq,), qvel (nv,), in place) at their
        range, or at the frame's own position where that was already outside it, with qvel and the
        returned qacc (nv,) 0 there: the joint rests against its limit."""
        q0 = anchor.qpos[self._qadr]
        low, high = np.minimum(self._low, q0), np.maximum(self._high, q0)
        moved = qpos[self._qadr]
        stopped = (moved < low) | (moved > high)
        if not stopped.any():
            return qacc
        qpos[self._qadr] = np.clip(moved, low, high)
        dofs = self._dadr[stopped]
        qvel[dofs] = 0.0
        qacc = qacc.copy()
        qacc[dofs] = 0.0
        return qacc
