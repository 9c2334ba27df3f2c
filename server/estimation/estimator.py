"""What the session runtime needs from a state estimator, and how one is configured
(`estimation/factory.py` makes one).

A session resolves its settings once (`resolve_config`: the request, then the model's defaults,
then a preset), makes its estimator from them on the shared worker pool, and then drives it one
tick at a time::

    config = resolve_config(model=model, scenario="PASSIVE", dt=0.05, requested={"r": 0.02},
                            model_defaults={}, preset="JITDYN", measured={"qpos", "qvel"})
    estimator = make_estimator(model, config, pool=pool)
    estimator.initialise(first)                       # tick 0
    estimate = estimator.predict(ctrl=None)           # a later tick without its frame
    estimator.advance(ctrl=None)                      # a later tick with its frame: advance ...
    estimate = estimator.update(frame)                # ... and answer from the frame

Estimators: the unscented Kalman filter (estimation/ukf.py; a PASSIVE one that may become DRIVEN,
estimation/switch.py) and the dead-reckoning extrapolators of IEEE 1278 (estimation/deadreckoning.py). State layouts: x = [q (nq), qd (nv)] in PASSIVE and EXTERNAL,
[q, qd, qdd (nv)] in CONTROLLED, and for the UKF in DRIVEN [q, qd, f (nv)] (force model RANDOM_WALK)
or [q, qd, f, fd (nv)] (INTEGRATED_RANDOM_WALK), f the unknown generalized force; covariances live
in the tangent space, (k nv, k nv) with k = 2, 3 or 4, which differs from len(x) only for models
with ball or free joints (estimation/manifold.py).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Final, Protocol, TypeVar, runtime_checkable

import mujoco
import numpy as np

from jitdyn.errors import InvalidArgument
from jitdyn.server.estimation.manifold import has_manifold

__all__ = [
    "CHANNELS",
    "LARGE_STATE",
    "SETTING_FIELDS",
    "Channel",
    "Estimate",
    "Estimator",
    "EstimatorConfig",
    "EstimatorKind",
    "ForceModel",
    "Forecast",
    "Measurement",
    "NoiseModel",
    "Preset",
    "Scenario",
    "SigmaScheme",
    "WrongModel",
    "check_against_model",
    "check_measurement",
    "check_vector",
    "default_scenario",
    "derivative_order",
    "force_blocks",
    "is_pendulum_like",
    "linear_force_applies",
    "preset_values",
    "read_only",
    "resolve_config",
    "state_dimension",
    "steps_per_tick",
]


class EstimatorKind(enum.StrEnum):
    UKF = "UKF"
    STATIC = "STATIC"
    CONSTANT_VELOCITY = "CONSTANT_VELOCITY"
    CONSTANT_ACCELERATION = "CONSTANT_ACCELERATION"


class Scenario(enum.StrEnum):
    PASSIVE = "PASSIVE"
    CONTROLLED = "CONTROLLED"
    EXTERNAL = "EXTERNAL"
    DRIVEN = "DRIVEN"


class ForceModel(enum.StrEnum):
    """How the unknown generalized force of DRIVEN evolves between ticks."""

    RANDOM_WALK = "RANDOM_WALK"  # f' = f + w: the force is held over a prediction
    INTEGRATED_RANDOM_WALK = "INTEGRATED_RANDOM_WALK"  # f' = f + fd dt, fd' = fd + w: its trend is kept


class Forecast(enum.StrEnum):
    """What answers a tick without a frame (estimation/forecast.py)."""

    FILTER = "FILTER"  # the filter's predicted mean
    COMBINED = "COMBINED"  # the least-error-variance combination of the model's rollout and the
    # IEEE 1278 extrapolators, weighted by how each did on the session's own frames


class WrongModel(enum.StrEnum):
    """What a UKF does when its NIS says its model is wrong."""

    KEEP = "KEEP"  # nothing but the divergence guard (the thesis)
    DRIVEN = "DRIVEN"  # PASSIVE: the session's filter becomes DRIVEN, from that frame (switch.py)
    RESTART = "RESTART"  # start again from the frame after RESTART_UPDATES far out (ukf.py)


class NoiseModel(enum.StrEnum):
    """Whether R and Q stay as configured or follow the innovations (estimation/adaptive.py)."""

    FIXED = "FIXED"
    ADAPTIVE = "ADAPTIVE"


class SigmaScheme(enum.StrEnum):
    MERWE = "MERWE"
    SIMPLEX = "SIMPLEX"
    UNIFORM = "UNIFORM"
    # DRIVEN, random walk, no ball or free joints: simplex points over [q, qd], the unknown force
    # carried linearly beside them (estimation/ukf.py); elsewhere SIMPLEX.
    SIMPLEX_LINEAR_FORCE = "SIMPLEX_LINEAR_FORCE"


class Preset(enum.StrEnum):
    JITDYN = "JITDYN"
    THESIS = "THESIS"


class Channel(enum.StrEnum):
    QPOS = "qpos"
    QVEL = "qvel"
    QACC = "qacc"
    CTRL = "ctrl"


CHANNELS: Final = frozenset(c.value for c in Channel)

# The JITDYN preset switches to simplex points (n + 1 instead of 2n + 1) from this state dimension
# on: myoHand's 46 states at a 2 ms tick need it to stay inside the tick (benchmarks/RESULTS.md);
# in DRIVEN, to simplex points over [q, qd] with the force beside them (2 nv + 1 instead of 3 nv + 1).
LARGE_STATE: Final = 32

# JITDYN's DRIVEN defaults (docs/experiments.md, "Dead reckoning over gaps", says how they were chosen).
DRIVEN_FORCE_MODEL: Final = ForceModel.RANDOM_WALK
DRIVEN_FORCE_VAR: Final = 10.0
DRIVEN_Q_VAR: Final = 1e-4
DRIVEN_ALPHA: Final = 0.3
DRIVEN_R: Final = 1e-2

# Settings a request or a model's metadata may set, and their types.
SETTING_FIELDS: Final = (
    "estimator",
    "sigma_points",
    "alpha",
    "beta",
    "kappa",
    "p0",
    "q_var",
    "r",
    "force_model",
    "force_var",
    "noise_model",
    "forecast",
    "wrong_model",
)


_E = TypeVar("_E", bound=enum.StrEnum)


def _enum(kind: type[_E], value: object, name: str) -> _E:
    if isinstance(value, str):
        try:
            return kind(value)
        except ValueError:
            pass
    raise InvalidArgument(f"{name} must be one of {[k.value for k in kind]}, got {value!r}")


def _real(value: object, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise InvalidArgument(f"{name} must be a number, got {value!r}")
    number = float(value)
    if not math.isfinite(number):
        raise InvalidArgument(f"{name} must be finite, got {number}")
    return number


@dataclass(frozen=True)
class EstimatorConfig:
    """Every estimator setting of one session, complete and checked.

    Strings are accepted for the enum fields and become the enums (which compare equal to them).
    Checks that need the model (n + kappa > 0, dt against the timestep) are `resolve_config`'s
    and `make_estimator`'s.
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

    def __post_init__(self) -> None:
        set_ = object.__setattr__  # frozen: normalise through the back door, once, here
        set_(self, "estimator", _enum(EstimatorKind, self.estimator, "estimator"))
        set_(self, "scenario", _enum(Scenario, self.scenario, "scenario"))
        set_(self, "sigma_points", _enum(SigmaScheme, self.sigma_points, "sigma_points"))
        set_(self, "force_model", _enum(ForceModel, self.force_model, "force_model"))
        set_(self, "noise_model", _enum(NoiseModel, self.noise_model, "noise_model"))
        set_(self, "forecast", _enum(Forecast, self.forecast, "forecast"))
        set_(self, "wrong_model", _enum(WrongModel, self.wrong_model, "wrong_model"))
        for name in ("alpha", "beta", "kappa", "p0", "q_var", "r", "dt", "force_var"):
            set_(self, name, _real(getattr(self, name), name))
        if not 0.0 < self.alpha <= 1.0:
            raise InvalidArgument(f"alpha must be in (0, 1], got {self.alpha}")
        if self.p0 <= 0.0:
            raise InvalidArgument(f"p0 must be > 0, got {self.p0}")
        if self.q_var < 0.0:
            raise InvalidArgument(f"q_var must be >= 0, got {self.q_var}")
        if self.force_var < 0.0:
            raise InvalidArgument(f"force_var must be >= 0, got {self.force_var}")
        if self.r <= 0.0:
            # R = 0 makes the innovation covariance singular as soon as P collapses onto the
            # measurement: the gain is then undefined.
            raise InvalidArgument(f"r must be > 0, got {self.r}")
        if self.dt <= 0.0:
            raise InvalidArgument(f"dt must be > 0 seconds, got {self.dt}")
        steps = self.steps_per_tick
        if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 1:
            raise InvalidArgument(f"steps_per_tick must be an integer >= 1, got {steps!r}")
        set_(self, "steps_per_tick", int(steps))
        if isinstance(self.measured, str):
            raise InvalidArgument(
                f"measured must be a set of channel names, got the string {self.measured!r}"
            )
        measured = frozenset(str(c).lower() for c in self.measured)
        if not measured <= CHANNELS:
            raise InvalidArgument(f"measured must be a subset of {sorted(CHANNELS)}, got {sorted(measured)}")
        if Channel.QPOS not in measured:
            raise InvalidArgument(f"measured must include 'qpos', got {sorted(measured)}")
        set_(self, "measured", measured)


@dataclass(frozen=True)
class Measurement:
    """One frame's measured channels: qpos (nq,), qvel (nv,), qacc (nv,), ctrl (nu,); None when the
    channel is not measured. Estimators check shapes and finiteness themselves.
    """

    qpos: np.ndarray
    qvel: np.ndarray | None = None
    qacc: np.ndarray | None = None
    ctrl: np.ndarray | None = None


@dataclass(frozen=True)
class Estimate:
    """An estimator's answer for one tick. Every array is a read-only copy.

    qpos (nq,), qvel (nv,), qacc (nv,); state: the estimator's own mean (see the module docstring
    for its layouts); covariance (n, n) in the tangent space, None for dead reckoning; nis:
    normalised innovation squared of the measurement just used, None when none was (or it was not
    finite); reinitialised: the divergence guard restarted the estimator from a measurement;
    adapted: the adaptive noise model changed R or Q by more than a tenth since the last estimate
    that said so; absorbed: the NIS of a window of updates was far outside its interval and the
    filter widened its covariance (and, for a PASSIVE or EXTERNAL filter, started estimating the
    unknown force) to follow the measurements, or the first frame after a gap was past the
    divergence guard's NIS limit and the filter widened its prediction before using it (nis is
    then the NIS against the widened prediction).
    """

    qpos: np.ndarray
    qvel: np.ndarray
    qacc: np.ndarray
    state: np.ndarray
    covariance: np.ndarray | None
    nis: float | None = None
    reinitialised: bool = False
    adapted: bool = False
    absorbed: bool = False
    # Over a gap with Forecast.COMBINED: the weights of the predictors that answered, in
    # estimation/forecast.py's PREDICTORS order; None when the filter answered alone.
    forecast_weights: tuple[float, ...] | None = None
    # The scenario of the filter that answered: a PASSIVE session's becomes DRIVEN when a wrong
    # model is absorbed (estimation/switch.py).
    scenario: str = ""


def check_vector(value: object, size: int, name: str) -> np.ndarray:
    """A private, read-only float64 copy of `value`, which must be finite with shape (size,)."""
    try:
        array = np.array(value, dtype=np.float64)  # a private copy: the caller may reuse its buffer
    except (TypeError, ValueError):
        raise InvalidArgument(f"{name} must be an array of {size} numbers, got {value!r}") from None
    if array.shape != (size,):
        raise InvalidArgument(f"{name} must have shape ({size},), got {array.shape}")
    if not np.isfinite(array).all():
        raise InvalidArgument(f"{name} must be finite, got {array.tolist()}")
    array.flags.writeable = False
    return array


def check_measurement(m: Measurement, model: mujoco.MjModel, measured: frozenset[str]) -> Measurement:
    """A checked, private, read-only copy of `m`: shapes, finiteness, and every measured state
    channel present (ctrl may be absent: a controller on the server may supply it)."""
    missing = sorted(c for c in measured & {"qvel", "qacc"} if getattr(m, c) is None)
    if missing:
        raise InvalidArgument(f"measurement must have the measured channels {missing}, got None")

    def channel(value: np.ndarray | None, size: int, name: str) -> np.ndarray | None:
        return None if value is None else check_vector(value, size, f"measurement.{name}")

    qpos = check_vector(m.qpos, model.nq, "measurement.qpos")
    return Measurement(
        qpos=qpos,
        qvel=channel(m.qvel, model.nv, "qvel"),
        qacc=channel(m.qacc, model.nv, "qacc"),
        ctrl=channel(m.ctrl, model.nu, "ctrl"),
    )


def read_only(array: np.ndarray) -> np.ndarray:
    """A read-only copy of `array`, to hand out."""
    copy = np.array(array, dtype=np.float64)
    copy.flags.writeable = False
    return copy


@runtime_checkable
class Estimator(Protocol):
    """One session's state estimator, driven one tick at a time from one thread."""

    @property
    def state_dimension(self) -> int:
        """Side of the covariance: 2 nv, or 3 nv in CONTROLLED (tangent space)."""
        ...

    @property
    def state_size(self) -> int:
        """len(Estimate.state): nq + nv, or nq + 2 nv in CONTROLLED."""
        ...

    def initialise(self, m: Measurement) -> None:
        """Start from the first frame: x0 from it, P0 = p0 I."""
        ...

    def predict(self, *, ctrl: np.ndarray | None) -> Estimate:
        """Advance one tick (steps_per_tick physics steps). ctrl (nu,): the control over this tick
        in CONTROLLED (None holds the last one); ignored in the other scenarios."""
        ...

    def advance(self, *, ctrl: np.ndarray | None) -> None:
        """predict() without its answer, for a tick whose frame update() answers next: the same
        state afterwards, without the estimate (and the gap's answer) no one reads."""
        ...

    def update(self, m: Measurement) -> Estimate:
        """Correct the tick just predicted with its frame; may re-initialise (divergence guard)."""
        ...

    def extrapolate(self, seconds: float) -> Estimate:
        """The estimate `seconds` ahead (rounded to physics steps), without changing the estimator;
        0 gives the current estimate."""
        ...

    def snapshot(self) -> object:
        """Everything needed to come back to this point (timewarp); immutable, cheap."""
        ...

    def restore(self, snap: object) -> None:
        """Return to a snapshot of this estimator: replaying the same inputs then gives the same
        states, bit for bit."""
        ...


def derivative_order(scenario: Scenario | str) -> int:
    """How many derivatives of q the state holds per dof: 2 ([q, qd]) or 3 ([q, qd, qdd])."""
    return 3 if scenario == Scenario.CONTROLLED else 2


def force_blocks(scenario: Scenario | str, force_model: ForceModel | str = ForceModel.RANDOM_WALK) -> int:
    """How many nv-blocks of unknown force the UKF's state holds: 0, or in DRIVEN 1 (f) or 2 (f, fd)."""
    if scenario != Scenario.DRIVEN:
        return 0
    return 2 if force_model == ForceModel.INTEGRATED_RANDOM_WALK else 1


def state_dimension(
    model: mujoco.MjModel, scenario: Scenario | str, force_model: ForceModel | str = ForceModel.RANDOM_WALK
) -> int:
    """The tangent dimension of the UKF's state: 2 nv, 3 nv in CONTROLLED, 3 or 4 nv in DRIVEN."""
    return (derivative_order(scenario) + force_blocks(scenario, force_model)) * int(model.nv)


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
) -> dict[str, object]:
    """Every setting of `preset` for this model and scenario.

    THESIS: reference/thesis-experiments.md exactly: Merwe points, alpha 0.001, beta 2, P0 0.2 I,
    R 0.01 I; kappa = 3 - n (n = state dimension: 3 - 2 dof passive and external, 3 - 3 dof
    controlled) for pendulum-like models and 0 for the others (`is_pendulum_like`); Q variance 0.1
    passive, 0.2 controlled (5 for models that are not pendulum-like: the biped), 50 external.

    JITDYN: the thesis' noise model (P0, Q variance, R) with sigma points that stay numerically
    sound at any n: alpha = 1, beta = 2 and kappa = 3 - n only while that is positive (n < 3),
    else 0. Then lambda = kappa >= 0 and every Merwe weight is O(1) (Wm0 = kappa / (n + kappa),
    Wi = 1 / (2 (n + kappa)) ~ 0.011 at n = 46, Wc0 = Wm0 + 2), where the thesis' alpha = 0.001,
    kappa = 3 - n gives Wm0 ~ -n / (3 alpha^2) ~ -1.5e7 at n = 46 and an indefinite covariance
    (server/estimation/sigma.py, MerweScaled). From n = LARGE_STATE on, simplex points (n + 1, all weights
    1 / (n + 1)) halve the physics work, which keeps myoHand's cycle inside its 2 ms tick; in
    DRIVEN (random walk, no ball or free joints) SIMPLEX_LINEAR_FORCE keeps the unknown force out
    of them (myoHand: 47 points instead of 70).
    """
    preset = _enum(Preset, preset, "preset")
    scenario = _enum(Scenario, scenario, "scenario")
    force_model = DRIVEN_FORCE_MODEL
    n = state_dimension(model, scenario, force_model)
    pendulum = is_pendulum_like(model)
    q_var = {
        Scenario.PASSIVE: 0.1,
        Scenario.CONTROLLED: 0.2 if pendulum else 5.0,
        Scenario.EXTERNAL: 50.0,
        Scenario.DRIVEN: 50.0,
    }[scenario]
    common: dict[str, object] = {
        "estimator": "UKF",
        "beta": 2.0,
        "p0": 0.2,
        "q_var": q_var,
        "r": 0.01,
        "force_model": force_model.value,
        "force_var": DRIVEN_FORCE_VAR,
    }
    if preset == Preset.THESIS:
        return {
            **common,
            "sigma_points": "MERWE",
            "alpha": 0.001,
            "kappa": float(3 - n) if pendulum else 0.0,
            "noise_model": NoiseModel.FIXED.value,
            "forecast": Forecast.FILTER.value,
            "wrong_model": WrongModel.KEEP.value,
        }
    if scenario == Scenario.DRIVEN:
        # The unknown force carries what the thesis' q_var = 50 stood for; what is left is the
        # model's own error, and the adaptation finds its size.
        # A narrower spread (alpha 0.3: central weight about -10) keeps the sigma points of a force
        # whose variance is large inside the range where a tick's response to it is linear.
        common.update(q_var=DRIVEN_Q_VAR, r=DRIVEN_R)
    large = "SIMPLEX_LINEAR_FORCE" if linear_force_applies(model, scenario, force_model) else "SIMPLEX"
    return {
        **common,
        "sigma_points": large if n >= LARGE_STATE else "MERWE",
        "alpha": DRIVEN_ALPHA if scenario == Scenario.DRIVEN else 1.0,
        "kappa": float(max(0, 3 - n)),
        # Adaptive noise is the default of the scenario a client gets when it names none for a
        # driven model; the thesis' scenarios keep the noise they were measured with unless asked.
        "noise_model": (NoiseModel.ADAPTIVE if scenario == Scenario.DRIVEN else NoiseModel.FIXED).value,
        # The scored combination answers gaps where the force is unknown (docs/experiments.md),
        # below LARGE_STATE: on myoHand (n = 69) its scoring tripled the tick's compute and its gap
        # answers were worse than the filter's (measured, docs/experiments.md).
        "forecast": (
            Forecast.COMBINED if scenario == Scenario.DRIVEN and n < LARGE_STATE else Forecast.FILTER
        ).value,
        # A PASSIVE filter whose innovations say something drives the body becomes DRIVEN. A
        # CONTROLLED or EXTERNAL one that has lost the body starts again from the frame: over a gap
        # a CONTROLLED filter holds the last control while the body's changes, and with its small
        # Q it then took 4 % of each innovation and never caught up (the gaps experiment's
        # CONTROLLED pendulum: 2 rad of error, its truth's law thrown off until MuJoCo gave up).
        # DRIVEN's adaptive noise absorbs a wrong model instead.
        "wrong_model": {
            Scenario.PASSIVE: WrongModel.DRIVEN,
            Scenario.CONTROLLED: WrongModel.RESTART,
            Scenario.EXTERNAL: WrongModel.RESTART,
        }.get(scenario, WrongModel.KEEP).value,
    }


def linear_force_applies(
    model: mujoco.MjModel, scenario: Scenario | str, force_model: ForceModel | str
) -> bool:
    """Whether SIMPLEX_LINEAR_FORCE keeps the force out of the sigma set here (else it is SIMPLEX):
    DRIVEN, the random walk, and a state that is a plain vector (no ball or free joints)."""
    return scenario == Scenario.DRIVEN and force_model == ForceModel.RANDOM_WALK and not has_manifold(model)


def _check_settings(values: Mapping[str, object], name: str) -> None:
    unknown = sorted(set(values) - set(SETTING_FIELDS))
    if unknown:
        raise InvalidArgument(
            f"{name} has unknown settings {unknown}; expected some of {list(SETTING_FIELDS)}"
        )


def steps_per_tick(model: mujoco.MjModel, dt: float) -> int:
    """dt / timestep, which must be a whole number >= 1."""
    dt = _real(dt, "dt")
    timestep = float(model.opt.timestep)
    steps = round(dt / timestep)
    if dt <= 0.0 or steps < 1 or abs(steps * timestep - dt) > 1e-9 * max(dt, 1.0):
        raise InvalidArgument(
            f"dt must be a whole multiple (>= 1) of the model's timestep {timestep} s, got {dt}"
        )
    return int(steps)


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


def resolve_config(
    *,
    model: mujoco.MjModel,
    scenario: Scenario | str,
    dt: float,
    requested: Mapping[str, object],
    model_defaults: Mapping[str, object],
    preset: Preset | str = Preset.JITDYN,
    measured: Iterable[str],
) -> EstimatorConfig:
    """The complete settings of a session: each field from the request if set there, else from the
    model's defaults for the scenario, else from the preset (`preset_values`).

    requested, model_defaults: some of estimator, sigma_points, alpha, beta, kappa, p0, q_var, r,
    force_model, force_var, noise_model.
    Raises InvalidArgument naming the first bad field.
    """
    _check_settings(requested, "requested")
    _check_settings(model_defaults, "model_defaults")
    if isinstance(measured, str):
        raise InvalidArgument(f"measured must be a set of channel names, got the string {measured!r}")
    values = {**preset_values(preset, model=model, scenario=scenario), **model_defaults, **requested}
    if (
        values["sigma_points"] == SigmaScheme.SIMPLEX_LINEAR_FORCE
        and "sigma_points" not in {**model_defaults, **requested}
        and not linear_force_applies(model, scenario, str(values["force_model"]))
    ):
        # The preset's choice for its own force model; a request for another keeps the force in
        # the points, and the settings echoed back say so.
        values["sigma_points"] = SigmaScheme.SIMPLEX.value
    config = EstimatorConfig(
        estimator=values["estimator"],  # type: ignore[arg-type]
        scenario=scenario,  # type: ignore[arg-type]
        sigma_points=values["sigma_points"],  # type: ignore[arg-type]
        alpha=values["alpha"],  # type: ignore[arg-type]
        beta=values["beta"],  # type: ignore[arg-type]
        kappa=values["kappa"],  # type: ignore[arg-type]
        p0=values["p0"],  # type: ignore[arg-type]
        q_var=values["q_var"],  # type: ignore[arg-type]
        r=values["r"],  # type: ignore[arg-type]
        force_model=values["force_model"],  # type: ignore[arg-type]
        force_var=values["force_var"],  # type: ignore[arg-type]
        noise_model=values["noise_model"],  # type: ignore[arg-type]
        forecast=values["forecast"],  # type: ignore[arg-type]
        wrong_model=values["wrong_model"],  # type: ignore[arg-type]
        dt=dt,
        steps_per_tick=steps_per_tick(model, dt),
        measured=frozenset(measured),
    )
    if config.wrong_model == WrongModel.DRIVEN and config.scenario != Scenario.PASSIVE:
        # It would be a silent KEEP: only a PASSIVE filter has a DRIVEN filter to become.
        raise InvalidArgument(
            f"wrong_model DRIVEN turns a PASSIVE filter into a DRIVEN one; this session's scenario is "
            f"{config.scenario}: choose RESTART or KEEP"
        )
    check_against_model(model, config)
    return config
