"""SessionService over real gRPC on a loopback port 0: paging, filters, statuses, tenant isolation,
and the conversion of index rows to messages."""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable, Iterator

import grpc
import pytest
from google.protobuf import timestamp_pb2

from jitdyn.server.transport.session_service import estimator_to_pb
from jitdyn.storage.index import SessionIndex
from jitdyn.storage.records import SessionHeader, SessionSummaryInfo
from jitdyn.v1 import common_pb2, session_pb2, session_pb2_grpc

T0 = dt.datetime(2026, 11, 21, 10, 0, 0, tzinfo=dt.UTC)
Metadata = Callable[[str], list[tuple[str, str]]]


@pytest.fixture()
def stub(session_server: str) -> Iterator[session_pb2_grpc.SessionServiceStub]:
    with grpc.insecure_channel(session_server) as channel:
        yield session_pb2_grpc.SessionServiceStub(channel)  # type: ignore[no-untyped-call]


def stamp(value: dt.datetime) -> timestamp_pb2.Timestamp:
    result = timestamp_pb2.Timestamp()
    result.FromDatetime(value)
    return result


def test_get_session_converts_every_field(
    stub: session_pb2_grpc.SessionServiceStub,
    index: SessionIndex,
    make_header: Callable[..., SessionHeader],
    as_tenant: Metadata,
) -> None:
    header = make_header(
        tenant="lab",
        scenario="CONTROLLED",
        clock="REALTIME",
        subject_pseudonym="ab" * 32,
        subject_attributes={"sex": "F", "age_band": "40-49"},
        estimator={
            "estimator": "UKF",
            "preset": "THESIS",
            "sigma_points": "SIMPLEX",
            "alpha": 0.001,
            "kappa": 0,
        },
    )
    index.create(header, log_path="logs/x.arrows")
    response = stub.GetSession(
        session_pb2.GetSessionRequest(session_id=header.session_id), metadata=as_tenant("lab")
    )
    session = response.session
    assert session.session_id == header.session_id
    assert (session.model_id, session.model_name, session.model_version) == (header.model_id, "pendulum_3", 1)
    assert session.scenario == common_pb2.SCENARIO_CONTROLLED
    assert session.clock == common_pb2.CLOCK_REALTIME
    assert session.dt == 0.01
    assert session.status == session_pb2.SESSION_STATUS_OPEN
    assert session.started_at.ToDatetime(dt.UTC) == T0
    assert not session.HasField("ended_at")
    assert not session.HasField("summary")
    assert session.location == ""
    assert session.subject_pseudonym == "ab" * 32
    assert dict(session.subject_attributes) == {"sex": "F", "age_band": "40-49"}
    assert session.estimator == common_pb2.EstimatorSettings(
        estimator=common_pb2.ESTIMATOR_UKF,
        preset=common_pb2.PRESET_THESIS,
        sigma_points=common_pb2.SIGMA_POINTS_SIMPLEX,
        alpha=0.001,
        kappa=0.0,
    )

    summary = SessionSummaryInfo(
        ticks=3, frames=4, measured=2, predicted=1, rejected=1, late=0, duration=0.03
    )
    end = T0 + dt.timedelta(seconds=30)
    index.finish(
        header.session_id, status="COMPLETE", summary=summary, location="frames/f.parquet", ended_at=end
    )
    session = stub.GetSession(
        session_pb2.GetSessionRequest(session_id=header.session_id), metadata=as_tenant("lab")
    ).session
    assert session.status == session_pb2.SESSION_STATUS_COMPLETE
    assert session.ended_at.ToDatetime(dt.UTC) == end
    assert (session.summary.ticks, session.summary.frames, session.summary.rejected) == (3, 4, 1)
    assert session.summary.location == session.location == "frames/f.parquet"
    assert session.summary.duration == pytest.approx(0.03)


def test_get_session_of_another_tenant_is_not_found(
    stub: session_pb2_grpc.SessionServiceStub,
    index: SessionIndex,
    make_header: Callable[..., SessionHeader],
    as_tenant: Metadata,
) -> None:
    header = make_header(tenant="lab")
    index.create(header, log_path="")
    for tenant in ("other", ""):
        with pytest.raises(grpc.RpcError) as error:
            stub.GetSession(
                session_pb2.GetSessionRequest(session_id=header.session_id), metadata=as_tenant(tenant)
            )
        assert error.value.code() == grpc.StatusCode.NOT_FOUND
        assert error.value.details() == f"session {header.session_id!r} not found"
    with pytest.raises(grpc.RpcError) as error:
        stub.GetSession(session_pb2.GetSessionRequest())
    assert error.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert error.value.details() == "session_id must be set, got an empty string"


def test_list_sessions_pages_and_filters(
    stub: session_pb2_grpc.SessionServiceStub,
    index: SessionIndex,
    make_header: Callable[..., SessionHeader],
    as_tenant: Metadata,
) -> None:
    headers = [
        make_header(
            tenant="lab",
            started_at=T0 + dt.timedelta(minutes=i),
            scenario="EXTERNAL" if i % 3 == 0 else "PASSIVE",
            subject_pseudonym="cd" * 32 if i == 4 else "",
            model_name="pendulum_1" if i == 5 else "pendulum_3",
        )
        for i in range(7)
    ]
    for h in headers:
        index.create(h, log_path="")
    index.finish(
        headers[2].session_id, status="RECOVERED", summary=SessionSummaryInfo(), location="frames/r.parquet"
    )
    index.create(make_header(tenant="other"), log_path="")

    listed: list[str] = []
    token = ""
    pages = 0
    while True:
        response = stub.ListSessions(
            session_pb2.ListSessionsRequest(page_size=3, page_token=token), metadata=as_tenant("lab")
        )
        listed += [s.session_id for s in response.sessions]
        pages += 1
        token = response.next_page_token
        if not token:
            break
    assert pages == 3
    assert listed == [h.session_id for h in reversed(headers)]

    def ids(**fields: object) -> list[str]:
        request = session_pb2.ListSessionsRequest(**fields)  # type: ignore[arg-type]
        return [s.session_id for s in stub.ListSessions(request, metadata=as_tenant("lab")).sessions]

    assert ids(scenario=common_pb2.SCENARIO_EXTERNAL) == [headers[i].session_id for i in (6, 3, 0)]
    assert ids(subject_pseudonym="cd" * 32) == [headers[4].session_id]
    assert ids(model_name="pendulum_1") == [headers[5].session_id]
    assert ids(model_id="sha256:nothing") == []
    assert ids(status=session_pb2.SESSION_STATUS_RECOVERED) == [headers[2].session_id]
    assert ids(
        started_after=stamp(T0 + dt.timedelta(minutes=1)), started_before=stamp(T0 + dt.timedelta(minutes=3))
    ) == [headers[2].session_id, headers[1].session_id]
    # page_size 0 means 50.
    assert len(ids(page_size=0)) == 7
    # Another tenant sees its own session only.
    response = stub.ListSessions(session_pb2.ListSessionsRequest(), metadata=as_tenant("other"))
    assert len(response.sessions) == 1 and response.next_page_token == ""


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"page_size": 1001}, "page_size must be at most 1000, got 1001"),
        ({"page_token": "not-a-token"}, "page_token 'not-a-token' is not a token this server issued"),
        (
            {"started_after": stamp(T0 + dt.timedelta(hours=1)), "started_before": stamp(T0)},
            "started_after (2026-11-21T11:00:00+00:00) must not be later than started_before",
        ),
        ({"status": 9}, "status must be a SESSION_STATUS value, got 9"),
    ],
)
def test_list_sessions_invalid_arguments(
    stub: session_pb2_grpc.SessionServiceStub, fields: dict[str, object], message: str
) -> None:
    with pytest.raises(grpc.RpcError) as error:
        stub.ListSessions(session_pb2.ListSessionsRequest(**fields))  # type: ignore[arg-type]
    assert error.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert error.value.details().startswith(message)


def test_estimator_conversion_tolerates_unknown_names() -> None:
    message = estimator_to_pb(
        {"estimator": "ukf", "preset": "PRESET_JITDYN", "sigma_points": "NEW", "r": 1, "x": 2}
    )
    assert message == common_pb2.EstimatorSettings(
        estimator=common_pb2.ESTIMATOR_UKF, preset=common_pb2.PRESET_JITDYN, r=1.0
    )
