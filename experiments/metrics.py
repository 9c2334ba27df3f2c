"""Estimation metrics of the thesis and beyond: aRMSE, NEES and NIS with chi-square intervals, and the
error of dead reckoning over gaps without frames. Pure functions of numpy arrays::

    per_joint = rmse(true_q, est_q)              # (n,)
    c = consistency(nees(true_x - est_x, P), dim=x_dim)
    c.mean, c.single, c.averaged                  # average NEES and its two 95 % intervals

Shapes: T ticks, n joints (or state components), `(T, n)` arrays; covariances `(T, n, n)`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from jitdyn.server.estimation.extrapolators import extrapolate
from jitdyn.vocabulary import EstimatorKind

__all__ = [
    "ChiSquareInterval",
    "Consistency",
    "GapErrors",
    "armse",
    "chi_square_interval",
    "consistency",
    "dead_reckon",
    "gap_error_profile",
    "gap_errors",
    "nees",
    "rmse",
    "ticks_since_frame",
]


def _as_2d(name: str, values: np.ndarray | Sequence[Sequence[float]]) -> np.ndarray:
    array = np.asarray(values, dtype=float)
    if array.ndim == 1:
        # A single joint given as a plain series.
        array = array[:, None]
    if array.ndim != 2:
        raise ValueError(f"{name} must have shape (T, n), got {array.shape}")
    return array


def rmse(truth: np.ndarray, estimate: np.ndarray) -> np.ndarray:
    """RMSE over time of every column: sqrt(mean_t (truth - estimate)^2); shapes (T, n) -> (n,).

    NaN ticks (no estimate) are left out, per column; a column with no finite tick is NaN.
    """
    truth2, estimate2 = _as_2d("truth", truth), _as_2d("estimate", estimate)
    if truth2.shape != estimate2.shape:
        raise ValueError(
            f"truth and estimate must have the same shape, got {truth2.shape} and {estimate2.shape}"
        )
    if truth2.shape[0] == 0:
        raise ValueError("truth and estimate must have at least one tick, got 0")
    squared = (truth2 - estimate2) ** 2
    finite = np.isfinite(squared)
    counts = finite.sum(axis=0)
    sums = np.where(finite, squared, 0.0).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(np.where(counts > 0, sums / np.maximum(counts, 1), np.nan))


def armse(truth: np.ndarray, estimate: np.ndarray) -> float:
    """The thesis' aRMSE: the RMSE over time of every joint, averaged over the joints."""
    return float(np.mean(rmse(truth, estimate)))


def nees(errors: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """Normalised estimation error squared per tick: e_t^T P_t^-1 e_t; (T, n), (T, n, n) -> (T,).

    `errors` are truth - estimate. P is solved against, not inverted, which keeps the badly
    conditioned covariances of the thesis' settings as accurate as they can be; a singular P gives
    inf (or NaN where the error lies in its null space), which the caller sees rather than a crash.
    """
    e = _as_2d("errors", errors)
    p = np.asarray(covariances, dtype=float)
    t, n = e.shape
    if p.shape != (t, n, n):
        raise ValueError(f"covariances must have shape {(t, n, n)} to match errors {e.shape}, got {p.shape}")
    out = np.empty(t)
    for k in range(t):
        try:
            out[k] = float(e[k] @ np.linalg.solve(p[k], e[k]))
        except np.linalg.LinAlgError:
            out[k] = np.inf if np.any(e[k] != 0) else np.nan
    return out


@dataclass(frozen=True, slots=True)
class ChiSquareInterval:
    """The two-sided interval of the mean of `samples` chi-square variables of `dof` degrees each."""

    low: float
    high: float
    dof: int
    samples: int
    confidence: float

    def contains(self, value: float) -> bool:
        return self.low <= value <= self.high


def chi_square_interval(dof: int, *, samples: int = 1, confidence: float = 0.95) -> ChiSquareInterval:
    """[chi2.ppf(a/2, N dof) / N, chi2.ppf(1 - a/2, N dof) / N] for N = `samples`, a = 1 - confidence.

    With N = 1 it is the thesis' interval for one NEES sample. With N ticks it is the interval for
    their average, under the hypothesis that the samples are independent (Bar-Shalom et al. 2001,
    5.4.2); successive ticks of one run are correlated, so it is narrower than the truth would be.
    """
    if dof < 1:
        raise ValueError(f"dof must be >= 1, got {dof}")
    if samples < 1:
        raise ValueError(f"samples must be >= 1, got {samples}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    tail = (1.0 - confidence) / 2.0
    total = dof * samples
    return ChiSquareInterval(
        low=float(chi2.ppf(tail, total)) / samples,
        high=float(chi2.ppf(1.0 - tail, total)) / samples,
        dof=dof,
        samples=samples,
        confidence=confidence,
    )


@dataclass(frozen=True, slots=True)
class Consistency:
    """A series of NEES (or NIS) values against chi-square with `dof` degrees of freedom."""

    mean: float  # average over the finite samples (the thesis' "average NEES")
    median: float
    samples: int  # finite samples averaged
    single: ChiSquareInterval  # one sample (the thesis' "NEES CI")
    averaged: ChiSquareInterval  # the average of `samples` samples
    fraction_inside: float  # share of single samples inside `single`; 0.95 for a consistent filter

    @property
    def consistent(self) -> bool:
        """Whether the average lies inside the interval for an average."""
        return self.averaged.contains(self.mean)

    @property
    def verdict(self) -> str:
        """'consistent', 'pessimistic' (P too large: NEES low) or 'optimistic' (NEES high)."""
        if self.mean < self.averaged.low:
            return "pessimistic"
        if self.mean > self.averaged.high:
            return "optimistic"
        return "consistent"


def consistency(values: np.ndarray | Sequence[float], *, dof: int, confidence: float = 0.95) -> Consistency:
    """Average NEES/NIS and where it lies; non-finite samples (a singular P) are left out of it."""
    v = np.asarray(values, dtype=float).ravel()
    finite = v[np.isfinite(v)]
    if finite.size == 0:
        raise ValueError(f"values must hold at least one finite sample, got {v.size} samples, none finite")
    single = chi_square_interval(dof, samples=1, confidence=confidence)
    inside = (finite >= single.low) & (finite <= single.high)
    return Consistency(
        mean=float(finite.mean()),
        median=float(np.median(finite)),
        samples=int(finite.size),
        single=single,
        averaged=chi_square_interval(dof, samples=int(finite.size), confidence=confidence),
        fraction_inside=float(inside.mean()),
    )


def dead_reckon(
    kind: EstimatorKind, *, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, horizon: float
) -> tuple[np.ndarray, np.ndarray]:
    """The open-loop extrapolation of (q, qd) by `horizon` seconds from the last frame's state.

    A plain reference for the server's baselines: STATIC holds q and qd; CONSTANT_VELOCITY moves q
    with qd; CONSTANT_ACCELERATION moves q with qd and qdd, and qd with qdd. Joints are treated as
    flat coordinates (hinge and slide joints; not quaternions).
    """
    if horizon < 0:
        raise ValueError(f"horizon must be >= 0 seconds, got {horizon}")
    q0, v0, a0 = (np.asarray(x, dtype=float) for x in (q, qd, qdd))
    if not q0.shape == v0.shape == a0.shape:
        raise ValueError(f"q, qd and qdd must have the same shape, got {q0.shape}, {v0.shape}, {a0.shape}")
    q_at, qd_at, _ = extrapolate(kind, q0, v0, a0, horizon)  # ValueError for another kind
    return q_at, qd_at


def ticks_since_frame(received: np.ndarray | Sequence[bool]) -> np.ndarray:
    """For every tick, how many ticks ago the last frame came: 0 on a tick with its frame.

    Ticks before the first frame have no reference and get -1. (T,) bool -> (T,) int.
    """
    r = np.asarray(received, dtype=bool).ravel()
    out = np.full(r.shape, -1, dtype=int)
    last = -1
    for k, got in enumerate(r):
        if got:
            last = k
        if last >= 0:
            out[k] = k - last
    return out


def gap_error_profile(
    truth: np.ndarray, estimate: np.ndarray, received: np.ndarray | Sequence[bool]
) -> dict[int, float]:
    """The q error as a function of the time without frames: {ticks since the last frame: RMS error}.

    The RMS runs over every joint and every tick at that distance from its last frame, so a gap of
    h ticks contributes to the entries 1..h. Ticks with a frame (distance 0) and ticks before the
    first frame are left out. (T, n), (T, n), (T,) -> {h: rms}.
    """
    truth2, estimate2 = _as_2d("truth", truth), _as_2d("estimate", estimate)
    if truth2.shape != estimate2.shape:
        raise ValueError(
            f"truth and estimate must have the same shape, got {truth2.shape} and {estimate2.shape}"
        )
    since = ticks_since_frame(received)
    if since.shape[0] != truth2.shape[0]:
        raise ValueError(f"received must have one flag per tick ({truth2.shape[0]}), got {since.shape[0]}")
    squared = ((truth2 - estimate2) ** 2).mean(axis=1)
    return {int(h): float(np.sqrt(squared[since == h].mean())) for h in np.unique(since) if h > 0}


@dataclass(frozen=True, slots=True)
class GapErrors:
    """The q error of one estimator at the end of gaps of given lengths."""

    estimator: str
    dt: float
    by_gap: Mapping[float, float]  # gap length (s) -> RMS q error at the first tick >= that long
    ticks: Mapping[float, int]  # gap length (s) -> the whole ticks it was rounded up to


def gap_errors(
    estimator: str,
    profile: Mapping[int, float],
    *,
    dt: float,
    gaps: Sequence[float] = (0.035, 0.100, 0.200),
) -> GapErrors:
    """Reads the errors at the given gap lengths off a `gap_error_profile`.

    A gap of g seconds is the first tick at least g after the last frame: ceil(g / dt) ticks (with a
    1e-9 tolerance, so 0.1 / 0.05 is 2 ticks, not 3). A length the run had no gap that long for is
    NaN.
    """
    if dt <= 0:
        raise ValueError(f"dt must be > 0 seconds, got {dt}")
    by_gap: dict[float, float] = {}
    ticks: dict[float, int] = {}
    for g in gaps:
        if g <= 0:
            raise ValueError(f"gap lengths must be > 0 seconds, got {g}")
        h = int(np.ceil(g / dt - 1e-9))
        ticks[g] = h
        by_gap[g] = profile.get(h, float("nan"))
    return GapErrors(estimator=estimator, dt=dt, by_gap=by_gap, ticks=ticks)
