"""StreamSession in LOCKSTEP over real gRPC: dynamics, rejections, fatal errors, storage."""

from __future__ import annotations

import math
import sqlite3
from pathlib import Path
from typing import Any

import grpc
import mujoco
import numpy as np
import pyarrow.parquet as pq
import pytest

from jitdyn.client import FrameData, Rejection, SessionOptions, TickResult
from jitdyn.errors import InvalidArgument, NotFound
from jitdyn.registry import builtin_model_path
from jitdyn.v1 import dynamics_pb2, dynamics_pb2_grpc


def _model(name: str) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(builtin_model_path(name)))


def _trajectory(
    model: mujoco.MjModel, ticks: int, dt: float, *, seed: int = 0
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Truth of a passive chain from a seeded displacement: (qpos, qvel, qacc) per tick."""
    data = mujoco.MjData(model)
    data.qpos[:] = np.random.default_rng(seed).uniform(-0.8, 0.8, model.nq)
    mujoco.mj_forward(model, data)
    steps = round(dt / model.opt.timestep)
    out = []
    for _ in range(ticks):
        out.append((data.qpos.copy(), data.qvel.copy(), data.qacc.copy()))
        for _ in range(steps):
            mujoco.mj_step(model, data)
        mujoco.mj_forward(model, data)
    return out


def _inverse(model: mujoco.MjModel, qpos: np.ndarray, qvel: np.ndarray, qacc: np.ndarray) -> np.ndarray:
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:], data.qacc[:] = qpos, qvel, qacc
    mujoco.mj_inverse(model, data)
    return data.qfrc_inverse.copy()


def test_measured_results_carry_mj_inverse_of_the_frame(client: Any) -> None:
    model = _model("pendulum_3")
    truth = _trajectory(model, 20, 0.05)
    options = SessionOptions(model_name="pendulum_3", dt=0.05, measured=("qpos", "qvel", "qacc"))
    with client.open_session(options) as session:
        assert session.opened.model.name == "pendulum_3"
        assert session.opened.steps_per_tick == 2
        for k, (q, v, a) in enumerate(truth):
            result = session.send_frame(FrameData(seq=k, t=k * 0.05, qpos=q, qvel=v, qacc=a))
            assert isinstance(result, TickResult), result
            assert result.source == "MEASURED"
            assert result.seq == k and result.frame_received
            np.testing.assert_array_equal(result.qpos, q)
            np.testing.assert_array_equal(result.qacc, a)
            np.testing.assert_allclose(result.qfrc_inverse, _inverse(model, q, v, a), rtol=0, atol=1e-12)
        summary = session.close()
    assert summary.measured == 20 and summary.predicted == 0 and summary.rejected == 0


def test_qacc_by_finite_difference_when_the_frame_has_none(client: Any) -> None:
    model = _model("pendulum_2")
    truth = _trajectory(model, 5, 0.05, seed=3)
    with client.open_session(SessionOptions(model_name="pendulum_2", dt=0.05)) as session:
        results = [
            session.send_frame(FrameData(seq=k, t=k * 0.05, qpos=q, qvel=v))
            for k, (q, v, _) in enumerate(truth)
        ]
    for k in range(1, 5):
        expected = (truth[k][1] - truth[k - 1][1]) / 0.05
        np.testing.assert_allclose(results[k].qacc, expected, atol=1e-12)
        np.testing.assert_allclose(
            results[k].qfrc_inverse, _inverse(model, truth[k][0], truth[k][1], expected), atol=1e-9
        )


def _send_and_expect(session: Any, frame: dynamics_pb2.Frame, reason: str, text: str) -> None:
    session._send(dynamics_pb2.StreamSessionRequest(frame=frame))
    answer = session._answer()
    assert isinstance(answer, Rejection), answer
    assert answer.reason == reason
    assert text in answer.message, answer.message


def test_every_rejection_reason_and_the_session_goes_on(client: Any) -> None:
    options = SessionOptions(model_name="pendulum_1", dt=0.05, history=3)
    with client.open_session(options) as session:
        ok = session.send_frame(FrameData(seq=0, t=0.0, qpos=[0.2], qvel=[0.0]))
        assert isinstance(ok, TickResult)

        bad_crc = FrameData(seq=1, t=0.05, qpos=[0.2], qvel=[0.0]).to_message()
        bad_crc.checksum ^= 0xFFFF
        _send_and_expect(session, bad_crc, "BAD_CHECKSUM", "frame 1: checksum is 0x")

        _send_and_expect(
            session,
            FrameData(seq=1, t=0.05, qpos=[0.2, 0.1], qvel=[0.0]).to_message(),
            "BAD_SHAPE",
            "frame 1: qpos must have 1 values, got 2",
        )
        _send_and_expect(
            session,
            FrameData(seq=1, t=0.05, qpos=[0.2], qvel=[0.0], qacc=[1.0]).to_message(),
            "BAD_SHAPE",
            "frame 1: qacc must be empty",
        )
        _send_and_expect(
            session,
            FrameData(seq=1, t=0.05, qpos=[math.nan], qvel=[0.0]).to_message(),
            "NOT_FINITE",
            "frame 1: qpos[0] must be finite, got nan",
        )
        _send_and_expect(
            session,
            FrameData(seq=0, t=0.0, qpos=[0.2], qvel=[0.0]).to_message(),
            "DUPLICATE",
            "frame 0: tick 0 already has a frame",
        )
        _send_and_expect(
            session,
            FrameData(seq=9, t=0.45, qpos=[0.2], qvel=[0.0]).to_message(),
            "OUT_OF_ORDER",
            "LOCKSTEP expects the next tick 1",
        )
        for k in range(1, 6):
            assert session.skip(k).source == "PREDICTED"
        _send_and_expect(
            session,
            FrameData(seq=1, t=0.05, qpos=[0.2], qvel=[0.0]).to_message(),
            "TOO_OLD",
            "late frames are applied back to tick 3 (history 3 ticks), got 1",
        )
        skip_again = session.skip(2)
        assert isinstance(skip_again, Rejection) and skip_again.reason == "DUPLICATE"
        late = session.send_frame(FrameData(seq=4, t=0.2, qpos=[0.1], qvel=[0.0]))
        assert isinstance(late, TickResult) and late.source == "CORRECTED" and late.late_ticks == 2
        after = session.send_frame(FrameData(seq=6, t=0.3, qpos=[0.1], qvel=[0.0]))
        assert isinstance(after, TickResult) and after.source == "MEASURED"
        summary = session.close()
    assert summary.rejected == 8
    assert (summary.measured, summary.predicted, summary.corrected, summary.late) == (2, 5, 1, 1)


def test_skip_in_realtime_is_wrong_clock(client: Any) -> None:
    options = SessionOptions(model_name="pendulum_1", dt=0.05, clock="REALTIME")
    with client.open_session(options) as session:
        answer = session.skip(0)
        while not isinstance(answer, Rejection):
            answer = session._answer()
        assert answer.reason == "WRONG_CLOCK"
        session.close()


def _raw_stream(server: Any, requests: list[dynamics_pb2.StreamSessionRequest]) -> grpc.RpcError:
    with grpc.insecure_channel(server.address) as channel:
        stub = dynamics_pb2_grpc.DynamicsServiceStub(channel)
        with pytest.raises(grpc.RpcError) as caught:
            for _ in stub.StreamSession(iter(requests), timeout=30):
                pass
        return caught.value


def test_frame_before_open_is_failed_precondition(server: Any) -> None:
    error = _raw_stream(server, [dynamics_pb2.StreamSessionRequest(frame=dynamics_pb2.Frame(seq=0))])
    assert error.code() == grpc.StatusCode.FAILED_PRECONDITION
    assert error.details() == "the first message of a session must be `open`, got `frame`"


def test_second_open_is_invalid_argument(server: Any) -> None:
    open_ = SessionOptions(model_name="pendulum_1", dt=0.05).to_message()
    error = _raw_stream(server, [dynamics_pb2.StreamSessionRequest(open=open_)] * 2)
    assert error.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "open must be sent once" in error.details()


@pytest.mark.parametrize(
    ("options", "error", "text"),
    [
        (SessionOptions(model_name="no_such_model", dt=0.05), NotFound, "no_such_model"),
        (
            SessionOptions(model_name="pendulum_1", dt=0.0),
            InvalidArgument,
            "open.dt must be in (0, 10.0] seconds, got 0.0",
        ),
        (
            SessionOptions(model_name="pendulum_1", dt=0.06),
            InvalidArgument,
            "open.dt must be a whole multiple (>= 1) of the model's timestep 0.025 s, got 0.06",
        ),
        (
            SessionOptions(
                model_name="pendulum_1", dt=0.05, scenario="CONTROLLED", measured=("qpos", "qvel")
            ),
            InvalidArgument,
            "open.measured must include CHANNEL_CTRL in SCENARIO_CONTROLLED",
        ),
        (
            SessionOptions(model_name="pendulum_1", dt=0.05, history=20000),
            InvalidArgument,
            "open.history must be at most 10000 ticks, got 20000",
        ),
        (
            SessionOptions(model_name="pendulum_1", dt=0.05, horizon="HALF_ROUND_TRIP"),
            InvalidArgument,
            "needs open.clock CLOCK_REALTIME",
        ),
    ],
)
def test_bad_open_is_refused_with_a_precise_status(
    client: Any, options: SessionOptions, error: type, text: str
) -> None:
    with pytest.raises(error) as caught:
        client.open_session(options)
    assert text in str(caught.value)


def test_the_session_is_stored_as_parquet_and_indexed(server: Any, client: Any) -> None:
    model = _model("pendulum_3")
    truth = _trajectory(model, 12, 0.05, seed=5)
    options = SessionOptions(
        model_name="pendulum_3",
        dt=0.05,
        subject_id="patient-4711",
        subject_attributes={"side": "left", "age": "43"},
    )
    with client.open_session(options) as session:
        assert session.opened.dropped_attributes == ()
        for k, (q, v, _) in enumerate(truth):
            if k in (4, 5):
                session.skip(k)
            else:
                session.send_frame(FrameData(seq=k, t=k * 0.05, qpos=q, qvel=v))
        session_id = session.opened.session_id
        summary = session.close()
    data_root = Path(server.services.data_root)
    path = data_root / summary.location
    assert path.is_file() and path.suffix == ".parquet"
    assert "model=pendulum_3" in summary.location
    table = pq.read_table(path)
    results = [r for r in table.to_pylist() if r["kind"] == "result"]
    assert [r["seq"] for r in results] == list(range(12))
    assert [r["source"] for r in results].count("PREDICTED") == 2
    np.testing.assert_allclose(results[0]["frame_qpos"], truth[0][0])
    with sqlite3.connect(data_root / "index.sqlite") as db:
        row = db.execute(
            "SELECT status, ticks, measured, predicted, location, subject_pseudonym FROM sessions WHERE session_id = ?",
            (session_id,),
        ).fetchone()
    assert row[:5] == ("COMPLETE", 12, 10, 2, summary.location)
    assert len(row[5]) == 64 and "4711" not in row[5]


def test_hostile_values_are_rejected_or_survived_and_the_session_is_stored(client: Any) -> None:
    with client.open_session(SessionOptions(model_name="pendulum_1", dt=0.05)) as session:
        huge = session.send_frame(FrameData(seq=2**64 - 1, t=0.0, qpos=[0.1], qvel=[0.0]))
        assert isinstance(huge, Rejection) and huge.reason == "OUT_OF_ORDER" and huge.seq == 2**64 - 1
        absurd = session.send_frame(FrameData(seq=0, t=0.0, qpos=[1e300], qvel=[-1e300]))
        assert isinstance(absurd, TickResult)
        predicted = session.skip(1)
        assert isinstance(predicted, TickResult) and np.isfinite(predicted.qpos).all()
        summary = session.close()
    assert (summary.ticks, summary.rejected) == (2, 1) and summary.location.endswith(".parquet")
