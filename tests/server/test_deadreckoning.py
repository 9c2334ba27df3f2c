"""The IEEE 1278 dead-reckoning baselines (server/estimation/deadreckoning.py)."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from jitdyn.errors import FailedPrecondition, InvalidArgument
from jitdyn.server.estimation.config import EstimatorConfig, resolve_config
from jitdyn.server.estimation.deadreckoning import DeadReckoning
from jitdyn.server.estimation.interface import Measurement

# Two slides: generalized coordinates are plain positions, so every formula can be checked exactly.
SLIDES = """
<mujoco>
  <option timestep="0.01"/>
  <worldbody>
    <body>
      <joint name="x" type="slide" axis="1 0 0"/>
      <joint name="y" type="slide" axis="0 1 0"/>
      <geom type="sphere" size="0.1" mass="1"/>
    </body>
  </worldbody>
  <actuator><motor joint="x"/></actuator>
</mujoco>
"""

# The same slides, x limited to [-1, 1.2] and y to [-2.5, -1.9]; a hinge z limited to [0, 1] beside them.
LIMITED = """
<mujoco>
  <option timestep="0.01"/>
  <worldbody>
    <body>
      <joint name="x" type="slide" axis="1 0 0" range="-1 1.2"/>
      <joint name="y" type="slide" axis="0 1 0" range="-2.5 -1.9"/>
      <geom type="sphere" size="0.1" mass="1"/>
      <body>
        <joint name="z" type="hinge" axis="0 0 1" range="0 1"/>
        <geom type="sphere" size="0.1" mass="1"/>
      </body>
    </body>
  </worldbody>
</mujoco>
"""

FREE_BODY = """
<mujoco>
  <option timestep="0.01"/>
  <worldbody>
    <body><freejoint/><geom type="box" size="0.3 0.2 0.1" mass="1"/></body>
  </worldbody>
</mujoco>
"""


def config(
    kind: str,
    *,
    scenario: str = "PASSIVE",
    measured: frozenset[str] = frozenset({"qpos", "qvel", "qacc"}),
    xml: str = SLIDES,
) -> tuple[mujoco.MjModel, EstimatorConfig]:
    model = mujoco.MjModel.from_xml_string(xml)
    return model, resolve_config(
        model=model,
        scenario=scenario,
        dt=0.05,
        requested={"estimator": kind},
        model_defaults={},
        preset="JITDYN",
        measured=measured,
    )


Q0, V0, A0 = np.array([1.0, -2.0]), np.array([0.5, 0.25]), np.array([-1.0, 4.0])
FRAME = Measurement(qpos=Q0, qvel=V0, qacc=A0)


@pytest.mark.parametrize(
    ("kind", "qpos", "qvel", "qacc"),
    [
        ("STATIC", lambda t: Q0, lambda t: V0, lambda t: A0),
        ("CONSTANT_VELOCITY", lambda t: Q0 + V0 * t, lambda t: V0, lambda t: 0 * A0),
        (
            "CONSTANT_ACCELERATION",
            lambda t: Q0 + V0 * t + 0.5 * A0 * t**2,
            lambda t: V0 + A0 * t,
            lambda t: A0,
        ),
    ],
)
def test_extrapolation_formulae(kind: str, qpos, qvel, qacc) -> None:  # type: ignore[no-untyped-def]
    model, cfg = config(kind)
    estimator = DeadReckoning(model, cfg)
    estimator.initialise(FRAME)
    for tick in range(1, 4):
        estimate = estimator.predict(ctrl=None)
        t = 0.05 * tick
        np.testing.assert_allclose(estimate.qpos, qpos(t), rtol=0, atol=1e-14)
        np.testing.assert_allclose(estimate.qvel, qvel(t), rtol=0, atol=1e-14)
        np.testing.assert_allclose(estimate.qacc, qacc(t), rtol=0, atol=1e-14)
        np.testing.assert_array_equal(estimate.state, np.concatenate([estimate.qpos, estimate.qvel]))
        assert (estimate.covariance, estimate.nis, estimate.reinitialised) == (None, None, False)
    ahead = estimator.extrapolate(0.02)
    np.testing.assert_allclose(ahead.qpos, qpos(0.17), rtol=0, atol=1e-14)
    again = estimator.predict(ctrl=None)  # extrapolate changed nothing
    np.testing.assert_allclose(again.qpos, qpos(0.2), rtol=0, atol=1e-14)


def test_a_frame_re_anchors_and_unmeasured_channels_come_from_differences() -> None:
    model, cfg = config("CONSTANT_ACCELERATION", measured=frozenset({"qpos"}))
    estimator = DeadReckoning(model, cfg)
    estimator.initialise(Measurement(qpos=np.array([0.0, 0.0])))
    still = estimator.predict(ctrl=None)
    np.testing.assert_array_equal(still.qpos, [0.0, 0.0])  # no velocity known from one frame
    anchored = estimator.update(Measurement(qpos=np.array([0.1, -0.2])))  # one tick later
    np.testing.assert_allclose(anchored.qvel, [2.0, -4.0])
    np.testing.assert_allclose(anchored.qacc, [40.0, -80.0])  # from the zero velocity before
    estimator.predict(ctrl=None)
    estimator.predict(ctrl=None)
    later = estimator.update(Measurement(qpos=np.array([0.3, -0.6])))  # two ticks later
    np.testing.assert_allclose(later.qvel, [2.0, -4.0])
    np.testing.assert_allclose(later.qacc, [0.0, 0.0], atol=1e-12)


@pytest.mark.parametrize("kind", ["CONSTANT_VELOCITY", "CONSTANT_ACCELERATION"])
def test_an_extrapolation_stops_a_limited_joint_at_its_range(kind: str) -> None:
    model, cfg = config(kind, xml=LIMITED)
    estimator = DeadReckoning(model, cfg)
    # x starts inside and runs into 1.2 after 0.29 s; y starts past -1.9 and moves further out (its
    # qdd too); the hinge z moves back from 0.1 rad at 0.6 rad/s, below 0 after 0.17 s.
    q0, v0, a0 = np.array([1.0, -1.8, 0.1]), np.array([0.7, 0.25, -0.6]), np.array([0.0, 4.0, 0.0])
    estimator.initialise(Measurement(qpos=q0, qvel=v0, qacc=a0))
    free = DeadReckoning(*config(kind))  # the unlimited slides: the extrapolation as it would be
    free.initialise(Measurement(qpos=q0[:2], qvel=v0[:2], qacc=a0[:2]))
    accelerating = kind == "CONSTANT_ACCELERATION"
    for tick in range(1, 9):
        t = 0.05 * tick
        estimate, unlimited = estimator.predict(ctrl=None), free.predict(ctrl=None)
        x, z = min(1.0 + 0.7 * t, 1.2), max(0.1 - 0.6 * t, 0.0)
        np.testing.assert_allclose(estimate.qpos[[0, 2]], [x, z], rtol=0, atol=1e-14)
        # y was already out of its range at the frame: held there, not pulled in, not carried further.
        assert estimate.qpos[1] == -1.8 and unlimited.qpos[1] > -1.8
        stopped = np.array([x == 1.2, True, z == 0.0])
        np.testing.assert_array_equal(estimate.qvel[stopped], 0.0)
        np.testing.assert_array_equal(estimate.qvel[~stopped], v0[~stopped])
        np.testing.assert_array_equal(estimate.qacc, a0 * (~stopped) if accelerating else 0.0)
    assert estimator.extrapolate(10.0).qpos[0] == 1.2
    anchored = estimator.update(Measurement(qpos=q0, qvel=v0, qacc=a0))  # a frame is answered as it came
    np.testing.assert_array_equal(anchored.qpos, q0)
    np.testing.assert_array_equal(anchored.qvel, v0)


def test_controlled_state_carries_qdd_and_the_control_is_ignored() -> None:
    model, cfg = config(
        "CONSTANT_VELOCITY", scenario="CONTROLLED", measured=frozenset({"qpos", "qvel", "qacc", "ctrl"})
    )
    estimator = DeadReckoning(model, cfg)
    assert (estimator.state_dimension, estimator.state_size) == (6, 6)
    estimator.initialise(Measurement(qpos=Q0, qvel=V0, qacc=A0, ctrl=np.array([3.0])))
    estimate = estimator.predict(ctrl=np.array([100.0]))
    np.testing.assert_allclose(estimate.state, np.concatenate([Q0 + 0.05 * V0, V0, [0.0, 0.0]]))


def test_quaternions_turn_on_their_manifold() -> None:
    model, cfg = config("CONSTANT_VELOCITY", xml=FREE_BODY, measured=frozenset({"qpos", "qvel"}))
    estimator = DeadReckoning(model, cfg)
    assert (estimator.state_dimension, estimator.state_size) == (12, 13)
    spin = np.array([0.0, 0.0, 0.0, 0.0, 0.0, np.pi])  # half a turn per second about z
    estimator.initialise(Measurement(qpos=np.array([0, 0, 1, 1, 0, 0, 0.0]), qvel=spin))
    for _ in range(10):
        estimate = estimator.predict(ctrl=None)
    np.testing.assert_allclose(
        estimate.qpos, [0, 0, 1, np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)], atol=1e-12
    )


def test_snapshot_restore_and_contract() -> None:
    model, cfg = config("CONSTANT_ACCELERATION")
    estimator = DeadReckoning(model, cfg)
    with pytest.raises(FailedPrecondition, match=r"^predict needs an initialised estimator"):
        estimator.predict(ctrl=None)
    with pytest.raises(
        InvalidArgument, match=r"^measurement must have the measured channels \['qacc'\], got None$"
    ):
        estimator.initialise(Measurement(qpos=Q0, qvel=V0))
    estimator.initialise(FRAME)
    estimator.predict(ctrl=None)
    snapshot = estimator.snapshot()
    first = [estimator.predict(ctrl=None).state for _ in range(3)]
    estimator.restore(snapshot)
    replay = [estimator.predict(ctrl=None).state for _ in range(3)]
    np.testing.assert_array_equal(first, replay)
    assert not first[0].flags.writeable
    with pytest.raises(InvalidArgument, match=r"^snap must be a snapshot of this estimator, got _Snapshot$"):
        DeadReckoning(model, cfg).restore(snapshot)
    with pytest.raises(InvalidArgument, match=r"^seconds must be finite and >= 0, got inf$"):
        estimator.extrapolate(float("inf"))
    _, ukf = config("UKF")
    with pytest.raises(
        InvalidArgument, match=r"^config.estimator must be a dead-reckoning estimator, got UKF$"
    ):
        DeadReckoning(model, ukf)
