"""benchmarks/linearised.py's reference EKF on a free body: its mean is the process model's own
steps on the manifold, its covariance the tick's tangent Jacobian, and its guard restarts it from
a frame whose NIS stays far out, as the UKF's does. The benchmark itself runs for minutes."""

from __future__ import annotations

import importlib
from pathlib import Path
from types import ModuleType

import mujoco
import numpy as np
import pytest

from jitdyn.server.estimation.config import resolve_config
from jitdyn.server.estimation.interface import Measurement
from jitdyn.server.estimation.propagate import process_model
from jitdyn.vocabulary import Scenario

ROOT = Path(__file__).resolve().parents[2]
BALL = """
<mujoco>
  <option timestep="0.002"/>
  <worldbody>
    <body name="ball" pos="0 0 1">
      <freejoint/>
      <geom type="sphere" size="0.1" mass="1" contype="0" conaffinity="0"/>
    </body>
  </worldbody>
</mujoco>
"""
DT = 0.01


@pytest.fixture
def linearised(monkeypatch: pytest.MonkeyPatch) -> ModuleType:
    monkeypatch.syspath_prepend(str(ROOT))  # benchmarks/ is a folder of the checkout, not installed
    return importlib.import_module("benchmarks.linearised")


def make(linearised: ModuleType, first: Measurement) -> tuple[mujoco.MjModel, object]:
    model = mujoco.MjModel.from_xml_string(BALL)
    config = resolve_config(
        model=model,
        scenario=Scenario.EXTERNAL,
        dt=DT,
        requested={"forecast": "FILTER", "noise_model": "FIXED"},
        model_defaults={},
        measured={"qpos", "qvel"},
    )
    return model, linearised.LinearisedFilter(model, config, first)


def spinning() -> Measurement:
    quat = np.array([np.cos(0.3), np.sin(0.3), 0.0, 0.0])
    return Measurement(qpos=np.concatenate([[0.1, -0.2, 1.0], quat]), qvel=np.array([0.5, 0, 0.2, 0, 0, 0.0]))


def test_the_mean_is_the_process_models_steps_on_the_manifold(linearised: ModuleType) -> None:
    model, ekf = make(linearised, spinning())
    q = ekf.predict()
    own = process_model(model, scenario=Scenario.EXTERNAL)
    d = mujoco.MjData(own)
    d.qpos[:], d.qvel[:] = spinning().qpos, spinning().qvel
    mujoco.mj_step(own, d, round(DT / model.opt.timestep))
    np.testing.assert_allclose(q, d.qpos, atol=1e-12)
    assert q.shape == (7,) and ekf.P.shape == (12, 12)
    assert abs(np.linalg.norm(q[3:]) - 1.0) < 1e-12


def test_the_covariance_follows_the_tangent_jacobian(linearised: ModuleType) -> None:
    # A free sphere without angular velocity: over a tick T, a position (angle) moves by T times
    # its velocity's perturbation, so P0 = p I gives p (1 + T^2) + Q on each position's diagonal.
    first = Measurement(qpos=spinning().qpos, qvel=np.zeros(6))
    _, ekf = make(linearised, first)
    p0, q = ekf.P0[0, 0], ekf.Q.copy()
    ekf.predict()
    expected = p0 * (1.0 + DT**2) + np.diagonal(q)[:6]
    np.testing.assert_allclose(np.diagonal(ekf.P)[:6], expected, rtol=1e-5)
    np.testing.assert_allclose(ekf.P[:6, 6:], np.diag(np.full(6, p0 * DT)) + q[:6, 6:], rtol=1e-4, atol=1e-9)


def test_a_frame_far_out_twice_restarts_it_from_the_frame(linearised: ModuleType) -> None:
    _, ekf = make(linearised, spinning())
    for side in (1.0, -1.0):  # each frame 3 m off the filter's x in its own direction
        far = Measurement(qpos=spinning().qpos + np.array([3.0 * side, 0, 0, 0, 0, 0, 0]), qvel=np.zeros(6))
        ekf.predict()
        ekf.update(far)
        assert ekf.restarts == (side < 0)
    np.testing.assert_array_equal(ekf.x[:7], far.qpos)
    np.testing.assert_array_equal(ekf.P, ekf.P0)
