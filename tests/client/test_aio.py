"""The asyncio SDK against a real server: LOCKSTEP and REALTIME sessions, the registry, errors."""

from __future__ import annotations

import asyncio
import math
from typing import Any

import numpy as np
import pytest

from jitdyn.client import AsyncClient, FrameData, Rejection, SessionOptions, SyncSample, TickResult
from jitdyn.errors import FailedPrecondition, InvalidArgument, NotFound
from jitdyn.v1 import dynamics_pb2

SLIDER = '<mujoco><worldbody><body><joint name="x" type="slide"/><geom size=".1" mass="1"/></body></worldbody></mujoco>'


def test_lockstep_frame_skip_late_frame_rejection_and_summary(server: Any) -> None:
    async def run() -> None:
        async with AsyncClient(server.address, timeout=60) as client:
            await client.wait_ready()
            options = SessionOptions(model_name="pendulum_1", dt=0.05)
            async with await client.open_session(options) as session:
                assert session.opened.model.name == "pendulum_1" and session.opened.steps_per_tick == 2
                written: list[dynamics_pb2.StreamSessionRequest] = []
                write = session._call.write

                async def spy(request: dynamics_pb2.StreamSessionRequest) -> None:
                    written.append(request)
                    await write(request)

                session._call.write = spy  # type: ignore[method-assign]

                first = await session.send_frame(FrameData(seq=0, t=0.0, qpos=[0.3], qvel=[0.0]))
                assert isinstance(first, TickResult), first
                assert (first.seq, first.source, first.frame_received) == (0, "MEASURED", True)
                np.testing.assert_array_equal(first.qpos, [0.3])
                assert first.qfrc_inverse.shape == (1,) and not first.qfrc_inverse.flags.writeable
                assert written[0].frame.HasField("checksum")  # the contract's CRC32C, computed by the SDK

                for seq in (1, 2):
                    predicted = await session.skip(seq)
                    assert isinstance(predicted, TickResult) and predicted.source == "PREDICTED"
                    assert predicted.seq == seq and not predicted.frame_received

                late = await session.send_frame(FrameData(seq=1, t=0.05, qpos=[0.25], qvel=[0.0]))
                assert isinstance(late, TickResult), late
                assert (late.source, late.late_ticks) == ("CORRECTED", 2)

                bad = await session.send_frame(FrameData(seq=3, t=0.15, qpos=[0.2, 0.1], qvel=[0.0]))
                assert bad == Rejection(
                    seq=3, reason="BAD_SHAPE", message="frame 3: qpos must have 1 values, got 2"
                )

                after = await session.send_frame(FrameData(seq=3, t=0.15, qpos=[0.2], qvel=[0.0]))
                assert isinstance(after, TickResult) and after.source == "MEASURED"

                summary = await session.close()
                assert await session.close() == summary  # safe twice
                with pytest.raises(FailedPrecondition, match="the session is closed"):
                    await session.skip(4)
            assert (
                summary.ticks,
                summary.measured,
                summary.predicted,
                summary.corrected,
                summary.rejected,
            ) == (4, 2, 2, 1, 1)
            assert summary.late == 1 and "model=pendulum_1" in summary.location
            stored = await client.get_session(session.opened.session_id)
            assert stored.summary.ticks == 4
            assert session.opened.session_id in [s.session_id async for s in client.list_sessions()]
        await client.close()  # safe twice

    asyncio.run(run())


def test_realtime_one_result_per_tick_and_clock_sync(server: Any) -> None:
    dt, ticks = 0.05, 20

    async def run() -> tuple[list[TickResult | Rejection | SyncSample], int]:
        async with AsyncClient(server.address, timeout=60) as client:
            options = SessionOptions(model_name="pendulum_1", dt=dt, clock="REALTIME")
            async with await client.open_session(options) as session:

                async def produce() -> None:
                    for k in range(ticks):
                        await asyncio.sleep(max(0.0, k * dt - session.now()))
                        await session.send(
                            FrameData(seq=k, t=k * dt, qpos=[0.2 * math.cos(k * dt)], qvel=[0.0])
                        )

                async def consume() -> list[TickResult | Rejection | SyncSample]:
                    answers: list[TickResult | Rejection | SyncSample] = []
                    async for answer in session.results(timeout=10):
                        answers.append(answer)
                        if isinstance(answer, TickResult) and answer.seq == ticks - 1:
                            break
                    return answers

                _, answers = await asyncio.gather(produce(), consume())
                summary = await session.close()
        return answers, summary.ticks

    answers, stored_ticks = asyncio.run(run())
    on_time = [a for a in answers if isinstance(a, TickResult) and a.source != "CORRECTED"]
    assert [r.seq for r in on_time] == list(range(ticks))
    assert sum(r.source == "MEASURED" for r in on_time) >= ticks // 2
    assert not [a for a in answers if isinstance(a, Rejection)]
    assert stored_ticks >= ticks
    samples = [a for a in answers if isinstance(a, SyncSample)]
    assert len(samples) >= 2  # the probe at open, and one sent with the frames after sync_interval
    assert all(abs(s.offset) < 0.05 and 0.0 <= s.round_trip < 0.5 for s in samples)
    # The server completes an exchange only from the receive time the next probe reports.
    assert samples[-1].server_round_trip > 0.0


def test_register_get_and_list_models(server: Any) -> None:
    async def run() -> None:
        async with AsyncClient(server.address) as client:
            model, created = await client.register_model(
                name="aio_slider", mjcf=SLIDER, description="a slide joint", tags=("aio-test",)
            )
            assert created and (model.name, model.version, model.nq, model.joint_names) == (
                "aio_slider",
                1,
                1,
                ("x",),
            )
            again, created_again = await client.register_model(name="aio_slider", mjcf=SLIDER)
            assert (again.id, created_again) == (model.id, False)
            assert await client.get_model(name="aio_slider") == model
            message = await client.get_model_message(model_id=model.id)
            assert message.metadata.description == "a slide joint"
            assert [m.id async for m in client.list_models(tag="aio-test")] == [model.id]
            names = [m.name async for m in client.list_models(page_size=1)]  # one page per model
            assert {"aio_slider", "pendulum_1", "pendulum_2", "pendulum_3"} <= set(names)
            assert len(names) == len(set(names))

    asyncio.run(run())


def test_errors_are_jitdyn_exceptions_with_the_servers_message(server: Any) -> None:
    async def run() -> None:
        async with AsyncClient(server.address) as client:
            with pytest.raises(NotFound) as caught:
                await client.get_model(name="no_such_model")
            assert str(caught.value).startswith(
                "no model is named 'no_such_model'; the registered models are "
            )
            with pytest.raises(NotFound) as opening:
                await client.open_session(SessionOptions(model_name="no_such_model", dt=0.05))
            assert "no model is named 'no_such_model'" in str(opening.value)
            with pytest.raises(InvalidArgument, match=r"open.dt must be in \(0, 10.0\] seconds, got 0.0"):
                await client.open_session(SessionOptions(model_name="pendulum_1", dt=0.0))
            with pytest.raises(InvalidArgument, match="clock must be one of"):
                await client.open_session(SessionOptions(model_name="pendulum_1", clock="SOMETIMES"))

    asyncio.run(run())


def test_an_exception_inside_the_session_cancels_it(server: Any) -> None:
    async def run() -> None:
        async with AsyncClient(server.address) as client:
            with pytest.raises(RuntimeError, match="caller's failure"):
                async with await client.open_session(
                    SessionOptions(model_name="pendulum_1", dt=0.05)
                ) as session:
                    await session.send_frame(FrameData(seq=0, t=0.0, qpos=[0.1], qvel=[0.0]))
                    raise RuntimeError("caller's failure")
            with pytest.raises(FailedPrecondition, match="the session ended without a summary"):
                await session.close()
            assert session._reader.done()

    asyncio.run(run())


def test_answers_that_arrive_while_close_waits_are_kept(server: Any) -> None:
    """As the sync client: the ticks the server answers as it closes come out of `results`."""

    async def run() -> list[int]:
        async with AsyncClient(server.address, timeout=30) as client:
            options = SessionOptions(model_name="pendulum_1", dt=0.05, clock="REALTIME")
            session = await client.open_session(options)
            for k in range(10):
                await session.send(FrameData(seq=k, t=k * 0.05, qpos=[0.3], qvel=[0.0]))
            await session.close()
            return sorted({a.seq async for a in session.results(timeout=1) if isinstance(a, TickResult)})

    assert asyncio.run(run()) == list(range(10))
