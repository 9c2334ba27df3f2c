"""The settings of one session's estimator: `EstimatorConfig`, the presets that fill what a session
leaves unset (`preset_values`), and `resolve_config`, which puts a session's settings together.

Every setting's name, type and range is a row of jitdyn.estimator_settings.SETTINGS; this module
checks through it and adds what needs the model (dt against the timestep, n + kappa > 0)::

    config = resolve_config(model=model, scenario=Scenario.PASSIVE, dt=0.05, requested={"r": 0.02},
                            model_defaults={}, preset=Preset.JITDYN, measured={"qpos", "qvel"})
    estimator = make_estimator(model, config, pool=pool)      # estimation/factory.py
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Final

import mujoco
import numpy as np

from jitdyn.errors import InvalidArgument
from jitdyn.estimator_settings import SETTINGS, SettingValue, check_for_scenario
from jitdyn.estimator_settings import steps_per_tick as tick_steps
from jitdyn.roles import JointRole
from jitdyn.server.estimation.layout import linear_force_applies, state_dimension
from jitdyn.vocabulary import (
    Channel,
    EstimatorKind,
    ForceModel,
    Forecast,
    NoiseModel,
    Preset,
    Scenario,
    SigmaScheme,
    WrongModel,
    parse,
)

__all__ = [
    "CHANNELS",
    "LARGE_STATE",
    "SETTING_FIELDS",
    "Engine",
    "EstimatorConfig",
    "check_against_model",
    "default_scenario",
    "is_driven",
    "is_pendulum_like",
    "preset_values",
    "resolve_config",
    "steps_per_tick",
]

CHANNELS: Final = frozenset(c.value for c in Channel)

# The JITDYN preset switches to simplex points (n + 1 instead of 2n + 1) from this state dimension
# on, to keep myoHand's 46 states inside a 2 ms tick (benchmarks/RESULTS.md); in DRIVEN, to simplex
# points over [q, qd] with the force beside them (2 nv + 1 instead of 3 nv + 1).
LARGE_STATE: Final = 32

# JITDYN's DRIVEN defaults (docs/experiments.md, "Dead reckoning over gaps", says how they were chosen).
DRIVEN_FORCE_MODEL: Final = ForceModel.RANDOM_WALK
DRIVEN_FORCE_VAR: Final = 10.0
DRIVEN_Q_VAR: Final = 1e-4
DRIVEN_ALPHA: Final = 0.3
DRIVEN_R: Final = 1e-2


class Engine(enum.Enum):
    """What computes a UKF's algebra. Not a session setting (nothing a client asks for or sees):
    the preset chooses it, and both give the same numbers (tests/server/test_fast.py)."""

    FILTERPY = "FILTERPY"  # filterpy's UnscentedKalmanFilter: the THESIS preset's, as the thesis ran
    FAST = "FAST"  # estimation/fast.py: array operations over the sigma set, in Python
    NATIVE = "NATIVE"  # estimation/native/: the same filter compiled, the JITDYN preset's


# Settings a request or a model's metadata may set: every row of the table but the preset, which
# chooses the others.
SETTING_FIELDS: Final = tuple(name for name in SETTINGS if name != "preset")


@dataclass(frozen=True)
class EstimatorConfig:
    """Every estimator setting of one session, complete and checked.

    The setting fields take what the settings table's rows take (a member or its name; a finite
    number in range) and hold the member or the float. Checks that need the model (n + kappa > 0,
    dt against the timestep) are `check_against_model`'s.
    """

    estimator: EstimatorKind
    scenario: Scenario
    sigma_points: SigmaScheme
    alpha: float  # spread of the sigma points, (0, 1]
    beta: float  # prior knowledge of the distribution (2: Gaussian)
    kappa: float  # secondary scaling; n + kappa > 0 for Merwe points
    p0: float  # P0 = p0 I, > 0
    q_var: float  # variance of the discrete white-noise process model, >= 0
    r: float  # R = r I over the measured channels, > 0
    dt: float  # tick, s
    steps_per_tick: int  # physics steps per tick: dt / model timestep
    measured: frozenset[str] = field(default_factory=lambda: frozenset({"qpos", "qvel"}))
    # DRIVEN: the unknown force's evolution, and its process noise as an acceleration intensity,
    # (m/s^2)^2/s or (rad/s^2)^2/s for RANDOM_WALK, (m/s^3)^2/s or (rad/s^3)^2/s for the rate of
    # INTEGRATED_RANDOM_WALK, scaled into force units by the mass matrix's diagonal at qpos0.
    force_model: ForceModel = ForceModel.RANDOM_WALK
    force_var: float = 1e4
    # ADAPTIVE: R and Q follow the innovations within bounds, a wrong model is absorbed.
    noise_model: NoiseModel = NoiseModel.FIXED
    # What answers a tick without a frame: the filter, or the scored combination (DRIVEN only).
    forecast: Forecast = Forecast.FILTER
    # What a NIS far out does: nothing, PASSIVE becomes DRIVEN, or a restart from the frame.
    wrong_model: WrongModel = WrongModel.KEEP
    # Not a setting: the implementation of the filter's algebra (resolve_config: the preset's).
    engine: Engine = Engine.FILTERPY
    # Not a setting: with the NATIVE engine, the forecast combination in it too (False: the Python
    # ForecastCombiner, its reference, which tests and benchmarks run beside it; foresight.py).
    native_forecast: bool = True
    # Not a setting: with the NATIVE engine, a tick's numeric steps in one native call (False: one
    # call a step, their reference, which tests and benchmarks run beside it; native/tick.py).
    native_tick: bool = True
    # Not settings: the model's joint roles (jitdyn.roles), which the prior of human motion matches
    # (estimation/prior.py; none: no prior), and the prior's subjects left out (model tags
    # "prior.without.<subject>": a recording of that person is never scored by a prior of it).
    roles: tuple[JointRole, ...] = ()
    prior_without: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        set_ = object.__setattr__  # frozen: normalise through the back door, once, here
        set_(self, "scenario", parse(Scenario, self.scenario, argument="scenario"))
        for name in SETTING_FIELDS:
            set_(self, name, SETTINGS[name].check(getattr(self, name), argument=name))
        set_(self, "dt", _seconds(self.dt))
        steps = self.steps_per_tick
        if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 1:
            raise InvalidArgument(f"steps_per_tick must be an integer >= 1, got {steps!r}")
        set_(self, "steps_per_tick", int(steps))
        set_(self, "measured", _channels(self.measured))
        if not isinstance(self.engine, Engine):
            raise InvalidArgument(f"engine must be an Engine, got {self.engine!r}")


def _seconds(dt: object) -> float:
    if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not math.isfinite(dt) or dt <= 0.0:
        raise InvalidArgument(f"dt must be a positive number of seconds, got {dt!r}")
    return float(dt)


def _channels(measured: object) -> frozenset[str]:
    if isinstance(measured, str):
        raise InvalidArgument(f"measured must be a set of channel names, got the string {measured!r}")
    if not isinstance(measured, Iterable):
        raise InvalidArgument(f"measured must be a set of channel names, got {measured!r}")
    channels = frozenset(str(c).lower() for c in measured)
    if not channels <= CHANNELS:
        raise InvalidArgument(f"measured must be a subset of {sorted(CHANNELS)}, got {sorted(channels)}")
    if Channel.QPOS not in channels:
        raise InvalidArgument(f"measured must include 'qpos', got {sorted(channels)}")
    return channels


def is_driven(model: mujoco.MjModel) -> bool:
    """A model whose motion something drives: it has actuators (motors, muscles)."""
    return int(model.nu) > 0


def default_scenario(model: mujoco.MjModel) -> tuple[Scenario, str]:
    """The scenario of a session whose client names none, and why."""
    if is_driven(model):
        return Scenario.DRIVEN, (
            f"the model has {int(model.nu)} actuators, whose forces a session does not see: "
            "the unknown generalized force is estimated as part of the state"
        )
    return Scenario.PASSIVE, "the model has no actuators: only its own passive forces act"


def is_pendulum_like(model: mujoco.MjModel) -> bool:
    """The thesis' pendulums, as a rule for any model: hinge joints only and no activation state.

    The thesis used Julier's kappa = 3 - n and Q variance 0.2 (controlled) for its 1-3 link
    pendulums, and kappa = 0, Q variance 5 (controlled) for everything else it ran (the biped, with
    slide joints and contact; myoElbow and myoHand, with muscle activations). Hinges-only and
    na = 0 separates the two exactly on the thesis' models.
    """
    hinge = int(mujoco.mjtJoint.mjJNT_HINGE)
    return bool(model.na == 0 and model.njnt > 0 and all(int(t) == hinge for t in model.jnt_type))


def preset_values(
    preset: Preset | str, *, model: mujoco.MjModel, scenario: Scenario | str
) -> dict[str, SettingValue]:
    """Every setting of `preset` (every name of SETTING_FIELDS) for this model and scenario.

    THESIS: the thesis' chapter 4 exactly (experiments/thesis.py runs it; docs/experiments.md
    gives its tables beside the thesis' own): Merwe points, alpha 0.001, beta 2, P0 0.2 I,
    R 0.01 I; kappa = 3 - n (n = state dimension: 3 - 2 dof passive and external, 3 - 3 dof
    controlled) for pendulum-like models and 0 for the others (`is_pendulum_like`); Q variance 0.1
    passive, 0.2 controlled (5 for models that are not pendulum-like: the biped), 50 external.

    JITDYN: the thesis' noise model with sigma points that stay numerically sound at any n, and
    adaptive noise, the scored forecast and a response to a wrong model where the force is unknown
    (`_jitdyn_values`; docs/decisions/0020-jitdyn-sigma-points.md says why).
    """
    preset = parse(Preset, preset, argument="preset")
    scenario = parse(Scenario, scenario, argument="scenario")
    pendulum = is_pendulum_like(model)
    q_var = {
        Scenario.PASSIVE: 0.1,
        Scenario.CONTROLLED: 0.2 if pendulum else 5.0,
        Scenario.EXTERNAL: 50.0,
        Scenario.DRIVEN: 50.0,
    }[scenario]
    common: dict[str, SettingValue] = {
        "estimator": EstimatorKind.UKF,
        "beta": 2.0,
        "p0": 0.2,
        "q_var": q_var,
        "r": 0.01,
        "force_model": DRIVEN_FORCE_MODEL,
        "force_var": DRIVEN_FORCE_VAR,
    }
    n = state_dimension(model, scenario, DRIVEN_FORCE_MODEL)
    if preset == Preset.THESIS:
        return {
            **common,
            "sigma_points": SigmaScheme.MERWE,
            "alpha": 0.001,
            "kappa": float(3 - n) if pendulum else 0.0,
            "noise_model": NoiseModel.FIXED,
            "forecast": Forecast.FILTER,
            "wrong_model": WrongModel.KEEP,
        }
    return {**common, **_jitdyn_values(model, scenario, n)}


def _jitdyn_values(model: mujoco.MjModel, scenario: Scenario, n: int) -> dict[str, SettingValue]:
    """JITDYN's settings beyond the thesis' noise model, for a state of dimension n.

    alpha = 1, beta = 2, kappa = 3 - n only while that is positive: every Merwe weight is O(1) at
    any n. From n = LARGE_STATE on, simplex points (SIMPLEX_LINEAR_FORCE in DRIVEN where it
    applies). DRIVEN: the unknown force carries what the thesis' q_var stood for, the spread is
    narrower (alpha 0.3), the noise adaptive, and gaps below LARGE_STATE are answered by the scored
    combination. A wrong model: PASSIVE becomes DRIVEN, CONTROLLED and EXTERNAL restart
    (docs/decisions/0021-wrong-model-restart.md), DRIVEN's adaptive noise absorbs it.
    """
    driven = scenario == Scenario.DRIVEN
    values: dict[str, SettingValue] = {"q_var": DRIVEN_Q_VAR, "r": DRIVEN_R} if driven else {}
    if n < LARGE_STATE:
        sigma_points = SigmaScheme.MERWE
    elif linear_force_applies(model, scenario, DRIVEN_FORCE_MODEL):
        sigma_points = SigmaScheme.SIMPLEX_LINEAR_FORCE
    else:
        sigma_points = SigmaScheme.SIMPLEX
    wrong_model = {
        Scenario.PASSIVE: WrongModel.DRIVEN,
        Scenario.CONTROLLED: WrongModel.RESTART,
        Scenario.EXTERNAL: WrongModel.RESTART,
    }.get(scenario, WrongModel.KEEP)
    return {
        **values,
        "sigma_points": sigma_points,
        "alpha": DRIVEN_ALPHA if driven else 1.0,
        "kappa": float(max(0, 3 - n)),
        "noise_model": NoiseModel.ADAPTIVE if driven else NoiseModel.FIXED,
        "forecast": Forecast.COMBINED if driven and n < LARGE_STATE else Forecast.FILTER,
        "wrong_model": wrong_model,
    }


def _ekf_values(scenario: Scenario) -> dict[str, SettingValue]:
    """What the linearised filter runs where a request or the model's defaults set nothing: fixed
    noise, the filter's own answer over a gap, and in PASSIVE the guard's restart in place of the
    switch to DRIVEN, which is the UKF's (estimation/linearised.py)."""
    values: dict[str, SettingValue] = {"noise_model": NoiseModel.FIXED, "forecast": Forecast.FILTER}
    if scenario == Scenario.PASSIVE:
        values["wrong_model"] = WrongModel.RESTART
    return values


def _check_names(values: Mapping[str, object], argument: str) -> None:
    unknown = sorted(set(values) - set(SETTING_FIELDS))
    if unknown:
        raise InvalidArgument(
            f"{argument} has unknown settings {unknown}; expected some of {list(SETTING_FIELDS)}"
        )


def steps_per_tick(model: mujoco.MjModel, dt: float) -> int:
    """dt / the model's timestep, which must be a whole number >= 1 (the settings table's rule)."""
    return tick_steps(dt, float(model.opt.timestep), argument="dt")


def check_against_model(model: mujoco.MjModel, config: EstimatorConfig) -> None:
    """The checks of `config` that need the model."""
    expected = steps_per_tick(model, config.dt)
    if config.steps_per_tick != expected:
        raise InvalidArgument(
            f"steps_per_tick must be dt / timestep = {expected}, got {config.steps_per_tick}"
        )
    n = state_dimension(model, config.scenario, config.force_model)
    if (
        config.estimator == EstimatorKind.UKF
        and config.sigma_points == SigmaScheme.MERWE
        and n + config.kappa <= 0
    ):
        raise InvalidArgument(
            f"kappa must make n + kappa > 0 for Merwe sigma points (state dimension n = {n}), "
            f"got kappa = {config.kappa}"
        )


_NONE_SET: Final[Mapping[str, object]] = MappingProxyType({})


def resolve_config(
    *,
    model: mujoco.MjModel,
    scenario: Scenario | str,
    dt: float,
    requested: Mapping[str, object] = _NONE_SET,
    model_defaults: Mapping[str, object] = _NONE_SET,
    preset: Preset | str = Preset.JITDYN,
    measured: Iterable[str],
    engine: Engine = Engine.NATIVE,
) -> EstimatorConfig:
    """The complete settings of a session: each field from the request if set there, else from the
    model's defaults for the scenario, else from the preset (`preset_values`).

    requested, model_defaults: some of SETTING_FIELDS (default: none set). engine: what computes
    the JITDYN preset's filter (NATIVE or its reference FAST); THESIS always runs FILTERPY.
    Raises InvalidArgument naming the first bad field.
    """
    _check_names(requested, "requested")
    _check_names(model_defaults, "model_defaults")
    if isinstance(measured, str):
        raise InvalidArgument(f"measured must be a set of channel names, got the string {measured!r}")
    scenario = parse(Scenario, scenario, argument="scenario")
    chosen = {**model_defaults, **requested}
    values = {**preset_values(preset, model=model, scenario=scenario), **chosen}
    if values["sigma_points"] == SigmaScheme.SIMPLEX_LINEAR_FORCE and "sigma_points" not in chosen:
        force_model = parse(ForceModel, values["force_model"], argument="force_model")
        if not linear_force_applies(model, scenario, force_model):
            # The preset's choice for its own force model; a request for another keeps the force
            # in the points, and the settings echoed back say so.
            values["sigma_points"] = SigmaScheme.SIMPLEX
    if SETTINGS["estimator"].check(values["estimator"], argument="estimator") == EstimatorKind.EKF:
        values.update({k: v for k, v in _ekf_values(scenario).items() if k not in chosen})
    # Checked and normalised against the table by EstimatorConfig itself.
    settings: dict[str, Any] = {name: values[name] for name in SETTING_FIELDS}
    config = EstimatorConfig(
        **settings,
        scenario=scenario,
        dt=dt,
        steps_per_tick=steps_per_tick(model, dt),
        measured=frozenset(measured),
        engine=Engine.FILTERPY if parse(Preset, preset, argument="preset") == Preset.THESIS else engine,
    )
    check_for_scenario(config.scenario, {"wrong_model": config.wrong_model}, argument="settings")
    check_against_model(model, config)
    return config
