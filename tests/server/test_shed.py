"""Shedding a tick: what an overloaded REALTIME server answers on time instead of late, without
running the estimator, and how the session carries on (server/runtime/session.py `shed`)."""

from __future__ import annotations

import mujoco
import numpy as np

from jitdyn.registry import builtin_model_path
from jitdyn.server.estimation.config import resolve_config
from jitdyn.server.estimation.dynamics import Dynamics
from jitdyn.server.estimation.factory import make_estimator
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.runtime.frames import FrameIn
from jitdyn.server.runtime.session import Place, SessionRuntime
from jitdyn.vocabulary import Scenario, Source

DT = 0.05


def _frames(model: mujoco.MjModel, ticks: int) -> list[FrameIn]:
    data = mujoco.MjData(model)
    data.qpos[:] = [0.5, -0.3, 0.2]
    steps = round(DT / model.opt.timestep)
    frames = []
    for k in range(ticks):
        frames.append(
            FrameIn(
                seq=k,
                t=k * DT,
                qpos=data.qpos.copy(),
                qvel=data.qvel.copy(),
                qacc=None,
                ctrl=None,
                sensordata=None,
                received=k * DT,
            )
        )
        for _ in range(steps):
            mujoco.mj_step(model, data)
    return frames


def _runtime(model: mujoco.MjModel, pool: WorkerPool) -> SessionRuntime:
    """A PASSIVE session's runtime with the JITDYN preset's filter, a history of 50 ticks."""
    config = resolve_config(
        model=model,
        scenario=Scenario.PASSIVE,
        dt=DT,
        requested={},
        model_defaults={},
        preset="JITDYN",
        measured={"qpos", "qvel"},
    )
    return SessionRuntime(
        model=model,
        estimator=make_estimator(model, config, pool=pool),
        dynamics=Dynamics(model, outputs=frozenset({"INVERSE_DYNAMICS"})),
        dt=DT,
        scenario=Scenario.PASSIVE,
        history=50,
    )


def test_a_shed_tick_answers_from_the_frame_or_the_last_answer_and_the_session_recovers() -> None:
    model = mujoco.MjModel.from_xml_path(str(builtin_model_path("pendulum_3")))
    frames = _frames(model, 14)
    with WorkerPool(1) as pool:
        runtime = _runtime(model, pool)
        for k in range(4):
            assert not runtime.advance(frames[k]).late_compute
        predicted = runtime.advance(None)  # tick 4, the estimator's own prediction
        assert predicted.source == Source.PREDICTED and not predicted.late_compute

        # Tick 5 shed without a frame: tick 4's answer repeated, nothing computed.
        repeated = runtime.shed(None)
        assert (repeated.seq, repeated.source, repeated.late_compute) == (5, Source.PREDICTED, True)
        np.testing.assert_array_equal(repeated.qpos, predicted.qpos)
        assert repeated.t == 5 * DT
        # The shed tick stays in the history: a late frame may still repair it.
        assert runtime.classify(4) == Place.LATE and runtime.classify(5) == Place.LATE
        # The estimator is behind until then: tick 6 without a frame is shed too, even through `advance`.
        assert runtime.advance(None).late_compute

        # Tick 5's frame, late: the timewarp replays ticks 5 and 6 properly, and the estimator is
        # where it would be had nothing been shed.
        corrected = runtime.apply_late(frames[5])
        assert (corrected.source, corrected.late_ticks) == (Source.CORRECTED, 2)
        ahead = runtime.advance(None)  # tick 7
        assert ahead.source == Source.PREDICTED and not ahead.late_compute
        assert np.max(np.abs(ahead.qpos - frames[7].qpos)) < 0.05

        # Shed with a frame: MEASURED from the frame, the estimator re-initialised from it.
        measured = runtime.shed(frames[8])
        assert (measured.source, measured.late_compute) == (Source.MEASURED, True)
        assert measured.estimate is not None and measured.estimate.reinitialised
        np.testing.assert_array_equal(measured.qpos, frames[8].qpos)
        # From there the estimator runs again, on time, and predicts near the truth.
        assert not runtime.advance(frames[9]).late_compute
        ahead = runtime.advance(None)
        assert ahead.source == Source.PREDICTED and not ahead.late_compute
        assert np.max(np.abs(ahead.qpos - frames[10].qpos)) < 0.05

        counts = runtime.counts
        assert (counts.ticks, counts.late_compute, counts.corrected) == (11, 3, 1)
        assert (counts.measured, counts.predicted) == (6, 5)


def test_shedding_before_the_first_frame_answers_the_rest_pose() -> None:
    model = mujoco.MjModel.from_xml_path(str(builtin_model_path("pendulum_1")))
    with WorkerPool(1) as pool:
        runtime = _runtime(model, pool)
        first = runtime.shed(None)
        assert (first.seq, first.source, first.late_compute) == (0, Source.PREDICTED, True)
        np.testing.assert_array_equal(first.qpos, model.qpos0)


def test_after_skipped_ticks_late_frames_reach_back_only_to_the_first_tick_after_them() -> None:
    """A server far behind skips ticks (answers them not at all) and drops the history with them:
    a late frame for a tick before the skip is too old, and the runtime says from which tick late
    frames apply again, which the server's TOO_OLD message names (it used to name the start of a
    history that was gone)."""
    model = mujoco.MjModel.from_xml_path(str(builtin_model_path("pendulum_3")))
    frames = _frames(model, 12)
    with WorkerPool(1) as pool:
        runtime = _runtime(model, pool)
        for k in range(4):
            runtime.advance(frames[k] if k != 2 else None)
        assert runtime.oldest_late_tick == 0 and runtime.classify(2) == Place.LATE
        runtime.skip(3)  # ticks 4, 5 and 6: never answered
        assert runtime.next_tick == 7 and runtime.counts.skipped == 3
        assert runtime.oldest_late_tick == 7
        assert runtime.classify(2) == Place.TOO_OLD and runtime.classify(5) == Place.TOO_OLD
        runtime.advance(None)  # tick 7, shed: the estimator is behind until a frame comes
        runtime.advance(frames[8])
        assert runtime.oldest_late_tick == 7 and runtime.classify(7) == Place.LATE
