from jitdyn.v1 import common_pb2 as _common_pb2
from jitdyn.v1 import model_registry_pb2 as _model_registry_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Horizon(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    HORIZON_UNSPECIFIED: _ClassVar[Horizon]
    HORIZON_NONE: _ClassVar[Horizon]
    HORIZON_HALF_ROUND_TRIP: _ClassVar[Horizon]

class Source(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    SOURCE_UNSPECIFIED: _ClassVar[Source]
    SOURCE_MEASURED: _ClassVar[Source]
    SOURCE_PREDICTED: _ClassVar[Source]
    SOURCE_CORRECTED: _ClassVar[Source]

class RejectReason(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    REJECT_REASON_UNSPECIFIED: _ClassVar[RejectReason]
    REJECT_REASON_BAD_CHECKSUM: _ClassVar[RejectReason]
    REJECT_REASON_BAD_SHAPE: _ClassVar[RejectReason]
    REJECT_REASON_NOT_FINITE: _ClassVar[RejectReason]
    REJECT_REASON_DUPLICATE: _ClassVar[RejectReason]
    REJECT_REASON_TOO_OLD: _ClassVar[RejectReason]
    REJECT_REASON_OUT_OF_ORDER: _ClassVar[RejectReason]
    REJECT_REASON_WRONG_CLOCK: _ClassVar[RejectReason]
HORIZON_UNSPECIFIED: Horizon
HORIZON_NONE: Horizon
HORIZON_HALF_ROUND_TRIP: Horizon
SOURCE_UNSPECIFIED: Source
SOURCE_MEASURED: Source
SOURCE_PREDICTED: Source
SOURCE_CORRECTED: Source
REJECT_REASON_UNSPECIFIED: RejectReason
REJECT_REASON_BAD_CHECKSUM: RejectReason
REJECT_REASON_BAD_SHAPE: RejectReason
REJECT_REASON_NOT_FINITE: RejectReason
REJECT_REASON_DUPLICATE: RejectReason
REJECT_REASON_TOO_OLD: RejectReason
REJECT_REASON_OUT_OF_ORDER: RejectReason
REJECT_REASON_WRONG_CLOCK: RejectReason

class StreamSessionRequest(_message.Message):
    __slots__ = ("open", "frame", "skip", "sync", "close")
    OPEN_FIELD_NUMBER: _ClassVar[int]
    FRAME_FIELD_NUMBER: _ClassVar[int]
    SKIP_FIELD_NUMBER: _ClassVar[int]
    SYNC_FIELD_NUMBER: _ClassVar[int]
    CLOSE_FIELD_NUMBER: _ClassVar[int]
    open: OpenSession
    frame: Frame
    skip: Skip
    sync: SyncPing
    close: CloseSession
    def __init__(self, open: _Optional[_Union[OpenSession, _Mapping]] = ..., frame: _Optional[_Union[Frame, _Mapping]] = ..., skip: _Optional[_Union[Skip, _Mapping]] = ..., sync: _Optional[_Union[SyncPing, _Mapping]] = ..., close: _Optional[_Union[CloseSession, _Mapping]] = ...) -> None: ...

class StreamSessionResponse(_message.Message):
    __slots__ = ("opened", "result", "rejected", "sync", "closed")
    OPENED_FIELD_NUMBER: _ClassVar[int]
    RESULT_FIELD_NUMBER: _ClassVar[int]
    REJECTED_FIELD_NUMBER: _ClassVar[int]
    SYNC_FIELD_NUMBER: _ClassVar[int]
    CLOSED_FIELD_NUMBER: _ClassVar[int]
    opened: SessionOpened
    result: Result
    rejected: Rejected
    sync: SyncPong
    closed: SessionClosed
    def __init__(self, opened: _Optional[_Union[SessionOpened, _Mapping]] = ..., result: _Optional[_Union[Result, _Mapping]] = ..., rejected: _Optional[_Union[Rejected, _Mapping]] = ..., sync: _Optional[_Union[SyncPong, _Mapping]] = ..., closed: _Optional[_Union[SessionClosed, _Mapping]] = ...) -> None: ...

class Subject(_message.Message):
    __slots__ = ("id", "attributes")
    class AttributesEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: str
        def __init__(self, key: _Optional[str] = ..., value: _Optional[str] = ...) -> None: ...
    ID_FIELD_NUMBER: _ClassVar[int]
    ATTRIBUTES_FIELD_NUMBER: _ClassVar[int]
    id: str
    attributes: _containers.ScalarMap[str, str]
    def __init__(self, id: _Optional[str] = ..., attributes: _Optional[_Mapping[str, str]] = ...) -> None: ...

class OpenSession(_message.Message):
    __slots__ = ("model_id", "model_name", "inline_model", "model_version", "scenario", "dt", "clock", "estimator", "measured", "outputs", "horizon", "subject", "grace", "history")
    MODEL_ID_FIELD_NUMBER: _ClassVar[int]
    MODEL_NAME_FIELD_NUMBER: _ClassVar[int]
    INLINE_MODEL_FIELD_NUMBER: _ClassVar[int]
    MODEL_VERSION_FIELD_NUMBER: _ClassVar[int]
    SCENARIO_FIELD_NUMBER: _ClassVar[int]
    DT_FIELD_NUMBER: _ClassVar[int]
    CLOCK_FIELD_NUMBER: _ClassVar[int]
    ESTIMATOR_FIELD_NUMBER: _ClassVar[int]
    MEASURED_FIELD_NUMBER: _ClassVar[int]
    OUTPUTS_FIELD_NUMBER: _ClassVar[int]
    HORIZON_FIELD_NUMBER: _ClassVar[int]
    SUBJECT_FIELD_NUMBER: _ClassVar[int]
    GRACE_FIELD_NUMBER: _ClassVar[int]
    HISTORY_FIELD_NUMBER: _ClassVar[int]
    model_id: str
    model_name: str
    inline_model: _model_registry_pb2.RegisterModelRequest
    model_version: int
    scenario: _common_pb2.Scenario
    dt: float
    clock: _common_pb2.Clock
    estimator: _common_pb2.EstimatorSettings
    measured: _containers.RepeatedScalarFieldContainer[_common_pb2.Channel]
    outputs: _containers.RepeatedScalarFieldContainer[_common_pb2.Output]
    horizon: Horizon
    subject: Subject
    grace: float
    history: int
    def __init__(self, model_id: _Optional[str] = ..., model_name: _Optional[str] = ..., inline_model: _Optional[_Union[_model_registry_pb2.RegisterModelRequest, _Mapping]] = ..., model_version: _Optional[int] = ..., scenario: _Optional[_Union[_common_pb2.Scenario, str]] = ..., dt: _Optional[float] = ..., clock: _Optional[_Union[_common_pb2.Clock, str]] = ..., estimator: _Optional[_Union[_common_pb2.EstimatorSettings, _Mapping]] = ..., measured: _Optional[_Iterable[_Union[_common_pb2.Channel, str]]] = ..., outputs: _Optional[_Iterable[_Union[_common_pb2.Output, str]]] = ..., horizon: _Optional[_Union[Horizon, str]] = ..., subject: _Optional[_Union[Subject, _Mapping]] = ..., grace: _Optional[float] = ..., history: _Optional[int] = ...) -> None: ...

class Frame(_message.Message):
    __slots__ = ("seq", "t", "qpos", "qvel", "qacc", "ctrl", "sensordata", "checksum")
    SEQ_FIELD_NUMBER: _ClassVar[int]
    T_FIELD_NUMBER: _ClassVar[int]
    QPOS_FIELD_NUMBER: _ClassVar[int]
    QVEL_FIELD_NUMBER: _ClassVar[int]
    QACC_FIELD_NUMBER: _ClassVar[int]
    CTRL_FIELD_NUMBER: _ClassVar[int]
    SENSORDATA_FIELD_NUMBER: _ClassVar[int]
    CHECKSUM_FIELD_NUMBER: _ClassVar[int]
    seq: int
    t: float
    qpos: _containers.RepeatedScalarFieldContainer[float]
    qvel: _containers.RepeatedScalarFieldContainer[float]
    qacc: _containers.RepeatedScalarFieldContainer[float]
    ctrl: _containers.RepeatedScalarFieldContainer[float]
    sensordata: _containers.RepeatedScalarFieldContainer[float]
    checksum: int
    def __init__(self, seq: _Optional[int] = ..., t: _Optional[float] = ..., qpos: _Optional[_Iterable[float]] = ..., qvel: _Optional[_Iterable[float]] = ..., qacc: _Optional[_Iterable[float]] = ..., ctrl: _Optional[_Iterable[float]] = ..., sensordata: _Optional[_Iterable[float]] = ..., checksum: _Optional[int] = ...) -> None: ...

class Skip(_message.Message):
    __slots__ = ("seq",)
    SEQ_FIELD_NUMBER: _ClassVar[int]
    seq: int
    def __init__(self, seq: _Optional[int] = ...) -> None: ...

class SyncPing(_message.Message):
    __slots__ = ("id", "client_send_time", "previous_id", "previous_receive_time")
    ID_FIELD_NUMBER: _ClassVar[int]
    CLIENT_SEND_TIME_FIELD_NUMBER: _ClassVar[int]
    PREVIOUS_ID_FIELD_NUMBER: _ClassVar[int]
    PREVIOUS_RECEIVE_TIME_FIELD_NUMBER: _ClassVar[int]
    id: int
    client_send_time: float
    previous_id: int
    previous_receive_time: float
    def __init__(self, id: _Optional[int] = ..., client_send_time: _Optional[float] = ..., previous_id: _Optional[int] = ..., previous_receive_time: _Optional[float] = ...) -> None: ...

class SyncPong(_message.Message):
    __slots__ = ("id", "client_send_time", "server_receive_time", "server_send_time", "offset", "round_trip")
    ID_FIELD_NUMBER: _ClassVar[int]
    CLIENT_SEND_TIME_FIELD_NUMBER: _ClassVar[int]
    SERVER_RECEIVE_TIME_FIELD_NUMBER: _ClassVar[int]
    SERVER_SEND_TIME_FIELD_NUMBER: _ClassVar[int]
    OFFSET_FIELD_NUMBER: _ClassVar[int]
    ROUND_TRIP_FIELD_NUMBER: _ClassVar[int]
    id: int
    client_send_time: float
    server_receive_time: float
    server_send_time: float
    offset: float
    round_trip: float
    def __init__(self, id: _Optional[int] = ..., client_send_time: _Optional[float] = ..., server_receive_time: _Optional[float] = ..., server_send_time: _Optional[float] = ..., offset: _Optional[float] = ..., round_trip: _Optional[float] = ...) -> None: ...

class CloseSession(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class SessionOpened(_message.Message):
    __slots__ = ("session_id", "model", "estimator", "state_dimension", "measured", "outputs", "grace", "history", "dropped_attributes", "subject_pseudonym", "dt", "steps_per_tick")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    MODEL_FIELD_NUMBER: _ClassVar[int]
    ESTIMATOR_FIELD_NUMBER: _ClassVar[int]
    STATE_DIMENSION_FIELD_NUMBER: _ClassVar[int]
    MEASURED_FIELD_NUMBER: _ClassVar[int]
    OUTPUTS_FIELD_NUMBER: _ClassVar[int]
    GRACE_FIELD_NUMBER: _ClassVar[int]
    HISTORY_FIELD_NUMBER: _ClassVar[int]
    DROPPED_ATTRIBUTES_FIELD_NUMBER: _ClassVar[int]
    SUBJECT_PSEUDONYM_FIELD_NUMBER: _ClassVar[int]
    DT_FIELD_NUMBER: _ClassVar[int]
    STEPS_PER_TICK_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    model: _model_registry_pb2.Model
    estimator: _common_pb2.EstimatorSettings
    state_dimension: int
    measured: _containers.RepeatedScalarFieldContainer[_common_pb2.Channel]
    outputs: _containers.RepeatedScalarFieldContainer[_common_pb2.Output]
    grace: float
    history: int
    dropped_attributes: _containers.RepeatedScalarFieldContainer[str]
    subject_pseudonym: str
    dt: float
    steps_per_tick: int
    def __init__(self, session_id: _Optional[str] = ..., model: _Optional[_Union[_model_registry_pb2.Model, _Mapping]] = ..., estimator: _Optional[_Union[_common_pb2.EstimatorSettings, _Mapping]] = ..., state_dimension: _Optional[int] = ..., measured: _Optional[_Iterable[_Union[_common_pb2.Channel, str]]] = ..., outputs: _Optional[_Iterable[_Union[_common_pb2.Output, str]]] = ..., grace: _Optional[float] = ..., history: _Optional[int] = ..., dropped_attributes: _Optional[_Iterable[str]] = ..., subject_pseudonym: _Optional[str] = ..., dt: _Optional[float] = ..., steps_per_tick: _Optional[int] = ...) -> None: ...

class Result(_message.Message):
    __slots__ = ("seq", "t", "source", "qpos", "qvel", "qacc", "qfrc_inverse", "qacc_forward", "actuator_force", "sensordata", "covariance_diagonal", "nis", "frame_received", "late_ticks", "frame_delay", "compute_us", "receive_to_send_us", "durable_seq", "reinitialised", "horizon", "filter_state", "covariance")
    SEQ_FIELD_NUMBER: _ClassVar[int]
    T_FIELD_NUMBER: _ClassVar[int]
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    QPOS_FIELD_NUMBER: _ClassVar[int]
    QVEL_FIELD_NUMBER: _ClassVar[int]
    QACC_FIELD_NUMBER: _ClassVar[int]
    QFRC_INVERSE_FIELD_NUMBER: _ClassVar[int]
    QACC_FORWARD_FIELD_NUMBER: _ClassVar[int]
    ACTUATOR_FORCE_FIELD_NUMBER: _ClassVar[int]
    SENSORDATA_FIELD_NUMBER: _ClassVar[int]
    COVARIANCE_DIAGONAL_FIELD_NUMBER: _ClassVar[int]
    NIS_FIELD_NUMBER: _ClassVar[int]
    FRAME_RECEIVED_FIELD_NUMBER: _ClassVar[int]
    LATE_TICKS_FIELD_NUMBER: _ClassVar[int]
    FRAME_DELAY_FIELD_NUMBER: _ClassVar[int]
    COMPUTE_US_FIELD_NUMBER: _ClassVar[int]
    RECEIVE_TO_SEND_US_FIELD_NUMBER: _ClassVar[int]
    DURABLE_SEQ_FIELD_NUMBER: _ClassVar[int]
    REINITIALISED_FIELD_NUMBER: _ClassVar[int]
    HORIZON_FIELD_NUMBER: _ClassVar[int]
    FILTER_STATE_FIELD_NUMBER: _ClassVar[int]
    COVARIANCE_FIELD_NUMBER: _ClassVar[int]
    seq: int
    t: float
    source: Source
    qpos: _containers.RepeatedScalarFieldContainer[float]
    qvel: _containers.RepeatedScalarFieldContainer[float]
    qacc: _containers.RepeatedScalarFieldContainer[float]
    qfrc_inverse: _containers.RepeatedScalarFieldContainer[float]
    qacc_forward: _containers.RepeatedScalarFieldContainer[float]
    actuator_force: _containers.RepeatedScalarFieldContainer[float]
    sensordata: _containers.RepeatedScalarFieldContainer[float]
    covariance_diagonal: _containers.RepeatedScalarFieldContainer[float]
    nis: float
    frame_received: bool
    late_ticks: int
    frame_delay: float
    compute_us: int
    receive_to_send_us: int
    durable_seq: int
    reinitialised: bool
    horizon: float
    filter_state: _containers.RepeatedScalarFieldContainer[float]
    covariance: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, seq: _Optional[int] = ..., t: _Optional[float] = ..., source: _Optional[_Union[Source, str]] = ..., qpos: _Optional[_Iterable[float]] = ..., qvel: _Optional[_Iterable[float]] = ..., qacc: _Optional[_Iterable[float]] = ..., qfrc_inverse: _Optional[_Iterable[float]] = ..., qacc_forward: _Optional[_Iterable[float]] = ..., actuator_force: _Optional[_Iterable[float]] = ..., sensordata: _Optional[_Iterable[float]] = ..., covariance_diagonal: _Optional[_Iterable[float]] = ..., nis: _Optional[float] = ..., frame_received: _Optional[bool] = ..., late_ticks: _Optional[int] = ..., frame_delay: _Optional[float] = ..., compute_us: _Optional[int] = ..., receive_to_send_us: _Optional[int] = ..., durable_seq: _Optional[int] = ..., reinitialised: _Optional[bool] = ..., horizon: _Optional[float] = ..., filter_state: _Optional[_Iterable[float]] = ..., covariance: _Optional[_Iterable[float]] = ...) -> None: ...

class Rejected(_message.Message):
    __slots__ = ("seq", "reason", "message")
    SEQ_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    seq: int
    reason: RejectReason
    message: str
    def __init__(self, seq: _Optional[int] = ..., reason: _Optional[_Union[RejectReason, str]] = ..., message: _Optional[str] = ...) -> None: ...

class SessionClosed(_message.Message):
    __slots__ = ("summary",)
    SUMMARY_FIELD_NUMBER: _ClassVar[int]
    summary: SessionSummary
    def __init__(self, summary: _Optional[_Union[SessionSummary, _Mapping]] = ...) -> None: ...

class SessionSummary(_message.Message):
    __slots__ = ("ticks", "frames", "measured", "predicted", "corrected", "rejected", "late", "location", "mean_compute_us", "max_compute_us", "duration")
    TICKS_FIELD_NUMBER: _ClassVar[int]
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    MEASURED_FIELD_NUMBER: _ClassVar[int]
    PREDICTED_FIELD_NUMBER: _ClassVar[int]
    CORRECTED_FIELD_NUMBER: _ClassVar[int]
    REJECTED_FIELD_NUMBER: _ClassVar[int]
    LATE_FIELD_NUMBER: _ClassVar[int]
    LOCATION_FIELD_NUMBER: _ClassVar[int]
    MEAN_COMPUTE_US_FIELD_NUMBER: _ClassVar[int]
    MAX_COMPUTE_US_FIELD_NUMBER: _ClassVar[int]
    DURATION_FIELD_NUMBER: _ClassVar[int]
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
    def __init__(self, ticks: _Optional[int] = ..., frames: _Optional[int] = ..., measured: _Optional[int] = ..., predicted: _Optional[int] = ..., corrected: _Optional[int] = ..., rejected: _Optional[int] = ..., late: _Optional[int] = ..., location: _Optional[str] = ..., mean_compute_us: _Optional[float] = ..., max_compute_us: _Optional[float] = ..., duration: _Optional[float] = ...) -> None: ...
