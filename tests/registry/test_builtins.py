"""The built-in models: the thesis' geometry, found from the checkout, and plausible physics."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from jitdyn.registry import BUILTIN_NAMES, builtin_model_path, builtin_models


def load(name: str) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(builtin_model_path(name)))


@pytest.mark.parametrize("n", [1, 2, 3])
def test_pendulums_have_the_thesis_geometry(n: int) -> None:
    model = load(f"pendulum_{n}")
    assert (model.nq, model.nv, model.nu) == (n, n, n)
    assert model.opt.timestep == 0.025
    np.testing.assert_allclose(model.opt.gravity, [0, 0, -9.81])
    assert [model.joint(i).name for i in range(n)] == [f"hinge_{i + 1}" for i in range(n)]
    np.testing.assert_array_equal(model.jnt_type, mujoco.mjtJoint.mjJNT_HINGE)
    np.testing.assert_array_equal(model.jnt_axis, [[0, 1, 0]] * n)
    assert not model.jnt_limited.any()
    assert not model.dof_damping.any() and not model.dof_armature.any() and not model.dof_frictionloss.any()
    np.testing.assert_allclose(model.body_mass[1:], 1.0)
    np.testing.assert_allclose(model.geom_size[:, 0], 0.05)
    np.testing.assert_allclose(2 * model.geom_size[:, 1], 1.0)  # capsule half-length: 1 m rods
    np.testing.assert_allclose(
        model.body_pos[2:].reshape(-1, 3), np.tile([0, 0, -1], (n - 1, 1))
    )  # hung from the end
    np.testing.assert_allclose(model.body_ipos[1:], [[0, 0, -0.5]] * n)
    assert not model.geom_contype.any() and not model.geom_conaffinity.any()
    np.testing.assert_array_equal(model.actuator_gear[:, 0], 1.0)
    assert not model.actuator_ctrllimited.any()


def test_pendulum_energy_is_kept_without_friction() -> None:
    model = load("pendulum_3")
    model.opt.enableflags |= mujoco.mjtEnableBit.mjENBL_ENERGY
    data = mujoco.MjData(model)
    data.qpos[:] = [0.5, -0.3, 0.2]
    mujoco.mj_forward(model, data)
    start = data.energy.sum()
    for _ in range(round(10 / model.opt.timestep)):  # 10 s
        mujoco.mj_step(model, data)
    assert data.ncon == 0
    assert abs(data.energy.sum() - start) < 1e-3


def test_biped_has_the_thesis_joints_in_order() -> None:
    model = load("biped")
    assert [model.joint(i).name for i in range(model.njnt)] == [
        "root_x",
        "root_z",
        "left_hip",
        "left_absorber",
        "right_hip",
        "right_absorber",
    ]
    slide, hinge = mujoco.mjtJoint.mjJNT_SLIDE, mujoco.mjtJoint.mjJNT_HINGE
    assert list(model.jnt_type) == [slide, slide, hinge, slide, hinge, slide]
    assert model.opt.timestep == 0.001
    assert [model.actuator(i).name for i in range(model.nu)] == [
        "left_hip",
        "left_absorber",
        "right_hip",
        "right_absorber",
    ]
    assert list(model.jnt_limited) == [0, 0, 0, 1, 0, 1]
    legs = [model.body("left_leg").id, model.body("right_leg").id]
    np.testing.assert_allclose(model.body_mass[legs], 1.0)
    assert model.dof_damping[3] > 0 and model.jnt_stiffness[3] > 0  # the absorber is a spring-damper


def simulate(*, controlled: bool, seconds: float) -> np.ndarray:
    """The biped from upright with a small push; with `controlled`, PD holds the legs at +-0.25 rad."""
    model = load("biped")
    data = mujoco.MjData(model)
    data.qvel[0] = 0.3
    target = np.array([0.0, 0.0, 0.25, 0.0, -0.25, 0.0])
    for _ in range(int(seconds / model.opt.timestep)):
        if controlled:
            for actuator, joint, kp, kd in (
                (0, 2, 200, 20),
                (1, 3, 2000, 50),
                (2, 4, 200, 20),
                (3, 5, 2000, 50),
            ):
                data.ctrl[actuator] = kp * (target[joint] - data.qpos[joint]) - kd * data.qvel[joint]
        mujoco.mj_step(model, data)
    return data.qpos.copy()


def test_biped_falls_without_control_and_stands_under_pd() -> None:
    fallen = simulate(controlled=False, seconds=5.0)
    held = simulate(controlled=True, seconds=5.0)
    # root_z is the hip's height change: 1.05 m would be lying on the ground.
    assert fallen[1] < -0.9
    assert -0.06 < held[1] < 0.0
    np.testing.assert_allclose(held[[2, 4]], [0.25, -0.25], atol=0.02)


def test_builtins_are_read_with_their_descriptions() -> None:
    models = builtin_models()
    assert [model.name for model in models] == list(BUILTIN_NAMES)
    for model in models:
        assert model.description and "-->" not in model.description
        assert model.tags[0] == "builtin"
    with pytest.raises(ValueError, match="no built-in model is named 'pendulum_9'"):
        builtin_model_path("pendulum_9")
