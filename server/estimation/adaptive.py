"""Noise that the filter learns from its innovations, within bounds, and a window of NIS that tells
when the model is wrong (an adaptive UKF)::

    adapter = NoiseAdapter(r0=np.full(m, 1e-2), q0=Q0, bounds=BOUNDS)
    R, Q = adapter.R, adapter.Q
    verdict = adapter.observe(innovation=y, consecutive=True, gain=K, nis=nis)
    verdict.adapted, verdict.absorb

- R (diagonal) from the innovations y = z - h(x-) of consecutive ticks: the fourth difference of
  five consecutive samples of white noise of variance s^2 has variance 70 s^2, while that of a
  smooth signal is of order its fourth derivative times dt^4, negligible at the ticks of wearables.
  R is the square of a robust scale of the last `window_r` fourth differences (1.4826 median |d4| /
  sqrt(70), the MAD), so that the kinks of a motion (a force that jumps) do not pass for noise.
  Why not covariance matching on the innovations: docs/decisions/0023-adaptive-r-from-differences.md.
- Q keeps its configured structure (the discrete white-noise blocks) and is rescaled per state
  component, Q = S^1/2 Q0 S^1/2, where s_i matches the running mean of (K y)_i^2, the correction the
  filter had to make (Mohamed and Schwarz 1999's Q = K C_y K^T, diagonal), with Sage and Husa's
  fading memory, weight d_k = (1 - b) / (1 - b^(k+1)).
- The whole Q (the unknown force's included) is also scaled by one factor, lambda, that matches the
  mean NIS to m, its mean for a consistent filter (covariance matching on the innovations, Mohamed
  and Schwarz 1999, with a scalar in place of their matrix; a stochastic-approximation step in the
  log): after each update, log lambda += gain phi (NIS / m - 1), each step clipped to
  +-`inflation_step`, phi = 1 - tr(S^-1 R) / m the share of the innovation covariance S that the
  prediction makes (the sensitivity of E[NIS] to log lambda), and log lambda leaks back towards 0
  by `inflation_leak` per update, so that it stays up only while the NIS keeps asking. Why phi and
  the leak, and what else was measured: docs/decisions/0024-noise-inflation.md.
- Over a gap the same Q is further scaled by mu, matched the same way to the NIS of the first frame
  after each gap, the only frame that tests a prediction of many ticks (a random walk of the force
  says its variance grows as the gap's length, where a muscle's or a controller's force drifts
  along a trend). Once a gap: gap_gain and gap_step are larger than lambda's.
- All are clipped to `AdaptationBounds`: a filter that learns cannot learn itself into a singular
  or absurd covariance.
- NIS: the mean of the last `window` NIS values against its chi-square interval. Far above it (past
  the 0.999 quantile of that mean) for a whole window means the model is wrong, not the noise: the
  caller absorbs it (widens P).

Pure numpy; one adapter per filter, driven from one thread; `snapshot()`/`restore()` for the
timewarp.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final

import numpy as np
from scipy.stats import chi2

__all__ = ["BOUNDS", "AdaptationBounds", "NoiseAdapter", "NoiseSnapshot", "Verdict", "checked_noise"]


_MAD_TO_SIGMA: Final = 1.4826  # median |N(0, 1)| = 0.6745 = 1 / 1.4826
_D4_VARIANCE: Final = 70.0  # var of the fourth difference of unit white noise: C(8, 4)


@dataclass(frozen=True)
class AdaptationBounds:
    """The limits of what the noise may learn.

    r_min, r_max: bounds of every diagonal entry of R, in the measured channels' units squared
    (rad^2, m^2; (rad/s)^2, (m/s)^2). 1e-10 is a sensor good to 1e-5 rad; 1e-2 one good to 0.1
    rad or 0.1 rad/s, the worst a wearable is taken to be (a larger innovation is the model's error,
    which the NIS window then sees, not noise). q_scale_min, q_scale_max: bounds of the factor s_i on the configured Q's diagonal.
    forgetting: Sage-Husa's b, the weight of the past (window about 1 / (1 - b) updates).
    window: updates in the NIS window; absorb_quantile: its mean must pass this quantile of the
    mean of `window` chi-square(m) samples, chi2.ppf(q, window m) / window, to absorb (0.999: about
    1.5 m for m = 6 and a window of 20; the thesis' EXTERNAL filters sat at 1e3 to 1e6 m).
    report_change: a relative change of R or Q that `Verdict.adapted` reports. window_r: fourth
    differences R is estimated from; min_differences: how many it needs before it replaces r0.
    inflation_min, inflation_max: bounds of lambda, the factor on the whole Q; inflation_gain: the
    step of log lambda per unit of NIS / m - 1; inflation_step: the largest step of log lambda of
    one update (one wild frame moves Q by at most exp(inflation_step)); inflation_leak: the share
    of log lambda forgotten per update (back towards 1, see the module docstring); gap_gain,
    gap_step: the same for mu, the further factor over a gap (bounded by inflation_min and
    inflation_max too). absorb_factor: what an absorption multiplies the adapted Q by
    (`NoiseAdapter.absorbed`), within q_scale_max.
    """

    r_min: float = 1e-10
    r_max: float = 1e-2
    q_scale_min: float = 1e-4
    q_scale_max: float = 1e4
    forgetting: float = 0.98
    window: int = 20
    absorb_quantile: float = 0.999
    report_change: float = 0.1
    window_r: int = 64
    min_differences: int = 8
    inflation_min: float = 1e-2
    inflation_max: float = 1e3
    inflation_gain: float = 0.2
    inflation_leak: float = 0.03
    inflation_step: float = 0.5
    gap_gain: float = 0.5
    gap_step: float = 1.5
    absorb_factor: float = 100.0


BOUNDS: Final = AdaptationBounds()


@dataclass(frozen=True)
class Verdict:
    """What one update taught: `adapted`, R or Q moved by more than `report_change` since the last
    verdict that said so; `absorb`, the NIS window says the model is wrong."""

    adapted: bool
    absorb: bool


@dataclass(frozen=True)
class NoiseSnapshot:
    """A NoiseAdapter's whole state."""

    r: np.ndarray
    q_est: np.ndarray
    count: int
    nis: np.ndarray
    nis_count: int
    recent: tuple[np.ndarray, ...]
    d4: np.ndarray
    d4_count: int
    reported_r: np.ndarray
    reported_s: np.ndarray
    log_inflation: float
    log_gap_inflation: float
    reported_inflation: float


def checked_noise(r0: np.ndarray, q0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """r0 (m,) positive and q0 (n, n), as float arrays; ValueError naming the one that is not."""
    r0 = np.asarray(r0, dtype=np.float64)
    q0 = np.asarray(q0, dtype=np.float64)
    if r0.ndim != 1 or not np.all(r0 > 0):
        raise ValueError(f"r0 must be a vector of positive variances, got {r0!r}")
    if q0.shape != (q0.shape[0], q0.shape[0]):
        raise ValueError(f"q0 must be square, got shape {q0.shape}")
    return r0, q0


class NoiseAdapter:
    """The adaptive R and Q of one filter (see the module docstring).

    r0 (m,): R's starting diagonal; q0 (n, n): the configured Q for one tick, whose structure is
    kept and whose diagonal sets the scale of s; adapt_q (n,) bool: the components whose Q adapts
    (None: all); inflate: whether lambda and mu follow the NIS (a DRIVEN filter's: its NIS out of its
    interval says the force moves faster than its random walk; a PASSIVE or EXTERNAL filter's says
    its model is wrong, which the NIS window must see, not a wider Q hide).
    """

    def __init__(
        self,
        *,
        r0: np.ndarray,
        q0: np.ndarray,
        adapt_q: np.ndarray | None = None,
        inflate: bool = True,
        bounds: AdaptationBounds = BOUNDS,
    ) -> None:
        r0, q0 = checked_noise(r0, q0)
        self._bounds = bounds
        self._inflate = bool(inflate)
        self._r0 = np.clip(r0, bounds.r_min, bounds.r_max)
        self._q0 = q0
        diag = np.diag(q0).copy()
        # A component with no configured noise (q_var = 0) gets none: there is no scale to adapt.
        self._q0_diag = np.where(diag > 0, diag, 1.0)
        self._q_free = diag > 0
        self._nis_limit: float | None = None
        if adapt_q is not None:
            self._q_free &= np.asarray(adapt_q, dtype=bool)
        self.reset()

    def reset(self) -> None:
        """Back to the configured R and Q, with an empty NIS window."""
        self._r = self._r0.copy()
        self._q_est = np.diag(self._q0).copy()
        self._count = 0
        self._nis = np.zeros(self._bounds.window)
        self._nis_count = 0
        self._recent: list[np.ndarray] = []
        self._d4 = np.zeros((self._bounds.window_r, self._r0.size))
        self._d4_count = 0
        self._reported_r = self._r.copy()
        self._reported_s = np.ones_like(self._q_est)
        self._log_inflation = 0.0
        self._log_gap_inflation = 0.0
        self._reported_inflation = 1.0
        self._changed()

    def _changed(self) -> None:
        """R, s or lambda changed: what is derived from them is computed again when next asked
        for. A tick asked for s three times and for Q and R once each, every time anew (5 % of a
        myoElbow DRIVEN tick, py-spy)."""
        self._derived: dict[str, np.ndarray] = {}

    def _cached(self, name: str, compute: Callable[[], np.ndarray]) -> np.ndarray:
        value = self._derived.get(name)
        if value is None:
            value = np.asarray(compute())
            value.flags.writeable = False  # handed out to the filter, shared until the next change
            self._derived[name] = value
        return value

    @property
    def window_full(self) -> bool:
        """The NIS window holds `window` values since the last reset or absorption."""
        return self._nis_count >= self._bounds.window

    @property
    def R(self) -> np.ndarray:
        """(m, m) the measurement noise in force (read-only)."""
        return self._cached("R", lambda: np.diag(self._r))

    @property
    def r_diagonal(self) -> np.ndarray:
        return np.array(self._r)

    @property
    def scale(self) -> np.ndarray:
        """(n,) s, the factor on each component of Q0's diagonal (read-only)."""
        return self._cached("scale", self._scale)

    def _scale(self) -> np.ndarray:
        b = self._bounds
        s = np.where(self._q_free, self._q_est / self._q0_diag, 1.0)
        return np.asarray(np.clip(s, b.q_scale_min, b.q_scale_max))

    @property
    def inflation(self) -> float:
        """lambda, the factor on the whole Q that the NIS asks for."""
        return math.exp(self._log_inflation)

    @property
    def gap_inflation(self) -> float:
        """mu, the further factor on Q over a gap that the first frames after gaps ask for."""
        return math.exp(self._log_gap_inflation)

    @property
    def Q_gap(self) -> np.ndarray:
        """(n, n) the process noise of a tick of a gap after its first: mu lambda S^1/2 Q0 S^1/2."""
        return self.gap_inflation * self.Q

    @property
    def Q(self) -> np.ndarray:
        """(n, n) the process noise in force for one tick: lambda S^1/2 Q0 S^1/2 (read-only)."""
        return self._cached("Q", lambda: self.q_for(self._q0))

    def q_for(self, q0: np.ndarray) -> np.ndarray:
        """Another horizon's configured Q (n, n), rescaled as this tick's is."""
        root = np.sqrt(self.scale * self.inflation)
        return np.asarray(root[:, None] * q0 * root[None, :])

    def observe(
        self,
        *,
        innovation: np.ndarray,
        consecutive: bool,
        gain: np.ndarray,
        nis: float | None,
        noise_share: float = 0.0,
    ) -> Verdict:
        """Learn from one update.

        innovation y (m,) = z - h(x-), which R is learnt from (its fourth differences) and Q (the
        correction K y); consecutive: the frame before it was the previous tick's; gain K (n, m);
        nis: y^T S^-1 y (None when not finite); noise_share: tr(S^-1 R) / m, the share of the
        innovation covariance that is the measurement's noise (lambda's step is scaled by the rest,
        see the module docstring).
        """
        if not np.all(np.isfinite(innovation)):
            return Verdict(adapted=False, absorb=False)
        b = self._bounds
        d = (1.0 - b.forgetting) / (1.0 - b.forgetting ** (self._count + 1))
        self._count += 1
        self._learn_r(innovation, consecutive=consecutive)
        # A filter on its way to the divergence guard can have gains whose squares overflow: such
        # an update teaches nothing (the guard re-initialises).
        with np.errstate(over="ignore", invalid="ignore"):
            correction = gain @ innovation
            q_next = (1.0 - d) * self._q_est + d * correction**2
        if np.all(np.isfinite(q_next)):
            self._q_est = q_next
        absorb = False
        if nis is not None and np.isfinite(nis):
            absorb = self._learn_nis(nis, m=innovation.size, noise_share=noise_share)
        self._changed()
        return Verdict(adapted=self._moved(), absorb=absorb)

    def _learn_r(self, y: np.ndarray, *, consecutive: bool) -> None:
        """R from the robust scale of the last fourth differences of y (m,), over consecutive ticks."""
        b = self._bounds
        if not consecutive:
            self._recent = []
        self._recent.append(np.array(y, dtype=np.float64))
        if len(self._recent) > 5:
            self._recent.pop(0)
        if len(self._recent) == 5 and y.size == self._r.size:
            y0, y1, y2, y3, y4 = self._recent
            self._d4[self._d4_count % b.window_r] = y4 - 4.0 * y3 + 6.0 * y2 - 4.0 * y1 + y0
            self._d4_count += 1
            if self._d4_count >= b.min_differences:
                filled = self._d4[: min(self._d4_count, b.window_r)]
                scale = _MAD_TO_SIGMA * _column_medians(np.abs(filled))
                self._r = np.clip(scale**2 / _D4_VARIANCE, b.r_min, b.r_max)

    def _learn_nis(self, nis: float, *, m: int, noise_share: float) -> bool:
        """lambda's step towards NIS / m = 1 (inflate only), and the NIS window: whether its mean is
        far out (absorb)."""
        b = self._bounds
        if nis >= 0.0 and self._inflate:
            share = min(max(1.0 - noise_share, 0.0), 1.0)
            step = b.inflation_gain * share * (nis / m - 1.0)
            step = min(max(step, -b.inflation_step), b.inflation_step)
            low, high = math.log(b.inflation_min), math.log(b.inflation_max)
            leaked = (1.0 - b.inflation_leak) * self._log_inflation
            self._log_inflation = min(max(leaked + step, low), high)
        self._nis[self._nis_count % b.window] = nis
        self._nis_count += 1
        if self._nis_count < b.window:
            return False
        if self._nis_limit is None:
            self._nis_limit = float(chi2.ppf(b.absorb_quantile, b.window * m)) / b.window
        return float(self._nis.mean()) > self._nis_limit

    def _moved(self) -> bool:
        """R, s or lambda moved by more than report_change since they were last reported."""
        b = self._bounds
        s = self.scale
        inflation = self.inflation
        moved = bool(
            np.any(np.abs(self._r - self._reported_r) > b.report_change * self._reported_r)
            or np.any(np.abs(s - self._reported_s) > b.report_change * self._reported_s)
            or abs(inflation - self._reported_inflation) > b.report_change * self._reported_inflation
        )
        if moved:
            self._reported_r = self._r.copy()
            self._reported_s = s
            self._reported_inflation = inflation
        return moved

    def observe_gap(self, *, nis: float, m: int) -> None:
        """The NIS (of dimension m) of the first frame after a gap, against the prediction over it."""
        b = self._bounds
        if not (self._inflate and math.isfinite(nis) and nis >= 0.0):
            return
        step = min(max(b.gap_gain * (nis / m - 1.0), -b.gap_step), b.gap_step)
        low, high = math.log(b.inflation_min), math.log(b.inflation_max)
        self._log_gap_inflation = min(max(self._log_gap_inflation + step, low), high)

    def absorbed(self) -> None:
        """After an absorption: the adapted part of Q widened by `absorb_factor`, within
        q_scale_max (so that its fading memory can forget it), and an empty NIS window, so the
        next verdict comes from the updates after it."""
        b = self._bounds
        self._q_est = np.minimum(self._q_est * b.absorb_factor, self._q0_diag * b.q_scale_max)
        self._changed()
        self._nis[:] = 0.0
        self._nis_count = 0

    def snapshot(self) -> NoiseSnapshot:
        return NoiseSnapshot(
            r=self._r.copy(),
            q_est=self._q_est.copy(),
            count=self._count,
            nis=self._nis.copy(),
            nis_count=self._nis_count,
            recent=tuple(self._recent),
            d4=self._d4.copy(),
            d4_count=self._d4_count,
            reported_r=self._reported_r.copy(),
            reported_s=self._reported_s.copy(),
            log_inflation=self._log_inflation,
            log_gap_inflation=self._log_gap_inflation,
            reported_inflation=self._reported_inflation,
        )

    def restore(self, snap: NoiseSnapshot) -> None:
        self._r = snap.r.copy()
        self._q_est = snap.q_est.copy()
        self._count = snap.count
        self._nis = snap.nis.copy()
        self._nis_count = snap.nis_count
        self._recent = list(snap.recent)
        self._d4 = snap.d4.copy()
        self._d4_count = snap.d4_count
        self._reported_r = snap.reported_r.copy()
        self._reported_s = snap.reported_s.copy()
        self._log_inflation = snap.log_inflation
        self._log_gap_inflation = snap.log_gap_inflation
        self._reported_inflation = snap.reported_inflation
        self._changed()


def _column_medians(a: np.ndarray) -> np.ndarray:
    """np.median(a, axis=0) for a finite (k, m) array, the same numbers (the middle value, or the
    mean of the two middle ones), without np.median's checks and bookkeeping: half of an update's
    adaptation at m = 46 (myoHand) was spent there."""
    k = a.shape[0]
    half = k // 2
    if k % 2:
        return np.asarray(np.partition(a, half, axis=0)[half])
    middle = np.partition(a, (half - 1, half), axis=0)
    return np.asarray((middle[half - 1] + middle[half]) / 2.0)
