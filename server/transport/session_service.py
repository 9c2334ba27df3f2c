"""SessionService: the stored sessions of the calling tenant, listed and described.

    servicer = SessionServicer(SessionIndex(engine))
    session_pb2_grpc.add_SessionServiceServicer_to_server(servicer, server)

The index is SQL behind a blocking driver, so every call runs in a worker thread and the event
loop keeps serving streams. Messages stop here: the index speaks `SessionRow`, converted by the
pure functions below.
"""

from __future__ import annotations

import asyncio
import datetime as _dt
from collections.abc import Mapping
from typing import TYPE_CHECKING, Final, TypeAlias, TypeVar

import grpc
from google.protobuf import timestamp_pb2

from jitdyn.errors import InvalidArgument
from jitdyn.server.transport.auth import tenant_of
from jitdyn.server.transport.status import translate_errors
from jitdyn.storage.index import MAX_PAGE_SIZE, SessionIndex, SessionRow
from jitdyn.storage.records import SessionSummaryInfo
from jitdyn.v1 import common_pb2, dynamics_pb2, session_pb2, session_pb2_grpc

if TYPE_CHECKING:
    # The stubs' generic enum wrapper: mypy-protobuf types each enum's values as its own int NewType.
    from google.protobuf.internal.enum_type_wrapper import _EnumTypeWrapper

    _SettingsEnum: TypeAlias = type[common_pb2.Estimator | common_pb2.Preset | common_pb2.SigmaPoints]

__all__ = [
    "DEFAULT_PAGE_SIZE",
    "SessionServicer",
    "estimator_to_pb",
    "session_to_pb",
    "summary_to_pb",
]

DEFAULT_PAGE_SIZE: Final = 50

_V = TypeVar("_V", bound=int)

# Enum fields of EstimatorSettings, stored by name without prefix: their enum and its prefix.
_ESTIMATOR_ENUMS: Final[dict[str, tuple[_SettingsEnum, str]]] = {
    "estimator": (common_pb2.Estimator, "ESTIMATOR_"),
    "preset": (common_pb2.Preset, "PRESET_"),
    "sigma_points": (common_pb2.SigmaPoints, "SIGMA_POINTS_"),
}
_ESTIMATOR_FLOATS: Final = ("alpha", "beta", "kappa", "p0", "q_var", "r")


def _timestamp(value: _dt.datetime) -> timestamp_pb2.Timestamp:
    stamp = timestamp_pb2.Timestamp()
    stamp.FromDatetime(value.astimezone(_dt.UTC))
    return stamp


def estimator_to_pb(settings: Mapping[str, object]) -> common_pb2.EstimatorSettings:
    """Stored estimator settings (EstimatorSettings field names, enum names with or without their
    prefix, any case) as the message. Keys and names the contract does not know are left unset
    rather than failing: one odd stored row must not break every listing that contains it."""
    message = common_pb2.EstimatorSettings()
    for field, (enum, prefix) in _ESTIMATOR_ENUMS.items():
        name = settings.get(field)
        if isinstance(name, str) and name:
            full = name.upper() if name.upper().startswith(prefix) else prefix + name.upper()
            try:
                setattr(message, field, enum.Value(full))
            except ValueError:
                continue
    for field in _ESTIMATOR_FLOATS:
        value = settings.get(field)
        if isinstance(value, int | float) and not isinstance(value, bool):
            setattr(message, field, float(value))
    return message


def summary_to_pb(summary: SessionSummaryInfo, *, location: str) -> dynamics_pb2.SessionSummary:
    return dynamics_pb2.SessionSummary(
        ticks=summary.ticks,
        frames=summary.frames,
        measured=summary.measured,
        predicted=summary.predicted,
        corrected=summary.corrected,
        rejected=summary.rejected,
        late=summary.late,
        location=location,
        mean_compute_us=summary.mean_compute_us,
        max_compute_us=summary.max_compute_us,
        duration=summary.duration,
    )


def session_to_pb(row: SessionRow) -> session_pb2.Session:
    """An index row as the `Session` message; the summary only once the session has ended."""
    message = session_pb2.Session(
        session_id=row.session_id,
        model_id=row.model_id,
        model_name=row.model_name,
        model_version=row.model_version,
        scenario=common_pb2.Scenario.Value(f"SCENARIO_{row.scenario}"),
        clock=common_pb2.Clock.Value(f"CLOCK_{row.clock}"),
        estimator=estimator_to_pb(row.estimator),
        dt=row.dt,
        subject_pseudonym=row.subject_pseudonym,
        subject_attributes=row.subject_attributes,
        started_at=_timestamp(row.started_at),
        status=session_pb2.SessionStatus.Value(f"SESSION_STATUS_{row.status}"),
        location=row.location,
    )
    if row.ended_at is not None:
        message.ended_at.CopyFrom(_timestamp(row.ended_at))
        message.summary.CopyFrom(summary_to_pb(row.summary, location=row.location))
    return message


def _enum_name(value: _V, enum: _EnumTypeWrapper[_V], prefix: str, field: str) -> str | None:
    """The stored name of a filter's enum value (None for UNSPECIFIED); InvalidArgument for a
    number the proto does not define."""
    if value == 0:
        return None
    try:
        name: str = enum.Name(value)
    except ValueError as exc:
        raise InvalidArgument(f"{field} must be a {prefix.rstrip('_')} value, got {value}") from exc
    return name.removeprefix(prefix)


class SessionServicer(session_pb2_grpc.SessionServiceServicer):
    """ListSessions and GetSession over a `SessionIndex`, for the caller's tenant only."""

    def __init__(self, index: SessionIndex) -> None:
        self._index = index

    @translate_errors
    async def ListSessions(
        self,
        request: session_pb2.ListSessionsRequest,
        context: grpc.aio.ServicerContext[session_pb2.ListSessionsRequest, session_pb2.ListSessionsResponse],
    ) -> session_pb2.ListSessionsResponse:
        tenant = tenant_of(context)
        if request.page_size > MAX_PAGE_SIZE:
            raise InvalidArgument(f"page_size must be at most {MAX_PAGE_SIZE}, got {request.page_size}")
        rows, token = await asyncio.to_thread(
            self._index.list,
            tenant=tenant,
            model_name=request.model_name or None,
            model_id=request.model_id or None,
            scenario=_enum_name(request.scenario, common_pb2.Scenario, "SCENARIO_", "scenario"),
            pseudonym=request.subject_pseudonym or None,
            started_after=(
                request.started_after.ToDatetime(_dt.UTC) if request.HasField("started_after") else None
            ),
            started_before=(
                request.started_before.ToDatetime(_dt.UTC) if request.HasField("started_before") else None
            ),
            status=_enum_name(request.status, session_pb2.SessionStatus, "SESSION_STATUS_", "status"),
            page_size=request.page_size or DEFAULT_PAGE_SIZE,
            page_token=request.page_token,
        )
        return session_pb2.ListSessionsResponse(
            sessions=[session_to_pb(row) for row in rows], next_page_token=token
        )

    @translate_errors
    async def GetSession(
        self,
        request: session_pb2.GetSessionRequest,
        context: grpc.aio.ServicerContext[session_pb2.GetSessionRequest, session_pb2.GetSessionResponse],
    ) -> session_pb2.GetSessionResponse:
        tenant = tenant_of(context)
        if not request.session_id:
            raise InvalidArgument("session_id must be set, got an empty string")
        row = await asyncio.to_thread(self._index.get, request.session_id, tenant=tenant)
        return session_pb2.GetSessionResponse(session=session_to_pb(row))
