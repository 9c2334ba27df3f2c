"""The adaptive noise in C++ (adaptive.cc) behind NoiseAdapter's surface (estimation/adaptive.py,
the reference it is held to), for the native engine's filters.

    adapter = NativeNoiseAdapter(r0=np.full(4, 0.01), q0=Q, adapt_q=None, inflate=True)
    verdict = adapter.observe(innovation=y, consecutive=True, gain=K, nis=nis, noise_share=share)
    Q = adapter.Q
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.stats import chi2

from jitdyn.server.estimation.adaptive import BOUNDS, AdaptationBounds, Verdict, checked_noise
from jitdyn.server.estimation.native import _ukf

__all__ = ["NativeNoiseAdapter"]


class NativeNoiseAdapter:
    """NoiseAdapter's interface (estimation/adaptive.py) over adaptive.cc's Adapter."""

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
        free = np.ones(q0.shape[0], dtype=bool) if adapt_q is None else np.asarray(adapt_q, dtype=bool)
        m = r0.size
        self._adapter = _ukf.Adapter(
            r0=r0,
            q0=q0,
            adapt_q=[bool(f) for f in free],
            inflate=bool(inflate),
            bounds=dataclasses.asdict(bounds),
            nis_limit=float(chi2.ppf(bounds.absorb_quantile, bounds.window * m)) / bounds.window,
        )
        self._q0 = q0
        self._m = m

    @property
    def native(self) -> _ukf.Adapter:
        """The compiled adapter, for native/tick.py."""
        return self._adapter

    def reset(self) -> None:
        self._adapter.reset()

    @property
    def window_full(self) -> bool:
        return bool(self._adapter.window_full)

    @property
    def R(self) -> np.ndarray:
        return np.diag(self._adapter.r_diagonal)

    @property
    def r_diagonal(self) -> np.ndarray:
        return np.asarray(self._adapter.r_diagonal)

    @property
    def scale(self) -> np.ndarray:
        return np.asarray(self._adapter.scale)

    @property
    def inflation(self) -> float:
        return float(self._adapter.inflation)

    @property
    def gap_inflation(self) -> float:
        return float(self._adapter.gap_inflation)

    @property
    def Q(self) -> np.ndarray:
        return self.q_for(self._q0)

    @property
    def Q_gap(self) -> np.ndarray:
        return self.gap_inflation * self.Q

    def q_for(self, q0: np.ndarray) -> np.ndarray:
        return np.asarray(self._adapter.q_for(np.asarray(q0, dtype=np.float64)))

    def observe(
        self,
        *,
        innovation: np.ndarray,
        consecutive: bool,
        gain: np.ndarray,
        nis: float | None,
        noise_share: float = 0.0,
    ) -> Verdict:
        if innovation.size != self._m:
            raise ValueError(f"innovation must have {self._m} entries, got {innovation.size}")
        adapted, absorb = self._adapter.observe(
            innovation=np.asarray(innovation, dtype=np.float64),
            consecutive=consecutive,
            gain=np.asarray(gain, dtype=np.float64),
            nis=float("nan") if nis is None else float(nis),
            noise_share=float(noise_share),
        )
        return Verdict(adapted=bool(adapted), absorb=bool(absorb))

    def observe_gap(self, *, nis: float, m: int) -> None:
        self._adapter.observe_gap(nis=float(nis), m=int(m))

    def absorbed(self) -> None:
        self._adapter.absorbed()

    def snapshot(self) -> _ukf.AdapterState:
        return self._adapter.snapshot()

    def restore(self, snap: _ukf.AdapterState) -> None:
        self._adapter.restore(snap)
