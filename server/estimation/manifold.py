"""States of models with ball or free joints (nq != nv), which are not vectors.

A filter state [qpos (nq), rest (k)] (rest: qvel, and qacc in CONTROLLED) lives on a manifold with
tangent vectors [dq (nv), drest (k)]. MuJoCo's mj_integratePos and mj_differentiatePos are its
addition and subtraction; the mean of sigma points is found in the tangent space of a reference
point and iterated (a Karcher mean, which needs no positive weights). The covariance is nv-based
throughout: what filterpy calls dim_x is the tangent dimension. Measurements [qpos, ...] have the
same structure.

    split = SplitManifold(model, rest=model.nv)      # x = [qpos, qvel]
    sigmas = split.add(x, deltas)                    # (m, nq + nv) from (m, 2 nv)
"""

from __future__ import annotations

from typing import Final

import mujoco
import numpy as np

__all__ = ["SplitManifold", "has_manifold"]

# The Karcher mean stops when its tangent step is this small (radians, metres), or after
# _MEAN_ITERATIONS: sigma points are close together, two or three iterations converge.
_MEAN_TOLERANCE: Final = 1e-12
_MEAN_ITERATIONS: Final = 20


def has_manifold(model: mujoco.MjModel) -> bool:
    """Whether the model has ball or free joints, whose positions are quaternions."""
    return bool(model.nq != model.nv)


class SplitManifold:
    """[qpos (nq) | vector (rest)] with tangent [nv | rest]. Every operation is batched over
    leading rows and returns new arrays.
    """

    def __init__(self, model: mujoco.MjModel, *, rest: int) -> None:
        self._model = model
        self.nq = model.nq
        self.nv = model.nv
        self.rest = rest
        self.dim = model.nq + rest  # a point
        self.tangent_dim = model.nv + rest  # a tangent vector

    def add(self, x: np.ndarray, dx: np.ndarray) -> np.ndarray:
        """x (dim,) or (m, dim), dx (tangent_dim,) or (m, tangent_dim): x moved along dx."""
        x2, dx2 = np.atleast_2d(x), np.atleast_2d(dx)
        rows = max(x2.shape[0], dx2.shape[0])
        out = np.empty((rows, self.dim))
        out[:] = x2
        out[:, self.nq :] += dx2[:, self.nv :]
        for i in range(rows):
            qpos = out[i, : self.nq]
            # mj_integratePos works in place and renormalises the quaternions.
            mujoco.mj_integratePos(self._model, qpos, dx2[i if dx2.shape[0] > 1 else 0, : self.nv], 1.0)
        return out if (x.ndim == 2 or dx.ndim == 2) else np.asarray(out[0])

    def residual(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """a ⊖ b: the tangent vector that takes b to a. a, b (dim,) or (m, dim)."""
        a2, b2 = np.atleast_2d(a), np.atleast_2d(b)
        rows = max(a2.shape[0], b2.shape[0])
        out = np.empty((rows, self.tangent_dim))
        out[:, self.nv :] = a2[:, self.nq :] - b2[:, self.nq :]
        for i in range(rows):
            mujoco.mj_differentiatePos(
                self._model,
                out[i, : self.nv],
                1.0,
                b2[i if b2.shape[0] > 1 else 0, : self.nq],
                a2[i if a2.shape[0] > 1 else 0, : self.nq],
            )
        return out if (a.ndim == 2 or b.ndim == 2) else np.asarray(out[0])

    def mean(self, points: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """The weighted mean of points (m, dim) with weights (m,) summing to 1 -> (dim,).

        Starts from the point of largest weight (Merwe's centre point, when there is one).
        """
        mean = points[int(np.argmax(weights))].copy()
        mean[self.nq :] = weights @ points[:, self.nq :]
        for _ in range(_MEAN_ITERATIONS):
            step = weights @ self.residual(points, mean)[:, : self.nv]
            mujoco.mj_integratePos(self._model, mean[: self.nq], step, 1.0)
            if float(np.max(np.abs(step), initial=0.0)) < _MEAN_TOLERANCE:
                break
        return np.asarray(mean)
