"""client.objects: the research objects are deterministic with a seed and move as documented."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from jitdyn.experiments.objects import Biped, Pendulum, Scenario, UnstableSimulation, load_source, make_object
from jitdyn.experiments.recorded import load_isen, load_xsens, research_object, xsens_path


def _run(obj, seed, ticks):
    states = [obj.reset(seed)]
    for _ in range(ticks):
        s = states[-1]
        ctrl = obj.control(s.t, s.qpos, s.qvel) if obj.scenario is Scenario.CONTROLLED else None
        states.append(obj.step(ctrl))
    return np.array([np.concatenate([s.qpos, s.qvel, s.qacc, s.ctrl]) for s in states])


@pytest.mark.parametrize(
    ("name", "scenario", "ticks"),
    [
        ("pendulum_1", Scenario.PASSIVE, 20),
        ("pendulum_3", Scenario.CONTROLLED, 20),
        ("pendulum_2", Scenario.EXTERNAL, 20),
        ("biped", Scenario.EXTERNAL, 100),
    ],
)
def test_same_seed_same_trajectory_other_seed_another(name, scenario, ticks):
    a = _run(make_object(name, scenario), 3, ticks)
    b = _run(make_object(name, scenario), 3, ticks)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, _run(make_object(name, scenario), 4, ticks))


def test_reset_replays_the_same_run_on_the_same_object():
    obj = make_object("pendulum_2", Scenario.PASSIVE)
    np.testing.assert_array_equal(_run(obj, 0, 10), _run(obj, 0, 10))


def test_time_ctrl_and_acceleration_of_a_state():
    obj = Pendulum(1, Scenario.PASSIVE, jitter=0.0)
    s0 = obj.reset(0)
    assert s0.t == 0.0 and s0.qpos[0] == pytest.approx(np.pi / 4)
    np.testing.assert_array_equal(s0.ctrl, [0.0])
    # A thin rod about its end: I = m l^2 / 3, so qacc = -(m g l / 2) sin(q) / I = -1.5 g sin(q); the
    # capsule's round caps put some mass beyond the ends, which makes it 3.5 % less.
    assert s0.qacc[0] == pytest.approx(-1.5 * 9.81 * np.sin(np.pi / 4), rel=0.05)
    s1 = obj.step()
    assert s1.t == pytest.approx(0.05)
    assert s1.qpos[0] < s0.qpos[0]  # it falls


def test_controlled_pendulum_reaches_the_symmetrical_position_every_second():
    obj = Pendulum(1, Scenario.EXTERNAL)
    obj.reset(0)
    q = {}
    for k in range(1, 61):
        q[k] = obj.step().qpos[0]
    # -theta0 at t = 0: near +theta0 just before t = 1 s, near -theta0 just before t = 2 s, ...
    assert q[20] == pytest.approx(np.pi / 4, abs=0.12)
    assert q[40] == pytest.approx(-np.pi / 4, abs=0.12)
    assert q[60] == pytest.approx(np.pi / 4, abs=0.12)


def test_the_controlled_frame_carries_the_control_that_acted():
    obj = Pendulum(2, Scenario.CONTROLLED)
    s = obj.reset(0)
    u = obj.control(s.t, s.qpos, s.qvel)
    np.testing.assert_array_equal(obj.step(u).ctrl, u)


def test_biped_keeps_rocking_on_its_feet():
    obj = Biped(Scenario.EXTERNAL)
    s = obj.reset(0)
    xs = []
    for _ in range(800):  # 4 s
        s = obj.step()
        xs.append(s.qpos[0])
    assert -0.1 < s.qpos[1] < 0.1  # the hip neither fell nor flew
    assert max(xs) - min(xs) > 0.2  # and it moved


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: Pendulum(1, Scenario.PASSIVE).step(), "step before reset: call reset"),
        (lambda: Biped(Scenario.PASSIVE), "the biped cannot move passively"),
        (lambda: make_object("pendulum_9", Scenario.PASSIVE), "object must be one of"),
        (lambda: load_source("nope"), "model must be one of"),
        (
            lambda: Pendulum(1, Scenario.PASSIVE, dt=0.06),
            "dt must be a positive whole multiple of the model's timestep 0.025, got 0.06",
        ),
    ],
)
def test_misuse_is_refused_with_a_precise_message(call, message):
    with pytest.raises((ValueError, RuntimeError), match=message):
        call()


def test_ctrl_is_required_in_controlled_and_refused_otherwise():
    controlled = Pendulum(1, Scenario.CONTROLLED)
    controlled.reset(0)
    with pytest.raises(ValueError, match="ctrl is required in the CONTROLLED scenario"):
        controlled.step()
    with pytest.raises(ValueError, match=r"ctrl must have shape \(1,\), got \(2,\)"):
        controlled.step(np.zeros(2))
    external = Pendulum(1, Scenario.EXTERNAL)
    external.reset(0)
    with pytest.raises(ValueError, match="ctrl must be None in the EXTERNAL scenario"):
        external.step(np.zeros(1))


def test_a_truth_that_blows_up_says_so_instead_of_resetting():
    obj = Pendulum(1, Scenario.CONTROLLED)
    obj.reset(0)
    with pytest.raises(UnstableSimulation, match=r"the simulation became unstable by t = 0.05 s") as error:
        obj.step(np.array([1e12]))
    assert error.value.t == pytest.approx(0.05)


def test_myoelbow_raises_and_lowers_the_forearm_deterministically():
    from jitdyn.experiments.objects import MyoElbow

    def run(seed):
        obj = MyoElbow()
        obj.reset(seed)
        return np.array([obj.step().qpos[0] for _ in range(1000)])  # 2 s: up to the top

    a = run(1)
    np.testing.assert_array_equal(a, run(1))
    assert not np.array_equal(a, run(2))
    assert a[-1] - a[0] > 0.8  # raised from 0.3 towards 1.5 rad


def test_myohand_bends_the_index_first():
    from jitdyn.experiments.objects import MyoHand

    obj = MyoHand()
    obj.reset(0)
    index = obj.model.joint("mcp2_flexion_r").qposadr[0]
    for _ in range(200):  # 0.4 s: the index's flexion peaks at a quarter period
        s = obj.step()
    assert s.qpos[index] > 1.0
    assert obj.scenario is Scenario.EXTERNAL
    with pytest.raises(ValueError, match="myohand runs only in the EXTERNAL scenario, got CONTROLLED"):
        MyoHand(Scenario.CONTROLLED)


@pytest.mark.parametrize(("name", "seconds"), [("isen_gait", 10.29), ("isen_tasks", 17.99)])
def test_the_isen_recordings_replay_both_legs_at_100_hz(name: str, seconds: float) -> None:
    """biomdp's iSen angles: hip and knee flexion of both legs, 100 Hz, in radians; the chain's
    four hinges take them, and the replay ends with the recording."""
    obj = research_object(name, Scenario.EXTERNAL)
    assert (obj.nv, obj.dt, obj.name) == (4, 0.01, "isen_legs")
    assert abs(obj.seconds - seconds) < 1e-9
    first = obj.reset(0)
    assert np.all(np.abs(first.qpos) < np.radians(120))
    states = [obj.step() for _ in range(round(obj.seconds / obj.dt))]
    # The knees flex: over the stepping part each knee reaches past 40 degrees.
    assert np.degrees(np.max([s.qpos[1] for s in states])) > 40
    with pytest.raises(IndexError, match="the recording ends at"):
        obj.step()


def test_a_part_of_the_isen_recording_must_be_one_of_its_parts() -> None:
    with pytest.raises(
        ValueError, match=r"part must be one of \['isen_gait', 'isen_tasks'\], got 'isen_run'"
    ):
        load_isen("isen_run")


def test_the_xsens_walk_replays_one_leg_at_100_hz() -> None:
    """scikit-kinematics' Xsens thigh and shank sensors: hip and knee flexion of one leg while
    walking, 100 Hz, in radians; the two hinges take them, and the replay ends with the walk."""
    obj = research_object("xsens_gait", Scenario.EXTERNAL)
    assert (obj.nv, obj.dt, obj.name) == (2, 0.01, "xsens_leg")
    assert abs(obj.seconds - 24.24) < 1e-9
    obj.reset(0)
    q = np.degrees([obj.step().qpos for _ in range(round(obj.seconds / obj.dt))])
    # A walk: the hip swings between about -12 and 29 degrees, the knee between about -6 and 53.
    assert np.allclose(q.min(axis=0), (-12.2, -6.3), atol=0.5)
    assert np.allclose(q.max(axis=0), (28.5, 52.8), atol=0.5)
    # Steady strides of about 1.3 s: the knee's flexion a stride later is nearly the same.
    knee = q[:, 1] - q[:, 1].mean()
    lags = np.arange(80, 150)
    correlation = [np.corrcoef(knee[:-lag], knee[lag:])[0, 1] for lag in lags]
    assert 1.2 < lags[int(np.argmax(correlation))] * obj.dt < 1.35
    assert max(correlation) > 0.9
    with pytest.raises(IndexError, match="the recording ends at"):
        obj.step()


def test_the_xsens_sensors_must_hold_a_walk(tmp_path: Path) -> None:
    short = tmp_path / "short.txt"
    lines = xsens_path("walking_xsens_upperLeg.txt").read_text(encoding="utf-8").splitlines()
    short.write_text("\n".join(lines[:1000]), encoding="utf-8")
    with pytest.raises(ValueError, match=r"short.txt must hold a finite walk of 10 s or more, got 8.3 s"):
        load_xsens((short, short))


# An elbow (qpos0 0, range [0, 2.27] as myoelbow's) and a slider whose range is narrower than the
# demo's smallest move; a free joint, which has no range.
_LIMITED = """
<mujoco>
  <compiler angle="radian"/>
  <worldbody>
    <body pos="0 0 1"><joint name="elbow" type="hinge" axis="0 1 0" range="0 2.27"/>
      <geom type="capsule" size=".03" fromto="0 0 0 0 0 -.3" mass="1"/></body>
    <body pos="1 0 1"><joint name="slider" type="slide" axis="0 0 1" range="-0.1 0.1"/>
      <geom size=".05" mass="1"/></body>
    <body pos="2 0 1"><freejoint/><geom size=".05" mass="1"/></body>
  </worldbody>
</mujoco>
"""


def test_qpos_limits_are_the_ranges_of_limited_hinges_and_slides() -> None:
    import mujoco

    from jitdyn.experiments.objects import qpos_limits

    lo, hi = qpos_limits(mujoco.MjModel.from_xml_string(_LIMITED))
    np.testing.assert_allclose(lo[:2], [0.0, -0.1])
    np.testing.assert_allclose(hi[:2], [2.27, 0.1])
    assert np.all(np.isneginf(lo[2:])) and np.all(np.isposinf(hi[2:]))


@pytest.mark.parametrize("seed", range(8))
def test_the_demos_start_pose_keeps_inside_the_joint_ranges(seed: int) -> None:
    import mujoco

    from jitdyn.experiments.demo import _start_pose

    model = mujoco.MjModel.from_xml_string(_LIMITED)
    qpos = _start_pose(model, np.random.default_rng(seed))
    assert 0.227 - 1e-12 <= qpos[0] <= 2.27 * 0.9 + 1e-12, qpos[0]
    assert -0.08 - 1e-12 <= qpos[1] <= 0.08 + 1e-12, qpos[1]
    assert not np.allclose(qpos[2:], model.qpos0[2:])  # the free joint moved, on its manifold
    np.testing.assert_allclose(np.linalg.norm(qpos[5:9]), 1.0)
