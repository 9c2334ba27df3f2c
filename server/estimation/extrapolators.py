"""IEEE 1278.1's dead-reckoning extrapolators (DIS's DRM F/R), written once: how each moves a state
(q0, qd0, qdd0) by t seconds. Every user of them calls these: the DeadReckoning estimator
(estimation/deadreckoning.py, which moves quaternions of ball and free joints by mj_integratePos
with `mean_velocity`), the forecast combination's predictors (estimation/forecast.py), motion
matching's fallback (estimation/matching.py), the experiments' reference (experiments/metrics.py)
and benchmarks/learned.py::

    q, qd, qdd = extrapolate(EstimatorKind.CONSTANT_ACCELERATION, q0, qd0, qdd0, t)   # flat coordinates

- STATIC: q and qd held (q(t) = q0, qd = qd0), qdd = 0.
- CONSTANT_VELOCITY: q(t) = q0 + qd0 t; qd = qd0; qdd = 0.
- CONSTANT_ACCELERATION: q(t) = q0 + (qd0 + qdd0 t / 2) t; qd = qd0 + qdd0 t; qdd = qdd0.

Arrays broadcast: t a scalar, or a column (S, 1) against rows of states (S, nv).
"""

from __future__ import annotations

import numpy as np

from jitdyn.vocabulary import EstimatorKind

__all__ = ["EXTRAPOLATORS", "extrapolate", "mean_velocity", "moved", "velocity"]

# The extrapolators, in the forecast combination's order after MODEL.
EXTRAPOLATORS = (EstimatorKind.STATIC, EstimatorKind.CONSTANT_VELOCITY, EstimatorKind.CONSTANT_ACCELERATION)


def _accelerating(qd0: np.ndarray, qdd0: np.ndarray, t: float | np.ndarray) -> np.ndarray:
    """CONSTANT_ACCELERATION's mean velocity over t: qd0 + qdd0 t / 2."""
    return qd0 + 0.5 * t * qdd0


def _check(kind: EstimatorKind) -> None:
    if kind not in EXTRAPOLATORS:
        raise ValueError(f"kind must be a dead-reckoning estimator (IEEE 1278.1, DRM F/R), got {kind!r}")


def mean_velocity(
    kind: EstimatorKind, qd0: np.ndarray, qdd0: np.ndarray, t: float | np.ndarray
) -> np.ndarray:
    """The velocity that, held over t, moves q as `kind` does (mj_integratePos takes it for the
    joints that are not flat): 0, qd0, or qd0 + qdd0 t / 2."""
    _check(kind)
    if kind == EstimatorKind.STATIC:
        return np.zeros(np.broadcast_shapes(np.shape(qd0), np.shape(t)))
    if kind == EstimatorKind.CONSTANT_VELOCITY:
        return np.asarray(qd0)
    return np.asarray(_accelerating(qd0, qdd0, t))


def velocity(kind: EstimatorKind, qd0: np.ndarray, qdd0: np.ndarray, t: float | np.ndarray) -> np.ndarray:
    """qd at t: qd0, or qd0 + qdd0 t (CONSTANT_ACCELERATION)."""
    _check(kind)
    if kind == EstimatorKind.CONSTANT_ACCELERATION:
        return np.asarray(qd0 + qdd0 * t)
    return np.broadcast_to(qd0, np.broadcast_shapes(np.shape(qd0), np.shape(t))).copy()


def moved(
    q0: np.ndarray, qd0: np.ndarray, qdd0: np.ndarray, t: float | np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(q, qd, qdd) of every extrapolator, in EXTRAPOLATORS' order on a new axis before the last
    ((..., 3, nv)), in flat coordinates: one pass for the forecast's scoring of every probe."""
    shape = np.broadcast_shapes(np.shape(q0), np.shape(t))
    q, qd, qdd = np.empty((3, *shape[:-1], 3, shape[-1]))
    q[..., 0, :] = q0
    q[..., 1, :] = q0 + qd0 * t
    q[..., 2, :] = q0 + _accelerating(qd0, qdd0, t) * t
    qd[..., 0, :] = qd[..., 1, :] = qd0
    qd[..., 2, :] = qd0 + qdd0 * t
    qdd[..., :2, :] = 0.0
    qdd[..., 2, :] = qdd0
    return q, qd, qdd


def extrapolate(
    kind: EstimatorKind, q0: np.ndarray, qd0: np.ndarray, qdd0: np.ndarray, t: float | np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(q, qd, qdd) t seconds on from (q0, qd0, qdd0), in flat coordinates (hinge and slide joints)."""
    _check(kind)
    k = EXTRAPOLATORS.index(kind)
    q, qd, qdd = moved(q0, qd0, qdd0, t)
    return q[..., k, :].copy(), qd[..., k, :].copy(), qdd[..., k, :].copy()
