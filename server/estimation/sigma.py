"""Sigma-point schemes for jitdyn's unscented filter, in the shape filterpy's UKF expects
(`num_sigmas()`, `Wm`, `Wc`, `sigma_points(x, P)`), plus what filterpy's own lack:

- a square root that survives an indefinite covariance (`RobustCholesky`),
- a state that is not a vector (`add`: ball and free joints move on their manifold, server/estimation/manifold.py),
- a simplex whose unit points are computed once, not rebuilt on every call (filterpy's
  SimplexSigmaPoints grows its matrix row by row in Python each time: ~1 ms at n = 46).

`MerweScaled` reproduces filterpy's MerweScaledSigmaPoints bit for bit (tests/server/test_ukf.py),
and `Simplex` with alpha = 1 its SimplexSigmaPoints.

    points = make_sigma_points(SigmaScheme.MERWE, n=6, alpha=1.0, beta=2.0, kappa=0.0)
    sigmas = points.sigma_points(x, P)                       # (13, 6)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Final, Protocol

import numpy as np
from scipy.linalg.lapack import dpotrf

from jitdyn.errors import InvalidArgument
from jitdyn.vocabulary import SigmaScheme

__all__ = [
    "SCHEMES",
    "Add",
    "MerweScaled",
    "RobustCholesky",
    "SigmaPoints",
    "Simplex",
    "UniformSpherical",
    "cholesky_upper",
    "make_sigma_points",
    "nearest_positive_definite",
    "sigma_count",
]

# The schemes this module builds; SIMPLEX_LINEAR_FORCE is SIMPLEX over part of the state.
SCHEMES: Final = (SigmaScheme.MERWE, SigmaScheme.SIMPLEX, SigmaScheme.UNIFORM)

# x (nx,), dx (m, n) tangent steps -> (m, nx). Plain vector states use `_vector_add`.
Add = Callable[[np.ndarray, np.ndarray], np.ndarray]

# Eigenvalues of a repaired covariance are at least this fraction of the largest one: enough for a
# Cholesky factor, small enough not to inflate a well-conditioned matrix.
_EIGEN_FLOOR: Final = 1e-12


def _vector_add(x: np.ndarray, dx: np.ndarray) -> np.ndarray:
    # x - (-dx) is x + dx exactly in IEEE arithmetic; written as filterpy writes it so that the
    # points are bit-identical to its own.
    return np.asarray(x - (-dx))


class SigmaPoints(Protocol):
    """What filterpy's UnscentedKalmanFilter needs from a scheme."""

    n: int
    Wm: np.ndarray
    Wc: np.ndarray

    def num_sigmas(self) -> int: ...

    def sigma_points(self, x: np.ndarray, P: np.ndarray) -> np.ndarray: ...


def cholesky_upper(A: np.ndarray) -> np.ndarray | None:
    """U with U.T @ U = A, or None when A is not positive definite.

    LAPACK's potrf as scipy.linalg.cholesky calls it (so the factor is the same, bit for bit),
    without that function's per-call checks, which cost 5x the factorisation at these sizes.
    """
    factor, info = dpotrf(A, lower=0, clean=1, overwrite_a=0)
    return np.asarray(factor) if info == 0 else None


def nearest_positive_definite(P: np.ndarray) -> np.ndarray:
    """The symmetric positive definite matrix nearest to P in the Frobenius norm, up to the floor:
    symmetrise, then clip the eigenvalues to at least `_EIGEN_FLOOR` times the largest.

    P (n, n) finite; returns a new (n, n) array.
    """
    S = 0.5 * (P + P.T)
    eigenvalues, vectors = np.linalg.eigh(S)
    top = float(np.max(np.abs(eigenvalues))) if eigenvalues.size else 0.0
    floor = max(top * _EIGEN_FLOOR, np.finfo(float).tiny)
    clipped = np.maximum(eigenvalues, floor)
    R = (vectors * clipped) @ vectors.T
    return np.asarray(0.5 * (R + R.T))


class RobustCholesky:
    """Upper Cholesky factor U (U.T @ U = A) as scipy gives it; an A that is not positive definite
    is first repaired with `nearest_positive_definite`, and counted in `repairs`.

    A non-finite A gives a factor of NaN rather than an exception: the sigma points become NaN and
    the filter's divergence guard re-initialises, instead of the session dying mid-tick.
    """

    def __init__(self) -> None:
        self.repairs = 0
        self.last_repaired = False  # whether the latest call had to repair its matrix

    def __call__(self, A: np.ndarray) -> np.ndarray:
        self.last_repaired = False
        if not np.isfinite(A).all():
            return np.full_like(A, np.nan)
        factor = cholesky_upper(A)
        if factor is not None:
            return factor
        self.repairs += 1
        self.last_repaired = True
        factor = cholesky_upper(nearest_positive_definite(A))
        # The eigenvalue floor makes the repaired matrix factorisable; NaN only if it still is not.
        return factor if factor is not None else np.full_like(A, np.nan)


class MerweScaled:
    """Van der Merwe's scaled sigma points: 2n + 1 points, as in the thesis and filterpy.

    With lambda = alpha^2 (n + kappa) - n, the points are x and x +- the rows of
    sqrt((n + lambda) P); Wm0 = lambda / (n + lambda), Wc0 = Wm0 + 1 - alpha^2 + beta, and every
    other weight is 1 / (2 (n + lambda)). n + kappa must be positive.

    The weights explain why the thesis' alpha = 0.001, kappa = 3 - n fails for large n:
    n + lambda = 3e-6, so Wm0 = 1 - n / 3e-6 ~ -1.5e7 at n = 46 and the other weights ~ +1.7e5. The
    mean and covariance are then differences of terms 1e7 times larger than themselves, and the
    centre point's covariance term, Wc0 times the square of the (second-order) gap between the
    propagated centre and the mean, is hugely negative: the covariance comes out indefinite.
    """

    def __init__(
        self,
        n: int,
        *,
        alpha: float,
        beta: float,
        kappa: float,
        sqrt: Callable[[np.ndarray], np.ndarray] | None = None,
        add: Add | None = None,
    ) -> None:
        if n + kappa <= 0:
            raise InvalidArgument(f"kappa must make n + kappa > 0 (n = {n}), got kappa = {kappa}")
        self.n = n
        self.alpha, self.beta, self.kappa = alpha, beta, kappa
        self.sqrt = sqrt if sqrt is not None else RobustCholesky()
        self.add = add if add is not None else _vector_add
        lambda_ = alpha**2 * (n + kappa) - n
        self._scale = lambda_ + n
        # Computed exactly as filterpy computes them, so that the reference check is bit-exact.
        c = 0.5 / (n + lambda_)
        self.Wc = np.full(2 * n + 1, c)
        self.Wm = np.full(2 * n + 1, c)
        self.Wc[0] = lambda_ / (n + lambda_) + (1 - alpha**2 + beta)
        self.Wm[0] = lambda_ / (n + lambda_)

    def num_sigmas(self) -> int:
        return 2 * self.n + 1

    def sigma_points(self, x: np.ndarray, P: np.ndarray) -> np.ndarray:
        """x (nx,), P (n, n) -> (2n + 1, nx), ordered x, x + U[k], x - U[k]."""
        U = self.sqrt(self._scale * P)
        sigmas = np.empty((2 * self.n + 1, x.shape[0]))
        sigmas[0] = x
        sigmas[1 : self.n + 1] = self.add(x, U)
        sigmas[self.n + 1 :] = self.add(x, -U)
        return sigmas


class _EqualWeights:
    """Points of equal weight: Wm = 1 / count and Wc = Wm / alpha^2, which restores the covariance
    the alpha shrank. Subclasses give `num_sigmas` and prepare what their points need."""

    def __init__(
        self,
        n: int,
        *,
        alpha: float,
        sqrt: Callable[[np.ndarray], np.ndarray] | None = None,
        add: Add | None = None,
    ) -> None:
        self.n = n
        self.alpha = alpha
        self.sqrt = sqrt if sqrt is not None else RobustCholesky()
        self.add = add if add is not None else _vector_add
        self.Wm = np.full(self.num_sigmas(), 1.0 / self.num_sigmas())
        self.Wc = self.Wm / alpha**2
        self._prepare()

    def num_sigmas(self) -> int:
        raise NotImplementedError

    def _prepare(self) -> None:
        raise NotImplementedError


class Simplex(_EqualWeights):
    """Simplex sigma points (Moireau and Chapelle): n + 1 points, the fewest that match a mean and
    a covariance. x + alpha * sqrt(n) U.T s_i over the vertices s_i of a regular simplex;
    Wm = 1 / (n + 1) and Wc = Wm / alpha^2, which restores the covariance the alpha shrank.
    With alpha = 1 the points are filterpy's SimplexSigmaPoints'.
    """

    def num_sigmas(self) -> int:
        return self.n + 1

    def _prepare(self) -> None:
        self._unit: np.ndarray = self.alpha * np.sqrt(self.n) * _simplex_vertices(self.n)  # (n, n + 1)

    def sigma_points(self, x: np.ndarray, P: np.ndarray) -> np.ndarray:
        """x (nx,), P (n, n) -> (n + 1, nx)."""
        return self.from_factor(x, self.sqrt(P))

    @property
    def unit(self) -> np.ndarray:
        """(n, n + 1) the points' offsets for a unit covariance: point i is x + (U.T @ unit)[:, i]."""
        return self._unit

    def from_factor(self, x: np.ndarray, U: np.ndarray) -> np.ndarray:
        """The points of x (nx,) and a covariance whose upper square root U (n, n) is known."""
        return self.add(x, (U.T @ self._unit).T)


class UniformSpherical(_EqualWeights):
    """The symmetric set of 2n points x +- alpha * sqrt(n) U[k] with uniform weights: Wm = 1 / (2n),
    Wc = Wm / alpha^2. No centre point, so no weight can be negative whatever n is.
    """

    def num_sigmas(self) -> int:
        return 2 * self.n

    def _prepare(self) -> None:
        self._scale = self.n * self.alpha**2

    def sigma_points(self, x: np.ndarray, P: np.ndarray) -> np.ndarray:
        """x (nx,), P (n, n) -> (2n, nx), ordered x + U[k], x - U[k]."""
        U = self.sqrt(self._scale * P)
        sigmas = np.empty((2 * self.n, x.shape[0]))
        sigmas[: self.n] = self.add(x, U)
        sigmas[self.n :] = self.add(x, -U)
        return sigmas


def _simplex_vertices(n: int) -> np.ndarray:
    """The (n, n + 1) vertices of filterpy's unit simplex (its `Istar`), built as it builds them."""
    lambda_ = n / (n + 1)
    istar = np.array([[-1 / np.sqrt(2 * lambda_), 1 / np.sqrt(2 * lambda_)]])
    for d in range(2, n + 1):
        row = np.ones((1, istar.shape[1] + 1)) * 1.0 / np.sqrt(lambda_ * d * (d + 1))
        row[0, -1] = -d / np.sqrt(lambda_ * d * (d + 1))
        istar = np.r_[np.c_[istar, np.zeros(istar.shape[0])], row]
    return istar


def sigma_count(scheme: SigmaScheme | str, n: int) -> int:
    """How many points `scheme` uses for a state of tangent dimension n."""
    counts = {SigmaScheme.MERWE: 2 * n + 1, SigmaScheme.SIMPLEX: n + 1, SigmaScheme.UNIFORM: 2 * n}
    if scheme not in counts:
        raise InvalidArgument(f"sigma_points must be one of {[str(s) for s in SCHEMES]}, got {scheme!r}")
    return counts[scheme]


def make_sigma_points(
    scheme: SigmaScheme | str,
    *,
    n: int,
    alpha: float,
    beta: float,
    kappa: float,
    sqrt: Callable[[np.ndarray], np.ndarray] | None = None,
    add: Add | None = None,
) -> MerweScaled | Simplex | UniformSpherical:
    """The scheme named `scheme` for tangent dimension n (beta and kappa are Merwe's only)."""
    if n < 1:
        raise InvalidArgument(f"n must be >= 1, got {n}")
    if not (math.isfinite(alpha) and 0.0 < alpha <= 1.0):
        raise InvalidArgument(f"alpha must be in (0, 1], got {alpha}")
    if scheme == SigmaScheme.MERWE:
        return MerweScaled(n, alpha=alpha, beta=beta, kappa=kappa, sqrt=sqrt, add=add)
    if scheme == SigmaScheme.SIMPLEX:
        return Simplex(n, alpha=alpha, sqrt=sqrt, add=add)
    if scheme == SigmaScheme.UNIFORM:
        return UniformSpherical(n, alpha=alpha, sqrt=sqrt, add=add)
    raise InvalidArgument(f"sigma_points must be one of {[str(s) for s in SCHEMES]}, got {scheme!r}")
