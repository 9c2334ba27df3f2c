"""What the registry says about a model: small frozen types, how a compiled model fills them, and the
rules on names, tags, descriptions and estimator defaults."""

from __future__ import annotations

import dataclasses
import datetime
import math
import re
from collections.abc import Iterable, Mapping
from typing import Any

import mujoco

from jitdyn.errors import InvalidArgument

__all__ = [
    "ESTIMATOR_SETTINGS",
    "SCENARIOS",
    "ActuatorInfo",
    "JointInfo",
    "ModelInfo",
    "ModelMetadata",
    "ModelShape",
    "check_metadata",
    "check_name",
    "check_tag",
    "describe_model",
]

_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_.-]{0,63}")
_TAG = re.compile(r"[A-Za-z0-9_.-]{1,64}")
MAX_TAGS = 32
MAX_DESCRIPTION = 4096

# The keys of `ModelMetadata.defaults`: jitdyn.v1.Scenario names without their prefix.
SCENARIOS = ("PASSIVE", "CONTROLLED", "EXTERNAL", "DRIVEN")
# The settings one scenario's defaults may hold (the fields of jitdyn.v1.EstimatorSettings): enum
# fields take the enum's value names without prefix, the others a number.
ESTIMATOR_SETTINGS: Mapping[str, tuple[str, ...] | None] = {
    "estimator": ("UKF", "STATIC", "CONSTANT_VELOCITY", "CONSTANT_ACCELERATION"),
    "preset": ("JITDYN", "THESIS"),
    "sigma_points": ("MERWE", "SIMPLEX", "UNIFORM", "SIMPLEX_LINEAR_FORCE"),
    "force_model": ("RANDOM_WALK", "INTEGRATED_RANDOM_WALK"),
    "noise_model": ("FIXED", "ADAPTIVE"),
    "forecast": ("FILTER", "COMBINED"),
    "wrong_model": ("KEEP", "DRIVEN", "RESTART"),
    "force_var": None,
    "alpha": None,
    "beta": None,
    "kappa": None,
    "p0": None,
    "q_var": None,
    "r": None,
}

_JOINT_TYPES = {
    int(mujoco.mjtJoint.mjJNT_FREE): "free",
    int(mujoco.mjtJoint.mjJNT_BALL): "ball",
    int(mujoco.mjtJoint.mjJNT_SLIDE): "slide",
    int(mujoco.mjtJoint.mjJNT_HINGE): "hinge",
}

# What an actuator's transmission acts on, and what an unnamed one of those is called.
_TRANSMISSION_TARGETS = {
    int(mujoco.mjtTrn.mjTRN_JOINT): (mujoco.mjtObj.mjOBJ_JOINT, "joint"),
    int(mujoco.mjtTrn.mjTRN_JOINTINPARENT): (mujoco.mjtObj.mjOBJ_JOINT, "joint"),
    int(mujoco.mjtTrn.mjTRN_SLIDERCRANK): (mujoco.mjtObj.mjOBJ_SITE, "site"),
    int(mujoco.mjtTrn.mjTRN_TENDON): (mujoco.mjtObj.mjOBJ_TENDON, "tendon"),
    int(mujoco.mjtTrn.mjTRN_SITE): (mujoco.mjtObj.mjOBJ_SITE, "site"),
    int(mujoco.mjtTrn.mjTRN_BODY): (mujoco.mjtObj.mjOBJ_BODY, "body"),
}


@dataclasses.dataclass(frozen=True, kw_only=True)
class JointInfo:
    """One joint: `type` is 'free', 'ball', 'slide' or 'hinge'; `lower`/`upper` (m or rad) are 0
    unless `limited`; the addresses index qpos and qvel."""

    name: str
    type: str
    limited: bool
    lower: float
    upper: float
    qpos_address: int
    dof_address: int


@dataclasses.dataclass(frozen=True, kw_only=True)
class ActuatorInfo:
    """One actuator: `target` is the joint, tendon, site or body it acts on ("" for none); the
    control is clamped to [`lower`, `upper`] when `ctrl_limited`."""

    name: str
    target: str
    ctrl_limited: bool
    lower: float
    upper: float


@dataclasses.dataclass(frozen=True, kw_only=True)
class ModelMetadata:
    """What a registrant says about a model.

    Attributes:
      description: free text, at most 4096 characters.
      tags: at most 32 tags of 1-64 characters of [A-Za-z0-9_.-].
      defaults: estimator settings per scenario, e.g. {"PASSIVE": {"alpha": 0.001, "preset":
        "THESIS"}}: keys in SCENARIOS, settings in ESTIMATOR_SETTINGS.
    """

    description: str = ""
    tags: tuple[str, ...] = ()
    defaults: Mapping[str, Mapping[str, Any]] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True, kw_only=True)
class ModelShape:
    """The sizes, joints and actuators of a compiled model."""

    nq: int
    nv: int
    nu: int
    na: int
    nsensor: int
    nbody: int
    timestep: float
    joints: tuple[JointInfo, ...]
    actuators: tuple[ActuatorInfo, ...]


@dataclasses.dataclass(frozen=True, kw_only=True)
class ModelInfo:
    """A registered model. `id` is its content id (registry.content_id), `version` counts from 1
    within `name` and `tenant`; `nsensor` is the number of sensor values (nsensordata); `created_at`
    is in UTC."""

    id: str
    name: str
    version: int
    tenant: str
    builtin: bool
    nq: int
    nv: int
    nu: int
    na: int
    nsensor: int
    nbody: int
    timestep: float
    joints: tuple[JointInfo, ...]
    actuators: tuple[ActuatorInfo, ...]
    description: str
    tags: tuple[str, ...]
    defaults: Mapping[str, Mapping[str, Any]]
    created_at: datetime.datetime

    @property
    def metadata(self) -> ModelMetadata:
        return ModelMetadata(description=self.description, tags=self.tags, defaults=self.defaults)


def _name_of(model: mujoco.MjModel, kind: mujoco.mjtObj, index: int, fallback: str) -> str:
    return mujoco.mj_id2name(model, kind, index) or f"{fallback}{index}"


def describe_model(model: mujoco.MjModel) -> ModelShape:
    """The sizes, joints and actuators of `model`; unnamed ones are called "joint<i>", "actuator<i>"."""
    joints = []
    for i in range(model.njnt):
        limited = bool(model.jnt_limited[i])
        lower, upper = (float(model.jnt_range[i, 0]), float(model.jnt_range[i, 1])) if limited else (0.0, 0.0)
        joints.append(
            JointInfo(
                name=_name_of(model, mujoco.mjtObj.mjOBJ_JOINT, i, "joint"),
                type=_JOINT_TYPES[int(model.jnt_type[i])],
                limited=limited,
                lower=lower,
                upper=upper,
                qpos_address=int(model.jnt_qposadr[i]),
                dof_address=int(model.jnt_dofadr[i]),
            )
        )
    actuators = []
    for i in range(model.nu):
        target = ""
        kind = _TRANSMISSION_TARGETS.get(int(model.actuator_trntype[i]))
        target_id = int(model.actuator_trnid[i, 0])
        if kind is not None and target_id >= 0:
            target = _name_of(model, kind[0], target_id, kind[1])
        actuators.append(
            ActuatorInfo(
                name=_name_of(model, mujoco.mjtObj.mjOBJ_ACTUATOR, i, "actuator"),
                target=target,
                ctrl_limited=bool(model.actuator_ctrllimited[i]),
                lower=float(model.actuator_ctrlrange[i, 0]),
                upper=float(model.actuator_ctrlrange[i, 1]),
            )
        )
    return ModelShape(
        nq=int(model.nq),
        nv=int(model.nv),
        nu=int(model.nu),
        na=int(model.na),
        nsensor=int(model.nsensordata),
        nbody=int(model.nbody),
        timestep=float(model.opt.timestep),
        joints=tuple(joints),
        actuators=tuple(actuators),
    )


def check_name(name: object, *, argument: str = "name") -> str:
    """`name` when it is 1-64 characters of [A-Za-z0-9_.-] starting with a letter."""
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise InvalidArgument(
            f"{argument} must be 1-64 characters of [A-Za-z0-9_.-] starting with a letter, got {name!r}"
        )
    return name


def check_tag(tag: object, *, argument: str = "tag") -> str:
    """`tag` when it is 1-64 characters of [A-Za-z0-9_.-]."""
    if not isinstance(tag, str) or not _TAG.fullmatch(tag):
        raise InvalidArgument(f"{argument} must be 1-64 characters of [A-Za-z0-9_.-], got {tag!r}")
    return tag


def _check_setting(scenario: str, key: object, value: object) -> Any:
    where = f"metadata.defaults[{scenario!r}]"
    if not isinstance(key, str) or key not in ESTIMATOR_SETTINGS:
        raise InvalidArgument(f"{where} has setting {key!r}; expected one of {', '.join(ESTIMATOR_SETTINGS)}")
    choices = ESTIMATOR_SETTINGS[key]
    if choices is not None:
        if value not in choices:
            raise InvalidArgument(f"{where}[{key!r}] must be one of {', '.join(choices)}, got {value!r}")
        if key == "wrong_model" and value == "DRIVEN" and scenario != "PASSIVE":
            # Refused at open too; here the registrant hears it, not the first user of the model.
            raise InvalidArgument(
                f"{where}['wrong_model'] DRIVEN is for PASSIVE, the only scenario that can turn DRIVEN"
            )
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InvalidArgument(f"{where}[{key!r}] must be a finite number, got {value!r}")
    number = float(value)
    if key == "alpha" and not 0 < number <= 1:
        raise InvalidArgument(f"{where}['alpha'] must be in (0, 1], got {number!r}")
    if key in ("p0", "r") and not number > 0:
        raise InvalidArgument(f"{where}[{key!r}] must be positive, got {number!r}")
    if key in ("q_var", "force_var") and not number >= 0:
        raise InvalidArgument(f"{where}[{key!r}] must be non-negative, got {number!r}")
    return number


def check_metadata(metadata: object) -> ModelMetadata:
    """A normalized copy of `metadata` (tags a tuple, numbers floats, plain dicts); InvalidArgument
    naming the first field that breaks a rule."""
    if not isinstance(metadata, ModelMetadata):
        raise InvalidArgument(f"metadata must be a ModelMetadata, got {type(metadata).__name__}")
    description = metadata.description
    if not isinstance(description, str) or len(description) > MAX_DESCRIPTION:
        shown = f"{len(description)} characters" if isinstance(description, str) else repr(description)
        raise InvalidArgument(
            f"metadata.description must be text of at most {MAX_DESCRIPTION} characters, got {shown}"
        )
    tags = metadata.tags
    if isinstance(tags, str) or not isinstance(tags, Iterable):
        raise InvalidArgument(f"metadata.tags must be a sequence of tags, got {tags!r}")
    tags = tuple(tags)
    if len(tags) > MAX_TAGS:
        raise InvalidArgument(f"metadata.tags has {len(tags)} tags, more than {MAX_TAGS}")
    for i, tag in enumerate(tags):
        check_tag(tag, argument=f"metadata.tags[{i}]")
    tags = tuple(dict.fromkeys(tags))  # a repeated tag says nothing more
    if not isinstance(metadata.defaults, Mapping):
        raise InvalidArgument(f"metadata.defaults must map scenarios to settings, got {metadata.defaults!r}")
    defaults: dict[str, dict[str, Any]] = {}
    for scenario, settings in metadata.defaults.items():
        if scenario not in SCENARIOS:
            raise InvalidArgument(
                f"metadata.defaults has scenario {scenario!r}; expected one of {', '.join(SCENARIOS)}"
            )
        if not isinstance(settings, Mapping):
            raise InvalidArgument(
                f"metadata.defaults[{scenario!r}] must map settings to values, got {settings!r}"
            )
        defaults[scenario] = {key: _check_setting(scenario, key, value) for key, value in settings.items()}
    return ModelMetadata(description=description, tags=tags, defaults=defaults)
