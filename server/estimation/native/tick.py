"""A tick's numeric steps in one native call (tick.cc) for an UnscentedFilter on the native engine:
the process noise, the forecast combination's advance, predict, the activations' clip and tidy; on
a frame that is on time also the update's noise, the update, tidy, the adaptive noise's
observation, the estimate's qacc and the combiner's observation of the frame; and the timewarp's
snapshot of all of it in one copy (TickState). What stays in Python, and why:
docs/decisions/0212-one-native-call-a-tick.md.

    tick = NativeTick.of(parts)           # None: this filter runs its steps one call each
    prediction = tick.advance(gap=False)  # a tick without its frame
    result = tick.step(z)                 # a tick with its frame on time
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from jitdyn.server.estimation.answer import activation_bounds
from jitdyn.server.estimation.guard import COVARIANCE_LIMIT
from jitdyn.server.estimation.native import TickState, _ukf
from jitdyn.server.estimation.native.adaptive import NativeNoiseAdapter
from jitdyn.server.estimation.native.combiner import NativeCombiner
from jitdyn.server.estimation.native.filter import NativeUKF
from jitdyn.server.estimation.parts import FilterParts
from jitdyn.vocabulary import Scenario

__all__ = ["NativeTick", "Prediction", "Step"]

# What the estimate's qacc is computed under in the native call (tick.h TickForce): CONTROLLED
# has it in x, and EXTERNAL's restored force is computed after the update, in Python.
_FORCE = {Scenario.PASSIVE: 1, Scenario.DRIVEN: 2, Scenario.CONTROLLED: 0, Scenario.EXTERNAL: 0}


@dataclass(frozen=True, slots=True)
class Prediction:
    """A tick's prediction: x and P finite, P's largest variance, and whether the guard sees a
    divergence in them; act (na,) the clipped activations."""

    finite: bool
    largest_variance: float
    diverged: bool
    act: np.ndarray


@dataclass(frozen=True, slots=True)
class Step:
    """An on-time tick. updated False: its prediction diverged, and nothing more was done. nis
    None: not finite. x (size,), P (n, n): the posterior; qacc (nv,) the estimate's, or None where
    Python computes it."""

    updated: bool
    finite: bool
    nis: float | None
    largest_variance: float
    observed: bool
    adapted: bool
    absorb: bool
    act: np.ndarray
    x: np.ndarray
    P: np.ndarray
    qacc: np.ndarray | None
    observed_frame: bool  # the combiner observed the frame and this posterior


class NativeTick:
    """tick.cc's Tick over one filter's native core, adapter and combiner (module docstring)."""

    def __init__(self, parts: FilterParts, kf: NativeUKF) -> None:
        adapter = parts.adapter
        combiner = parts.foresight.combiner if parts.foresight is not None else None
        if adapter is not None and not isinstance(adapter, NativeNoiseAdapter):
            raise TypeError(f"adapter must be a NativeNoiseAdapter, got {type(adapter).__name__}")
        if combiner is not None and not isinstance(combiner, NativeCombiner):
            raise TypeError(f"combiner must be a NativeCombiner, got {type(combiner).__name__}")
        low, high = activation_bounds(parts.model)
        self._kf = kf
        self._tick = _ukf.Tick(
            kf.native,
            adapter=adapter.native if adapter is not None else None,
            combiner=combiner.native if combiner is not None else None,
            act_low=low,
            act_high=high,
            covariance_limit=COVARIANCE_LIMIT,
            force=_FORCE[parts.layout.scenario],
        )

    @classmethod
    def of(cls, parts: FilterParts) -> NativeTick | None:
        """The filter's, or None: another engine, the config's `native_tick` off, or a Python
        adapter or combiner (`native_forecast` off)."""
        kf, adapter = parts.kf, parts.adapter
        combiner = parts.foresight.combiner if parts.foresight is not None else None
        if not parts.config.native_tick or not isinstance(kf, NativeUKF):
            return None
        if adapter is not None and not isinstance(adapter, NativeNoiseAdapter):
            return None
        if combiner is not None and not isinstance(combiner, NativeCombiner):
            return None
        return cls(parts, kf)

    def advance(self, *, gap: bool) -> Prediction:
        """predict over one tick (gap: the tick after one without its frame: the gap's Q)."""
        finite, largest, diverged, act = self._tick.advance(gap)
        self._kf.held_act(act)
        return Prediction(finite=finite, largest_variance=largest, diverged=diverged, act=act)

    def snapshot(self) -> TickState:
        """x, P, the update's sigma points, the adapter's and the combiner's states: one copy."""
        return self._tick.snapshot()

    def restore(self, state: TickState) -> None:
        self._tick.restore(state)

    def step(self, z: np.ndarray, *, quiet: bool, qvel: np.ndarray | None) -> Step:
        """An on-time tick: advance(gap=False), then, unless it diverged, the update with z; the
        combiner observes the frame (qvel: its measured qvel) where the posterior is kept for
        sure (quiet: the guard's runs cannot restart the filter on this update; tick.h)."""
        answer = self._tick.step(z, quiet=quiet, qvel=qvel)
        updated, finite, nis, largest, observed, adapted, absorb, act, x, P, qacc, observed_frame = answer
        self._kf.held_act(act)
        return Step(
            updated=updated, finite=finite, nis=None if np.isnan(nis) else float(nis),
            largest_variance=largest, observed=observed, adapted=adapted, absorb=absorb, act=act,
            x=x, P=P, qacc=qacc, observed_frame=observed_frame,
        )  # fmt: skip
