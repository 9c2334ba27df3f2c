"""The fast engine (server/estimation/fast.py) against filterpy's (server/estimation/batched.py):
one UnscentedFilter each, the same config but the engine, the same frames and gaps."""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np
import pytest

from jitdyn.server.estimation.config import Engine, EstimatorConfig
from jitdyn.server.estimation.fast import FastUKF
from jitdyn.server.estimation.interface import Measurement
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.estimation.ukf import UnscentedFilter
from tests.server.test_ukf import BALL_PENDULUM, config_for, pendulum, simulate, swing

# Ticks without their frame: single ticks, a gap of three, and one long enough for DRIVEN's
# gap handling (the combination's answers, the widened prior).
SKIPPED = {3, 4, 9, 15, 16, 17, 30, 31, 32, 33, 34, 35}


def run(model: mujoco.MjModel, config: EstimatorConfig, frames: list[Measurement]) -> list[np.ndarray]:
    """Every estimate's state, covariance and NIS, a second frame for tick 20 included."""
    out: list[np.ndarray] = []
    with WorkerPool(1) as pool:
        estimator = UnscentedFilter(model, config, pool=pool)
        estimator.initialise(frames[0])
        for k in range(1, len(frames)):
            estimate = estimator.predict(ctrl=frames[k].ctrl)
            if k not in SKIPPED:
                estimate = estimator.update(frames[k])
                if k == 20:
                    estimate = estimator.update(frames[k])
            nis = np.array([np.nan if estimate.nis is None else estimate.nis])
            out += [np.array(estimate.state), np.array(estimate.covariance), nis]
        extrapolated = estimator.extrapolate(2 * config.dt)
        out += [np.array(extrapolated.state), np.array(extrapolated.covariance)]
    return out


def frames_of(model: mujoco.MjModel, config: EstimatorConfig) -> list[Measurement]:
    if model.nq != model.nv:  # the ball pendulum, swinging and twisting
        d = mujoco.MjData(model)
        d.qpos[:] = [np.cos(0.4), np.sin(0.4), 0.0, 0.0]
        d.qvel[:] = [0.0, 0.5, 1.5]
        frames = []
        for _ in range(40):
            frames.append(Measurement(qpos=d.qpos.copy(), qvel=d.qvel.copy()))
            mujoco.mj_step(model, d, config.steps_per_tick)
        return frames
    qpos0 = np.array([0.8, -0.4])
    frames = simulate(model, 40, config.steps_per_tick, qpos0=qpos0, control=lambda k: swing(k)[:2])
    if config.scenario == "CONTROLLED":
        return frames
    return [Measurement(qpos=f.qpos, qvel=f.qvel) for f in frames]


@pytest.mark.parametrize(
    ("model_name", "scenario", "sigma_points"),
    [
        ("pendulum", "PASSIVE", "MERWE"),
        ("pendulum", "CONTROLLED", "MERWE"),
        ("pendulum", "EXTERNAL", "MERWE"),
        ("pendulum", "DRIVEN", "MERWE"),
        ("pendulum", "PASSIVE", "SIMPLEX"),
        ("pendulum", "EXTERNAL", "UNIFORM"),
        ("ball", "PASSIVE", "MERWE"),
        ("ball", "CONTROLLED", "MERWE"),
        ("ball", "EXTERNAL", "SIMPLEX"),
        ("ball", "DRIVEN", "MERWE"),
    ],
)
def test_fast_engine_equals_filterpys(model_name: str, scenario: str, sigma_points: str) -> None:
    """Same sigma scheme and inputs: the same states, covariances and NIS to 1e-9 (rtol and atol);
    on plain vector states the operations are filterpy's own, in its order."""
    model = pendulum(2) if model_name == "pendulum" else mujoco.MjModel.from_xml_string(BALL_PENDULUM)
    fast = dataclasses.replace(config_for(model, scenario, sigma_points=sigma_points), engine=Engine.FAST)
    reference = dataclasses.replace(fast, engine=Engine.FILTERPY)
    frames = frames_of(model, fast)
    with WorkerPool(1) as pool:
        assert isinstance(UnscentedFilter(model, fast, pool=pool)._kf.inner, FastUKF)
        assert not isinstance(UnscentedFilter(model, reference, pool=pool)._kf.inner, FastUKF)
    got, expected = run(model, fast, frames), run(model, reference, frames)
    for i, (a, b) in enumerate(zip(got, expected, strict=True)):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9, err_msg=f"output {i}")
    if model_name == "pendulum":
        for a, b in zip(got, expected, strict=True):
            np.testing.assert_array_equal(a, b)


def test_the_thesis_preset_keeps_filterpy() -> None:
    model = pendulum(2)
    assert config_for(model, "PASSIVE", preset="THESIS").engine == Engine.FILTERPY
    assert config_for(model, "PASSIVE").engine == Engine.NATIVE
