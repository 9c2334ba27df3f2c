"""Which of a model's joints are a person's hip, knee and ankle flexion: what the prior of human
motion (server/estimation/prior.py) is matched on. A model says it through tags at registration,
or jitdyn infers it from common joint names and says so (`jitdyn models show`)::

    roles = joint_roles(info.joints, info.tags)      # (JointRole, ...) of the joints that have one
    tags = ("role.knee_extension_r.knee_angle_r",)   # knee_angle_r: the right knee, + = extension

A role names the joint (hip, knee, ankle), its positive direction (flexion or extension;
dorsiflexion or plantarflexion for the ankle) and its side (_l, _r, or none). The tag
`role.<role>.<joint>` declares one; `role.none.<joint>` says a joint has none. Once a model
declares a role, nothing is inferred for it. Inferred: a hinge whose name holds hip, knee or ankle
and no word of another axis (adduction, rotation, inversion, ...), one per joint and side; its side
from r/right or l/left in the name; its sign from the name (flexion, extension, plantar...), else
from its range (a hip's and a knee's larger excursion is flexion, an ankle's plantarflexion), else
taken as +. Joints with no role are matched by nothing: the session's own history answers them.
Why tags and names: docs/decisions/0187-joint-roles.md.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Final, Protocol

from jitdyn.errors import InvalidArgument
from jitdyn.vocabulary import JointType

__all__ = ["KINDS", "JointRole", "RoleTarget", "joint_roles", "role_name"]

# The joints a role names, and the words for their positive and negative directions.
KINDS: Final = ("hip", "knee", "ankle")
_MOTIONS: Final = {
    "hip": ("flexion", "extension"),
    "knee": ("flexion", "extension"),
    "ankle": ("dorsiflexion", "plantarflexion"),
}
_TAG: Final = "role."
# A word of another axis than flexion in a joint's name.
_OTHER_AXIS: Final = re.compile(r"add|abd|rot|roll|yaw|inv|ever|subtalar|tilt|list|varus|valgus|twist")
_RIGHT: Final = re.compile(r"(^|[^a-z])(r|right)([^a-z]|$)|^right|right$")
_LEFT: Final = re.compile(r"(^|[^a-z])(l|left)([^a-z]|$)|^left|left$")


class RoleTarget(Protocol):
    """What a role is read from: a joint as registry.info.JointInfo describes it."""

    @property
    def name(self) -> str: ...
    @property
    def type(self) -> JointType: ...
    @property
    def limited(self) -> bool: ...
    @property
    def lower(self) -> float: ...
    @property
    def upper(self) -> float: ...
    @property
    def dof_address(self) -> int: ...


@dataclass(frozen=True)
class JointRole:
    """A joint's role: its name and dof, `kind` one of KINDS, `side` "l", "r" or "", `sign` +1
    when its positive direction is flexion (dorsiflexion), and how it is known: `source` is
    "declared" or the inference's reason."""

    joint: str
    dof: int
    kind: str
    side: str
    sign: float
    source: str

    @property
    def role(self) -> str:
        """The role as a tag names it: knee_flexion_r, ankle_plantarflexion, ..."""
        return role_name(self.kind, self.sign, self.side)

    @property
    def inferred(self) -> bool:
        return self.source != "declared"


def role_name(kind: str, sign: float, side: str) -> str:
    motion = _MOTIONS[kind][0 if sign > 0 else 1]
    return f"{kind}_{motion}" + (f"_{side}" if side else "")


def _parse_role(text: str, *, tag: str) -> tuple[str, float, str]:
    """(kind, sign, side) of a role's name; InvalidArgument naming the tag."""
    for kind, (plus, minus) in _MOTIONS.items():
        for motion, sign in ((plus, 1.0), (minus, -1.0)):
            stem = f"{kind}_{motion}"
            if text == stem or text in (f"{stem}_l", f"{stem}_r"):
                return kind, sign, text[len(stem) + 1 :]
    choices = ", ".join(f"{k}_{m}" for k, ms in _MOTIONS.items() for m in ms)
    raise InvalidArgument(
        f"tag {tag!r}: no role {text!r}; a role is one of {choices}, with _l or _r, or none"
    )


def joint_roles(joints: Sequence[RoleTarget], tags: Iterable[str]) -> tuple[JointRole, ...]:
    """The roles of `joints` (see the module docstring), in joint order; InvalidArgument for a role
    tag naming no joint, no role, or a joint that is not a hinge, or a joint twice."""
    by_name = {joint.name: joint for joint in joints}
    declared: dict[str, JointRole | None] = {}
    for tag in tags:
        if not tag.startswith(_TAG):
            continue
        role, _, name = tag[len(_TAG) :].partition(".")
        joint = by_name.get(name)
        if joint is None:
            raise InvalidArgument(f"tag {tag!r}: the model has no joint {name!r}")
        if name in declared:
            raise InvalidArgument(f"tag {tag!r}: joint {name!r} has a role already")
        if role == "none":
            declared[name] = None
            continue
        if JointType(joint.type) != JointType.HINGE:
            raise InvalidArgument(f"tag {tag!r}: joint {name!r} is a {joint.type}, a role needs a hinge")
        kind, sign, side = _parse_role(role, tag=tag)
        declared[name] = JointRole(name, int(joint.dof_address), kind, side, sign, "declared")
    if declared:
        return tuple(r for j in joints if (r := declared.get(j.name)) is not None)
    return _inferred(joints)


def _inferred(joints: Sequence[RoleTarget]) -> tuple[JointRole, ...]:
    """Roles read from names; a kind and side that two joints claim is given to neither."""
    roles = [r for r in map(_infer, joints) if r is not None]
    claims: dict[tuple[str, str], int] = {}
    for role in roles:
        claims[role.kind, role.side] = claims.get((role.kind, role.side), 0) + 1
    return tuple(r for r in roles if claims[r.kind, r.side] == 1)


def _infer(joint: RoleTarget) -> JointRole | None:
    name = joint.name.lower()
    if JointType(joint.type) != JointType.HINGE or _OTHER_AXIS.search(name):
        return None
    kinds = [k for k in KINDS if k in name]
    if len(kinds) != 1:
        return None
    kind = kinds[0]
    side = "r" if _RIGHT.search(name) else "l" if _LEFT.search(name) else ""
    plus = _MOTIONS[kind][0]
    if "extension" in name or "plantar" in name:
        sign, how = -1.0, "inferred from its name"
    elif "flex" in name:
        sign, how = 1.0, "inferred from its name"
    elif joint.limited and abs(joint.lower) != abs(joint.upper):
        larger_up = abs(joint.upper) > abs(joint.lower)
        # A hip's and a knee's larger excursion is flexion; an ankle's is plantarflexion.
        sign = (1.0 if larger_up else -1.0) * (-1.0 if kind == "ankle" else 1.0)
        how = "inferred from its name, its sign from its range"
    else:
        sign, how = 1.0, f"inferred from its name, + taken as {plus}"
    return JointRole(joint.name, int(joint.dof_address), kind, side, sign, how)
