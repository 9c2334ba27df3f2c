"""A PASSIVE filter that turns into a DRIVEN one when its own innovations say the model is wrong
(wrong_model DRIVEN)::

    estimator = SwitchingFilter(model, config, pool=pool)   # config.scenario PASSIVE,
    ...                                                     # config.wrong_model DRIVEN
    estimate = estimator.update(frame)      # estimate.absorbed: switched at this update

A client that names PASSIVE for a body something drives (a person's limb, a motor) gets a filter
whose prediction leaves the measurements tick after tick: its NIS stays far above the chi-square
distribution of a consistent filter. After WINDOW updates whose mean NIS passes the 1 - 1e-9 quantile
of the mean of WINDOW chi-square(m) samples (m the measurement dimension), the session's filter
becomes SCENARIO_DRIVEN with PRESET_JITDYN's DRIVEN settings (the unknown force in the state,
adaptive noise, the forecast combination), which replays the window's ticks (frames and gaps) from
its first frame, so that it has learnt its force and scored its forecasts by the time it answers;
the estimate of that update says `absorbed`. A filter whose model is right never gets there (its NIS has that distribution).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Final

import mujoco
import numpy as np
from scipy.stats import chi2

from jitdyn.errors import InvalidArgument
from jitdyn.server.estimation.config import SETTING_FIELDS, EstimatorConfig, preset_values
from jitdyn.server.estimation.interface import Estimate, Measurement
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.estimation.ukf import FilterSnapshot, NativeSnapshot, UnscentedFilter
from jitdyn.vocabulary import Channel, Preset, Scenario, WrongModel

__all__ = ["ABSORB_QUANTILE", "WINDOW", "SwitchingFilter"]

# Updates in the NIS window, and the quantile its mean must pass: 8 updates of a 6-dimensional
# measurement must average more than 19.6 (a consistent filter averages 6, and passes this once in
# 1e9 windows; a PASSIVE filter on a driven body averaged 1e3 to 1e8, docs/experiments.md). Eight
# updates: a pendulum at 50 ms ticks switches within 0.4 s, before the gaps experiment's first gap.
WINDOW: Final = 8
ABSORB_QUANTILE: Final = 1.0 - 1e-9
# The settings of the DRIVEN filter that replaces a wrong PASSIVE one: PRESET_JITDYN's for DRIVEN,
# but for what stays the session's own: its estimator, its prior (beta, p0) and its wrong_model.
_KEPT_FIELDS: Final = ("estimator", "beta", "p0", "wrong_model")
_DRIVEN_FIELDS: Final = tuple(name for name in SETTING_FIELDS if name not in _KEPT_FIELDS)


@dataclass(frozen=True)
class _Snapshot:
    owner: int
    switched: bool
    first: FilterSnapshot | NativeSnapshot
    second: FilterSnapshot | NativeSnapshot | None
    nis: tuple[float, ...]
    log: tuple[Measurement | None, ...]


class SwitchingFilter:
    """A PASSIVE UKF that becomes DRIVEN on a NIS window far out (module docstring). Implements
    `Estimator`."""

    def __init__(self, model: mujoco.MjModel, config: EstimatorConfig, *, pool: WorkerPool) -> None:
        if config.scenario != Scenario.PASSIVE or config.wrong_model != WrongModel.DRIVEN:
            raise InvalidArgument(
                "a SwitchingFilter needs scenario PASSIVE and wrong_model DRIVEN, "
                f"got {config.scenario} and {config.wrong_model}"
            )
        self._first = UnscentedFilter(model, config, pool=pool)
        driven = preset_values(Preset.JITDYN, model=model, scenario=Scenario.DRIVEN)
        # Members and floats of the table's rows, which EstimatorConfig checks again.
        settings: dict[str, Any] = {name: driven[name] for name in _DRIVEN_FIELDS}
        self._driven_config = dataclasses.replace(config, scenario=Scenario.DRIVEN, **settings)
        self._model = model
        self._pool = pool
        self._second: UnscentedFilter | None = None
        self._switched = False
        self._nis: list[float] = []
        # The ticks of the window, from its first frame: the frame, or None for a tick without one.
        self._log: list[Measurement | None] = []
        m = (2 if Channel.QVEL in config.measured else 1) * int(model.nv)
        self._limit = float(chi2.ppf(ABSORB_QUANTILE, WINDOW * m)) / WINDOW

    @property
    def _active(self) -> UnscentedFilter:
        if self._switched and self._second is not None:
            return self._second
        return self._first

    @property
    def config(self) -> EstimatorConfig:
        return self._active.config

    @property
    def switched(self) -> bool:
        """The session's filter is the DRIVEN one."""
        return self._switched

    @property
    def state_dimension(self) -> int:
        return self._active.state_dimension

    @property
    def state_size(self) -> int:
        return self._active.state_size

    @property
    def nsigma(self) -> int:
        return self._active.nsigma

    def initialise(self, m: Measurement) -> None:
        self._switched = False
        self._nis = []
        self._log = [m]
        self._first.initialise(m)

    def predict(self, *, ctrl: np.ndarray | None) -> Estimate:
        if not self._switched:
            self._log.append(None)
        return self._active.predict(ctrl=ctrl)

    def advance(self, *, ctrl: np.ndarray | None) -> None:
        if not self._switched:
            self._log.append(None)
        self._active.advance(ctrl=ctrl)

    def step(self, *, ctrl: np.ndarray | None, m: Measurement) -> Estimate:
        if not self._switched:
            self._log.append(None)
        return self._after(m, self._active.step(ctrl=ctrl, m=m))

    def update(self, m: Measurement) -> Estimate:
        return self._after(m, self._active.update(m))

    def _after(self, m: Measurement, estimate: Estimate) -> Estimate:
        """What the active filter's estimate of frame m makes the switch do."""
        if self._switched:
            return estimate
        if self._log and self._log[-1] is None:
            self._log[-1] = m
        else:
            self._log.append(m)  # a second frame for one tick: a tick of its own in the replay
        while sum(e is not None for e in self._log) > WINDOW + 1 or (self._log and self._log[0] is None):
            self._log.pop(0)
        if estimate.reinitialised or estimate.nis is None:
            self._nis = []
            return estimate
        self._nis.append(estimate.nis)
        if len(self._nis) > WINDOW:
            self._nis.pop(0)
        # np.add.reduce / n is np.mean's sum and division, without its wrappers (4 % of a tick).
        if len(self._nis) < WINDOW or float(np.add.reduce(np.array(self._nis))) / WINDOW <= self._limit:
            return estimate
        if self._second is None:
            self._second = UnscentedFilter(self._model, self._driven_config, pool=self._pool)
        second = self._second
        first, *rest = self._log
        if first is None:
            raise RuntimeError("unreachable: the log starts with a frame")
        second.forget()
        second.initialise(first)
        answer = second.extrapolate(0.0)
        for entry in rest:
            if entry is None:
                second.predict(ctrl=None)
            else:
                answer = second.step(ctrl=None, m=entry)
        self._switched = True
        self._log = []
        return dataclasses.replace(answer, nis=estimate.nis, absorbed=True)

    def extrapolate(self, seconds: float) -> Estimate:
        return self._active.extrapolate(seconds)

    def glance(self, seconds: float) -> Estimate:
        return self._active.glance(seconds)

    def snapshot(self) -> _Snapshot:
        return _Snapshot(
            owner=id(self),
            switched=self._switched,
            first=self._first.snapshot(),
            second=self._second.snapshot() if self._second is not None else None,
            nis=tuple(self._nis),
            log=tuple(self._log),
        )

    def restore(self, snap: object) -> None:
        if not isinstance(snap, _Snapshot) or snap.owner != id(self):
            raise InvalidArgument(f"snap must be a snapshot of this estimator, got {type(snap).__name__}")
        self._first.restore(snap.first)
        if snap.second is not None and self._second is not None:
            self._second.restore(snap.second)
        self._switched = snap.switched
        self._nis = list(snap.nis)
        self._log = list(snap.log)
