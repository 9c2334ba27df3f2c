"""The unscented filter's algebra as a few array operations over the whole sigma set: the engine
of the JITDYN preset (filterpy's UnscentedKalmanFilter, through estimation/batched.py, stays the
THESIS preset's and the reference this one is tested against, tests/server/test_fast.py).

    kf = FastUKF(propagate=propagate, vector=True, dim_x=4, dim_z=4, dt=0.05, hx=hx, fx=None,
                 points=points, z_index=slice(0, 4))
    kf.predict(UT=unscented_transform)
    kf.update(z)

Same maths, same order of floating-point operations as filterpy's predict and update for plain
vector states, so the two agree bit for bit there; what goes is the bookkeeping around it:
- the sigma points that filterpy redraws at the end of every predict for the update are drawn
  when the update (or a reader of `sigmas_f`) asks for them, from the same (x, P): a tick without
  a frame (a gap) no longer pays a Cholesky factorisation for points nobody uses;
- the measurement of every point is one slice of the sigma set (hx picks entries of x), not a
  Python call per point; no deepcopy of z, no x_prior / P_prior / x_post / P_post copies (nothing
  reads them).
States on a manifold (ball and free joints) take their mean and residuals from estimation/manifold.py.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from jitdyn.server.estimation.batched import BatchedUKF, SigmaPropagation

__all__ = ["FastUKF"]


class FastUKF(BatchedUKF):
    """filterpy's UKF with predict and update as array operations (module docstring). z_index
    picks the measured entries of x (a slice, or an index array)."""

    x: np.ndarray
    P: np.ndarray

    def __init__(
        self,
        *,
        propagate: SigmaPropagation,
        vector: bool,
        z_index: slice | np.ndarray,
        **kwargs: Any,
    ) -> None:
        self._drawn: tuple[np.ndarray, np.ndarray] | None = None
        self._sigmas: np.ndarray = np.zeros(0)
        super().__init__(propagate=propagate, vector=vector, **kwargs)
        self._z_index = z_index

    # filterpy's predict ends by drawing the update's points from the prior; they are drawn from
    # that same (x, P) when first read.
    @property
    def sigmas_f(self) -> np.ndarray:
        if self._drawn is not None:
            x, P = self._drawn
            self._drawn = None
            self._sigmas = self.points_fn.sigma_points(x, P)
        return self._sigmas

    @sigmas_f.setter
    def sigmas_f(self, value: np.ndarray) -> None:
        self._drawn = None
        self._sigmas = value

    def predict(self, dt: object = None, UT: Any = None, fx: object = None, **fx_args: object) -> None:
        """x, P <- the unscented transform of the propagated sigma points of (x, P), plus Q."""
        sigmas = self.points_fn.sigma_points(self.x, self.P)
        moved = self._propagate(sigmas, nstep=None)
        if self._vector:
            x = np.dot(self.Wm, moved)
            y = moved - x[np.newaxis, :]
            # filterpy's y.T diag(Wc) y, its products in its order: diag(Wc) @ y is Wc[:, None] * y
            # exactly (every other term is a product with 0.0).
            P = np.dot(y.T, self.Wc[:, None] * y)
            P += self.Q
        else:
            x, P = UT(moved, self.Wm, self.Wc, self.Q, self.x_mean, self.residual_x)
        self.x, self.P = x, P
        self._drawn = (x, P)

    def update(
        self, z: np.ndarray, R: object = None, UT: Any = None, hx: object = None, **hx_args: object
    ) -> None:
        """The unscented update with measurement z (dim_z entries of x, on the manifold if any)."""
        sigmas_f = self.sigmas_f
        sigmas_h = np.ascontiguousarray(sigmas_f[:, self._z_index])  # as filterpy builds it: same sums
        Wm, Wc = self.Wm, self.Wc
        if self._vector:
            zp = np.dot(Wm, sigmas_h)
            dz = sigmas_h - zp[np.newaxis, :]
            weighted = Wc[:, None] * dz
            S = np.dot(dz.T, weighted)
            S += self.R
            dx = sigmas_f - self.x
        else:
            # estimation/batched.py's tangent_unscented_transform, its residuals kept for Pxz.
            zp = self.z_mean(sigmas_h, Wm)
            dz = self.residual_z(sigmas_h, zp)
            weighted = Wc[:, None] * dz
            S = dz.T @ weighted + self.R
            dx = self.residual_x(sigmas_f, self.x)
        self.sigmas_h = sigmas_h
        self.S = S
        self.SI = self.inv(S)
        Pxz = dx.T @ weighted
        self.K = np.dot(Pxz, self.SI)
        self.y = self.residual_z(z, zp)
        self.x = self.state_add(self.x, np.dot(self.K, self.y))
        self.P = self.P - np.dot(self.K, np.dot(S, self.K.T))
        self.z = np.array(z)
