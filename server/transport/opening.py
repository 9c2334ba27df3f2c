"""Checking an `open` request into a `SessionPlan`: every option resolved, every default applied.

Errors are `InvalidArgument` naming the field, what was expected and what arrived; a model that
does not exist is `NotFound` (raised by the registry).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, TypeVar

from jitdyn.errors import InvalidArgument
from jitdyn.server.transport.model_messages import settings_from_message
from jitdyn.v1 import common_pb2, dynamics_pb2

if TYPE_CHECKING:
    # The stubs' generic enum wrapper: mypy-protobuf types each enum's values as its own int NewType.
    from google.protobuf.internal.enum_type_wrapper import _EnumTypeWrapper

__all__ = ["ESTIMATOR_FIELDS", "SessionPlan", "enum_name", "plan_session"]

# Optional scalar fields of EstimatorSettings, by name.
ESTIMATOR_FIELDS = ("alpha", "beta", "kappa", "p0", "q_var", "r", "force_var")
_MAX_DT = 10.0
_DEFAULT_HISTORY = 50
_MAX_HISTORY = 10_000
_MAX_SUBJECT_ID = 256

_V = TypeVar("_V", bound=int)


def enum_name(enum: _EnumTypeWrapper[_V], value: _V, *, argument: str = "") -> str:
    """An enum value's name without its type prefix: Scenario 1 -> "PASSIVE". A value the enum does
    not define (proto3 enums are open: any int arrives) is InvalidArgument naming `argument`."""
    try:
        full = enum.Name(value)
    except ValueError:
        known = ", ".join(enum.keys())
        raise InvalidArgument(
            f"{argument or enum.DESCRIPTOR.name} must be one of {known}, got the undefined value {value}"
        ) from None
    prefix = "".join("_" + c if c.isupper() and i else c for i, c in enumerate(enum.DESCRIPTOR.name)).upper()
    return full[len(prefix) + 1 :] if full.startswith(prefix + "_") else full


@dataclass(frozen=True)
class SessionPlan:
    """A checked `open`: what the session will run. The model is resolved separately."""

    scenario: str | None  # PASSIVE | CONTROLLED | EXTERNAL | DRIVEN; None: the server picks for the model
    clock: str  # LOCKSTEP | REALTIME
    dt: float  # s
    steps_per_tick: int
    measured: frozenset[str]  # of qpos, qvel, qacc, ctrl
    outputs: frozenset[str]  # of INVERSE_DYNAMICS, FORWARD_DYNAMICS, SENSORS, FILTER_STATE
    horizon: str  # NONE | HALF_ROUND_TRIP
    grace: float  # s
    history: int  # ticks
    estimator_request: dict[str, object]  # the EstimatorSettings fields the client set
    preset: str  # JITDYN | THESIS
    subject_id: str
    subject_attributes: dict[str, str]


def _estimator_request(settings: common_pb2.EstimatorSettings) -> tuple[dict[str, object], str]:
    request = settings_from_message(settings, argument="open.estimator")
    for name in ESTIMATOR_FIELDS:
        value = request.get(name)
        if isinstance(value, float) and not math.isfinite(value):
            raise InvalidArgument(f"open.estimator.{name} must be finite, got {value}")
    preset = str(request.pop("preset", "JITDYN"))
    return request, preset


def plan_session(open_: dynamics_pb2.OpenSession, *, timestep: float) -> SessionPlan:
    """Check `open_` against a model with physics `timestep` (s)."""
    scenario = (
        enum_name(common_pb2.Scenario, open_.scenario, argument="open.scenario") if open_.scenario else None
    )
    clock = enum_name(common_pb2.Clock, open_.clock, argument="open.clock") if open_.clock else "LOCKSTEP"
    dt = open_.dt
    if not math.isfinite(dt) or dt <= 0.0 or dt > _MAX_DT:
        raise InvalidArgument(f"open.dt must be in (0, {_MAX_DT}] seconds, got {dt}")
    steps = round(dt / timestep)
    if steps < 1 or abs(steps * timestep - dt) > 1e-9 * max(dt, 1.0):
        raise InvalidArgument(
            f"open.dt must be a whole multiple of the model's timestep {timestep} s, got {dt} "
            f"({dt / timestep:.6g} timesteps)"
        )
    measured = {enum_name(common_pb2.Channel, c, argument="open.measured") for c in open_.measured}
    if "UNSPECIFIED" in measured:
        raise InvalidArgument("open.measured must not contain CHANNEL_UNSPECIFIED")
    measured_lower = frozenset(c.lower() for c in measured)
    if not measured_lower:
        measured_lower = frozenset({"qpos", "qvel", "ctrl"} if scenario == "CONTROLLED" else {"qpos", "qvel"})
    if "qpos" not in measured_lower:
        raise InvalidArgument(
            f"open.measured must include CHANNEL_QPOS, got {sorted(c.upper() for c in measured_lower)}"
        )
    if scenario == "CONTROLLED" and "ctrl" not in measured_lower:
        raise InvalidArgument(
            "open.measured must include CHANNEL_CTRL in SCENARIO_CONTROLLED (the estimator predicts "
            f"with the frames' controls), got {sorted(c.upper() for c in measured_lower)}"
        )
    outputs = frozenset(
        enum_name(common_pb2.Output, o, argument="open.outputs") for o in open_.outputs
    ) or frozenset({"INVERSE_DYNAMICS"})
    if "UNSPECIFIED" in outputs:
        raise InvalidArgument("open.outputs must not contain OUTPUT_UNSPECIFIED")
    horizon = (
        enum_name(dynamics_pb2.Horizon, open_.horizon, argument="open.horizon") if open_.horizon else "NONE"
    )
    if horizon == "HALF_ROUND_TRIP" and clock != "REALTIME":
        raise InvalidArgument(
            "open.horizon HORIZON_HALF_ROUND_TRIP needs open.clock CLOCK_REALTIME, got CLOCK_LOCKSTEP"
        )
    grace = open_.grace
    if not math.isfinite(grace) or grace < 0.0 or grace >= 10 * dt:
        raise InvalidArgument(f"open.grace must be in [0, 10 dt = {10 * dt:g}) seconds, got {grace}")
    if grace == 0.0:
        grace = dt / 2.0
    history = open_.history or _DEFAULT_HISTORY
    if history > _MAX_HISTORY:
        raise InvalidArgument(f"open.history must be at most {_MAX_HISTORY} ticks, got {history}")
    estimator_request, preset = _estimator_request(open_.estimator)
    subject_id = open_.subject.id
    if len(subject_id) > _MAX_SUBJECT_ID:
        raise InvalidArgument(
            f"open.subject.id must be at most {_MAX_SUBJECT_ID} characters, got {len(subject_id)}"
        )
    return SessionPlan(
        scenario=scenario,
        clock=clock,
        dt=dt,
        steps_per_tick=steps,
        measured=measured_lower,
        outputs=outputs,
        horizon=horizon,
        grace=grace,
        history=history,
        estimator_request=estimator_request,
        preset=preset,
        subject_id=subject_id,
        subject_attributes=dict(open_.subject.attributes),
    )
