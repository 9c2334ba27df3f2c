from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Scenario(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    SCENARIO_UNSPECIFIED: _ClassVar[Scenario]
    SCENARIO_PASSIVE: _ClassVar[Scenario]
    SCENARIO_CONTROLLED: _ClassVar[Scenario]
    SCENARIO_EXTERNAL: _ClassVar[Scenario]

class Clock(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    CLOCK_UNSPECIFIED: _ClassVar[Clock]
    CLOCK_REALTIME: _ClassVar[Clock]
    CLOCK_LOCKSTEP: _ClassVar[Clock]

class Estimator(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    ESTIMATOR_UNSPECIFIED: _ClassVar[Estimator]
    ESTIMATOR_UKF: _ClassVar[Estimator]
    ESTIMATOR_STATIC: _ClassVar[Estimator]
    ESTIMATOR_CONSTANT_VELOCITY: _ClassVar[Estimator]
    ESTIMATOR_CONSTANT_ACCELERATION: _ClassVar[Estimator]

class SigmaPoints(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    SIGMA_POINTS_UNSPECIFIED: _ClassVar[SigmaPoints]
    SIGMA_POINTS_MERWE: _ClassVar[SigmaPoints]
    SIGMA_POINTS_SIMPLEX: _ClassVar[SigmaPoints]
    SIGMA_POINTS_UNIFORM: _ClassVar[SigmaPoints]

class Preset(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    PRESET_UNSPECIFIED: _ClassVar[Preset]
    PRESET_JITDYN: _ClassVar[Preset]
    PRESET_THESIS: _ClassVar[Preset]

class Channel(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    CHANNEL_UNSPECIFIED: _ClassVar[Channel]
    CHANNEL_QPOS: _ClassVar[Channel]
    CHANNEL_QVEL: _ClassVar[Channel]
    CHANNEL_QACC: _ClassVar[Channel]
    CHANNEL_CTRL: _ClassVar[Channel]

class Output(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    OUTPUT_UNSPECIFIED: _ClassVar[Output]
    OUTPUT_INVERSE_DYNAMICS: _ClassVar[Output]
    OUTPUT_FORWARD_DYNAMICS: _ClassVar[Output]
    OUTPUT_SENSORS: _ClassVar[Output]
    OUTPUT_FILTER_STATE: _ClassVar[Output]
SCENARIO_UNSPECIFIED: Scenario
SCENARIO_PASSIVE: Scenario
SCENARIO_CONTROLLED: Scenario
SCENARIO_EXTERNAL: Scenario
CLOCK_UNSPECIFIED: Clock
CLOCK_REALTIME: Clock
CLOCK_LOCKSTEP: Clock
ESTIMATOR_UNSPECIFIED: Estimator
ESTIMATOR_UKF: Estimator
ESTIMATOR_STATIC: Estimator
ESTIMATOR_CONSTANT_VELOCITY: Estimator
ESTIMATOR_CONSTANT_ACCELERATION: Estimator
SIGMA_POINTS_UNSPECIFIED: SigmaPoints
SIGMA_POINTS_MERWE: SigmaPoints
SIGMA_POINTS_SIMPLEX: SigmaPoints
SIGMA_POINTS_UNIFORM: SigmaPoints
PRESET_UNSPECIFIED: Preset
PRESET_JITDYN: Preset
PRESET_THESIS: Preset
CHANNEL_UNSPECIFIED: Channel
CHANNEL_QPOS: Channel
CHANNEL_QVEL: Channel
CHANNEL_QACC: Channel
CHANNEL_CTRL: Channel
OUTPUT_UNSPECIFIED: Output
OUTPUT_INVERSE_DYNAMICS: Output
OUTPUT_FORWARD_DYNAMICS: Output
OUTPUT_SENSORS: Output
OUTPUT_FILTER_STATE: Output

class EstimatorSettings(_message.Message):
    __slots__ = ("estimator", "preset", "sigma_points", "alpha", "beta", "kappa", "p0", "q_var", "r")
    ESTIMATOR_FIELD_NUMBER: _ClassVar[int]
    PRESET_FIELD_NUMBER: _ClassVar[int]
    SIGMA_POINTS_FIELD_NUMBER: _ClassVar[int]
    ALPHA_FIELD_NUMBER: _ClassVar[int]
    BETA_FIELD_NUMBER: _ClassVar[int]
    KAPPA_FIELD_NUMBER: _ClassVar[int]
    P0_FIELD_NUMBER: _ClassVar[int]
    Q_VAR_FIELD_NUMBER: _ClassVar[int]
    R_FIELD_NUMBER: _ClassVar[int]
    estimator: Estimator
    preset: Preset
    sigma_points: SigmaPoints
    alpha: float
    beta: float
    kappa: float
    p0: float
    q_var: float
    r: float
    def __init__(self, estimator: _Optional[_Union[Estimator, str]] = ..., preset: _Optional[_Union[Preset, str]] = ..., sigma_points: _Optional[_Union[SigmaPoints, str]] = ..., alpha: _Optional[float] = ..., beta: _Optional[float] = ..., kappa: _Optional[float] = ..., p0: _Optional[float] = ..., q_var: _Optional[float] = ..., r: _Optional[float] = ...) -> None: ...
