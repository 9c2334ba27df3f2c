"""`jitdyn sessions export ID --format mcap`: one stored session as an MCAP file that Foxglove
opens: its time series as JSON messages, and the model's body poses as Foxglove's 3D frames.

    exported = export_mcap(session_id, data_root=root, engine=engine, out=Path("walk.mcap"))
    exported.path, exported.counts     # {"/tf": 300, "/jitdyn/joint_states": 300, ...}

Every message is logged at its tick's time: the session's start (UTC) plus the tick's `t`, so
that Foxglove's timeline is the session's own. The channels (topics) are CHANNELS; the body poses
are MuJoCo's forward kinematics (mj_kinematics) of the latest answer of each tick, on the model the
registry stored for the session. Why JSON and Foxglove's well-known schemas:
docs/decisions/0175-mcap-in-json.md.
"""

from __future__ import annotations

import datetime
import heapq
import json
import os
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Final

import mujoco
import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.compute as pc
import sqlalchemy as sa

from jitdyn.cli.mcap_schemas import SCHEMAS, Topic
from jitdyn.errors import FailedPrecondition
from jitdyn.registry.store import session_model
from jitdyn.storage.columns import list_matrix
from jitdyn.storage.export import SOURCE_CODES, atomic_write, element_names, export_target, latest_results
from jitdyn.storage.index import SessionIndex, SessionRow
from jitdyn.storage.stored import read_stored
from jitdyn.storage.timeline import Timeline, session_timeline
from jitdyn.vocabulary import Source

__all__ = ["CHANNELS", "Exported", "body_transforms", "export_mcap"]

Floats = npt.NDArray[np.float64]

# The topics an export writes, each with its schema's name (cli/mcap_schemas.py).
CHANNELS: Final = {
    Topic.JOINT_STATES: "jitdyn.JointStates",
    Topic.FORCES: "jitdyn.Forces",
    Topic.FRAMES: "jitdyn.Frames",
    Topic.SOURCE: "jitdyn.Source",
    Topic.LATENESS: "jitdyn.Lateness",
    Topic.REJECTIONS: "jitdyn.Rejection",
    Topic.TRANSFORMS: "foxglove.FrameTransforms",
}
# The frame every body's transform chain ends in, as Foxglove's 3D panel's fixed frame.
WORLD: Final = "world"
# The result columns the forces channel carries, when the session asked for them.
_FORCE_COLUMNS: Final = ("qfrc_inverse", "qacc_forward", "actuator_force")
_EPOCH: Final = datetime.datetime(1970, 1, 1, tzinfo=datetime.UTC)
_CODES: Final = {source.value: int(code) for source, code in SOURCE_CODES.items()}


@dataclass(frozen=True)
class Exported:
    """What was written: the file and the number of messages of each topic."""

    path: Path
    counts: Mapping[str, int]


@dataclass(frozen=True)
class _Session:
    row: SessionRow
    metadata: dict[str, Any]
    table: pa.Table
    model: mujoco.MjModel


def _values(row: Floats) -> list[float | None]:
    """A vector as JSON numbers; NaN and infinities (which JSON lacks) as null."""
    return [float(v) if np.isfinite(v) else None for v in row]


def _stamp(ns: int) -> dict[str, int]:
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def body_names(model: mujoco.MjModel) -> list[str]:
    """The frame id of each body: its MJCF name, `body<i>` when unnamed, the world body WORLD."""
    names = [WORLD]
    for b in range(1, model.nbody):
        names.append(mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b) or f"body{b}")
    return names


def _conjugate(q: Floats) -> Floats:
    conjugate: Floats = q * np.array([1.0, -1.0, -1.0, -1.0])
    return conjugate


def _multiply(a: Floats, b: Floats) -> Floats:
    """Hamilton products of quaternions (w, x, y, z), row by row: (n, 4) x (n, 4) -> (n, 4)."""
    aw, ax, ay, az = a.T
    bw, bx, by, bz = b.T
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=1,
    )


def body_transforms(model: mujoco.MjModel, data: mujoco.MjData, qpos: Floats) -> tuple[Floats, Floats]:
    """Each body's pose in its parent body's frame at `qpos` (nq,): translations (nbody - 1, 3) and
    quaternions (nbody - 1, 4, w first), the world body left out."""
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    child = np.arange(1, model.nbody)
    parent = model.body_parentid[child]
    offset = data.xpos[child] - data.xpos[parent]
    rotations = data.xmat[parent].reshape(-1, 3, 3)
    translation = np.einsum("nji,nj->ni", rotations, offset)  # R_parent^T (x_child - x_parent)
    rotation = _multiply(_conjugate(data.xquat[parent]), data.xquat[child])
    return translation, rotation


def _transforms(session: _Session, ticks: pa.Table, times: list[int]) -> Iterator[tuple[int, dict[str, Any]]]:
    model = session.model
    data = mujoco.MjData(model)
    names = body_names(model)
    parents = [names[p] for p in model.body_parentid[1:]]
    qpos = list_matrix(ticks["qpos"])
    if qpos is None:
        return
    for i, ns in enumerate(times):
        if not np.isfinite(qpos[i]).all():
            continue
        translation, rotation = body_transforms(model, data, qpos[i])
        stamp = _stamp(ns)
        yield (
            ns,
            {
                "transforms": [
                    {
                        "timestamp": stamp,
                        "parent_frame_id": parent,
                        "child_frame_id": child,
                        "translation": dict(zip("xyz", map(float, t), strict=True)),
                        "rotation": {"x": float(r[1]), "y": float(r[2]), "z": float(r[3]), "w": float(r[0])},
                    }
                    for parent, child, t, r in zip(parents, names[1:], translation, rotation, strict=True)
                ]
            },
        )


def _named(
    session: _Session, ticks: pa.Table, columns: tuple[str, ...]
) -> dict[str, tuple[list[str], Floats]]:
    """The columns of `columns` the session stored, each with its element names."""
    found = {}
    for column in columns:
        matrix = list_matrix(ticks[column]) if column in ticks.column_names else None
        if matrix is not None:
            found[column] = (element_names(column, session.metadata, matrix.shape[1]), matrix)
    return found


def _vectors(
    session: _Session, ticks: pa.Table, times: list[int], columns: tuple[str, ...]
) -> Iterator[tuple[int, dict[str, Any]]]:
    """One message a tick of `columns` as {column: {"name": [...], "value": [...]}}."""
    found = _named(session, ticks, columns)
    seqs = ticks["seq"].to_pylist()
    sources = ticks["source"].to_pylist()
    for i, ns in enumerate(times):
        message: dict[str, Any] = {"timestamp": _stamp(ns), "seq": seqs[i], "source": sources[i]}
        for column, (names, matrix) in found.items():
            message[column] = {"name": names, "value": _values(matrix[i])}
        yield ns, message


def _frames(session: _Session, times_of: Mapping[int, int]) -> Iterator[tuple[int, dict[str, Any]]]:
    """The measured frame of each tick that had one used, on time or late (a rejected frame is on
    /jitdyn/rejections, not here)."""
    table = session.table
    frames = table.filter(pc.and_(pc.equal(table["kind"], "result"), pc.is_valid(table["frame_qpos"])))
    found = _named(session, frames, ("frame_qpos", "frame_qvel", "frame_qacc", "frame_ctrl"))
    seen: set[int] = set()
    for i, seq in enumerate(frames["seq"].to_pylist()):
        if seq in seen:
            continue  # the frame of a tick answered again (CORRECTED after CORRECTED)
        seen.add(seq)
        message: dict[str, Any] = {"timestamp": _stamp(times_of[seq]), "seq": seq}
        for column, (names, matrix) in found.items():
            message[column.removeprefix("frame_")] = {"name": names, "value": _values(matrix[i])}
        yield times_of[seq], message


def _sources(timeline: Timeline, times: list[int]) -> Iterator[tuple[int, dict[str, Any]]]:
    for i, ns in enumerate(times):
        source = str(timeline.source[i])
        corrected = bool(timeline.corrected[i])
        yield (
            ns,
            {
                "timestamp": _stamp(ns),
                "seq": int(timeline.seq[i]),
                "source": source,
                "code": _CODES[source],
                "corrected": corrected,
                "final_code": _CODES[Source.CORRECTED.value] if corrected else _CODES[source],
                "framed": bool(timeline.framed[i]),
            },
        )


def _lateness(timeline: Timeline, times: list[int]) -> Iterator[tuple[int, dict[str, Any]]]:
    for i, ns in enumerate(times):
        delay = float(timeline.frame_delay[i])
        yield (
            ns,
            {
                "timestamp": _stamp(ns),
                "seq": int(timeline.seq[i]),
                "frame_delay": delay if np.isfinite(delay) else None,
                "compute_us": float(timeline.compute_us[i]),
                "receive_to_send_us": float(timeline.receive_to_send_us[i]),
            },
        )


def _rejections(timeline: Timeline, start_ns: int) -> Iterator[tuple[int, dict[str, Any]]]:
    rejected = timeline.rejections
    for seq, t, reason in zip(rejected.seq, rejected.t, rejected.reason, strict=True):
        ns = start_ns + round(float(t) * 1e9)
        yield ns, {"timestamp": _stamp(ns), "seq": int(seq), "reason": str(reason)}


def _load(session_id: str, *, data_root: Path, engine: sa.Engine, tenant: str) -> _Session:
    row = SessionIndex(engine).get(session_id, tenant=tenant)
    metadata, table = read_stored(row, data_root=data_root, environ=os.environ, purpose="export")
    mjcf, assets = session_model(engine, data_root, row)
    try:
        model = mujoco.MjModel.from_xml_string(mjcf, assets=assets)
    except ValueError as error:  # MuJoCo's compile error: the registry compiled it, this copy did not
        raise FailedPrecondition(
            f"the model of session {row.session_id} ({row.model_id}) does not compile here: "
            f"{' '.join(str(error).split())}"
        ) from None
    return _Session(row=row, metadata=metadata, table=table, model=model)


def _messages(session: _Session) -> Iterator[tuple[str, Iterator[tuple[int, dict[str, Any]]]]]:
    """Each topic's messages as (log time in ns since the epoch, JSON object), in time order."""
    # In whole microseconds, as the index holds it (a float of ns since 1970 would round to 256 ns).
    start_ns = (session.row.started_at - _EPOCH) // datetime.timedelta(microseconds=1) * 1000
    ticks = latest_results(session.table)
    times = [start_ns + round(t * 1e9) for t in ticks["t"].to_pylist()]
    timeline = session_timeline(session.table)
    times_of = dict(zip(ticks["seq"].to_pylist(), times, strict=True))
    yield Topic.JOINT_STATES, _vectors(session, ticks, times, ("qpos", "qvel", "qacc"))
    yield Topic.FORCES, _vectors(session, ticks, times, _FORCE_COLUMNS)
    yield Topic.FRAMES, _frames(session, times_of)
    yield Topic.SOURCE, _sources(timeline, times)
    yield Topic.LATENESS, _lateness(timeline, times)
    yield Topic.REJECTIONS, _rejections(timeline, start_ns)
    yield Topic.TRANSFORMS, _transforms(session, ticks, times)


def _summary(row: SessionRow) -> dict[str, str]:
    """The session as MCAP metadata (string values only)."""
    summary = {k: getattr(row.summary, k) for k in row.summary.__dataclass_fields__}
    return {
        "session_id": row.session_id,
        "model": f"{row.model_name} v{row.model_version}",
        "model_id": row.model_id,
        "scenario": row.scenario,
        "clock": row.clock,
        "dt": repr(row.dt),
        "status": row.status,
        "started_at": row.started_at.isoformat(),
        "summary": json.dumps(summary, default=str),
    }


def _tagged(
    topic: str, messages: Iterator[tuple[int, dict[str, Any]]]
) -> Iterator[tuple[int, str, dict[str, Any]]]:
    for ns, message in messages:
        yield ns, topic, message


def _write(session: _Session, stream: BinaryIO) -> dict[str, int]:
    """Every topic's messages, interleaved in time order (Foxglove streams a file front to back)."""
    from mcap.writer import Writer

    writer = Writer(stream)
    writer.start(profile="", library="jitdyn")
    channels: dict[str, int] = {}
    for topic, name in CHANNELS.items():
        schema = writer.register_schema(
            name=name, encoding="jsonschema", data=json.dumps(SCHEMAS[name]).encode("utf-8")
        )
        channels[topic] = writer.register_channel(topic=topic, message_encoding="json", schema_id=schema)
    tagged = [_tagged(topic, messages) for topic, messages in _messages(session)]
    counts: dict[str, int] = dict.fromkeys(CHANNELS, 0)
    for ns, on, message in heapq.merge(*tagged, key=lambda item: item[0]):
        writer.add_message(
            channel_id=channels[on],
            log_time=ns,
            publish_time=ns,
            sequence=counts[on],
            data=json.dumps(message, allow_nan=False, separators=(",", ":")).encode("utf-8"),
        )
        counts[on] += 1
    writer.add_metadata("jitdyn.session", _summary(session.row))
    writer.finish()  # type: ignore[no-untyped-call]
    return counts


def export_mcap(
    session_id: str, *, data_root: Path, engine: sa.Engine, out: Path, tenant: str = ""
) -> Exported:
    """Write the session as MCAP to `out` (a file, or a folder to put `<id>.mcap` in),
    atomically.

    Raises NotFound for an unknown session, FailedPrecondition for a session still open or whose
    model the registry no longer holds, Unavailable when its data root does not answer.
    """
    session = _load(session_id, data_root=data_root, engine=engine, tenant=tenant)
    target = export_target(out, session_id, "mcap")
    counts: dict[str, int] = {}

    def write(path: Path) -> None:
        with open(path, "wb") as stream:
            counts.update(_write(session, stream))

    atomic_write(target, write)
    return Exported(path=target, counts=counts)
