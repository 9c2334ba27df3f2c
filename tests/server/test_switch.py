"""A PASSIVE filter on a driven body becomes DRIVEN when its NIS window says the model is wrong
(estimation/switch.py); on a passive body, and with the thesis' preset, it never does (issue 10)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import pytest

from jitdyn.client import FrameData, SessionOptions, TickResult
from jitdyn.server.estimation.config import resolve_config
from jitdyn.server.estimation.factory import make_estimator
from jitdyn.server.estimation.interface import Measurement
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.estimation.switch import WINDOW, SwitchingFilter

MODELS = Path(__file__).resolve().parents[2] / "models"


def _pendulum(n: int) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(MODELS / f"pendulum_{n}.xml"))


def _frames(model: mujoco.MjModel, ticks: int, *, amplitude: float) -> list[Measurement]:
    """A pendulum moved by its motors (a torque held over each 50 ms tick), or swinging freely."""
    d = mujoco.MjData(model)
    d.qpos[:] = 0.4
    steps = round(0.05 / model.opt.timestep)
    out = [Measurement(qpos=d.qpos.copy(), qvel=d.qvel.copy())]
    for k in range(1, ticks):
        d.ctrl[:] = amplitude * np.sin(0.25 * k + np.arange(model.nu))
        mujoco.mj_step(model, d, steps)
        out.append(Measurement(qpos=d.qpos.copy(), qvel=d.qvel.copy()))
    return out


def _config(model: mujoco.MjModel, preset: str = "JITDYN") -> Any:
    return resolve_config(
        model=model,
        scenario="PASSIVE",
        dt=0.05,
        requested={},
        model_defaults={},
        preset=preset,
        measured={"qpos", "qvel"},
    )


def test_a_passive_filter_on_a_driven_body_becomes_driven_after_one_window() -> None:
    model = _pendulum(2)
    frames = _frames(model, 80, amplitude=4.0)
    with WorkerPool(1) as pool:
        estimator = make_estimator(model, _config(model), pool=pool)
        assert isinstance(estimator, SwitchingFilter)
        assert estimator.state_dimension == 4
        estimator.initialise(frames[0])
        absorbed, errors = [], []
        for k in range(1, len(frames)):
            estimator.predict(ctrl=None)
            estimate = estimator.update(frames[k])
            absorbed.append(estimate.absorbed)
            assert estimate.scenario == ("DRIVEN" if k >= WINDOW else "PASSIVE")
            errors.append(float(np.max(np.abs(estimate.qpos - frames[k].qpos))))
        assert estimator.switched and estimator.state_dimension == 6
    # The window is full at update WINDOW; the NIS of a PASSIVE pendulum under 4 N m is far out.
    # (Later `absorbed` ticks are the DRIVEN filter's own adaptive noise widening its covariance.)
    assert absorbed.index(True) == WINDOW - 1
    # Then the DRIVEN filter follows the frames once its R has learnt these perfect ones (8 fourth
    # differences; measured: 0.03-0.05 rad for four updates, then 1e-5).
    assert max(errors[2 * WINDOW :]) < 1e-3, errors


@pytest.mark.parametrize("preset", ["JITDYN", "THESIS"])
def test_a_passive_filter_on_a_passive_body_never_switches(preset: str) -> None:
    model = _pendulum(3)
    frames = _frames(model, 300, amplitude=0.0)
    with WorkerPool(1) as pool:
        estimator = make_estimator(model, _config(model, preset), pool=pool)
        assert isinstance(estimator, SwitchingFilter) == (preset == "JITDYN")
        estimator.initialise(frames[0])
        for k in range(1, len(frames)):
            estimator.predict(ctrl=None)
            if k % 10 in (1, 2, 3):
                continue  # gaps too
            estimate = estimator.update(frames[k])
            assert not estimate.absorbed and estimate.scenario == "PASSIVE"


def test_the_thesis_preset_on_a_driven_body_stays_passive() -> None:
    model = _pendulum(2)
    frames = _frames(model, 60, amplitude=4.0)
    with WorkerPool(1) as pool:
        estimator = make_estimator(model, _config(model, "THESIS"), pool=pool)
        estimator.initialise(frames[0])
        for k in range(1, len(frames)):
            estimator.predict(ctrl=None)
            estimate = estimator.update(frames[k])
            assert estimate.scenario == "PASSIVE" and not estimate.absorbed


def test_a_replay_from_before_the_switch_switches_again_the_same_way() -> None:
    """The timewarp: a snapshot before the switch restores the PASSIVE filter, and replaying the
    same frames gives the same switch and the same states, bit for bit."""
    model = _pendulum(2)
    frames = _frames(model, 30, amplitude=4.0)
    with WorkerPool(1) as pool:
        estimator = make_estimator(model, _config(model), pool=pool)
        assert isinstance(estimator, SwitchingFilter)
        estimator.initialise(frames[0])
        for k in range(1, 4):
            estimator.predict(ctrl=None)
            estimator.update(frames[k])
        snap = estimator.snapshot()
        runs = []
        for _ in range(2):
            estimator.restore(snap)
            assert not estimator.switched
            states = []
            for k in range(4, len(frames)):
                estimator.predict(ctrl=None)
                states.append(estimator.update(frames[k]).state.copy())
            runs.append(states)
            assert estimator.switched
    for a, b in zip(*runs, strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_session_opened_passive_on_a_driven_body_says_it_became_driven(client: Any) -> None:
    model = _pendulum(2)
    frames = _frames(model, 30, amplitude=4.0)
    options = SessionOptions(model_name="pendulum_2", scenario="PASSIVE", dt=0.05, outputs=("FILTER_STATE",))
    with client.open_session(options) as session:
        assert session.opened.scenario == "PASSIVE"
        assert session.opened.estimator["wrong_model"] == "DRIVEN"
        results = []
        for k, m in enumerate(frames):
            result = session.send_frame(FrameData(seq=k, t=k * 0.05, qpos=m.qpos, qvel=m.qvel))
            assert isinstance(result, TickResult)
            results.append(result)
    switched = [k for k, r in enumerate(results) if r.absorbed]
    assert switched[0] == WINDOW  # tick 0 initialises; updates 1..WINDOW fill the window
    assert all(r.scenario == "PASSIVE" for r in results[:WINDOW])
    assert all(r.scenario == "DRIVEN" and r.filter_state.size == 6 for r in results[WINDOW:])


@pytest.mark.parametrize("wrong_model", [None, "KEEP"])
def test_a_controlled_session_that_lost_the_body_over_a_gap_starts_again(
    client: Any, wrong_model: str | None
) -> None:
    """CONTROLLED pendulum_2, LOCKSTEP: over a gap of 4 skipped ticks the body's motors push hard
    while the server holds the last control it was told (none). The frames after the gap are far
    from the filter's prediction; by default (the JITDYN preset's WRONG_MODEL_RESTART) the filter
    starts again from the second of them and then tracks the frames, where KEEP still lags."""
    model = _pendulum(2)
    steps = round(0.05 / model.opt.timestep)
    d = mujoco.MjData(model)
    d.qpos[:] = 0.4
    settings = {} if wrong_model is None else {"wrong_model": wrong_model}
    options = SessionOptions(
        model_name="pendulum_2",
        scenario="CONTROLLED",
        dt=0.05,
        clock="LOCKSTEP",
        measured=("qpos", "qvel", "ctrl"),
        estimator=settings,
        outputs=("FILTER_STATE",),
    )
    gap = range(10, 14)
    with client.open_session(options) as session:
        assert session.opened.estimator["wrong_model"] == (wrong_model or "RESTART")
        restarts, errors = [], []
        for k in range(24):
            ctrl = np.full(model.nu, 3.0) if k >= gap.start else np.zeros(model.nu)
            if k in gap:
                result = session.skip(k)
            else:
                frame = FrameData(
                    seq=k, t=k * 0.05, qpos=d.qpos.copy(), qvel=d.qvel.copy(), ctrl=d.ctrl.copy()
                )
                result = session.send_frame(frame)
                if k >= gap.stop:
                    restarts.append(result.reinitialised)
                    errors.append(float(np.max(np.abs(np.asarray(result.filter_state)[: model.nq] - d.qpos))))
            assert isinstance(result, TickResult)
            d.ctrl[:] = ctrl  # held over the next tick, which the next frame reports
            mujoco.mj_step(model, d, steps)
    if wrong_model is None:
        # NIS after the gap 270, 17, 66, 83 (chi-square(4)'s 0.999 quantile: 18.5): restarted at
        # the fourth frame, then NIS 0.1 and below.
        assert any(restarts[:4]) and not any(restarts[4:]), restarts
        assert max(errors[5:]) < 0.01, errors
    else:
        assert not any(restarts), restarts  # NIS 20-80 for ten frames: past the divergence guard's reach
        assert max(errors[5:]) > 0.05, errors
