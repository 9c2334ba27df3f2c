"""A REALTIME session's estimator, chosen from the model's measured cost: each candidate's cost is
measured once, when the model is registered, and stored with it (registry.costs); an open takes the
most accurate candidate whose stored cost fits its tick, or is refused with the rate that would fit
(docs/decisions/0204-the-estimator-chosen-by-stored-cost.md).

    costs = ModelCosts(registry, engine=Engine.NATIVE, share=0.5)
    table = costs.table(info, model)                  # stored, else measured now and stored
    chosen = table.choose(Scenario.DRIVEN, dt=0.002)  # ResourceExhausted when nothing fits
    chosen.settings                                   # {"estimator": ..., "sigma_points": ...}

The candidates of a scenario, most accurate first: the JITDYN preset's UKF (its own sigma points),
the UKF on simplex points when the preset's are Merwe's (SIMPLEX_LINEAR_FORCE where it applies),
and IEEE 1278's constant-velocity dead reckoning, which always fits. In EXTERNAL and DRIVEN the
linearised filter (EKF, one linearisation a step of up to 10 ms) is timed and shown after them, so
a user can ask for it by name; its gaps were less accurate than dead reckoning's on every big model
measured, so the cost never chooses it.
"""

from __future__ import annotations

import itertools
import logging
import math
import statistics
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final

import mujoco
import numpy as np

from jitdyn.errors import JitdynError, ResourceExhausted
from jitdyn.estimator_settings import SettingValue
from jitdyn.registry import CandidateCost, ModelInfo, ModelRegistry
from jitdyn.server.estimation.config import Engine, preset_values, resolve_config
from jitdyn.server.estimation.factory import make_estimator
from jitdyn.server.estimation.interface import Measurement
from jitdyn.server.estimation.layout import linear_force_applies
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.vocabulary import EstimatorKind, ForceModel, Preset, Scenario, SigmaScheme, proto_enum_name

_log = logging.getLogger(__name__)

__all__ = [
    "CHOICE_RATES",
    "EKF_SCENARIOS",
    "STEPS",
    "Chosen",
    "CostTable",
    "ModelCosts",
    "candidates",
    "measure_costs",
]

# The physics steps a tick spans in the timed runs of each candidate. A tick's cost is not affine in
# its steps: the forecast combination of DRIVEN scores every horizon up to 0.5 s, so a shorter tick
# has more of them (myoElbow DRIVEN's simplex set: 1.07 ms at one 2 ms step, less at four).
STEPS: Final = (1, 2, 5, 10)
# Cycles run and timed per run: the first ones warm the estimator, the median of the others counts.
_WARM: Final = 2
_TIMED: Final = 7
# A first cycle slower than this (a chain of 100 links: ~0.2 s at ten steps) is timed 1 + 3 times.
_SLOW_CYCLE: Final = 0.02  # s
_SLOW_RUNS: Final = 4
# The rates `models show` gives the choice at (those the model's timestep allows), beside the
# timestep's own.
CHOICE_RATES: Final = (1000.0, 500.0, 250.0, 200.0, 100.0, 50.0, 20.0)
_MAX_DT: Final = 10.0  # s: the contract's largest dt
_REMEMBERED: Final = 4096  # models whose stored costs a process keeps once read
# The scenarios whose candidates include the linearised filter (EKF), after dead reckoning: timed
# and shown, asked for by name (docs/decisions/0210-the-linearised-filter-as-a-candidate.md).
EKF_SCENARIOS: Final = (Scenario.EXTERNAL, Scenario.DRIVEN)


def candidates(model: mujoco.MjModel, scenario: Scenario) -> list[tuple[EstimatorKind, SigmaScheme | None]]:
    """The estimators a session of `model` in `scenario` may get, most accurate first."""
    preset = preset_values(Preset.JITDYN, model=model, scenario=scenario)
    first = SigmaScheme(str(preset["sigma_points"]))
    simplex = (
        SigmaScheme.SIMPLEX_LINEAR_FORCE
        if linear_force_applies(model, scenario, ForceModel.RANDOM_WALK)
        else SigmaScheme.SIMPLEX
    )
    found: list[tuple[EstimatorKind, SigmaScheme | None]] = [(EstimatorKind.UKF, first)]
    if simplex != first:
        found.append((EstimatorKind.UKF, simplex))
    found.append((EstimatorKind.CONSTANT_VELOCITY, None))
    if scenario in EKF_SCENARIOS:
        found.append((EstimatorKind.EKF, None))
    return found


def _settings(estimator: str, sigma_points: str) -> dict[str, SettingValue]:
    settings: dict[str, SettingValue] = {"estimator": EstimatorKind[estimator]}
    if sigma_points:
        settings["sigma_points"] = SigmaScheme[sigma_points]
    return settings


def _measured(scenario: Scenario) -> frozenset[str]:
    return frozenset({"qpos", "qvel", "ctrl"} if scenario == Scenario.CONTROLLED else {"qpos", "qvel"})


def _cycle_seconds(
    model: mujoco.MjModel,
    scenario: Scenario,
    settings: dict[str, SettingValue],
    *,
    steps: int,
    engine: Engine,
    pool: WorkerPool,
) -> float:
    """The median CPU seconds (this thread's) of one predict + update of a throwaway estimator at
    the model's rest pose, its tick `steps` physics steps long."""
    config = resolve_config(
        model=model,
        scenario=scenario,
        dt=steps * float(model.opt.timestep),
        requested=settings,
        measured=_measured(scenario),
        engine=engine,
    )
    estimator = make_estimator(model, config, pool=pool)
    zeros = np.zeros(model.nv)
    ctrl = np.zeros(model.nu) if scenario == Scenario.CONTROLLED else None
    measurement = Measurement(qpos=model.qpos0.copy(), qvel=zeros, ctrl=ctrl)
    estimator.initialise(measurement)
    timed: list[float] = []
    runs = _WARM + _TIMED
    while len(timed) < runs:
        started = time.thread_time()
        estimator.step(ctrl=ctrl, m=measurement)
        timed.append(time.thread_time() - started)
        if timed[0] > _SLOW_CYCLE:
            runs = _SLOW_RUNS  # a model this slow costs seconds a run: fewer cycles, the median still
    return statistics.median(timed[1 if runs == _SLOW_RUNS else _WARM :])


def measure_costs(model: mujoco.MjModel, *, engine: Engine) -> list[CandidateCost]:
    """Every candidate's cost on `model`, in every scenario it can run (CONTROLLED needs actuators):
    a fixed number of cycles at each of STEPS physics steps a tick, on one thread (a private pool
    of one worker, so that all of the work is on the thread timed)."""
    scenarios = [s for s in Scenario if s != Scenario.CONTROLLED or model.nu > 0]
    costs: list[CandidateCost] = []
    if model.nv == 0:
        return costs  # nothing moves: no estimator runs (an open says so), nothing to time
    with WorkerPool(1) as pool:
        for scenario in scenarios:
            for estimator, sigma in candidates(model, scenario):
                settings = _settings(estimator.name, sigma.name if sigma else "")
                try:
                    seconds = tuple(
                        _cycle_seconds(model, scenario, settings, steps=steps, engine=engine, pool=pool)
                        for steps in STEPS
                    )
                except (JitdynError, ValueError, ArithmeticError, np.linalg.LinAlgError) as error:
                    # A candidate this model cannot run is none of its candidates; the model
                    # registers all the same, and an open that asks for it is told why.
                    _log.warning("%s in %s cannot be timed on this model: %s", estimator, scenario, error)
                    continue
                costs.append(
                    CandidateCost(
                        scenario=scenario.name,
                        estimator=estimator.name,
                        sigma_points=sigma.name if sigma else "",
                        steps=STEPS,
                        seconds=seconds,
                    )
                )
    return costs


def describe(cost: CandidateCost) -> str:
    """ "ESTIMATOR_UKF with SIGMA_POINTS_MERWE", or the dead-reckoning estimator's name alone."""
    name = proto_enum_name(EstimatorKind[cost.estimator])
    if not cost.sigma_points:
        return name
    return f"{name} with {proto_enum_name(SigmaScheme[cost.sigma_points])}"


@dataclass(frozen=True, kw_only=True)
class Chosen:
    """The estimator an open gets by cost: its settings and why."""

    settings: dict[str, SettingValue]
    reason: str


@dataclass(frozen=True, kw_only=True)
class CostTable:
    """A model's stored costs, on a server that gives a tick at most `share` of dt."""

    costs: tuple[CandidateCost, ...]
    timestep: float
    share: float

    def of(self, scenario: Scenario) -> list[CandidateCost]:
        """The candidates of `scenario`, most accurate first (none when it was not measured)."""
        return [cost for cost in self.costs if cost.scenario == scenario.name]

    def steps(self, dt: float) -> int:
        return max(1, round(dt / self.timestep))

    def fits(self, cost: CandidateCost, dt: float) -> bool:
        return cost.at(self.steps(dt)) <= self.share * dt

    def max_rate(self, cost: CandidateCost) -> float:
        """The highest rate (Hz, dt a whole number of timesteps, at most 10 s) whose tick `cost`
        fits; 0: none. Solved on each straight piece of the cost, from the shortest tick up."""
        budget = self.share * self.timestep  # s of a tick's budget per step it spans
        last = max(1, math.floor(_MAX_DT / self.timestep + 1e-9))
        xs = cost.steps
        bounds = [(1, xs[0]), *itertools.pairwise(xs), (xs[-1], last)]
        for low, high in bounds:
            low, high = min(low, last), min(high, last)
            if self._fits_steps(cost, low):
                return 1.0 / (low * self.timestep)
            slope = (cost.at(high) - cost.at(low)) / (high - low) if high > low else 0.0
            spare = budget - slope  # what each further step leaves of its budget
            if spare > 0:
                # cost.at(low) + slope (k - low) <= budget k  <=>  k >= (at(low) - slope low) / spare
                steps = max(low, math.ceil((cost.at(low) - slope * low) / spare - 1e-9))
                if steps <= high and self._fits_steps(cost, steps):
                    return 1.0 / (steps * self.timestep)
                if steps + 1 <= high and self._fits_steps(cost, steps + 1):
                    return 1.0 / ((steps + 1) * self.timestep)
        return 0.0

    def _fits_steps(self, cost: CandidateCost, steps: int) -> bool:
        return cost.at(steps) <= self.share * steps * self.timestep

    def pick(self, scenario: Scenario, dt: float) -> CandidateCost | None:
        """The most accurate candidate of `scenario` that fits a tick of `dt`; None when none does."""
        return next((cost for cost in self.of(scenario) if self.fits(cost, dt)), None)

    def rates(self) -> list[float]:
        """The rates `models show` gives the choice at: the timestep's own and CHOICE_RATES'
        whole multiples of it, fastest first."""
        found = {round(1.0 / self.timestep, 6)}
        for rate in CHOICE_RATES:
            steps = 1.0 / rate / self.timestep
            if steps >= 1 - 1e-9 and abs(steps - round(steps)) < 1e-6:
                found.add(rate)
        return sorted(found, reverse=True)

    def choose(self, scenario: Scenario, dt: float) -> Chosen:
        """The most accurate candidate that fits dt, and why; ResourceExhausted naming the highest
        rate that would fit when none does."""
        listed = self.of(scenario)
        chosen = self.pick(scenario, dt)
        budget = f"{self.share:g} of dt {dt * 1e3:g} ms (--max-tick-share)"
        steps = self.steps(dt)
        if chosen is None:
            raise ResourceExhausted(_refusal(self, listed, scenario, dt, budget))
        head = f"chosen by cost, measured once when the model was registered: {describe(chosen)}"
        spent = f"{chosen.at(steps) * 1e3:.3g} ms a tick"
        if chosen is listed[0]:
            reason = f"{head}, the most accurate candidate, costs {spent}, within {budget}"
        else:
            over = "; ".join(
                f"{describe(cost)} costs {cost.at(steps) * 1e3:.3g} ms"
                for cost in listed[: listed.index(chosen)]
            )
            reason = f"{head} costs {spent}, within {budget}; {over}, over it"
        return Chosen(
            settings=_settings(chosen.estimator, chosen.sigma_points),
            reason=f"{reason} (name open.estimator.estimator or sigma_points to choose)",
        )


def _refusal(
    table: CostTable, listed: list[CandidateCost], scenario: Scenario, dt: float, budget: str
) -> str:
    """Why no candidate fits, and the highest rate at which one would."""
    steps = table.steps(dt)
    best = max(listed, key=table.max_rate)
    rate = table.max_rate(best)
    tried = "; ".join(f"{describe(cost)} {cost.at(steps) * 1e3:.3g} ms" for cost in listed)
    fits = (
        f"at most {rate:g} Hz (open.dt {1 / rate:g} s) fits {describe(best)}"
        if rate > 0
        else "no rate fits any of them"
    )
    return (
        f"no estimator of this model fits a tick of {1 / dt:g} Hz in {proto_enum_name(scenario)} within "
        f"{budget}; a tick costs {tried} (measured when the model was registered): {fits}"
    )


class ModelCosts:
    """The stored costs of models, measured (once per model, whatever the replica) where missing.
    What is stored for a content id never changes (the first measurement stored stands), so it is
    kept here once read: an open does not ask the index again."""

    def __init__(
        self,
        registry: ModelRegistry,
        *,
        engine: Engine,
        share: float,
        max_nv: int | None = None,
        measured: Callable[[], None] | None = None,
    ) -> None:
        self._registry = registry
        self._engine = engine
        self._share = share
        self._max_nv = max_nv  # a model with more dofs opens no session here: it is not timed
        # Told when a measurement ends: admission starts its window again (Admission.start_window),
        # so that the seconds of CPU it took are not read as its sessions' load and refuse the next.
        self._measured = measured
        self._lock = threading.Lock()  # one measurement at a time in this process
        self._known: dict[str, tuple[CandidateCost, ...]] = {}

    def _table(self, info: ModelInfo, costs: tuple[CandidateCost, ...]) -> CostTable:
        return CostTable(costs=costs, timestep=info.timestep, share=self._share)

    def _read(self, model_ids: list[str]) -> dict[str, tuple[CandidateCost, ...]]:
        found = {i: self._known[i] for i in model_ids if i in self._known}
        missing = [i for i in model_ids if i not in found]
        if missing:
            read = self._registry.costs(missing)
            if len(self._known) < _REMEMBERED:
                self._known.update(read)
            found.update(read)
        return found

    def stored(self, infos: list[ModelInfo]) -> dict[str, CostTable]:
        """The tables of those of `infos` whose costs are stored; nothing is measured."""
        found = self._read([info.id for info in infos])
        return {info.id: self._table(info, found[info.id]) for info in infos if info.id in found}

    def table(self, info: ModelInfo, model: mujoco.MjModel | None = None) -> CostTable:
        """The model's table: stored, else measured now (blocking: a few seconds for the largest
        models) and stored. A model registered before costs were measured is measured at its
        first open or show."""
        known = self._read([info.id]).get(info.id)
        if known is None and self._max_nv is not None and info.nv > self._max_nv:
            return self._table(info, ())  # not stored: a server that allows it measures it
        if known is None:
            with self._lock:
                known = self._read([info.id]).get(info.id)
                if known is None:
                    model = model if model is not None else self._registry.load(info.id, tenant=info.tenant)
                    try:
                        known = self._registry.store_costs(info.id, measure_costs(model, engine=self._engine))
                    finally:
                        if self._measured is not None:
                            self._measured()
                    self._known[info.id] = known
        return self._table(info, known)
