"""Conversions between the registry's types and the jitdyn.v1 model messages.

    model_message(info) -> jitdyn.v1.Model
    metadata_from_message(message) -> registry.ModelMetadata     # validated

Estimator defaults travel as `ScenarioDefaults` messages and live in the registry as plain dicts
keyed by the enums' value names without their prefix: {"PASSIVE": {"preset": "THESIS", "alpha":
0.001}}.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, Literal, TypeAlias, TypeVar

from google.protobuf import timestamp_pb2

from jitdyn.errors import InvalidArgument
from jitdyn.registry import ModelInfo, ModelMetadata
from jitdyn.registry.info import check_metadata
from jitdyn.v1 import common_pb2, model_registry_pb2

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
    "metadata_from_message",
    "metadata_message",
    "model_message",
    "settings_from_message",
    "settings_message",
]

_JOINT_TYPES = {
    "free": model_registry_pb2.JOINT_TYPE_FREE,
    "ball": model_registry_pb2.JOINT_TYPE_BALL,
    "slide": model_registry_pb2.JOINT_TYPE_SLIDE,
    "hinge": model_registry_pb2.JOINT_TYPE_HINGE,
}
# Enum settings: field -> (enum, prefix of its value names).
_ENUMS: dict[str, tuple[_SettingsEnum, str]] = {
    "estimator": (common_pb2.Estimator, "ESTIMATOR_"),
    "preset": (common_pb2.Preset, "PRESET_"),
    "sigma_points": (common_pb2.SigmaPoints, "SIGMA_POINTS_"),
    "force_model": (common_pb2.ForceModel, "FORCE_MODEL_"),
    "noise_model": (common_pb2.NoiseModel, "NOISE_MODEL_"),
    "forecast": (common_pb2.Forecast, "FORECAST_"),
    "wrong_model": (common_pb2.WrongModel, "WRONG_MODEL_"),
}
# A Literal, so that mypy checks the names against EstimatorSettings' fields (HasField).
_Number: TypeAlias = Literal["alpha", "beta", "kappa", "p0", "q_var", "r", "force_var"]
_NUMBERS: tuple[_Number, ...] = ("alpha", "beta", "kappa", "p0", "q_var", "r", "force_var")
_SCENARIO_PREFIX = "SCENARIO_"
_SCENARIO = common_pb2.Scenario

_V = TypeVar("_V", bound=int)


def _enum_name(enum: _EnumTypeWrapper[_V], prefix: str, value: _V, *, argument: str) -> str:
    try:
        return str(enum.Name(value)).removeprefix(prefix)
    except ValueError:
        raise InvalidArgument(f"{argument} has no value {value}") from None


def settings_from_message(settings: common_pb2.EstimatorSettings, *, argument: str) -> dict[str, Any]:
    """The settings a message sets: enums by name without prefix, unset ones left out."""
    result: dict[str, Any] = {}
    for field, (enum, prefix) in _ENUMS.items():
        value = getattr(settings, field)
        if value:
            result[field] = _enum_name(enum, prefix, value, argument=f"{argument}.{field}")
    for field in _NUMBERS:
        if settings.HasField(field):
            result[field] = getattr(settings, field)
    return result


def settings_message(settings: Mapping[str, Any]) -> common_pb2.EstimatorSettings:
    """The message of a settings dict (as `settings_from_message` makes)."""
    message = common_pb2.EstimatorSettings()
    for field, value in settings.items():
        if field in _ENUMS:
            enum, prefix = _ENUMS[field]
            setattr(message, field, enum.Value(prefix + value))
        else:
            setattr(message, field, value)
    return message


def metadata_from_message(message: model_registry_pb2.ModelMetadata) -> ModelMetadata:
    """The registry's ModelMetadata of a message, validated (registry.info.check_metadata).

    Raises:
      InvalidArgument: an unset or unknown scenario, two entries for one scenario, or a field that
        breaks the registry's rules.
    """
    defaults: dict[str, dict[str, Any]] = {}
    for i, entry in enumerate(message.defaults):
        argument = f"metadata.defaults[{i}]"
        if entry.scenario == common_pb2.SCENARIO_UNSPECIFIED:
            raise InvalidArgument(f"{argument}.scenario must be set (PASSIVE, CONTROLLED or EXTERNAL)")
        scenario = _enum_name(_SCENARIO, _SCENARIO_PREFIX, entry.scenario, argument=f"{argument}.scenario")
        if scenario in defaults:
            raise InvalidArgument(f"metadata.defaults has more than one entry for scenario {scenario}")
        defaults[scenario] = settings_from_message(entry.estimator, argument=f"{argument}.estimator")
    return check_metadata(
        ModelMetadata(description=message.description, tags=tuple(message.tags), defaults=defaults)
    )


def metadata_message(metadata: ModelMetadata) -> model_registry_pb2.ModelMetadata:
    """The message of the registry's ModelMetadata."""
    return model_registry_pb2.ModelMetadata(
        description=metadata.description,
        tags=list(metadata.tags),
        defaults=[
            model_registry_pb2.ScenarioDefaults(
                scenario=_SCENARIO.Value(_SCENARIO_PREFIX + scenario),
                estimator=settings_message(settings),
            )
            for scenario, settings in metadata.defaults.items()
        ],
    )


def model_message(info: ModelInfo) -> model_registry_pb2.Model:
    """The jitdyn.v1.Model of a registered model."""
    created_at = timestamp_pb2.Timestamp()
    created_at.FromDatetime(info.created_at)
    return model_registry_pb2.Model(
        id=info.id,
        name=info.name,
        version=info.version,
        dimensions=model_registry_pb2.Dimensions(
            nq=info.nq, nv=info.nv, nu=info.nu, na=info.na, nsensor=info.nsensor, nbody=info.nbody
        ),
        joints=[
            model_registry_pb2.Joint(
                name=joint.name,
                type=_JOINT_TYPES[joint.type],
                limited=joint.limited,
                range_lower=joint.lower,
                range_upper=joint.upper,
                qpos_address=joint.qpos_address,
                dof_address=joint.dof_address,
            )
            for joint in info.joints
        ],
        actuators=[
            model_registry_pb2.Actuator(
                name=actuator.name,
                target=actuator.target,
                ctrl_limited=actuator.ctrl_limited,
                ctrl_lower=actuator.lower,
                ctrl_upper=actuator.upper,
            )
            for actuator in info.actuators
        ],
        metadata=metadata_message(info.metadata),
        created_at=created_at,
        timestep=info.timestep,
        builtin=info.builtin,
    )
