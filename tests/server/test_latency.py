"""Latency compensation over real gRPC: predictions against the truth, the timewarp invariant,
REALTIME deadlines with delayed frames, and hostile estimator settings."""

from __future__ import annotations

import threading
import time
from typing import Any

import mujoco
import numpy as np
import pytest

from jitdyn.client import FrameData, Rejection, SessionOptions, SyncSample, TickResult
from jitdyn.errors import InvalidArgument
from jitdyn.registry import builtin_model_path


def _truth(name: str, ticks: int, dt: float, *, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    model = mujoco.MjModel.from_xml_path(str(builtin_model_path(name)))
    data = mujoco.MjData(model)
    data.qpos[:] = np.random.default_rng(seed).uniform(-0.6, 0.6, model.nq)
    steps = round(dt / model.opt.timestep)
    states = []
    for _ in range(ticks):
        states.append((data.qpos.copy(), data.qvel.copy()))
        for _ in range(steps):
            mujoco.mj_step(model, data)
    return states


def _gap_errors(
    client: Any, name: str, estimator: str, truth: list[tuple[np.ndarray, np.ndarray]]
) -> np.ndarray:
    """Max |q error| over every PREDICTED tick of 4-tick (200 ms) gaps every 10 ticks."""
    # The truth is passive: named, since a session that names no scenario gets DRIVEN on these
    # actuated pendulums.
    options = SessionOptions(model_name=name, scenario="PASSIVE", dt=0.05, estimator={"estimator": estimator})
    errors = []
    with client.open_session(options) as session:
        for k, (q, v) in enumerate(truth):
            if k >= 10 and k % 10 < 4:
                result = session.skip(k)
                assert isinstance(result, TickResult) and result.source == "PREDICTED"
                errors.append(np.max(np.abs(result.qpos - q)))
            else:
                result = session.send_frame(FrameData(seq=k, t=k * 0.05, qpos=q, qvel=v))
                assert isinstance(result, TickResult) and result.source == "MEASURED"
    return np.array(errors)


@pytest.mark.parametrize("name", ["pendulum_1", "pendulum_2", "pendulum_3"])
def test_ukf_predictions_track_the_truth_far_better_than_dead_reckoning(client: Any, name: str) -> None:
    truth = _truth(name, 60, 0.05, seed=7)
    ukf = _gap_errors(client, name, "UKF", truth)
    constant_velocity = _gap_errors(client, name, "CONSTANT_VELOCITY", truth)
    assert ukf.max() < 1e-2, ukf.max()
    assert ukf.max() < 0.1 * constant_velocity.max(), (ukf.max(), constant_velocity.max())


def _filter_states(
    client: Any, truth: list[tuple[np.ndarray, np.ndarray]], *, late: int | None, delay: int
) -> dict[int, TickResult]:
    options = SessionOptions(model_name="pendulum_3", dt=0.05, outputs=("INVERSE_DYNAMICS", "FILTER_STATE"))
    results: dict[int, TickResult] = {}
    with client.open_session(options) as session:
        for k, (q, v) in enumerate(truth):
            if k == late:
                results[k] = session.skip(k)  # type: ignore[assignment]
            else:
                answer = session.send_frame(FrameData(seq=k, t=k * 0.05, qpos=q, qvel=v))
                assert isinstance(answer, TickResult)
                results[k] = answer
            if late is not None and k == late + delay:
                q_late, v_late = truth[late]
                corrected = session.send_frame(FrameData(seq=late, t=late * 0.05, qpos=q_late, qvel=v_late))
                assert isinstance(corrected, TickResult)
                assert corrected.source == "CORRECTED" and corrected.late_ticks == delay + 1
                results[-1] = corrected
    return results


def test_timewarp_gives_the_state_of_a_frame_that_came_on_time(client: Any) -> None:
    truth = _truth("pendulum_3", 20, 0.05, seed=11)
    on_time = _filter_states(client, truth, late=None, delay=0)
    warped = _filter_states(client, truth, late=8, delay=4)
    assert warped[8].source == "PREDICTED"
    np.testing.assert_allclose(warped[-1].filter_state, on_time[8].filter_state, rtol=0, atol=1e-9)
    np.testing.assert_allclose(warped[-1].covariance, on_time[8].covariance, rtol=0, atol=1e-9)
    # Every tick after the late frame was applied continues from the state of the on-time run.
    for k in range(13, 20):
        np.testing.assert_allclose(warped[k].filter_state, on_time[k].filter_state, rtol=0, atol=1e-9)
        np.testing.assert_allclose(warped[k].covariance, on_time[k].covariance, rtol=0, atol=1e-9)


def test_realtime_answers_every_tick_by_its_deadline_while_frames_are_delayed(client: Any) -> None:
    dt, ticks, grace = 0.05, 40, 0.03
    truth = _truth("pendulum_2", ticks, dt, seed=2)
    delayed = {5, 6, 17, 30}  # these frames arrive 2.5 ticks late
    options = SessionOptions(model_name="pendulum_2", dt=dt, clock="REALTIME", grace=grace)
    with client.open_session(options) as session:
        # Clock exchanges first, as a real client does: the server then places client time on its
        # own clock however late `opened` reached the client.
        for _ in range(3):
            session.sync()
            time.sleep(0.005)
        timers = []
        for k, (q, v) in enumerate(truth):
            time.sleep(max(0.0, k * dt - session.now()))
            frame = FrameData(seq=k, t=k * dt, qpos=q, qvel=v)
            if k in delayed:
                timer = threading.Timer(2.5 * dt, session.send, args=(frame,))
                timer.start()
                timers.append(timer)
            else:
                session.send(frame)
        for timer in timers:
            timer.join()
        time.sleep(2 * dt)
        answers = session.poll()
        session.close()
    results = [a for a in answers if isinstance(a, TickResult)]
    offset = min((a for a in answers if isinstance(a, SyncSample)), key=lambda s: s.round_trip).offset
    assert not [a for a in answers if isinstance(a, Rejection)]
    first = {r.seq: r for r in results if r.source != "CORRECTED"}
    corrected = {r.seq for r in results if r.source == "CORRECTED"}
    assert sorted(first)[:ticks] == list(range(ticks))
    assert {first[k].source for k in delayed} == {"PREDICTED"}
    assert delayed <= corrected
    on_time = [k for k in range(ticks) if k not in delayed]
    assert sum(first[k].source == "MEASURED" for k in on_time) >= 0.8 * len(on_time)
    # On time: each answer left the server at its deadline (client time k dt + grace); allow for a
    # loaded 2-core machine in the tail, not in the median.
    lateness = [first[k].received_at - (session.clock_start + k * dt + grace) for k in range(ticks)]
    assert np.median(lateness) < 0.01 + abs(offset), np.median(lateness)
    assert max(lateness) < 0.1 + abs(offset), max(lateness)


@pytest.mark.parametrize(
    ("settings", "refused"),
    [
        ({"preset": "THESIS", "alpha": 0.001, "kappa": 3 - 6}, None),
        ({"q_var": 1e12}, None),
        ({"r": 0.0}, "r"),
        ({"alpha": -1.0}, "alpha"),
        ({"kappa": -100.0}, "kappa"),
    ],
)
def test_hostile_settings_never_crash_the_server(
    client: Any, settings: dict[str, float], refused: str | None
) -> None:
    truth = _truth("pendulum_3", 30, 0.05, seed=4)
    options = SessionOptions(model_name="pendulum_3", dt=0.05, estimator=settings)
    if refused is not None:
        with pytest.raises(InvalidArgument) as caught:
            client.open_session(options)
        assert refused in str(caught.value)
        return
    with client.open_session(options) as session:
        for k, (q, v) in enumerate(truth):
            answer = (
                session.skip(k)
                if k % 3 == 2
                else session.send_frame(FrameData(seq=k, t=k * 0.05, qpos=q, qvel=v))
            )
            assert isinstance(answer, TickResult)
            assert np.isfinite(answer.qpos).all() and np.isfinite(answer.qfrc_inverse).all()
        session.close()


FREE_BODY = """
<mujoco model="tumbler">
  <option gravity="0 0 0"/>
  <worldbody>
    <body name="box" pos="0 0 1"><freejoint name="root"/><geom type="box" size=".1 .2 .3" mass="1"/></body>
  </worldbody>
</mujoco>
"""


def test_a_free_joint_is_estimated_on_its_manifold(client: Any) -> None:
    """nq = 7, nv = 6: predictions keep a unit quaternion and follow a tumbling body."""
    model = mujoco.MjModel.from_xml_string(FREE_BODY)
    data = mujoco.MjData(model)
    data.qvel[:] = [0.1, 0.0, 0.0, 0.5, 1.0, 2.0]  # drifting and tumbling, no gravity
    truth = []
    for _ in range(30):
        truth.append((data.qpos.copy(), data.qvel.copy()))
        for _ in range(5):
            mujoco.mj_step(model, data)
    options = SessionOptions(
        inline_mjcf=FREE_BODY,
        inline_name="tumbler",
        dt=5 * model.opt.timestep,
        outputs=("INVERSE_DYNAMICS", "FILTER_STATE"),
    )
    with client.open_session(options) as session:
        assert session.opened.state_dimension == 12
        for k, (q, v) in enumerate(truth):
            if k >= 10 and k % 5 < 3:
                result = session.skip(k)
                assert isinstance(result, TickResult) and result.source == "PREDICTED"
                assert np.linalg.norm(result.qpos[3:7]) == pytest.approx(1.0, abs=1e-9)
                # The orientation error, as a rotation angle between the quaternions.
                angle = 2 * np.arccos(min(1.0, abs(float(np.dot(result.qpos[3:7], q[3:7])))))
                assert angle < 0.05, (k, angle)
                assert np.max(np.abs(result.qpos[:3] - q[:3])) < 1e-2
            else:
                result = session.send_frame(FrameData(seq=k, t=k * options.dt, qpos=q, qvel=v))
                assert isinstance(result, TickResult) and result.source == "MEASURED"
                assert result.filter_state.shape == (13,) and result.covariance.shape == (12, 12)
        session.close()


def test_thesis_weights_at_n_46_on_myohand_do_not_crash_the_server(client: Any) -> None:
    """kappa = 3 - n with alpha = 0.001 at n = 46: weights of order 1e7 (reference: indefinite
    covariances). The server repairs, guards, and keeps answering."""
    from jitdyn.client.myo import pack_myo_model

    mjcf, assets = pack_myo_model("myohand")
    model, _ = client.register_model(name="myohand", mjcf=mjcf, assets=assets)
    truth = mujoco.MjModel.from_xml_string(mjcf, assets)
    data = mujoco.MjData(truth)
    options = SessionOptions(
        model_name="myohand",
        dt=0.002,
        scenario="EXTERNAL",
        estimator={
            "preset": "THESIS",
            "sigma_points": "MERWE",
            "alpha": 0.001,
            "beta": 2.0,
            "kappa": 3.0 - 46,
        },
    )
    with client.open_session(options) as session:
        assert session.opened.state_dimension == 46
        for k in range(40):
            data.ctrl[:] = 0.5 * (1 + np.sin(0.3 * k + np.arange(truth.nu)))
            if k % 4 == 3:
                answer = session.skip(k)
            else:
                answer = session.send_frame(FrameData(seq=k, t=k * 0.002, qpos=data.qpos, qvel=data.qvel))
            assert isinstance(answer, TickResult)
            assert np.isfinite(answer.qpos).all() and np.isfinite(answer.qfrc_inverse).all()
            mujoco.mj_step(truth, data)
        summary = session.close()
    assert summary.ticks == 40
    # The server is fine: the next session opens and answers.
    with client.open_session(SessionOptions(model_id=model.id, dt=0.002, scenario="EXTERNAL")) as session:
        assert isinstance(
            session.send_frame(FrameData(seq=0, t=0.0, qpos=data.qpos, qvel=data.qvel)), TickResult
        )
