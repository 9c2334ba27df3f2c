import datetime

from google.protobuf import timestamp_pb2 as _timestamp_pb2
from jitdyn.v1 import common_pb2 as _common_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class JointType(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    JOINT_TYPE_UNSPECIFIED: _ClassVar[JointType]
    JOINT_TYPE_FREE: _ClassVar[JointType]
    JOINT_TYPE_BALL: _ClassVar[JointType]
    JOINT_TYPE_SLIDE: _ClassVar[JointType]
    JOINT_TYPE_HINGE: _ClassVar[JointType]
JOINT_TYPE_UNSPECIFIED: JointType
JOINT_TYPE_FREE: JointType
JOINT_TYPE_BALL: JointType
JOINT_TYPE_SLIDE: JointType
JOINT_TYPE_HINGE: JointType

class Joint(_message.Message):
    __slots__ = ("name", "type", "limited", "range_lower", "range_upper", "qpos_address", "dof_address")
    NAME_FIELD_NUMBER: _ClassVar[int]
    TYPE_FIELD_NUMBER: _ClassVar[int]
    LIMITED_FIELD_NUMBER: _ClassVar[int]
    RANGE_LOWER_FIELD_NUMBER: _ClassVar[int]
    RANGE_UPPER_FIELD_NUMBER: _ClassVar[int]
    QPOS_ADDRESS_FIELD_NUMBER: _ClassVar[int]
    DOF_ADDRESS_FIELD_NUMBER: _ClassVar[int]
    name: str
    type: JointType
    limited: bool
    range_lower: float
    range_upper: float
    qpos_address: int
    dof_address: int
    def __init__(self, name: _Optional[str] = ..., type: _Optional[_Union[JointType, str]] = ..., limited: _Optional[bool] = ..., range_lower: _Optional[float] = ..., range_upper: _Optional[float] = ..., qpos_address: _Optional[int] = ..., dof_address: _Optional[int] = ...) -> None: ...

class Actuator(_message.Message):
    __slots__ = ("name", "target", "ctrl_limited", "ctrl_lower", "ctrl_upper")
    NAME_FIELD_NUMBER: _ClassVar[int]
    TARGET_FIELD_NUMBER: _ClassVar[int]
    CTRL_LIMITED_FIELD_NUMBER: _ClassVar[int]
    CTRL_LOWER_FIELD_NUMBER: _ClassVar[int]
    CTRL_UPPER_FIELD_NUMBER: _ClassVar[int]
    name: str
    target: str
    ctrl_limited: bool
    ctrl_lower: float
    ctrl_upper: float
    def __init__(self, name: _Optional[str] = ..., target: _Optional[str] = ..., ctrl_limited: _Optional[bool] = ..., ctrl_lower: _Optional[float] = ..., ctrl_upper: _Optional[float] = ...) -> None: ...

class Dimensions(_message.Message):
    __slots__ = ("nq", "nv", "nu", "na", "nsensor", "nbody")
    NQ_FIELD_NUMBER: _ClassVar[int]
    NV_FIELD_NUMBER: _ClassVar[int]
    NU_FIELD_NUMBER: _ClassVar[int]
    NA_FIELD_NUMBER: _ClassVar[int]
    NSENSOR_FIELD_NUMBER: _ClassVar[int]
    NBODY_FIELD_NUMBER: _ClassVar[int]
    nq: int
    nv: int
    nu: int
    na: int
    nsensor: int
    nbody: int
    def __init__(self, nq: _Optional[int] = ..., nv: _Optional[int] = ..., nu: _Optional[int] = ..., na: _Optional[int] = ..., nsensor: _Optional[int] = ..., nbody: _Optional[int] = ...) -> None: ...

class ScenarioDefaults(_message.Message):
    __slots__ = ("scenario", "estimator")
    SCENARIO_FIELD_NUMBER: _ClassVar[int]
    ESTIMATOR_FIELD_NUMBER: _ClassVar[int]
    scenario: _common_pb2.Scenario
    estimator: _common_pb2.EstimatorSettings
    def __init__(self, scenario: _Optional[_Union[_common_pb2.Scenario, str]] = ..., estimator: _Optional[_Union[_common_pb2.EstimatorSettings, _Mapping]] = ...) -> None: ...

class ModelMetadata(_message.Message):
    __slots__ = ("description", "tags", "defaults")
    DESCRIPTION_FIELD_NUMBER: _ClassVar[int]
    TAGS_FIELD_NUMBER: _ClassVar[int]
    DEFAULTS_FIELD_NUMBER: _ClassVar[int]
    description: str
    tags: _containers.RepeatedScalarFieldContainer[str]
    defaults: _containers.RepeatedCompositeFieldContainer[ScenarioDefaults]
    def __init__(self, description: _Optional[str] = ..., tags: _Optional[_Iterable[str]] = ..., defaults: _Optional[_Iterable[_Union[ScenarioDefaults, _Mapping]]] = ...) -> None: ...

class Model(_message.Message):
    __slots__ = ("id", "name", "version", "dimensions", "joints", "actuators", "metadata", "created_at", "timestep", "builtin")
    ID_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    DIMENSIONS_FIELD_NUMBER: _ClassVar[int]
    JOINTS_FIELD_NUMBER: _ClassVar[int]
    ACTUATORS_FIELD_NUMBER: _ClassVar[int]
    METADATA_FIELD_NUMBER: _ClassVar[int]
    CREATED_AT_FIELD_NUMBER: _ClassVar[int]
    TIMESTEP_FIELD_NUMBER: _ClassVar[int]
    BUILTIN_FIELD_NUMBER: _ClassVar[int]
    id: str
    name: str
    version: int
    dimensions: Dimensions
    joints: _containers.RepeatedCompositeFieldContainer[Joint]
    actuators: _containers.RepeatedCompositeFieldContainer[Actuator]
    metadata: ModelMetadata
    created_at: _timestamp_pb2.Timestamp
    timestep: float
    builtin: bool
    def __init__(self, id: _Optional[str] = ..., name: _Optional[str] = ..., version: _Optional[int] = ..., dimensions: _Optional[_Union[Dimensions, _Mapping]] = ..., joints: _Optional[_Iterable[_Union[Joint, _Mapping]]] = ..., actuators: _Optional[_Iterable[_Union[Actuator, _Mapping]]] = ..., metadata: _Optional[_Union[ModelMetadata, _Mapping]] = ..., created_at: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., timestep: _Optional[float] = ..., builtin: _Optional[bool] = ...) -> None: ...

class RegisterModelRequest(_message.Message):
    __slots__ = ("name", "mjcf", "assets", "metadata")
    class AssetsEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: bytes
        def __init__(self, key: _Optional[str] = ..., value: _Optional[bytes] = ...) -> None: ...
    NAME_FIELD_NUMBER: _ClassVar[int]
    MJCF_FIELD_NUMBER: _ClassVar[int]
    ASSETS_FIELD_NUMBER: _ClassVar[int]
    METADATA_FIELD_NUMBER: _ClassVar[int]
    name: str
    mjcf: str
    assets: _containers.ScalarMap[str, bytes]
    metadata: ModelMetadata
    def __init__(self, name: _Optional[str] = ..., mjcf: _Optional[str] = ..., assets: _Optional[_Mapping[str, bytes]] = ..., metadata: _Optional[_Union[ModelMetadata, _Mapping]] = ...) -> None: ...

class RegisterModelResponse(_message.Message):
    __slots__ = ("model", "created")
    MODEL_FIELD_NUMBER: _ClassVar[int]
    CREATED_FIELD_NUMBER: _ClassVar[int]
    model: Model
    created: bool
    def __init__(self, model: _Optional[_Union[Model, _Mapping]] = ..., created: _Optional[bool] = ...) -> None: ...

class GetModelRequest(_message.Message):
    __slots__ = ("model_id", "name", "version")
    MODEL_ID_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    model_id: str
    name: str
    version: int
    def __init__(self, model_id: _Optional[str] = ..., name: _Optional[str] = ..., version: _Optional[int] = ...) -> None: ...

class GetModelResponse(_message.Message):
    __slots__ = ("model",)
    MODEL_FIELD_NUMBER: _ClassVar[int]
    model: Model
    def __init__(self, model: _Optional[_Union[Model, _Mapping]] = ...) -> None: ...

class ListModelsRequest(_message.Message):
    __slots__ = ("page_size", "page_token", "name", "tag")
    PAGE_SIZE_FIELD_NUMBER: _ClassVar[int]
    PAGE_TOKEN_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    TAG_FIELD_NUMBER: _ClassVar[int]
    page_size: int
    page_token: str
    name: str
    tag: str
    def __init__(self, page_size: _Optional[int] = ..., page_token: _Optional[str] = ..., name: _Optional[str] = ..., tag: _Optional[str] = ...) -> None: ...

class ListModelsResponse(_message.Message):
    __slots__ = ("models", "next_page_token")
    MODELS_FIELD_NUMBER: _ClassVar[int]
    NEXT_PAGE_TOKEN_FIELD_NUMBER: _ClassVar[int]
    models: _containers.RepeatedCompositeFieldContainer[Model]
    next_page_token: str
    def __init__(self, models: _Optional[_Iterable[_Union[Model, _Mapping]]] = ..., next_page_token: _Optional[str] = ...) -> None: ...
