"""The words of the contract, defined once: one StrEnum per jitdyn.v1 enum the Python code uses.

Every layer compares these members, never their text; a typo is a mypy error, not a silent miss.
A member's name is its proto value's name without the enum's prefix (`Scenario.PASSIVE` is
`SCENARIO_PASSIVE`), its value the text stored in Parquet, the index and the settings::

    to_proto(Scenario.PASSIVE)                          # 1, jitdyn.v1.SCENARIO_PASSIVE
    from_proto(Scenario, 1, argument="open.scenario")   # Scenario.PASSIVE
    from_proto(Scenario, 0, argument="open.scenario")   # None: unset

The conversions import the generated code only when called, so that the layers that know nothing
of the wire (estimation, the runtime) can use the words without loading protobuf.
"""

from __future__ import annotations

import enum
import functools
import importlib
from typing import Final, TypeVar

from jitdyn.errors import InvalidArgument

__all__ = [
    "WORDS",
    "Channel",
    "Clock",
    "EstimatorChoice",
    "EstimatorKind",
    "ForceModel",
    "Forecast",
    "Horizon",
    "JointType",
    "NoiseModel",
    "Output",
    "Preset",
    "RejectReason",
    "Scenario",
    "SessionStatus",
    "SigmaScheme",
    "Source",
    "WrongModel",
    "from_proto",
    "parse",
    "proto_enum_name",
    "to_proto",
]


class Scenario(enum.StrEnum):
    """What moves the body, as the filter models it (jitdyn.v1.Scenario)."""

    PASSIVE = "PASSIVE"  # only the model's own passive forces
    CONTROLLED = "CONTROLLED"  # known controls, sent in the frames
    EXTERNAL = "EXTERNAL"  # the force restored by inverse dynamics and held (the thesis)
    DRIVEN = "DRIVEN"  # an unknown generalized force, estimated as part of the state


class Clock(enum.StrEnum):
    """What advances a session's ticks (jitdyn.v1.Clock)."""

    REALTIME = "REALTIME"  # the server's clock, one answer per dt whether frames come or not
    LOCKSTEP = "LOCKSTEP"  # each frame or skip, answered at once


class Source(enum.StrEnum):
    """What answered a tick (jitdyn.v1.Source)."""

    MEASURED = "MEASURED"  # its frame, in time
    PREDICTED = "PREDICTED"  # the estimator, without its frame
    CORRECTED = "CORRECTED"  # its late frame, replayed (timewarp)


class RejectReason(enum.StrEnum):
    """Why a frame was not used (jitdyn.v1.RejectReason)."""

    BAD_CHECKSUM = "BAD_CHECKSUM"
    BAD_SHAPE = "BAD_SHAPE"
    NOT_FINITE = "NOT_FINITE"
    DUPLICATE = "DUPLICATE"
    TOO_OLD = "TOO_OLD"
    OUT_OF_ORDER = "OUT_OF_ORDER"
    WRONG_CLOCK = "WRONG_CLOCK"


class Horizon(enum.StrEnum):
    """How far ahead of its tick an answer is extrapolated (jitdyn.v1.Horizon)."""

    NONE = "NONE"
    HALF_ROUND_TRIP = "HALF_ROUND_TRIP"


class Channel(enum.StrEnum):
    """A measured channel of a frame (jitdyn.v1.Channel); the value is the frame field's name."""

    QPOS = "qpos"
    QVEL = "qvel"
    QACC = "qacc"
    CTRL = "ctrl"


class Output(enum.StrEnum):
    """The dynamics a client wants in every result (jitdyn.v1.Output)."""

    INVERSE_DYNAMICS = "INVERSE_DYNAMICS"
    FORWARD_DYNAMICS = "FORWARD_DYNAMICS"
    SENSORS = "SENSORS"
    FILTER_STATE = "FILTER_STATE"


class SessionStatus(enum.StrEnum):
    """Where a stored session stands (jitdyn.v1.SessionStatus)."""

    OPEN = "OPEN"
    COMPLETE = "COMPLETE"  # closed by its client
    RECOVERED = "RECOVERED"  # its server died; its log was compacted by the next one
    FAILED = "FAILED"  # ended by an error
    ABANDONED = "ABANDONED"  # its client went away without a close


class JointType(enum.StrEnum):
    """A MuJoCo joint's type (jitdyn.v1.JointType); the value is MJCF's name for it."""

    FREE = "free"
    BALL = "ball"
    SLIDE = "slide"
    HINGE = "hinge"


class EstimatorKind(enum.StrEnum):
    """The estimator of a session (jitdyn.v1.Estimator)."""

    UKF = "UKF"
    STATIC = "STATIC"  # IEEE 1278 dead reckoning: hold the last state
    CONSTANT_VELOCITY = "CONSTANT_VELOCITY"
    CONSTANT_ACCELERATION = "CONSTANT_ACCELERATION"
    EKF = "EKF"  # the linearised filter: server/estimation/linearised.py


class EstimatorChoice(enum.StrEnum):
    """How a session's estimator was chosen (jitdyn.v1.EstimatorChoice)."""

    BY_COST = "BY_COST"  # REALTIME: the most accurate candidate whose stored cost fits the tick
    ASKED = "ASKED"  # the open named the estimator or its sigma points
    MODEL_DEFAULTS = "MODEL_DEFAULTS"  # the model's defaults for the scenario named them
    PRESET = "PRESET"  # LOCKSTEP (no tick to fit) or THESIS: the preset's


class Preset(enum.StrEnum):
    """The source of the settings a session leaves unset (jitdyn.v1.Preset)."""

    JITDYN = "JITDYN"  # sound at any state dimension, adaptive where the force is unknown
    # The thesis' chapter 4 exactly (experiments/thesis.py; its tables: docs/experiments.md).
    THESIS = "THESIS"


class SigmaScheme(enum.StrEnum):
    """The sigma points of the UKF (jitdyn.v1.SigmaPoints)."""

    MERWE = "MERWE"
    SIMPLEX = "SIMPLEX"
    UNIFORM = "UNIFORM"
    # DRIVEN, random walk, no ball or free joints: simplex points over [q, qd], the unknown force
    # carried linearly beside them (server/estimation/linear_force.py); elsewhere SIMPLEX.
    SIMPLEX_LINEAR_FORCE = "SIMPLEX_LINEAR_FORCE"


class ForceModel(enum.StrEnum):
    """How the unknown generalized force of DRIVEN evolves between ticks (jitdyn.v1.ForceModel)."""

    RANDOM_WALK = "RANDOM_WALK"  # f' = f + w: the force is held over a prediction
    INTEGRATED_RANDOM_WALK = "INTEGRATED_RANDOM_WALK"  # f' = f + fd dt, fd' = fd + w: its trend is kept


class NoiseModel(enum.StrEnum):
    """Whether R and Q stay as configured or follow the innovations (jitdyn.v1.NoiseModel)."""

    FIXED = "FIXED"
    ADAPTIVE = "ADAPTIVE"


class Forecast(enum.StrEnum):
    """What answers a tick without a frame (jitdyn.v1.Forecast)."""

    FILTER = "FILTER"  # the filter's predicted mean
    COMBINED = "COMBINED"  # the model's rollout and the extrapolators, weighted by their scores


class WrongModel(enum.StrEnum):
    """What a UKF does when its NIS says its model is wrong (jitdyn.v1.WrongModel)."""

    KEEP = "KEEP"  # nothing but the divergence guard (the thesis)
    DRIVEN = "DRIVEN"  # PASSIVE only: the session's filter becomes DRIVEN, from that frame
    RESTART = "RESTART"  # start again from the frame


# Each word and its proto enum: (generated module under jitdyn.v1, enum name, value prefix).
WORDS: Final[dict[type[enum.StrEnum], tuple[str, str, str]]] = {
    Scenario: ("common_pb2", "Scenario", "SCENARIO_"),
    Clock: ("common_pb2", "Clock", "CLOCK_"),
    Channel: ("common_pb2", "Channel", "CHANNEL_"),
    Output: ("common_pb2", "Output", "OUTPUT_"),
    EstimatorKind: ("common_pb2", "Estimator", "ESTIMATOR_"),
    Preset: ("common_pb2", "Preset", "PRESET_"),
    SigmaScheme: ("common_pb2", "SigmaPoints", "SIGMA_POINTS_"),
    ForceModel: ("common_pb2", "ForceModel", "FORCE_MODEL_"),
    NoiseModel: ("common_pb2", "NoiseModel", "NOISE_MODEL_"),
    Forecast: ("common_pb2", "Forecast", "FORECAST_"),
    WrongModel: ("common_pb2", "WrongModel", "WRONG_MODEL_"),
    Source: ("dynamics_pb2", "Source", "SOURCE_"),
    RejectReason: ("dynamics_pb2", "RejectReason", "REJECT_REASON_"),
    Horizon: ("dynamics_pb2", "Horizon", "HORIZON_"),
    EstimatorChoice: ("dynamics_pb2", "EstimatorChoice", "ESTIMATOR_CHOICE_"),
    SessionStatus: ("session_pb2", "SessionStatus", "SESSION_STATUS_"),
    JointType: ("model_registry_pb2", "JointType", "JOINT_TYPE_"),
}

_W = TypeVar("_W", bound=enum.StrEnum)


@functools.cache
def _wrapper(kind: type[enum.StrEnum]) -> object:
    module, name, _ = WORDS[kind]
    return getattr(importlib.import_module(f"jitdyn.v1.{module}"), name)


def proto_enum_name(word: enum.StrEnum) -> str:
    """The full name of a member's proto value: Scenario.PASSIVE -> "SCENARIO_PASSIVE"."""
    return WORDS[type(word)][2] + word.name


def to_proto(word: enum.StrEnum) -> int:
    """The proto value of a member: Scenario.PASSIVE -> 1. Cached by kind and name: every result
    message asks it (2.2 us uncached, 1.2 cached), and members of two kinds with one name are
    equal strings (Scenario.DRIVEN == WrongModel.DRIVEN), so the member alone cannot be the key."""
    return _proto_value(type(word), word.name)


@functools.cache
def _proto_value(kind: type[enum.StrEnum], name: str) -> int:
    return int(_wrapper(kind).Value(WORDS[kind][2] + name))  # type: ignore[attr-defined]


def from_proto(kind: type[_W], value: int, *, argument: str) -> _W | None:
    """The member of a proto value, None for its UNSPECIFIED zero. A value the enum does not define
    (proto3 enums are open: any int arrives) is InvalidArgument naming `argument`."""
    if value == 0:
        return None
    wrapper = _wrapper(kind)
    try:
        full = str(wrapper.Name(value))  # type: ignore[attr-defined]
    except ValueError:
        known = ", ".join(proto_enum_name(member) for member in kind)
        raise InvalidArgument(f"{argument} must be one of {known}, got the undefined value {value}") from None
    return kind[full.removeprefix(WORDS[kind][2])]


def parse(kind: type[_W], text: object, *, argument: str) -> _W:
    """The member named by `text`: its value or its name, in any case ("passive", "PASSIVE",
    "SCENARIO_PASSIVE"); InvalidArgument naming `argument` and the choices otherwise."""
    if isinstance(text, kind):
        return text
    if isinstance(text, str):
        name = text.upper().removeprefix(WORDS[kind][2])
        if name in kind.__members__:
            return kind[name]
    choices = ", ".join(member.name for member in kind)
    raise InvalidArgument(f"{argument} must be one of {choices}, got {text!r}")
