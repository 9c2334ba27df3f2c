"""What the registry says about a model: small frozen types, how a compiled model fills them, and the
rules on names, tags, descriptions and estimator defaults (the settings' own rules are
jitdyn.estimator_settings')."""

from __future__ import annotations

import dataclasses
import datetime
import re
from collections.abc import Iterable, Mapping
from typing import Any

import mujoco

from jitdyn.errors import InvalidArgument
from jitdyn.estimator_settings import SETTINGS, SettingValue, check_for_scenario, check_settings
from jitdyn.vocabulary import JointType, Scenario, parse

__all__ = [
    "ActuatorInfo",
    "JointInfo",
    "ModelInfo",
    "ModelMetadata",
    "ModelShape",
    "check_metadata",
    "check_name",
    "check_tag",
    "describe_model",
    "joint_types",
    "stored_defaults",
]

_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_.-]{0,63}")
_TAG = re.compile(r"[A-Za-z0-9_.-]{1,64}")
MAX_TAGS = 32
MAX_DESCRIPTION = 4096

_JOINT_TYPES = {
    int(mujoco.mjtJoint.mjJNT_FREE): JointType.FREE,
    int(mujoco.mjtJoint.mjJNT_BALL): JointType.BALL,
    int(mujoco.mjtJoint.mjJNT_SLIDE): JointType.SLIDE,
    int(mujoco.mjtJoint.mjJNT_HINGE): JointType.HINGE,
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
    """One joint: `type` is its JointType (its MJCF name is accepted and parsed); `lower`/`upper`
    (m or rad) are 0 unless `limited`; the addresses index qpos and qvel."""

    name: str
    type: JointType
    limited: bool
    lower: float
    upper: float
    qpos_address: int
    dof_address: int

    def __post_init__(self) -> None:
        # Frozen: the member replaces the stored text ("hinge") once, here.
        object.__setattr__(self, "type", parse(JointType, self.type, argument="joint.type"))


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
        "THESIS"}}: keys name a vocabulary Scenario, settings rows of
        jitdyn.estimator_settings.SETTINGS. `check_metadata` makes them members and floats.
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
class ModelInfo(ModelShape):
    """A registered model: its shape, and `id` its content id (registry.content_id), `version`
    counting from 1 within `name` and `tenant`; `nsensor` is the number of sensor values
    (nsensordata); `created_at` is in UTC."""

    id: str
    name: str
    version: int
    tenant: str
    builtin: bool
    description: str
    tags: tuple[str, ...]
    defaults: Mapping[str, Mapping[str, Any]]
    created_at: datetime.datetime

    @property
    def metadata(self) -> ModelMetadata:
        return ModelMetadata(description=self.description, tags=self.tags, defaults=self.defaults)


def _name_of(model: mujoco.MjModel, kind: mujoco.mjtObj, index: int, fallback: str) -> str:
    return mujoco.mj_id2name(model, kind, index) or f"{fallback}{index}"


def joint_types(model: mujoco.MjModel) -> tuple[JointType, ...]:
    """The type of each of the model's joints, in its order."""
    return tuple(_JOINT_TYPES[int(t)] for t in model.jnt_type)


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


def _scenario(key: object) -> Scenario:
    try:
        return parse(Scenario, key, argument="metadata.defaults")
    except InvalidArgument:
        choices = ", ".join(member.name for member in Scenario)
        raise InvalidArgument(f"metadata.defaults has scenario {key!r}; expected one of {choices}") from None


def stored_defaults(stored: Mapping[str, Mapping[str, Any]]) -> dict[str, dict[str, SettingValue]]:
    """Defaults as the registry stored them (text), as members and floats again. Not re-checked:
    they passed `check_metadata` when registered, and a rule added since must not hide a model."""
    defaults: dict[str, dict[str, SettingValue]] = {}
    for key, settings in stored.items():
        scenario = Scenario[key]
        defaults[scenario] = {}
        for name, value in settings.items():
            choices = SETTINGS[name].choices
            defaults[scenario][name] = choices[str(value)] if choices is not None else float(value)
    return defaults


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
    # Keyed by Scenario members, which are str: readers look them up by either.
    defaults: dict[str, dict[str, SettingValue]] = {}
    for key, settings in metadata.defaults.items():
        scenario = _scenario(key)
        if scenario in defaults:
            raise InvalidArgument(f"metadata.defaults has more than one entry for scenario {scenario}")
        argument = f"metadata.defaults.{scenario}"
        defaults[scenario] = check_settings(settings, argument=argument)
        # Refused at open too; here the registrant hears it, not the first user of the model.
        check_for_scenario(scenario, defaults[scenario], argument=argument)
    return ModelMetadata(description=description, tags=tags, defaults=defaults)
