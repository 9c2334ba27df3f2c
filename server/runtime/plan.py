"""What a client asks for when it opens a session (`OpenRequest`), and the same checked against the
model into what the session will run (`SessionPlan`): every option resolved, every default applied.

    plan = plan_session(request, timestep=info.timestep)

Errors are `InvalidArgument` naming the field of `open`, what was expected and what arrived.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

from jitdyn.errors import InvalidArgument
from jitdyn.estimator_settings import SettingValue, check_settings, steps_per_tick
from jitdyn.registry import ModelMetadata
from jitdyn.vocabulary import Channel, Clock, Horizon, Output, Preset, Scenario, parse

__all__ = ["InlineModel", "ModelChoice", "OpenRequest", "Resume", "SessionPlan", "plan_session"]

_MAX_DT = 10.0  # s
_DEFAULT_HISTORY = 50  # ticks
_MAX_HISTORY = 10_000  # ticks
_MAX_SUBJECT_ID = 256  # characters


@dataclass(frozen=True, kw_only=True)
class InlineModel:
    """A model sent with the `open`, registered as it opens."""

    name: str
    mjcf: str
    assets: Mapping[str, bytes]
    metadata: ModelMetadata


@dataclass(frozen=True, kw_only=True)
class ModelChoice:
    """Which model a session runs: a registered one by content id, or by name and version (0: the
    newest), or one sent inline. Exactly one of `model_id`, `name` and `inline` is set."""

    model_id: str = ""
    name: str = ""
    version: int = 0
    inline: InlineModel | None = None


@dataclass(frozen=True, kw_only=True)
class OpenRequest:
    """An `open` as the transport read it: its words converted, nothing checked against a model.
    An unset word is None; empty sets are the defaults."""

    tenant: str
    model: ModelChoice
    scenario: Scenario | None = None  # None: the server picks for the model
    clock: Clock | None = None  # None: LOCKSTEP
    dt: float  # s
    measured: frozenset[Channel] = frozenset()
    outputs: frozenset[Output] = frozenset()
    horizon: Horizon | None = None  # None: NONE
    grace: float = 0.0  # s; 0: dt / 2
    history: int = 0  # ticks; 0: the default
    estimator: Mapping[str, SettingValue] = field(default_factory=dict)  # the settings the client set
    subject_id: str = ""
    subject_attributes: Mapping[str, str] = field(default_factory=dict)
    resume: Resume | None = None  # continue this session instead of opening a new one


@dataclass(frozen=True, slots=True)
class Resume:
    """A session to continue, and the token its `opened` carried."""

    session_id: str
    token: str = field(repr=False)  # a credential: never in a repr, a log line or an error


@dataclass(frozen=True, kw_only=True)
class SessionPlan:
    """A checked `open`: what the session will run. The model is resolved separately."""

    scenario: Scenario | None  # None: the server picks for the model
    clock: Clock
    dt: float  # s
    steps_per_tick: int
    measured: frozenset[Channel]
    outputs: frozenset[Output]
    horizon: Horizon
    grace: float  # s
    history: int  # ticks
    estimator_request: dict[str, SettingValue]  # the settings the client set, preset aside
    preset: Preset
    subject_id: str
    subject_attributes: dict[str, str]


def plan_session(request: OpenRequest, *, timestep: float) -> SessionPlan:
    """Check `request` against a model with physics `timestep` (s)."""
    dt = request.dt
    if not math.isfinite(dt) or dt <= 0.0 or dt > _MAX_DT:
        raise InvalidArgument(f"open.dt must be in (0, {_MAX_DT}] seconds, got {dt}")
    steps = steps_per_tick(dt, timestep, argument="open.dt")
    measured = _measured(request.measured, request.scenario)
    clock = request.clock or Clock.LOCKSTEP
    horizon = request.horizon or Horizon.NONE
    if horizon == Horizon.HALF_ROUND_TRIP and clock != Clock.REALTIME:
        raise InvalidArgument(
            "open.horizon HORIZON_HALF_ROUND_TRIP needs open.clock CLOCK_REALTIME, got CLOCK_LOCKSTEP"
        )
    grace = _grace(request.grace, dt)
    history = request.history or _DEFAULT_HISTORY
    if history > _MAX_HISTORY:
        raise InvalidArgument(f"open.history must be at most {_MAX_HISTORY} ticks, got {history}")
    estimator = check_settings(request.estimator, argument="open.estimator")
    preset = parse(Preset, estimator.pop("preset", Preset.JITDYN), argument="open.estimator.preset")
    if len(request.subject_id) > _MAX_SUBJECT_ID:
        raise InvalidArgument(
            f"open.subject.id must be at most {_MAX_SUBJECT_ID} characters, got {len(request.subject_id)}"
        )
    return SessionPlan(
        scenario=request.scenario,
        clock=clock,
        dt=dt,
        steps_per_tick=steps,
        measured=measured,
        outputs=request.outputs or frozenset({Output.INVERSE_DYNAMICS}),
        horizon=horizon,
        grace=grace,
        history=history,
        estimator_request=estimator,
        preset=preset,
        subject_id=request.subject_id,
        subject_attributes=dict(request.subject_attributes),
    )


def _measured(measured: frozenset[Channel], scenario: Scenario | None) -> frozenset[Channel]:
    """The channels every frame carries: qpos always, ctrl in CONTROLLED (the estimator predicts
    with the frames' controls); unset, qpos and qvel (and ctrl in CONTROLLED)."""
    if not measured:
        measured = frozenset({Channel.QPOS, Channel.QVEL})
        if scenario == Scenario.CONTROLLED:
            measured |= {Channel.CTRL}
    names = sorted(c.name for c in measured)
    if Channel.QPOS not in measured:
        raise InvalidArgument(f"open.measured must include CHANNEL_QPOS, got {names}")
    if scenario == Scenario.CONTROLLED and Channel.CTRL not in measured:
        raise InvalidArgument(
            "open.measured must include CHANNEL_CTRL in SCENARIO_CONTROLLED (the estimator predicts "
            f"with the frames' controls), got {names}"
        )
    return measured


def _grace(grace: float, dt: float) -> float:
    """How long (s) a tick waits for its frame past its time: [0, 10 dt); 0 is dt / 2."""
    if not math.isfinite(grace) or grace < 0.0 or grace >= 10 * dt:
        raise InvalidArgument(f"open.grace must be in [0, 10 dt = {10 * dt:g}) seconds, got {grace}")
    return grace or dt / 2.0
