"""filterpy's UnscentedKalmanFilter with its two per-point Python loops over the state replaced:
the process model runs on the whole sigma set at once (estimation/propagate.py), and the
cross-covariance is one matrix product. The maths is filterpy's, unchanged (tests/server/test_ukf.py
runs both side by side)::

    kf = BatchedUKF(propagate=propagate, vector=True, dim_x=4, dim_z=4, dt=0.05, hx=hx, fx=None,
                    points=points)
    kf.predict(UT=unscented_transform)
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np
from filterpy.kalman import UnscentedKalmanFilter

__all__ = ["BatchedUKF", "SigmaPropagation", "tangent_unscented_transform"]


class SigmaPropagation(Protocol):
    """The process model over a whole sigma set: (nsigma, len x) -> (nsigma, len x); nstep physics
    steps, None for a tick's."""

    def __call__(self, sigmas: np.ndarray, *, nstep: int | None) -> np.ndarray: ...


class BatchedUKF(UnscentedKalmanFilter):  # type: ignore[misc]
    """filterpy's filter, its process model `propagate` called once per sigma set; vector: the state
    is a plain vector (no ball or free joints), whose residuals are differences."""

    def __init__(self, *, propagate: SigmaPropagation, vector: bool, **kwargs: object) -> None:
        super().__init__(**kwargs)
        self._propagate = propagate
        self._vector = vector

    def compute_process_sigmas(self, dt: float, fx: object = None, **fx_args: object) -> None:
        sigmas = self.points_fn.sigma_points(self.x, self.P)
        self.sigmas_f = self._propagate(sigmas, nstep=None)

    def cross_variance(
        self, x: np.ndarray, z: np.ndarray, sigmas_f: np.ndarray, sigmas_h: np.ndarray
    ) -> np.ndarray:
        if self._vector:
            dx = sigmas_f - x
            dz = sigmas_h - z
        else:
            dx = self.residual_x(sigmas_f, x)
            dz = self.residual_z(sigmas_h, z)
        return np.asarray(dx.T @ (self.Wc[:, None] * dz))


def tangent_unscented_transform(
    sigmas: np.ndarray,
    Wm: np.ndarray,
    Wc: np.ndarray,
    noise_cov: np.ndarray | None,
    mean_fn: Callable[[np.ndarray, np.ndarray], np.ndarray],
    residual_fn: Callable[[np.ndarray, np.ndarray], np.ndarray],
) -> tuple[np.ndarray, np.ndarray]:
    """filterpy's unscented transform for points on a manifold: points (nsigma, dim) give a mean
    (dim,) but a covariance in the tangent space (n, n), which filterpy's own cannot shape."""
    mean = mean_fn(sigmas, Wm)
    spread = residual_fn(sigmas, mean)
    P = spread.T @ (Wc[:, None] * spread)
    if noise_cov is not None:
        P = P + noise_cov
    return mean, P
