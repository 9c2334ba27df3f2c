"""The topics of a session's MCAP export and the JSON Schema of each (MCAP's `jsonschema` encoding).

jitdyn's own time series are `jitdyn.*` schemas written here; the body poses use Foxglove's
well-known `foxglove.FrameTransforms`, whose name is what makes Foxglove's 3D panel read them, with
the fields of Foxglove's published schema (timestamp, parent_frame_id, child_frame_id,
translation, rotation).
"""

from __future__ import annotations

import enum
from typing import Any, Final

__all__ = ["SCHEMAS", "Topic"]


class Topic(enum.StrEnum):
    """An MCAP channel of the export."""

    JOINT_STATES = "/jitdyn/joint_states"
    FORCES = "/jitdyn/forces"
    FRAMES = "/jitdyn/frames"
    SOURCE = "/jitdyn/source"
    LATENESS = "/jitdyn/lateness"
    REJECTIONS = "/jitdyn/rejections"
    TRANSFORMS = "/tf"


def _number(description: str) -> dict[str, Any]:
    return {"type": "number", "description": description}


def _object(title: str, description: str, **properties: dict[str, Any]) -> dict[str, Any]:
    return {"title": title, "description": description, "type": "object", "properties": properties}


_TIME: Final = {
    "type": "object",
    "title": "time",
    "description": "The tick's time: the session's start (UTC) plus the tick's t",
    "properties": {
        "sec": {"type": "integer", "minimum": 0},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999},
    },
}
_SEQ: Final = {"type": "integer", "minimum": 0, "description": "The tick index, from 0"}
_SOURCE: Final = {
    "type": "string",
    "enum": ["MEASURED", "PREDICTED", "CORRECTED"],
    "description": "Where the estimate came from",
}


def _vector(description: str) -> dict[str, Any]:
    """A named vector: the names of its elements (joints, dofs, actuators) and their values."""
    return {
        "type": "object",
        "description": description,
        "properties": {
            "name": {"type": "array", "items": {"type": "string"}},
            "value": {"type": "array", "items": {"type": ["number", "null"]}},
        },
    }


def _xyz(title: str, description: str) -> dict[str, Any]:
    return _object(title, description, **{axis: _number(f"{axis} (m)") for axis in "xyz"})


_FRAME_TRANSFORM: Final = _object(
    "foxglove.FrameTransform",
    "A body's pose in its parent body's frame",
    timestamp=_TIME,
    parent_frame_id={"type": "string", "description": "The parent body's name ('world' for the root)"},
    child_frame_id={"type": "string", "description": "The body's name"},
    translation=_xyz("foxglove.Vector3", "The body's origin in the parent's frame (m)"),
    rotation=_object(
        "foxglove.Quaternion",
        "The body's orientation in the parent's frame",
        **{part: _number(f"{part} value") for part in "xyzw"},
    ),
)

SCHEMAS: Final[dict[str, dict[str, Any]]] = {
    "jitdyn.JointStates": _object(
        "jitdyn.JointStates",
        "The latest answer of a tick (a correction replaces its prediction): generalized positions "
        "(m, rad; quaternions for ball and free joints), velocities and accelerations",
        timestamp=_TIME,
        seq=_SEQ,
        source=_SOURCE,
        qpos=_vector("Generalized positions, named by joint (m, rad)"),
        qvel=_vector("Generalized velocities, named by dof (m/s, rad/s)"),
        qacc=_vector("Generalized accelerations, named by dof (m/s^2, rad/s^2)"),
    ),
    "jitdyn.Forces": _object(
        "jitdyn.Forces",
        "The latest answer's dynamics, those the session asked for",
        timestamp=_TIME,
        seq=_SEQ,
        source=_SOURCE,
        qfrc_inverse=_vector("Inverse dynamics: generalized forces, named by dof (N, N m)"),
        qacc_forward=_vector("Forward dynamics: accelerations, named by dof (m/s^2, rad/s^2)"),
        actuator_force=_vector("Forward dynamics: actuator forces, named by actuator"),
    ),
    "jitdyn.Frames": _object(
        "jitdyn.Frames",
        "What the tick's frame measured, whenever it came",
        timestamp=_TIME,
        seq=_SEQ,
        qpos=_vector("Measured generalized positions (m, rad)"),
        qvel=_vector("Measured generalized velocities (m/s, rad/s)"),
        qacc=_vector("Measured generalized accelerations (m/s^2, rad/s^2)"),
        ctrl=_vector("Controls (the actuators' units)"),
    ),
    "jitdyn.Source": _object(
        "jitdyn.Source",
        "How a tick was answered when it was due, and whether a late frame corrected it",
        timestamp=_TIME,
        seq=_SEQ,
        source=_SOURCE,
        code={"type": "integer", "description": "source as a number: 1 MEASURED, 2 PREDICTED"},
        corrected={"type": "boolean", "description": "A late frame replaced the answer (CORRECTED)"},
        final_code={"type": "integer", "description": "The latest answer's source: 3 when corrected"},
        framed={"type": "boolean", "description": "A frame was used for the tick, on time or late"},
    ),
    "jitdyn.Lateness": _object(
        "jitdyn.Lateness",
        "When the tick's frame arrived and how long the server took",
        timestamp=_TIME,
        seq=_SEQ,
        frame_delay={
            "type": ["number", "null"],
            "description": "REALTIME: the frame's arrival after its tick's time (s; negative: early); "
            "null without a frame",
        },
        compute_us=_number("Server time computing the answer sent when due (microseconds)"),
        receive_to_send_us=_number("From the message that triggered the answer to its send (microseconds)"),
    ),
    "jitdyn.Rejection": _object(
        "jitdyn.Rejection",
        "A frame the server did not use, and why (the session went on)",
        timestamp=_TIME,
        seq=_SEQ,
        reason={"type": "string", "description": "The RejectReason (BAD_SHAPE, TOO_OLD, ...)"},
    ),
    "foxglove.FrameTransforms": _object(
        "foxglove.FrameTransforms",
        "Every body's pose at the tick (MuJoCo's forward kinematics of the latest answer)",
        transforms={"type": "array", "items": _FRAME_TRANSFORM},
    ),
}
