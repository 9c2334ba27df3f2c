"""The typed Python client of jitdyn: register models, open sessions, send frames, read results.

    from jitdyn.client import Client, SessionOptions, FrameData

    with Client("127.0.0.1:50051") as c:
        with c.open_session(SessionOptions(model_name="pendulum_1", dt=0.05)) as s:
            r = s.send_frame(FrameData(seq=0, t=0.0, qpos=[0.3], qvel=[0.0]))
            r.qfrc_inverse          # numpy array, (nv,)
            s.skip(1).source        # "PREDICTED"
            summary = s.close()

Every call raises a `jitdyn.errors` exception for the status the server ends it with. Frames carry
the contract's CRC32C checksum unless told otherwise.
"""

from __future__ import annotations

import json
import math
import queue
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum, auto
from types import TracebackType
from typing import TYPE_CHECKING, Any, Final, Literal, Protocol, Self, TypeAlias, TypeVar

import grpc
import numpy as np

from jitdyn.checksum import frame_checksum
from jitdyn.errors import FailedPrecondition, InvalidArgument, JitdynError, error_for_status
from jitdyn.v1 import (
    common_pb2,
    dynamics_pb2,
    dynamics_pb2_grpc,
    model_registry_pb2,
    model_registry_pb2_grpc,
    session_pb2,
    session_pb2_grpc,
)

if TYPE_CHECKING:
    # The stubs' generic enum wrapper: mypy-protobuf types each enum's values as its own int NewType.
    from google.protobuf.internal.enum_type_wrapper import _EnumTypeWrapper

    _SettingsEnum: TypeAlias = type[
        common_pb2.Estimator
        | common_pb2.Preset
        | common_pb2.SigmaPoints
        | common_pb2.ForceModel
        | common_pb2.NoiseModel
        | common_pb2.Forecast
        | common_pb2.WrongModel
    ]

__all__ = [
    "IDEMPOTENT_METHODS",
    "MAX_MESSAGE_BYTES",
    "RETRY_POLICY",
    "Client",
    "FrameData",
    "ModelRef",
    "Opened",
    "Rejection",
    "Session",
    "SessionOptions",
    "Summary",
    "SyncSample",
    "TickResult",
]

MAX_MESSAGE_BYTES = 128 * 1024 * 1024

# The unary calls that change nothing are retried by gRPC itself (its service-config retry policy)
# when the server is UNAVAILABLE: a restart, a deploy, a replica going away behind a balancer.
# RegisterModel is left out: it is content-addressed, but a retry after a lost answer would say
# `created` false for a model the first attempt created. Streams (sessions) are never retried.
IDEMPOTENT_METHODS: Final = (
    ("jitdyn.v1.ModelRegistryService", "GetModel"),
    ("jitdyn.v1.ModelRegistryService", "ListModels"),
    ("jitdyn.v1.SessionService", "ListSessions"),
    ("jitdyn.v1.SessionService", "GetSession"),
)
# 5 attempts with backoffs of about 0.25, 0.5, 1 and 2 s (gRPC randomises each): a server that is
# back within about 3.5 s is not noticed.
RETRY_POLICY: Final = {
    "maxAttempts": 5,
    "initialBackoff": "0.25s",
    "maxBackoff": "2s",
    "backoffMultiplier": 2,
    "retryableStatusCodes": ["UNAVAILABLE"],
}
_SERVICE_CONFIG: Final = json.dumps(
    {
        "methodConfig": [
            {
                "name": [{"service": service, "method": method} for service, method in IDEMPOTENT_METHODS],
                "retryPolicy": RETRY_POLICY,
            }
        ]
    }
)
_CHANNEL_OPTIONS: Final = (
    ("grpc.max_receive_message_length", MAX_MESSAGE_BYTES),
    ("grpc.max_send_message_length", MAX_MESSAGE_BYTES),
    ("grpc.enable_retries", 1),
    ("grpc.service_config", _SERVICE_CONFIG),
)

_V = TypeVar("_V", bound=int)
_V_co = TypeVar("_V_co", bound=int, covariant=True)
_Request = TypeVar("_Request")
_Response = TypeVar("_Response")

_ESTIMATOR_ENUMS: dict[str, tuple[_SettingsEnum, str]] = {
    "estimator": (common_pb2.Estimator, "ESTIMATOR_"),
    "preset": (common_pb2.Preset, "PRESET_"),
    "sigma_points": (common_pb2.SigmaPoints, "SIGMA_POINTS_"),
    "force_model": (common_pb2.ForceModel, "FORCE_MODEL_"),
    "noise_model": (common_pb2.NoiseModel, "NOISE_MODEL_"),
    "forecast": (common_pb2.Forecast, "FORECAST_"),
    "wrong_model": (common_pb2.WrongModel, "WRONG_MODEL_"),
}
# A Literal, so that mypy checks the names against EstimatorSettings' fields (HasField).
_Scalar: TypeAlias = Literal["alpha", "beta", "kappa", "p0", "q_var", "r", "force_var"]
_ESTIMATOR_SCALARS: tuple[_Scalar, ...] = ("alpha", "beta", "kappa", "p0", "q_var", "r", "force_var")


class _EnumValues(Protocol[_V_co]):
    """What `_enum` needs of a generated enum; unlike the stubs' wrapper it takes a union of enums."""

    def Value(self, name: str) -> _V_co: ...
    def keys(self) -> list[str]: ...


def _enum(enum: _EnumValues[_V_co], prefix: str, name: str, what: str) -> _V_co:
    try:
        return enum.Value(prefix + name.upper())
    except ValueError:
        names = [n[len(prefix) :] for n in enum.keys() if not n.endswith("UNSPECIFIED")]  # noqa: SIM118 (an enum wrapper, not a dict)
        raise InvalidArgument(f"{what} must be one of {names}, got {name!r}") from None


def _name(enum: _EnumTypeWrapper[_V], prefix: str, value: _V) -> str:
    return str(enum.Name(value))[len(prefix) :]


def _array(values: Any) -> np.ndarray:
    array = np.asarray(values, dtype=np.float64)
    array.flags.writeable = False
    return array


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
    """What to open. Give exactly one of model_name, model_id, inline_mjcf."""

    model_name: str | None = None
    model_id: str | None = None
    model_version: int = 0
    inline_mjcf: str | None = None
    inline_name: str = "inline"
    inline_assets: Mapping[str, bytes] = field(default_factory=dict)
    # PASSIVE | CONTROLLED | EXTERNAL | DRIVEN; None: the server's choice for the model (DRIVEN
    # for a model with actuators, else PASSIVE), reported in Opened.scenario and scenario_reason.
    scenario: str | None = None
    dt: float = 0.05  # s
    clock: str = "LOCKSTEP"  # LOCKSTEP | REALTIME
    estimator: Mapping[str, object] = field(
        default_factory=dict
    )  # estimator, preset, sigma_points, alpha, ...
    measured: Sequence[str] = ()  # of qpos, qvel, qacc, ctrl; empty: the server's default
    outputs: Sequence[str] = ()  # of INVERSE_DYNAMICS, FORWARD_DYNAMICS, SENSORS, FILTER_STATE
    horizon: str = "NONE"  # NONE | HALF_ROUND_TRIP
    subject_id: str = ""
    subject_attributes: Mapping[str, str] = field(default_factory=dict)
    grace: float = 0.0  # s; 0: dt / 2
    history: int = 0  # ticks; 0: the server's default

    def to_message(self) -> dynamics_pb2.OpenSession:
        chosen = [n for n in ("model_name", "model_id", "inline_mjcf") if getattr(self, n)]
        if len(chosen) != 1:
            raise InvalidArgument(
                f"give exactly one of model_name, model_id, inline_mjcf; got {chosen or 'none'}"
            )
        message = dynamics_pb2.OpenSession(
            model_version=self.model_version,
            scenario=(
                _enum(common_pb2.Scenario, "SCENARIO_", self.scenario, "scenario")
                if self.scenario
                else common_pb2.SCENARIO_UNSPECIFIED
            ),
            dt=self.dt,
            clock=_enum(common_pb2.Clock, "CLOCK_", self.clock, "clock"),
            measured=[_enum(common_pb2.Channel, "CHANNEL_", c, "measured") for c in self.measured],
            outputs=[_enum(common_pb2.Output, "OUTPUT_", o, "outputs") for o in self.outputs],
            horizon=_enum(dynamics_pb2.Horizon, "HORIZON_", self.horizon, "horizon"),
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
        for key, setting in self.estimator.items():
            if key in _ESTIMATOR_ENUMS:
                enum, prefix = _ESTIMATOR_ENUMS[key]
                setattr(message.estimator, key, _enum(enum, prefix, str(setting), f"estimator[{key!r}]"))
            elif key in _ESTIMATOR_SCALARS:
                # `estimator` holds any object: float() converts it, or raises for one it cannot.
                setattr(message.estimator, key, float(setting))  # type: ignore[arg-type]
            else:
                raise InvalidArgument(
                    f"estimator keys must be among {sorted([*_ESTIMATOR_ENUMS, *_ESTIMATOR_SCALARS])}, got {key!r}"
                )
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
    source: str  # MEASURED | PREDICTED | CORRECTED
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
    # FORECAST_COMBINED over a gap: the weights of MODEL, STATIC, CONSTANT_VELOCITY and
    # CONSTANT_ACCELERATION in the answer; None when the filter answered alone.
    forecast_weights: tuple[float, ...] | None = None
    # The scenario of the filter that answered (DRIVEN after a wrong PASSIVE model was absorbed);
    # "" for dead reckoning.
    scenario: str = ""

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
        return cls(
            seq=result.seq,
            t=result.t,
            source=_name(dynamics_pb2.Source, "SOURCE_", result.source),
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
            scenario=_name(common_pb2.Scenario, "SCENARIO_", result.scenario) if result.scenario else "",
        )


@dataclass(frozen=True)
class Rejection:
    """A frame the server did not use."""

    seq: int
    reason: str  # BAD_CHECKSUM | BAD_SHAPE | NOT_FINITE | DUPLICATE | TOO_OLD | OUT_OF_ORDER | WRONG_CLOCK
    message: str


@dataclass(frozen=True)
class Opened:
    session_id: str
    model: ModelRef
    estimator: dict[str, object]
    state_dimension: int
    measured: tuple[str, ...]
    outputs: tuple[str, ...]
    grace: float
    history: int
    dropped_attributes: tuple[str, ...]
    subject_pseudonym: str
    dt: float
    steps_per_tick: int
    scenario: str = ""  # the scenario in force: PASSIVE | CONTROLLED | EXTERNAL | DRIVEN
    scenario_reason: str = ""  # why: asked for, or the server's choice for the model
    noise_reason: str = ""  # why the noise model in estimator["noise_model"]


@dataclass(frozen=True)
class Summary:
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


@dataclass(frozen=True)
class SyncSample:
    """One clock exchange, from the client's side: offset = server - client, seconds."""

    offset: float
    round_trip: float
    server_offset: float
    server_round_trip: float


def _opened(message: dynamics_pb2.SessionOpened) -> Opened:
    settings: dict[str, object] = {}
    for key, (enum, prefix) in _ESTIMATOR_ENUMS.items():
        settings[key] = _name(enum, prefix, getattr(message.estimator, key))
    for key in _ESTIMATOR_SCALARS:
        if message.estimator.HasField(key):
            settings[key] = getattr(message.estimator, key)
    return Opened(
        session_id=message.session_id,
        model=ModelRef.from_message(message.model),
        estimator=settings,
        state_dimension=message.state_dimension,
        measured=tuple(_name(common_pb2.Channel, "CHANNEL_", c).lower() for c in message.measured),
        outputs=tuple(_name(common_pb2.Output, "OUTPUT_", o) for o in message.outputs),
        grace=message.grace,
        history=message.history,
        dropped_attributes=tuple(message.dropped_attributes),
        subject_pseudonym=message.subject_pseudonym,
        dt=message.dt,
        steps_per_tick=message.steps_per_tick,
        scenario=_name(common_pb2.Scenario, "SCENARIO_", message.scenario),
        scenario_reason=message.scenario_reason,
        noise_reason=message.noise_reason,
    )


def _summary(message: dynamics_pb2.SessionSummary) -> Summary:
    return Summary(
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


def _status_error(error: grpc.RpcError) -> JitdynError:
    """The `jitdyn.errors` exception for the status an RPC ended with (sync or grpc.aio)."""
    return error_for_status(error.code(), error.details() or "")


def _auth_metadata(api_key: str | None) -> tuple[tuple[str, str], ...]:
    return (("authorization", f"Bearer {api_key}"),) if api_key else ()


def _register_request(
    *, name: str, mjcf: str, assets: Mapping[str, bytes] | None, description: str, tags: Sequence[str]
) -> model_registry_pb2.RegisterModelRequest:
    request = model_registry_pb2.RegisterModelRequest(name=name, mjcf=mjcf, assets=dict(assets or {}))
    request.metadata.description = description
    request.metadata.tags.extend(tags)
    return request


def _first_answer(response: dynamics_pb2.StreamSessionResponse) -> Opened:
    """The `opened` a session stream must begin with."""
    if response.WhichOneof("payload") != "opened":
        raise FailedPrecondition(f"the server answered `open` with `{response.WhichOneof('payload')}`")
    return _opened(response.opened)


def _sync_request(
    probe_id: int, client_send_time: float, last_probe: tuple[int, float] | None
) -> dynamics_pb2.StreamSessionRequest:
    """A clock probe sent at `client_send_time` (session clock, s), reporting the receive time of the
    last answered probe, `(id, t4)`, so the server can complete that exchange."""
    ping = dynamics_pb2.SyncPing(id=probe_id, client_send_time=client_send_time)
    if last_probe is not None:
        ping.previous_id, ping.previous_receive_time = last_probe
    return dynamics_pb2.StreamSessionRequest(sync=ping)


def _sync_sample(pong: dynamics_pb2.SyncPong, t4: float) -> SyncSample:
    """One NTP-style exchange from the client's side; `t4` is the pong's receive time on the session clock."""
    t1, t2, t3 = pong.client_send_time, pong.server_receive_time, pong.server_send_time
    return SyncSample(
        offset=((t2 - t1) + (t3 - t4)) / 2.0,
        round_trip=(t4 - t1) - (t3 - t2),
        server_offset=pong.offset,
        server_round_trip=pong.round_trip,
    )


def _answer(
    response: dynamics_pb2.StreamSessionResponse, *, received_at: float, clock_start: float
) -> TickResult | Rejection | SyncSample | Summary:
    """A response of the session stream as the SDK hands it out; times are time.monotonic() values."""
    kind = response.WhichOneof("payload")
    if kind == "result":
        return TickResult.from_message(response.result, received_at=received_at)
    if kind == "rejected":
        r = response.rejected
        return Rejection(
            seq=r.seq, reason=_name(dynamics_pb2.RejectReason, "REJECT_REASON_", r.reason), message=r.message
        )
    if kind == "sync":
        return _sync_sample(response.sync, received_at - clock_start)
    if kind == "closed":
        return _summary(response.closed.summary)
    raise FailedPrecondition(f"unexpected `{kind}` from the server")


class _End(Enum):
    """The end of a session's request or response queue."""

    END = auto()


_END: Final = _End.END


class Session:
    """One open session. Use as a context manager; `close()` is safe to call twice.

    LOCKSTEP: `send_frame` and `skip` return the server's one answer. REALTIME: `send` queues a frame
    without waiting, and `results()` or `poll()` give answers as they arrive, among them the
    `SyncSample`s of the clock probes the session sends by itself (at open, then every
    `sync_interval` seconds with the frames).
    """

    def __init__(
        self,
        stub: dynamics_pb2_grpc.DynamicsServiceStub,
        options: SessionOptions,
        *,
        timeout: float | None,
        metadata: Sequence[tuple[str, str]],
        checksum: bool,
        sync_interval: float = 0.5,
        on_end: Callable[[], None] | None = None,
    ) -> None:
        self._on_end = on_end  # called once the stream has ended: the client closes its connection
        self._requests: queue.Queue[dynamics_pb2.StreamSessionRequest | _End] = queue.Queue()
        self._responses: queue.Queue[
            tuple[float, dynamics_pb2.StreamSessionResponse] | grpc.RpcError | _End
        ] = queue.Queue()
        self._timeout = timeout
        self._checksum = checksum
        self._clock_start = time.monotonic()
        self._last_probe: tuple[int, float] | None = None
        self._probe_id = 0
        self._realtime = options.clock.upper() == "REALTIME"
        self._sync_interval = sync_interval
        self._last_sync_sent = -float("inf")
        self._closed = False
        self.summary: Summary | None = None
        open_request = dynamics_pb2.StreamSessionRequest(open=options.to_message())
        self._requests.put(open_request)
        self._call = stub.StreamSession(self._request_iterator(), metadata=tuple(metadata))
        self._reader = threading.Thread(target=self._read, name="jitdyn-session-reader", daemon=True)
        self._reader.start()
        first = self._get(self._timeout)
        if first is None:
            raise FailedPrecondition("the session stream has ended")
        opened = _first_answer(first[1])
        # The session clock starts when `opened` arrived (the reader's time of it, not the time
        # this thread got to it): the server's starts as it sends it, so the two differ by one
        # transit until `sync` exchanges measure the offset.
        self._clock_start = first[0]
        self.opened = opened
        if self._realtime:
            self.sync()

    # Plumbing.

    def _request_iterator(self) -> Iterator[dynamics_pb2.StreamSessionRequest]:
        while True:
            item = self._requests.get()
            if item is _END:
                return
            yield item

    def _read(self) -> None:
        try:
            for response in self._call:
                received_at = time.monotonic()
                if response.HasField("sync"):
                    # t4 of this exchange, reported by the next probe however late the caller reads it.
                    self._last_probe = (response.sync.id, received_at - self._clock_start)
                self._responses.put((received_at, response))
        except grpc.RpcError as error:
            self._responses.put(error)
        finally:
            self._responses.put(_END)
            if self._on_end is not None:
                self._on_end()

    def _next_response(self, timeout: float | None) -> dynamics_pb2.StreamSessionResponse:
        item = self._get(timeout)
        if item is None:
            raise FailedPrecondition("the session stream has ended")
        return item[1]

    def _get(self, timeout: float | None) -> tuple[float, dynamics_pb2.StreamSessionResponse] | None:
        try:
            item = self._responses.get(timeout=timeout)
        except queue.Empty:
            raise JitdynError(f"no answer from the server within {timeout} s") from None
        if item is _END:
            self._responses.put(_END)
            return None
        if isinstance(item, grpc.RpcError):
            self._responses.put(_END)
            raise _status_error(item)
        return item

    def _convert(
        self, item: tuple[float, dynamics_pb2.StreamSessionResponse]
    ) -> TickResult | Rejection | SyncSample | Summary:
        received_at, response = item
        answer = _answer(response, received_at=received_at, clock_start=self._clock_start)
        if isinstance(answer, Summary):
            self.summary = answer
        return answer

    def _send(self, request: dynamics_pb2.StreamSessionRequest) -> None:
        if self._closed:
            raise FailedPrecondition("the session is closed")
        self._requests.put(request)

    @property
    def clock_start(self) -> float:
        """The time.monotonic() value that is 0 on the session clock."""
        return self._clock_start

    def now(self) -> float:
        """The client's session clock: seconds since `opened` arrived. REALTIME frames are due at
        `seq * dt` on this clock."""
        return time.monotonic() - self._clock_start

    # LOCKSTEP.

    def send_frame(self, frame: FrameData) -> TickResult | Rejection:
        """Send one frame and wait for its answer (LOCKSTEP)."""
        self.send(frame)
        return self._answer()

    def skip(self, seq: int) -> TickResult | Rejection:
        """Tell the server tick `seq` had no frame; returns the PREDICTED result (LOCKSTEP)."""
        self._send(dynamics_pb2.StreamSessionRequest(skip=dynamics_pb2.Skip(seq=seq)))
        return self._answer()

    def _answer(self) -> TickResult | Rejection:
        while True:
            item = self._get(self._timeout)
            if item is None:
                raise FailedPrecondition("the session stream ended before the answer")
            answer = self._convert(item)
            if isinstance(answer, (TickResult, Rejection)):
                return answer

    # REALTIME (and LOCKSTEP, for callers that pipeline).

    def send(self, frame: FrameData) -> None:
        """Queue a frame without waiting for its answer. In REALTIME a clock probe goes along every
        `sync_interval` seconds, so the server keeps client time on its clock."""
        if self._realtime and self.now() - self._last_sync_sent >= self._sync_interval:
            self.sync()
        self._send(dynamics_pb2.StreamSessionRequest(frame=frame.to_message(checksum=self._checksum)))

    def results(self, *, timeout: float | None = None) -> Iterator[TickResult | Rejection | SyncSample]:
        """Answers as they arrive, until the session is closed or `timeout` passes with none."""
        while True:
            try:
                item = self._get(timeout)
            except JitdynError as error:
                if "no answer" in str(error):
                    return
                raise
            if item is None:
                return
            answer = self._convert(item)
            if isinstance(answer, Summary):
                return
            yield answer

    def poll(self) -> list[TickResult | Rejection | SyncSample]:
        """Every answer that has arrived, without waiting."""
        answers: list[TickResult | Rejection | SyncSample] = []
        while True:
            try:
                item = self._responses.get_nowait()
            except queue.Empty:
                return answers
            if item is _END or isinstance(item, grpc.RpcError):
                self._responses.put(item)
                if isinstance(item, grpc.RpcError):
                    self._responses.get_nowait()
                    raise _status_error(item)
                return answers
            answer = self._convert(item)
            if not isinstance(answer, Summary):
                answers.append(answer)

    def sync(self) -> None:
        """Send a clock probe; its answer comes back among the results (a `SyncSample`)."""
        self._probe_id += 1
        self._last_sync_sent = self.now()
        self._send(_sync_request(self._probe_id, self._last_sync_sent, self._last_probe))

    # Ending.

    def close(self) -> Summary:
        """Close the session; returns its summary (where it is stored, counts)."""
        if self._closed:
            if self.summary is None:
                raise FailedPrecondition("the session ended without a summary")
            return self.summary
        self._requests.put(dynamics_pb2.StreamSessionRequest(close=dynamics_pb2.CloseSession()))
        self._closed = True
        self._requests.put(_END)
        while self.summary is None:
            item = self._get(self._timeout)
            if item is None:
                raise FailedPrecondition("the session stream ended without a summary")
            self._convert(item)
        self._reader.join(timeout=5)
        return self.summary

    def cancel(self) -> None:
        """Drop the stream without closing (the server stores the session as FAILED)."""
        self._closed = True
        self._call.cancel()
        self._requests.put(_END)

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is None:
            self.close()
        elif not self._closed:
            self.cancel()


class Client:
    """A connection to a jitdyn server. Keyword-only options beyond the address."""

    def __init__(
        self,
        address: str = "127.0.0.1:50051",
        *,
        timeout: float | None = 60.0,
        api_key: str | None = None,
        root_certificates: bytes | None = None,
        checksum: bool = True,
        connection_per_session: bool = True,
    ) -> None:
        self._address = address
        self._root_certificates = root_certificates
        self._channel = self._new_channel(shared=True)
        # Each session on its own connection (its own HTTP/2 connection, not a stream of the
        # client's): `jitdyn serve --processes N` is N processes on one port, and the kernel spreads
        # connections, not streams, over them, so sessions sharing one connection share one process
        # and one core. False: every session on the client's one connection.
        self._connection_per_session = connection_per_session
        self._session_channels: set[grpc.Channel] = set()
        self._lock = threading.Lock()
        self._metadata = _auth_metadata(api_key)
        self._timeout = timeout
        self._checksum = checksum
        self._registry = model_registry_pb2_grpc.ModelRegistryServiceStub(self._channel)
        self._dynamics = dynamics_pb2_grpc.DynamicsServiceStub(self._channel)
        self._sessions = session_pb2_grpc.SessionServiceStub(self._channel)

    def wait_ready(self, timeout: float = 10.0) -> None:
        """Block until the server answers, or raise Unavailable."""
        try:
            grpc.channel_ready_future(self._channel).result(timeout=timeout)
        except grpc.FutureTimeoutError:
            raise error_for_status(
                grpc.StatusCode.UNAVAILABLE, f"no jitdyn server answered within {timeout} s"
            ) from None

    def _unary(
        self, method: grpc.UnaryUnaryMultiCallable[_Request, _Response], request: _Request
    ) -> _Response:
        try:
            return method(request, timeout=self._timeout, metadata=self._metadata)
        except grpc.RpcError as error:
            raise _status_error(error) from None

    def register_model(
        self,
        *,
        name: str,
        mjcf: str,
        assets: Mapping[str, bytes] | None = None,
        description: str = "",
        tags: Sequence[str] = (),
    ) -> tuple[ModelRef, bool]:
        """Register a model; returns it and whether it was new."""
        request = _register_request(name=name, mjcf=mjcf, assets=assets, description=description, tags=tags)
        response = self._unary(self._registry.RegisterModel, request)
        return ModelRef.from_message(response.model), response.created

    def get_model(self, *, model_id: str = "", name: str = "", version: int = 0) -> ModelRef:
        return ModelRef.from_message(
            self._unary(
                self._registry.GetModel,
                model_registry_pb2.GetModelRequest(model_id=model_id, name=name, version=version),
            ).model
        )

    def get_model_message(
        self, *, model_id: str = "", name: str = "", version: int = 0
    ) -> model_registry_pb2.Model:
        """The full `Model` message (joints with ranges, actuators, metadata)."""
        return self._unary(
            self._registry.GetModel,
            model_registry_pb2.GetModelRequest(model_id=model_id, name=name, version=version),
        ).model

    def list_models(self, *, name: str = "", tag: str = "", page_size: int = 0) -> Iterator[ModelRef]:
        """Every model matching the filters, page after page."""
        token = ""
        while True:
            page = self._unary(
                self._registry.ListModels,
                model_registry_pb2.ListModelsRequest(
                    page_size=page_size, page_token=token, name=name, tag=tag
                ),
            )
            for model in page.models:
                yield ModelRef.from_message(model)
            token = page.next_page_token
            if not token:
                return

    def list_sessions(
        self, request: session_pb2.ListSessionsRequest | None = None
    ) -> Iterator[session_pb2.Session]:
        """Every stored session matching the request's filters, newest first."""
        page_request = session_pb2.ListSessionsRequest()
        if request is not None:
            page_request.CopyFrom(request)
        while True:
            page = self._unary(self._sessions.ListSessions, page_request)
            yield from page.sessions
            if not page.next_page_token:
                return
            page_request.page_token = page.next_page_token

    def get_session(self, session_id: str) -> session_pb2.Session:
        return self._unary(
            self._sessions.GetSession, session_pb2.GetSessionRequest(session_id=session_id)
        ).session

    def _new_channel(self, *, shared: bool) -> grpc.Channel:
        # gRPC shares one connection between channels of the same target and arguments unless a
        # channel asks for its own subchannel pool.
        options = _CHANNEL_OPTIONS if shared else (*_CHANNEL_OPTIONS, ("grpc.use_local_subchannel_pool", 1))
        if self._root_certificates is not None:
            return grpc.secure_channel(
                self._address, grpc.ssl_channel_credentials(self._root_certificates), options=options
            )
        return grpc.insecure_channel(self._address, options=options)

    def open_session(self, options: SessionOptions) -> Session:
        """Open a session; raises the server's error (InvalidArgument, NotFound, ...) if it refuses."""
        stub, ended = self._dynamics, None
        if self._connection_per_session:
            channel = self._new_channel(shared=False)
            with self._lock:
                self._session_channels.add(channel)
            stub = dynamics_pb2_grpc.DynamicsServiceStub(channel)

            def ended() -> None:
                with self._lock:
                    if channel not in self._session_channels:
                        return
                    self._session_channels.discard(channel)
                channel.close()

        try:
            return Session(
                stub,
                options,
                timeout=self._timeout,
                metadata=self._metadata,
                checksum=self._checksum,
                on_end=ended,
            )
        except grpc.RpcError as error:
            raise _status_error(error) from None

    def close(self) -> None:
        """Close the connections (open sessions end with them); safe to call twice."""
        with self._lock:
            channels, self._session_channels = self._session_channels, set()
        for channel in channels:
            channel.close()
        self._channel.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
