"""The joints of a stored session, as its Parquet metadata names them, and which of them a plot
shows: the first MAX_SHOWN in the model's order unless the user names them (`--joints`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Final

from jitdyn.errors import InvalidArgument
from jitdyn.storage.records import JOINT_WIDTHS
from jitdyn.vocabulary import JointType

__all__ = ["MAX_SHOWN", "Joint", "choose_joints", "stored_joints"]

MAX_SHOWN: Final = 6


@dataclass(frozen=True)
class Joint:
    """One joint: where its values sit in qpos (nq) and in the dof vectors (nv), and their names."""

    name: str
    qpos: tuple[int, ...]
    qpos_names: tuple[str, ...]
    dofs: tuple[int, ...]
    dof_names: tuple[str, ...]
    # "rad" or "m" per dof; "" when the file does not say.
    dof_units: tuple[str, ...]


def stored_joints(metadata: dict[str, Any]) -> list[Joint]:
    """The session's joints in the model's order, from its file's metadata (storage.parquet)."""
    names = [str(n) for n in metadata.get("joint_names", [])]
    types = [str(t) for t in metadata.get("joint_types", [])]
    qpos_names = [str(n) for n in metadata.get("qpos_names", [])]
    dof_names = [str(n) for n in metadata.get("dof_names", [])]
    units = [str(u) for u in metadata.get("dof_units", [])]
    if len(types) != len(names) or any(t not in JOINT_WIDTHS for t in types):
        # No types stored: one value per joint, as for the hinge and slide joints of older files.
        types = [JointType.HINGE.value] * len(names)
    joints: list[Joint] = []
    q = v = 0
    for i, (name, joint_type) in enumerate(zip(names, types, strict=True)):
        width, ndof = JOINT_WIDTHS[JointType(joint_type)]
        qpos, dofs = tuple(range(q, q + width)), tuple(range(v, v + ndof))
        joints.append(
            Joint(
                name=name or f"joint {i}",
                qpos=qpos,
                qpos_names=tuple(qpos_names[j] if j < len(qpos_names) else str(j) for j in qpos),
                dofs=dofs,
                dof_names=tuple(dof_names[j] if j < len(dof_names) else str(j) for j in dofs),
                dof_units=tuple(units[j] if j < len(units) else "" for j in dofs),
            )
        )
        q, v = q + width, v + ndof
    return joints


def choose_joints(joints: Sequence[Joint], wanted: Sequence[str], *, model: str) -> list[Joint]:
    """The joints named in `wanted`, in that order; all of them up to MAX_SHOWN when it is empty.
    Raises InvalidArgument for a name the model does not have, listing the names it has."""
    if not wanted:
        return list(joints[:MAX_SHOWN])
    by_name = {joint.name: joint for joint in joints}
    unknown = [name for name in wanted if name not in by_name]
    if unknown:
        raise InvalidArgument(
            f"{model} has no joint {', '.join(map(repr, unknown))}; its joints are "
            f"{', '.join(j.name for j in joints) or 'none'}"
        )
    return [by_name[name] for name in dict.fromkeys(wanted)]
