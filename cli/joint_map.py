"""Which column of a recording drives which joint of a model, for `jitdyn replay` and `jitdyn lsl`:
by name (a column, or a Plug-in Gait component's motion, named as the joint), and by a map file
for the rest. A map file has one `JOINT = COLUMN` a line, `-COLUMN` for a column whose positive
sense is the joint's negative, and `#` comments::

    # pendulum_3's hinges driven by a leg's sagittal angles
    hinge_1 = RHipAngles.x
    hinge_2 = -RKneeAngles.x

Joints without a column are held at rest; columns without a joint are left out; the mapping says
both in one line (`JointMap.line`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from jitdyn.client import FrameData
from jitdyn.errors import InvalidArgument
from jitdyn.registry.info import JointInfo
from jitdyn.v1 import model_registry_pb2
from jitdyn.vocabulary import JointType, from_proto

__all__ = ["JointMap", "Link", "map_joints", "model_joints", "read_map_file"]

# A hinge turns, a slide moves: only they take one column each.
_SCALAR = (JointType.HINGE, JointType.SLIDE)
_REST = {JointType.FREE: (0, 0, 0, 1, 0, 0, 0), JointType.BALL: (1, 0, 0, 0)}


def model_joints(model: model_registry_pb2.Model) -> list[JointInfo]:
    """The joints of a registry `Model` message, in the model's order."""
    return [
        JointInfo(
            name=joint.name,
            type=from_proto(JointType, joint.type, argument="joint.type") or JointType.HINGE,
            limited=joint.limited,
            lower=joint.range_lower,
            upper=joint.range_upper,
            qpos_address=joint.qpos_address,
            dof_address=joint.dof_address,
        )
        for joint in model.joints
    ]


@dataclass(frozen=True)
class Link:
    """Column `column` (its index) drives `joint`, times `sign`."""

    joint: JointInfo
    column: int
    sign: float


@dataclass(frozen=True)
class JointMap:
    """The links of the recording's `columns` to the model's `joints`, in the model's order."""

    links: tuple[Link, ...]
    joints: tuple[JointInfo, ...]
    columns: tuple[str, ...]

    @property
    def held(self) -> tuple[str, ...]:
        """The joints no column drives."""
        driven = {link.joint.name for link in self.links}
        return tuple(joint.name for joint in self.joints if joint.name not in driven)

    @property
    def unused(self) -> tuple[str, ...]:
        """The columns that drive no joint."""
        used = {link.column for link in self.links}
        return tuple(column for i, column in enumerate(self.columns) if i not in used)

    def line(self) -> str:
        """'joints: hinge_1 <- RHipAngles.x, ...; held at rest (no column): ...; unused columns: ...'"""
        links = ", ".join(
            f"{link.joint.name} <- {'-' if link.sign < 0 else ''}{self.columns[link.column]}"
            for link in self.links
        )
        return (
            f"joints: {links}; held at rest (no column): {', '.join(self.held) or 'none'}; "
            f"unused columns: {', '.join(self.unused) or 'none'}"
        )

    def framer(
        self, *, nq: int, nv: int, degrees: bool
    ) -> Callable[[np.ndarray, np.ndarray, float, int], FrameData]:
        """A function of (angles (columns,), their velocities (columns,), t, seq) to that
        sample's frame: every column that drives a joint set, in radians for a hinge (`degrees`:
        the rotations are in degrees; a slide's metres are never converted), the other joints at
        rest."""
        rest = np.zeros(nq)
        for joint in self.joints:
            if joint.type in _REST:
                rest[joint.qpos_address : joint.qpos_address + len(_REST[joint.type])] = _REST[joint.type]
        scale = np.array(
            [
                link.sign * (math.pi / 180 if degrees and link.joint.type is JointType.HINGE else 1.0)
                for link in self.links
            ]
        )
        columns = [link.column for link in self.links]
        qpos_at = [link.joint.qpos_address for link in self.links]
        dof_at = [link.joint.dof_address for link in self.links]

        def frame(angles: np.ndarray, velocities: np.ndarray, t: float, seq: int) -> FrameData:
            qpos, qvel = rest.copy(), np.zeros(nv)
            qpos[qpos_at] = angles[columns] * scale
            qvel[dof_at] = velocities[columns] * scale
            return FrameData(seq=seq, t=t, qpos=qpos, qvel=qvel)

        return frame


def read_map_file(path: Path) -> list[tuple[str, str, float, int]]:
    """(joint, column, sign, line) of each `JOINT = [-]COLUMN` line of `path`."""
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise InvalidArgument(f"--map {path}: no such file") from None
    except UnicodeDecodeError:
        raise InvalidArgument(f"--map {path}: not a text file") from None
    entries = []
    for number, raw in enumerate(lines, 1):
        text = raw.partition("#")[0].strip()
        if not text:
            continue
        joint, equals, column = (part.strip() for part in text.partition("="))
        sign = 1.0
        if column.startswith("-"):
            sign, column = -1.0, column[1:].strip()
        if not equals or not joint or not column or " " in joint:
            raise InvalidArgument(
                f"--map {path}, line {number}: expected JOINT = COLUMN (or -COLUMN), got {raw.strip()!r}"
            )
        entries.append((joint, column, sign, number))
    if not entries:
        raise InvalidArgument(f"--map {path}: no JOINT = COLUMN line")
    return entries


def map_joints(
    joints: Sequence[JointInfo],
    columns: Sequence[str],
    *,
    find: Callable[[str], int | None],
    model: str,
    entries: Sequence[tuple[str, str, float, int]] = (),
    where: str = "",
) -> JointMap:
    """Link the columns to the joints: the map file's `entries` first, then every joint a column
    is named as (`find`: the column known by a name). InvalidArgument for an entry naming a joint
    the model lacks, a column the recording lacks, a joint that takes no single value, a joint
    given twice; and when no column drives any joint."""
    by_name = {joint.name: joint for joint in joints}
    links: dict[str, Link] = {}
    for joint_name, column, sign, line in entries:
        at = f"{where}, line {line}"
        joint = by_name.get(joint_name)
        if joint is None:
            raise InvalidArgument(
                f"{at}: {model} has no joint {joint_name!r}; its joints are {', '.join(by_name)}"
            )
        index = find(column)
        if index is None:
            raise InvalidArgument(
                f"{at}: the recording has no column {column!r}; its columns are {', '.join(columns)}"
            )
        if joint_name in links:
            raise InvalidArgument(f"{at}: joint {joint_name!r} is mapped twice")
        _check_scalar(joint, at)
        links[joint_name] = Link(joint=joint, column=index, sign=sign)
    taken = {link.column for link in links.values()}
    for joint in joints:
        index = find(joint.name)
        if joint.name not in links and joint.type in _SCALAR and index is not None and index not in taken:
            links[joint.name] = Link(joint=joint, column=index, sign=1.0)
            taken.add(index)
    if not links:
        raise InvalidArgument(
            f"no column of the recording names a joint of {model}: its joints are {', '.join(by_name)}, the "
            f"columns {', '.join(columns)}; map them with --map FILE (lines JOINT = COLUMN)"
        )
    ordered = tuple(sorted(links.values(), key=lambda link: link.joint.qpos_address))
    return JointMap(links=ordered, joints=tuple(joints), columns=tuple(columns))


def _check_scalar(joint: JointInfo, at: str) -> None:
    if joint.type not in _SCALAR:
        raise InvalidArgument(
            f"{at}: joint {joint.name!r} is a {joint.type} joint; a column drives a hinge or a slide only"
        )
