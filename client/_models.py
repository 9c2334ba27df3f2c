"""The SDK's values: frozen dataclasses for what a client sends and receives, and the small
functions that turn them into jitdyn.v1 messages and back. The sync and the async transport both
hand these out; neither adds a value of its own.

    options = SessionOptions(model_name="pendulum_1", dt=0.05, clock="REALTIME")
    options.clock                    # Clock.REALTIME: text is parsed to its vocabulary member once
    options.to_message()             # jitdyn.v1.OpenSession
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar, cast

import numpy as np

from jitdyn.checksum import frame_checksum
from jitdyn.errors import FailedPrecondition, InvalidArgument
from jitdyn.estimator_settings import SETTINGS, SettingValue
from jitdyn.settings_message import settings_from_message, settings_message
from jitdyn.v1 import common_pb2, dynamics_pb2, model_registry_pb2
from jitdyn.vocabulary import (
    Channel,
    Clock,
    EstimatorChoice,
    Horizon,
    Output,
    RejectReason,
    Scenario,
    Source,
    from_proto,
    parse,
    to_proto,
)

__all__ = [
    "FrameData",
    "ModelRef",
    "Opened",
    "Rejection",
    "ResumePolicy",
    "Resumption",
    "SessionOptions",
    "Summary",
    "SyncSample",
    "TickResult",
]
# The value types above are the SDK's public ones (jitdyn.client re-exports this list); the
# conversions below them are the transports' own, imported by name.


_Word = TypeVar("_Word", Channel, Output)


def _array(values: Any) -> np.ndarray:
    array = np.asarray(values, dtype=np.float64)
    array.flags.writeable = False
    return array


def _requested_settings(values: object) -> dict[str, SettingValue]:
    """A session's requested settings: names from the table, enum settings parsed to their member,
    numbers as floats. Ranges are left to the server, which judges them against the same table and
    answers with the field's full name (open.estimator.alpha)."""
    if not isinstance(values, Mapping):
        raise InvalidArgument(f"estimator must map setting names to values, got {values!r}")
    settings: dict[str, SettingValue] = {}
    for name, value in values.items():
        row = SETTINGS.get(name) if isinstance(name, str) else None
        if row is None:
            raise InvalidArgument(
                f"estimator has unknown setting {name!r}; expected one of {', '.join(SETTINGS)}"
            )
        if row.choices is not None:
            settings[name] = parse(row.choices, value, argument=f"estimator.{name}")
        elif isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
            raise InvalidArgument(f"estimator.{name} must be a number, got {value!r}")
        else:
            settings[name] = float(value)
    return settings


@dataclass(frozen=True)
class ModelRef:
    """A registered model, as the client needs it."""

    id: str
    name: str
    version: int
    nq: int
    nv: int
    nu: int
    na: int
    nsensordata: int
    timestep: float
    joint_names: tuple[str, ...]
    actuator_names: tuple[str, ...]
    builtin: bool
    tags: tuple[str, ...]
    description: str

    @classmethod
    def from_message(cls, model: model_registry_pb2.Model) -> ModelRef:
        dims = model.dimensions
        return cls(
            id=model.id,
            name=model.name,
            version=model.version,
            nq=dims.nq,
            nv=dims.nv,
            nu=dims.nu,
            na=dims.na,
            nsensordata=dims.nsensor,
            timestep=model.timestep,
            joint_names=tuple(j.name for j in model.joints),
            actuator_names=tuple(a.name for a in model.actuators),
            builtin=model.builtin,
            tags=tuple(model.metadata.tags),
            description=model.metadata.description,
        )


@dataclass(frozen=True)
class SessionOptions:
    """What to open. Give exactly one of model_name, model_id, inline_mjcf.

    The words take their jitdyn.vocabulary member or its text ("REALTIME", "realtime",
    "CLOCK_REALTIME"), parsed to the member on creation: a word that is none of them is
    InvalidArgument here. `estimator` maps names of jitdyn.estimator_settings.SETTINGS to values.
    """

    model_name: str | None = None
    model_id: str | None = None
    model_version: int = 0
    inline_mjcf: str | None = None
    inline_name: str = "inline"
    inline_assets: Mapping[str, bytes] = field(default_factory=dict)
    # None (or ""): the server's choice for the model (DRIVEN for a model with actuators, else
    # PASSIVE), reported in Opened.scenario and scenario_reason.
    scenario: Scenario | str | None = None
    dt: float = 0.05  # s
    clock: Clock | str = Clock.LOCKSTEP
    estimator: Mapping[str, object] = field(default_factory=dict)  # estimator, preset, alpha, ...
    measured: Sequence[Channel | str] = ()  # empty: the server's default
    outputs: Sequence[Output | str] = ()
    horizon: Horizon | str = Horizon.NONE
    subject_id: str = ""
    subject_attributes: Mapping[str, str] = field(default_factory=dict)
    grace: float = 0.0  # s; 0: dt / 2
    history: int = 0  # ticks; 0: the server's default

    def __post_init__(self) -> None:
        # Frozen: the parsed members replace the text once, as the dataclass docs show for derived fields.
        scenario = (
            None if self.scenario in (None, "") else parse(Scenario, self.scenario, argument="scenario")
        )
        object.__setattr__(self, "scenario", scenario)
        object.__setattr__(self, "clock", parse(Clock, self.clock, argument="clock"))
        object.__setattr__(self, "horizon", parse(Horizon, self.horizon, argument="horizon"))
        object.__setattr__(
            self, "measured", tuple(parse(Channel, c, argument="measured") for c in self.measured)
        )
        object.__setattr__(self, "outputs", tuple(parse(Output, o, argument="outputs") for o in self.outputs))
        object.__setattr__(self, "estimator", _requested_settings(self.estimator))

    def to_message(self) -> dynamics_pb2.OpenSession:
        chosen = [n for n in ("model_name", "model_id", "inline_mjcf") if getattr(self, n)]
        if len(chosen) != 1:
            raise InvalidArgument(
                f"give exactly one of model_name, model_id, inline_mjcf; got {chosen or 'none'}"
            )
        # The words and settings are members since __post_init__; the casts only tell mypy so, and
        # ValueType gives each proto value the type the stubs give its enum.
        message = dynamics_pb2.OpenSession(
            model_version=self.model_version,
            scenario=common_pb2.Scenario.ValueType(
                0 if self.scenario is None else to_proto(cast(Scenario, self.scenario))
            ),
            dt=self.dt,
            clock=common_pb2.Clock.ValueType(to_proto(cast(Clock, self.clock))),
            measured=[common_pb2.Channel.ValueType(to_proto(cast(Channel, c))) for c in self.measured],
            outputs=[common_pb2.Output.ValueType(to_proto(cast(Output, o))) for o in self.outputs],
            horizon=dynamics_pb2.Horizon.ValueType(to_proto(cast(Horizon, self.horizon))),
            estimator=settings_message(self.estimator),
            # The SDK reads StreamSessionResponse.results (client/_transport.py: unbatched).
            accept_result_batches=True,
            grace=self.grace,
            history=self.history,
        )
        if self.model_name:
            message.model_name = self.model_name
        elif self.model_id:
            message.model_id = self.model_id
        else:
            message.inline_model.name = self.inline_name
            message.inline_model.mjcf = self.inline_mjcf or ""
            for key, asset in self.inline_assets.items():
                message.inline_model.assets[key] = asset
        if self.subject_id:
            message.subject.id = self.subject_id
        for key, attribute in self.subject_attributes.items():
            message.subject.attributes[key] = attribute
        return message


@dataclass(frozen=True)
class FrameData:
    """One measured frame; channels the session does not measure stay None."""

    seq: int
    t: float
    qpos: Any
    qvel: Any = None
    qacc: Any = None
    ctrl: Any = None
    sensordata: Any = None

    def to_message(self, *, checksum: bool = True) -> dynamics_pb2.Frame:
        channels = {
            name: np.asarray(value, dtype=np.float64).ravel() if value is not None else np.empty(0)
            for name, value in (
                ("qpos", self.qpos),
                ("qvel", self.qvel),
                ("qacc", self.qacc),
                ("ctrl", self.ctrl),
                ("sensordata", self.sensordata),
            )
        }
        frame = dynamics_pb2.Frame(
            seq=self.seq,
            t=self.t,
            qpos=channels["qpos"].tolist(),
            qvel=channels["qvel"].tolist(),
            qacc=channels["qacc"].tolist(),
            ctrl=channels["ctrl"].tolist(),
            sensordata=channels["sensordata"].tolist(),
        )
        if checksum:
            frame.checksum = frame_checksum(seq=self.seq, t=self.t, **channels)
        return frame


@dataclass(frozen=True)
class TickResult:
    """The server's answer for one tick; arrays are read-only, empty when not asked for."""

    seq: int
    t: float
    source: Source
    qpos: np.ndarray
    qvel: np.ndarray
    qacc: np.ndarray
    qfrc_inverse: np.ndarray
    qacc_forward: np.ndarray
    actuator_force: np.ndarray
    sensordata: np.ndarray
    covariance_diagonal: np.ndarray
    filter_state: np.ndarray
    covariance: np.ndarray | None  # (nx, nx) with OUTPUT_FILTER_STATE
    nis: float | None
    frame_received: bool
    late_ticks: int
    frame_delay: float
    compute_us: int
    receive_to_send_us: int
    durable_seq: int | None
    reinitialised: bool
    horizon: float
    received_at: float  # client monotonic time the result arrived
    late_compute: bool = False  # answered on time without the estimator (an overloaded server)
    adapted: bool = False  # the adaptive noise model moved R or Q by more than a tenth
    absorbed: bool = False  # a NIS window far out: the filter widened its covariance
    # FORECAST_COMBINED over a gap: the weight of each predictor in the answer, in the order
    # `forecast_predictors` names them; None when the filter answered alone.
    forecast_weights: tuple[float, ...] | None = None
    # The scenario of the filter that answered (DRIVEN after a wrong PASSIVE model was absorbed);
    # None for dead reckoning.
    scenario: Scenario | None = None
    # The names of the predictors `forecast_weights` weighs ("MODEL", "STATIC", ..., "LEARNED").
    forecast_predictors: tuple[str, ...] | None = None

    @classmethod
    def from_message(cls, result: dynamics_pb2.Result, *, received_at: float) -> TickResult:
        # The covariance lives in the tangent space: its side is the state dimension, which is
        # less than len(filter_state) for models with ball or free joints.
        side = math.isqrt(len(result.covariance))
        covariance = (
            _array(result.covariance).reshape(side, side)
            if side and side * side == len(result.covariance)
            else None
        )
        source = from_proto(Source, result.source, argument="result.source")
        if source is None:
            raise FailedPrecondition(f"the server answered tick {result.seq} without a source")
        return cls(
            seq=result.seq,
            t=result.t,
            source=source,
            qpos=_array(result.qpos),
            qvel=_array(result.qvel),
            qacc=_array(result.qacc),
            qfrc_inverse=_array(result.qfrc_inverse),
            qacc_forward=_array(result.qacc_forward),
            actuator_force=_array(result.actuator_force),
            sensordata=_array(result.sensordata),
            covariance_diagonal=_array(result.covariance_diagonal),
            filter_state=_array(result.filter_state),
            covariance=covariance,
            nis=result.nis if result.HasField("nis") else None,
            frame_received=result.frame_received,
            late_ticks=result.late_ticks,
            frame_delay=result.frame_delay,
            compute_us=result.compute_us,
            receive_to_send_us=result.receive_to_send_us,
            durable_seq=result.durable_seq if result.HasField("durable_seq") else None,
            reinitialised=result.reinitialised,
            horizon=result.horizon,
            received_at=received_at,
            late_compute=result.late_compute,
            adapted=result.adapted,
            absorbed=result.absorbed,
            forecast_weights=tuple(result.forecast_weights) if result.forecast_weights else None,
            forecast_predictors=tuple(result.forecast_predictors) if result.forecast_predictors else None,
            scenario=from_proto(Scenario, result.scenario, argument="result.scenario"),
        )


@dataclass(frozen=True)
class Rejection:
    """A frame the server did not use."""

    seq: int
    reason: RejectReason
    message: str

    @classmethod
    def from_message(cls, rejected: dynamics_pb2.Rejected) -> Rejection:
        reason = from_proto(RejectReason, rejected.reason, argument="rejected.reason")
        if reason is None:
            raise FailedPrecondition(f"the server rejected frame {rejected.seq} without a reason")
        return cls(seq=rejected.seq, reason=reason, message=rejected.message)


@dataclass(frozen=True)
class Opened:
    """The session the server opened: its id, model, settings in force and clock."""

    session_id: str
    model: ModelRef
    estimator: dict[str, SettingValue]
    state_dimension: int
    measured: tuple[Channel, ...]
    outputs: tuple[Output, ...]
    grace: float
    history: int
    dropped_attributes: tuple[str, ...]
    subject_pseudonym: str
    dt: float
    steps_per_tick: int
    scenario: Scenario  # the scenario in force
    scenario_reason: str = ""  # why: asked for, or the server's choice for the model
    noise_reason: str = ""  # why the noise model in estimator["noise_model"]
    # Lets the SDK resume the session elsewhere; empty: not resumable. A credential: kept out of
    # the repr (the SDK presents the newest one it was given, which may be a later renewal).
    resume_token: str = field(default="", repr=False)
    resume_from_seq: int | None = None  # a resumed session: the first tick this stream expects
    resume_reason: str = ""  # a resumed session: how its estimator continues
    # How estimator["estimator"] and ["sigma_points"] were chosen (BY_COST: from the model's
    # stored cost, for the session's rate), and why; None from a server that does not say.
    estimator_choice: EstimatorChoice | None = None
    estimator_reason: str = ""

    @classmethod
    def from_message(cls, message: dynamics_pb2.SessionOpened) -> Opened:
        scenario = from_proto(Scenario, message.scenario, argument="opened.scenario")
        if scenario is None:
            raise FailedPrecondition("the server opened a session without a scenario")
        return cls(
            session_id=message.session_id,
            model=ModelRef.from_message(message.model),
            estimator=settings_from_message(message.estimator, argument="opened.estimator"),
            state_dimension=message.state_dimension,
            measured=_members(Channel, message.measured, argument="opened.measured"),
            outputs=_members(Output, message.outputs, argument="opened.outputs"),
            grace=message.grace,
            history=message.history,
            dropped_attributes=tuple(message.dropped_attributes),
            subject_pseudonym=message.subject_pseudonym,
            dt=message.dt,
            steps_per_tick=message.steps_per_tick,
            scenario=scenario,
            scenario_reason=message.scenario_reason,
            noise_reason=message.noise_reason,
            resume_token=message.resume_token,
            resume_from_seq=message.resume_from_seq if message.HasField("resume_from_seq") else None,
            resume_reason=message.resume_reason,
            estimator_choice=from_proto(
                EstimatorChoice, message.estimator_choice, argument="opened.estimator_choice"
            ),
            estimator_reason=message.estimator_reason,
        )


def _members(kind: type[_Word], values: Sequence[int], *, argument: str) -> tuple[_Word, ...]:
    return tuple(m for m in (from_proto(kind, v, argument=argument) for v in values) if m is not None)


@dataclass(frozen=True)
class Summary:
    """A closed session: its counts, timings and where it is stored."""

    ticks: int
    frames: int
    measured: int
    predicted: int
    corrected: int
    rejected: int
    late: int
    location: str
    mean_compute_us: float
    max_compute_us: float
    duration: float
    # Client-side: how often the SDK resumed the session on another stream (a replica lost or
    # draining), and the ticks it saw no answer for across those resumes (REALTIME ticks that passed
    # while the stream was down; LOCKSTEP frames are re-sent, so it misses none).
    resumes: int = 0
    missed: int = 0

    @classmethod
    def from_message(cls, message: dynamics_pb2.SessionSummary) -> Summary:
        return cls(
            ticks=message.ticks,
            frames=message.frames,
            measured=message.measured,
            predicted=message.predicted,
            corrected=message.corrected,
            rejected=message.rejected,
            late=message.late,
            location=message.location,
            mean_compute_us=message.mean_compute_us,
            max_compute_us=message.max_compute_us,
            duration=message.duration,
        )


@dataclass(frozen=True)
class ResumePolicy:
    """How a session resumes by itself when its stream breaks (UNAVAILABLE, a stream reset by a
    balancer whose replica died, or the server's `moving` notice): it opens again through the same
    target with the session's resume token, re-sends the frames not yet durable, and goes on.

    `attempts` resumes are tried, `initial_backoff` seconds apart at first, doubling up to
    `max_backoff`; then SessionLost. The defaults wait about 121 s in all: longer than a replica
    holds its sessions' rows while the shared index does not answer (120 s), so a session outlives
    any outage the server does. The SDK keeps at most `max_unacknowledged` frames that no
    result's `durable_seq` covers yet (ResumeBufferFull beyond). `enabled=False`: a broken stream
    raises as it always did."""

    enabled: bool = True
    attempts: int = 30
    initial_backoff: float = 0.1
    max_backoff: float = 5.0
    max_unacknowledged: int = 10_000
    open_timeout: float = 10.0  # seconds to wait for each resume's `opened`

    def backoff(self, attempt: int) -> float:
        """The wait before resume attempt `attempt` (0-based): none before the first."""
        return 0.0 if attempt == 0 else min(self.max_backoff, self.initial_backoff * 2 ** (attempt - 1))


@dataclass(frozen=True)
class Resumption:
    """One resume the SDK made: from which tick the new stream went on, why the stream broke, the
    server's `resume_reason`, how many opens it took and how long (seconds)."""

    session_id: str
    from_seq: int
    cause: str
    reason: str
    attempts: int
    took: float


@dataclass(frozen=True)
class SyncSample:
    """One clock exchange, from the client's side: offset = server - client, seconds."""

    offset: float
    round_trip: float
    server_offset: float
    server_round_trip: float

    @classmethod
    def from_pong(cls, pong: dynamics_pb2.SyncPong, t4: float) -> SyncSample:
        """One NTP-style exchange; `t4` is the pong's receive time on the session clock."""
        t1, t2, t3 = pong.client_send_time, pong.server_receive_time, pong.server_send_time
        return cls(
            offset=((t2 - t1) + (t3 - t4)) / 2.0,
            round_trip=(t4 - t1) - (t3 - t2),
            server_offset=pong.offset,
            server_round_trip=pong.round_trip,
        )


def register_request(
    *, name: str, mjcf: str, assets: Mapping[str, bytes] | None, description: str, tags: Sequence[str]
) -> model_registry_pb2.RegisterModelRequest:
    """The RegisterModel request of a model and what its registrant says about it."""
    request = model_registry_pb2.RegisterModelRequest(name=name, mjcf=mjcf, assets=dict(assets or {}))
    request.metadata.description = description
    request.metadata.tags.extend(tags)
    return request


def opened_from_response(response: dynamics_pb2.StreamSessionResponse) -> Opened:
    """The `opened` a session stream must begin with."""
    if response.WhichOneof("payload") != "opened":
        raise FailedPrecondition(f"the server answered `open` with `{response.WhichOneof('payload')}`")
    return Opened.from_message(response.opened)


def sync_request(
    probe_id: int, client_send_time: float, last_probe: tuple[int, float] | None
) -> dynamics_pb2.StreamSessionRequest:
    """A clock probe sent at `client_send_time` (session clock, s), reporting the receive time of the
    last answered probe, `(id, t4)`, so the server can complete that exchange."""
    ping = dynamics_pb2.SyncPing(id=probe_id, client_send_time=client_send_time)
    if last_probe is not None:
        ping.previous_id, ping.previous_receive_time = last_probe
    return dynamics_pb2.StreamSessionRequest(sync=ping)


def session_answer(
    response: dynamics_pb2.StreamSessionResponse, *, received_at: float, clock_start: float
) -> TickResult | Rejection | SyncSample | Summary:
    """A response of the session stream as the SDK hands it out; times are time.monotonic() values."""
    kind = response.WhichOneof("payload")
    if kind == "result":
        return TickResult.from_message(response.result, received_at=received_at)
    if kind == "rejected":
        return Rejection.from_message(response.rejected)
    if kind == "sync":
        return SyncSample.from_pong(response.sync, received_at - clock_start)
    if kind == "closed":
        return Summary.from_message(response.closed.summary)
    raise FailedPrecondition(f"unexpected `{kind}` from the server")
