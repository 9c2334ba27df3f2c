"""What the recorder stores: one `TickRecord` per event the server answered, the `SessionHeader`
that describes the session, and the `SessionSummaryInfo` written to the index when it ends.

These are plain values: the session runtime builds them, the recorder writes them, and the index,
query and export code read them back. Nothing here knows about gRPC or files.
"""

from __future__ import annotations

import datetime as _dt
import json
import re
import uuid
from collections.abc import Iterable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Final, Literal, TypeVar

import numpy as np
import numpy.typing as npt

from jitdyn.errors import InvalidArgument
from jitdyn.vocabulary import Clock, JointType, Scenario, SessionStatus

__all__ = [
    "FINAL_STATUSES",
    "FORCE_UNITS",
    "JOINT_WIDTHS",
    "KINDS",
    "SessionHeader",
    "SessionSummaryInfo",
    "TickRecord",
    "dof_units",
    "qpos_names",
    "stored_word",
]

Vector = npt.NDArray[np.float64]

KINDS: Final = ("result", "rejected")
# What a session can end as; it is OPEN until then.
FINAL_STATUSES: Final = tuple(status for status in SessionStatus if status != SessionStatus.OPEN)

_Word = TypeVar("_Word", bound=StrEnum)


def stored_word(
    kind: type[_Word], text: object, *, argument: str, among: Iterable[_Word] | None = None
) -> _Word:
    """The vocabulary member whose stored text is exactly `text` (and one of `among`, when given):
    what storage writes and reads is the member's value, never a guess at another spelling."""
    allowed = tuple(kind) if among is None else tuple(among)
    for member in allowed:
        if text == member.value:
            return member
    raise InvalidArgument(f"{argument} must be one of {', '.join(allowed)}, got {text!r}")


# Model names become a Hive partition folder (`model=<name>`), so they must be safe as one path
# component and need no escaping in any engine that reads the dataset.
_MODEL_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class TickRecord:
    """One event the server answered: a `result` of a tick, or a `rejected` frame.

    The arrays are 1-D float64 vectors: frame_qpos and qpos (nq,), frame_qvel, frame_qacc, qvel,
    qacc, qfrc_inverse and qacc_forward (nv,), frame_ctrl and actuator_force (nu,), frame_sensordata
    and sensordata (nsensordata,), covariance_diagonal (state dimension,), filter_state (nq + nv or
    nq + 2 nv,); None when absent. The recorder converts them on its commit thread, after `append`
    returned, so they must not be changed afterwards: hand over copies, never views of an MjData.
    Records are not compared with == (numpy arrays have no single truth value); compare fields.
    """

    kind: Literal["result", "rejected"]
    # The tick index the event belongs to.
    seq: int
    # A result's Source value (MEASURED, PREDICTED or CORRECTED); "" for a rejected frame.
    source: str = ""
    # The tick's time on the client clock (seconds since session start).
    t: float = 0.0
    # When the server answered (seconds since session start, server clock).
    server_time: float = 0.0
    frame_received: bool = False
    # The frame's own client time, when a frame arrived.
    frame_t: float | None = None
    frame_qpos: Vector | None = None
    frame_qvel: Vector | None = None
    frame_qacc: Vector | None = None
    frame_ctrl: Vector | None = None
    frame_sensordata: Vector | None = None
    late_ticks: int = 0
    # REALTIME: arrival relative to the tick's deadline on the server clock (seconds).
    frame_delay: float | None = None
    qpos: Vector | None = None
    qvel: Vector | None = None
    qacc: Vector | None = None
    qfrc_inverse: Vector | None = None
    qacc_forward: Vector | None = None
    actuator_force: Vector | None = None
    sensordata: Vector | None = None
    covariance_diagonal: Vector | None = None
    filter_state: Vector | None = None
    nis: float | None = None
    reinitialised: bool = False
    # Answered without the estimator, from what the server had (it was overloaded).
    late_compute: bool = False
    # A PREDICTED tick answered by the forecast combination: each predictor's weight.
    forecast_weights: Vector | None = None
    compute_us: int = 0
    receive_to_send_us: int = 0
    # The RejectReason name without its prefix (BAD_CHECKSUM, ...); "" for results.
    reject_reason: str = ""
    reject_message: str = ""


# (qpos values, dofs) of one joint of each type.
JOINT_WIDTHS: Final = {
    JointType.FREE: (7, 6),
    JointType.BALL: (4, 3),
    JointType.SLIDE: (1, 1),
    JointType.HINGE: (1, 1),
}


def qpos_names(joint_names: tuple[str, ...], joint_types: tuple[JointType, ...]) -> tuple[str, ...]:
    """Names of the nq qpos values: the joint's name for hinge and slide joints, suffixed with the
    component for ball (`_qw`..`_qz`) and free joints (`_x`, `_y`, `_z`, `_qw`..`_qz`)."""
    names: list[str] = []
    for name, joint_type in zip(joint_names, joint_types, strict=True):
        if joint_type == JointType.FREE:
            names += [f"{name}_{c}" for c in ("x", "y", "z", "qw", "qx", "qy", "qz")]
        elif joint_type == JointType.BALL:
            names += [f"{name}_{c}" for c in ("qw", "qx", "qy", "qz")]
        else:
            names.append(name)
    return tuple(names)


def dof_units(joint_types: tuple[JointType, ...]) -> tuple[str, ...]:
    """The unit of each of the nv degrees of freedom: "m" for translations, "rad" for rotations.
    Generalized forces along them are then N and N m."""
    units: list[str] = []
    for joint_type in joint_types:
        if joint_type == JointType.FREE:
            units += ["m", "m", "m", "rad", "rad", "rad"]
        elif joint_type == JointType.BALL:
            units += ["rad", "rad", "rad"]
        elif joint_type == JointType.SLIDE:
            units.append("m")
        else:
            units.append("rad")
    return tuple(units)


# The unit of a generalized force along a dof of each unit (dof_units).
FORCE_UNITS: Final = {"rad": "N m", "m": "N"}


@dataclass(frozen=True, slots=True, kw_only=True)
class SessionHeader:
    """What a session is: its model, settings and (anonymised) subject. Validated on creation.

    `estimator` holds the settings in force keyed by `EstimatorSettings` field names, enum values
    by name without their prefix, e.g. {"estimator": "UKF", "preset": "JITDYN", "sigma_points":
    "MERWE", "alpha": 0.001, ...}; it must be JSON-serialisable. `subject_attributes` must already
    have passed the allow-list (storage.anonymise.Anonymiser.filter_attributes).
    """

    session_id: str
    tenant: str
    model_id: str
    model_name: str
    model_version: int
    # One entry per joint, in MuJoCo's order.
    joint_names: tuple[str, ...]
    # One name per degree of freedom (nv).
    dof_names: tuple[str, ...]
    nq: int
    nv: int
    nu: int
    nsensordata: int
    # The model's physics timestep and the frame period (seconds).
    timestep: float
    dt: float
    # The member, or its exact text (as a log's JSON holds it), made the member on creation.
    scenario: Scenario | str
    clock: Clock | str
    estimator: dict[str, object]
    subject_pseudonym: str
    subject_attributes: dict[str, str]
    started_at: _dt.datetime
    # The joints' types (JointType, or its MJCF name), one per joint. They give the units of each
    # dof and the names of the qpos values; empty: units unknown ("") and qpos named by index unless
    # nq equals the number of joints.
    joint_types: tuple[JointType | str, ...] = field(default=())
    # Names of the nu actuators, for export column names; empty: numbered.
    actuator_names: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        try:
            canonical = str(uuid.UUID(self.session_id))
        except ValueError:
            canonical = ""
        if canonical != self.session_id:
            raise InvalidArgument(
                f"session_id must be a UUID in canonical form (36 lower-case characters), "
                f"got {self.session_id!r}"
            )
        if not _MODEL_NAME.fullmatch(self.model_name):
            raise InvalidArgument(
                "model_name must be 1 to 64 letters, digits, '_', '.' or '-', starting with a letter "
                f"or digit (it names a Parquet partition folder), got {self.model_name!r}"
            )
        # Frozen: the members replace the text once, here.
        object.__setattr__(self, "scenario", stored_word(Scenario, self.scenario, argument="scenario"))
        object.__setattr__(self, "clock", stored_word(Clock, self.clock, argument="clock"))
        for name in ("nq", "nv", "nu", "nsensordata"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 0:
                raise InvalidArgument(f"{name} must be a non-negative int, got {value!r}")
        if not (self.dt > 0 and self.timestep > 0):
            raise InvalidArgument(
                f"dt and timestep must be > 0, got dt={self.dt!r}, timestep={self.timestep!r}"
            )
        if self.joint_types and len(self.joint_types) != len(self.joint_names):
            raise InvalidArgument(
                f"joint_types must have one entry per joint ({len(self.joint_names)}), "
                f"got {len(self.joint_types)}"
            )
        unknown = [t for t in self.joint_types if t not in JOINT_WIDTHS]
        if unknown:
            raise InvalidArgument(f"joint_types must be among {', '.join(JointType)}, got {unknown!r}")
        joint_types = tuple(JointType(t) for t in self.joint_types)
        object.__setattr__(self, "joint_types", joint_types)
        nq = sum(JOINT_WIDTHS[t][0] for t in joint_types)
        nv = sum(JOINT_WIDTHS[t][1] for t in joint_types)
        if self.joint_types and (nq, nv) != (self.nq, self.nv):
            raise InvalidArgument(
                f"the joints {[t.value for t in joint_types]} span nq={nq}, nv={nv}, "
                f"but the header says nq={self.nq}, nv={self.nv}"
            )
        if len(self.dof_names) != self.nv:
            raise InvalidArgument(f"dof_names must have nv={self.nv} names, got {len(self.dof_names)}")
        if self.actuator_names and len(self.actuator_names) != self.nu:
            raise InvalidArgument(
                f"actuator_names must be empty or have nu={self.nu} names, got {len(self.actuator_names)}"
            )
        if self.started_at.tzinfo is None or self.started_at.utcoffset() is None:
            raise InvalidArgument(f"started_at must be timezone-aware (UTC), got naive {self.started_at!r}")
        try:
            json.dumps(self.estimator, allow_nan=False)
        except (TypeError, ValueError) as exc:
            raise InvalidArgument(f"estimator settings must be JSON-serialisable: {exc}") from exc

    @property
    def qpos_names(self) -> tuple[str, ...]:
        """Names of the nq qpos values (see `qpos_names`)."""
        if self.joint_types:
            return qpos_names(self.joint_names, tuple(JointType(t) for t in self.joint_types))
        if len(self.joint_names) == self.nq:
            return self.joint_names
        return tuple(str(i) for i in range(self.nq))

    @property
    def dof_units(self) -> tuple[str, ...]:
        """Unit of each degree of freedom, "m" or "rad" (see `dof_units`); "" when the joint
        types are not known."""
        if self.joint_types:
            return dof_units(tuple(JointType(t) for t in self.joint_types))
        return ("",) * self.nv

    @property
    def date(self) -> str:
        """The session's start date in UTC, YYYY-MM-DD: its Parquet partition."""
        return self.started_at.astimezone(_dt.UTC).date().isoformat()


@dataclass(frozen=True, slots=True, kw_only=True)
class SessionSummaryInfo:
    """What happened in a session, as counts and timings (the index row's summary columns).

    `ticks` counts distinct ticks answered; `frames` the frames received, rejected ones included;
    `late` the frames that arrived after their tick was answered. `duration` is the session's length
    on the server clock (seconds). `stats` holds JSON-serialisable statistics, e.g.
    {"qfrc_inverse": {"hinge_1": {"min": -3.1, "max": 2.7}}}.
    """

    ticks: int = 0
    frames: int = 0
    measured: int = 0
    predicted: int = 0
    corrected: int = 0
    rejected: int = 0
    late: int = 0
    mean_compute_us: float = 0.0
    max_compute_us: float = 0.0
    duration: float = 0.0
    stats: dict[str, object] = field(default_factory=dict)
