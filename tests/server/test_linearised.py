"""The linearised filter (server/estimation/linearised.py): the native tick (native/linearised.cc)
against the Python reference it mirrors, over 500 noisy frames with gaps, repeated frames, frames
far off (the guard's restart) and late frames' replays, on a hinge model and on a ball joint; and
what the filter refuses."""

from __future__ import annotations

import dataclasses
from collections import Counter

import mujoco
import numpy as np
import pytest

from jitdyn.errors import FailedPrecondition, InvalidArgument
from jitdyn.server.estimation.config import Engine, EstimatorConfig
from jitdyn.server.estimation.interface import Estimate, Measurement
from jitdyn.server.estimation.linearised import LinearisedFilter, PythonTick, coarsening, ekf_process_model
from jitdyn.server.estimation.native.linearised import NativeTick
from jitdyn.vocabulary import Scenario
from tests.server.test_native import ADAPTIVE_TOL, REPEATED, REPLAYED, SKIPPED, TICKS, ball_frames, frames_for
from tests.server.test_ukf import BALL_PENDULUM, config_for, pendulum

# |native - python| <= TOL (1 + |python|), entry by entry (as tests/server/test_native.py).
TOL = 1e-9
# DRIVEN estimates the force from the frames' accelerations, and one tick of the run amplifies the
# engines' rounding (Eigen's sums against OpenBLAS's) to 1.1e-9 on an AMD EPYC (below 1e-10 before
# and after it, and below 1e-9 on the machine it was written on): held as test_native holds DRIVEN.
DRIVEN_TOL = ADAPTIVE_TOL


def ekf_config(
    model: mujoco.MjModel, scenario: str, *, dt: float = 0.05, **requested: object
) -> EstimatorConfig:
    """The server's settings of an EKF session (resolve_config's: fixed noise, the filter's own
    forecast, PASSIVE's wrong_model RESTART)."""
    return config_for(model, scenario, dt=dt, estimator="EKF", **requested)


def flatten(estimate: Estimate, f: LinearisedFilter) -> list[np.ndarray]:
    nis = np.nan if estimate.nis is None else estimate.nis
    assert estimate.covariance is not None
    return [
        np.array(estimate.state),
        np.array(estimate.qacc),
        np.array(estimate.covariance),
        np.array([nis, float(estimate.reinitialised)]),
        np.array(f.qfrc),  # EXTERNAL's restored force
    ]


def run(
    model: mujoco.MjModel, config: EstimatorConfig, frames: list[Measurement], *, coarsen: int | None = None
) -> tuple[list[np.ndarray], Counter[str]]:
    """Every answer of a session, flattened, and how often each branch showed in them."""
    out: list[np.ndarray] = []
    seen: Counter[str] = Counter()
    f = LinearisedFilter(model, config, coarsen=coarsen)

    def answer(estimate: Estimate) -> None:
        out.extend(flatten(estimate, f))
        seen["reinitialised"] += estimate.reinitialised

    f.initialise(frames[0])
    snapshot = f.snapshot()
    for k in range(1, len(frames)):
        if k in REPLAYED:  # tick k - 3's frame came late: back before it, and forward again
            f.restore(snapshot)
            for j in range(k - 3, k):
                f.advance(ctrl=None)
                answer(f.update(frames[j]))
            seen["replayed"] += 1
        if k % 10 == 0:
            answer(f.glance(2 * config.dt))
            answer(f.extrapolate(config.dt))
        if k + 3 in REPLAYED:
            snapshot = f.snapshot()
        if k in SKIPPED:
            answer(f.predict(ctrl=None))
            continue
        f.advance(ctrl=None)
        answer(f.update(frames[k]))
        if k in REPEATED:
            answer(f.update(frames[k]))
    seen["restarts"] = f.restarts
    return out, seen


def assert_engines_agree(
    model: mujoco.MjModel, native: EstimatorConfig, frames: list[Measurement], *, coarsen: int | None = None
) -> Counter[str]:
    assert native.engine == Engine.NATIVE
    python = dataclasses.replace(native, engine=Engine.FAST)
    assert isinstance(LinearisedFilter(model, native).core, NativeTick)
    assert isinstance(LinearisedFilter(model, python).core, PythonTick)
    (got, seen), (expected, seen_python) = (
        run(model, native, frames, coarsen=coarsen),
        run(model, python, frames, coarsen=coarsen),
    )
    assert seen == seen_python
    assert len(got) == len(expected)
    tol = DRIVEN_TOL if native.scenario == Scenario.DRIVEN else TOL
    for i, (a, b) in enumerate(zip(got, expected, strict=True)):
        np.testing.assert_allclose(a, b, rtol=tol, atol=tol, err_msg=f"output {i} ({native.scenario})")
    assert seen["replayed"] == len(REPLAYED)
    return seen


@pytest.mark.parametrize("scenario", ["PASSIVE", "EXTERNAL", "DRIVEN"])
def test_native_tick_equals_the_python_reference(scenario: str) -> None:
    model = pendulum(2)
    config = ekf_config(model, scenario)
    frames = frames_for(model, config)
    assert len(frames) == TICKS
    seen = assert_engines_agree(model, config, frames)
    if scenario == "EXTERNAL":  # wrong_model RESTART: the frames far off start it again
        assert seen["restarts"] > 0, seen


def test_the_tick_chains_the_jacobians_of_its_steps() -> None:
    """Two of the model's steps a tick, each linearised (coarsen 1), in DRIVEN."""
    model = pendulum(2)
    config = ekf_config(model, "DRIVEN", dt=0.02)
    assert config.steps_per_tick == 2
    assert_engines_agree(model, config, frames_for(model, config), coarsen=1)


@pytest.mark.parametrize("scenario", ["EXTERNAL", "DRIVEN"])
def test_a_ball_joint_is_linearised_on_its_manifold_in_both_engines(scenario: str) -> None:
    model = mujoco.MjModel.from_xml_string(BALL_PENDULUM)
    config = ekf_config(model, scenario)
    frames = ball_frames(model, config)
    seen = assert_engines_agree(model, config, frames)
    assert seen["reinitialised"] > 0 or scenario == "DRIVEN", seen


def test_the_filter_follows_the_motion_it_is_fed() -> None:
    """Noisy frames of a swinging double pendulum with gaps of 3 ticks: the EKF's answers over the
    gaps are closer to the truth than the last frame held, and its covariance stays positive."""
    model = pendulum(2)
    config = ekf_config(model, "PASSIVE", dt=0.01)
    d = mujoco.MjData(model)
    d.qpos[:] = [0.6, -0.4]
    rng = np.random.default_rng(3)
    f = LinearisedFilter(model, config)
    errors: dict[str, list[float]] = {"ekf": [], "held": []}
    held = d.qpos.copy()
    for k in range(300):
        mujoco.mj_step(model, d)
        frame = Measurement(qpos=d.qpos + rng.normal(0, 0.01, 2), qvel=d.qvel + rng.normal(0, 0.1, 2))
        if k == 0:
            f.initialise(frame)
        elif k % 10 < 3:
            errors["ekf"].append(float(np.abs(f.predict(ctrl=None).qpos - d.qpos).mean()))
            errors["held"].append(float(np.abs(held - d.qpos).mean()))
            continue
        else:
            f.advance(ctrl=None)
            f.update(frame)
        held = frame.qpos
    assert np.mean(errors["ekf"]) < 0.3 * np.mean(errors["held"]), {k: np.mean(v) for k, v in errors.items()}
    assert np.all(np.linalg.eigvalsh(f.snapshot().P) > 0)


def test_coarsening_spans_at_most_ten_milliseconds_a_step() -> None:
    def model(timestep: float) -> mujoco.MjModel:
        return mujoco.MjModel.from_xml_string(f'<mujoco><option timestep="{timestep}"/></mujoco>')

    assert coarsening(model(0.001), 10) == 10  # myolegs_osl at 100 Hz: one step a tick
    assert coarsening(model(0.001), 50) == 10
    assert coarsening(model(0.001), 7) == 7
    assert coarsening(model(0.002), 1) == 1
    assert coarsening(model(0.004), 4) == 2
    assert coarsening(model(0.02), 3) == 1


@pytest.mark.parametrize(
    ("scenario", "requested", "message"),
    [
        ("CONTROLLED", {}, "scenario must be PASSIVE, EXTERNAL or DRIVEN, got CONTROLLED"),
        ("PASSIVE", {"wrong_model": "DRIVEN"}, "wrong_model must be KEEP or RESTART"),
        ("DRIVEN", {"noise_model": "ADAPTIVE"}, "noise_model must be FIXED, got ADAPTIVE"),
        ("DRIVEN", {"forecast": "COMBINED"}, "forecast must be FILTER, got COMBINED"),
        ("DRIVEN", {"force_model": "INTEGRATED_RANDOM_WALK"}, "force_model must be RANDOM_WALK"),
    ],
)
def test_what_it_does_not_run_is_refused_by_name(
    scenario: str, requested: dict[str, object], message: str
) -> None:
    model = pendulum(2)
    config = config_for(model, scenario, estimator="EKF", **requested)
    with pytest.raises(
        InvalidArgument, match=r"the linearised filter \(EKF\) runs no such session: " + message
    ):
        LinearisedFilter(model, config)


def test_snapshots_belong_to_their_filter_and_it_needs_its_first_frame() -> None:
    model = pendulum(2)
    config = ekf_config(model, "EXTERNAL")
    f, other = LinearisedFilter(model, config), LinearisedFilter(model, config)
    with pytest.raises(FailedPrecondition, match="advance needs an initialised estimator"):
        f.advance(ctrl=None)
    f.initialise(Measurement(qpos=np.zeros(2), qvel=np.zeros(2)))
    with pytest.raises(InvalidArgument, match="snap must be a snapshot of this estimator"):
        other.restore(f.snapshot())
    estimate = f.predict(ctrl=None)
    assert not estimate.state.flags.writeable and estimate.covariance is not None
    assert estimate.covariance.shape == (4, 4)


FREE_BALL = """
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
ENGINES = [Engine.NATIVE, Engine.FAST]


def free_ball(first: Measurement, engine: Engine, *, coarsen: int | None = None) -> LinearisedFilter:
    model = mujoco.MjModel.from_xml_string(FREE_BALL)
    config = dataclasses.replace(ekf_config(model, "EXTERNAL", dt=DT), engine=engine)
    ekf = LinearisedFilter(model, config, coarsen=coarsen)
    ekf.initialise(first)
    return ekf


def spinning() -> Measurement:
    quat = np.array([np.cos(0.3), np.sin(0.3), 0.0, 0.0])
    return Measurement(qpos=np.concatenate([[0.1, -0.2, 1.0], quat]), qvel=np.array([0.5, 0, 0.2, 0, 0, 0.0]))


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("coarsen", [1, None])
def test_the_mean_is_the_process_models_steps_on_the_manifold(engine: Engine, coarsen: int | None) -> None:
    """A free body: coarsen 1 takes the UKF's process model's five 2 ms steps, the default one
    implicitfast step of the tick."""
    ekf = free_ball(spinning(), engine, coarsen=coarsen)
    q = ekf.predict(ctrl=None).qpos
    model = mujoco.MjModel.from_xml_string(FREE_BALL)
    own = ekf_process_model(model, Scenario.EXTERNAL, 1 if coarsen == 1 else 5)
    d = mujoco.MjData(own)
    d.qpos[:], d.qvel[:] = spinning().qpos, spinning().qvel
    mujoco.mj_step(own, d, 5 if coarsen == 1 else 1)
    np.testing.assert_allclose(q, d.qpos, atol=1e-12)
    assert q.shape == (7,) and ekf.snapshot().P.shape == (12, 12)
    assert abs(np.linalg.norm(q[3:]) - 1.0) < 1e-12


@pytest.mark.parametrize("engine", ENGINES)
def test_the_covariance_follows_the_tangent_jacobian(engine: Engine) -> None:
    # A free sphere without angular velocity: over a tick T, a position (angle) moves by T times
    # its velocity's perturbation, so P0 = p I gives p (1 + T^2) + Q on each position's diagonal.
    ekf = free_ball(Measurement(qpos=spinning().qpos, qvel=np.zeros(6)), engine)
    p0, q = ekf.P0[0, 0], ekf.Q.copy()
    ekf.advance(ctrl=None)
    P = ekf.snapshot().P
    np.testing.assert_allclose(np.diagonal(P)[:6], p0 * (1.0 + DT**2) + np.diagonal(q)[:6], rtol=1e-5)
    np.testing.assert_allclose(P[:6, 6:], np.diag(np.full(6, p0 * DT)) + q[:6, 6:], rtol=1e-4, atol=1e-9)


@pytest.mark.parametrize("engine", ENGINES)
def test_a_frame_far_out_twice_restarts_it_from_the_frame(engine: Engine) -> None:
    ekf = free_ball(spinning(), engine)
    for side in (1.0, -1.0):  # each frame 3 m off the filter's x in its own direction
        far = Measurement(qpos=spinning().qpos + np.array([3.0 * side, 0, 0, 0, 0, 0, 0]), qvel=np.zeros(6))
        ekf.advance(ctrl=None)
        estimate = ekf.update(far)
        assert ekf.restarts == (side < 0) == estimate.reinitialised
    np.testing.assert_array_equal(estimate.state[:7], far.qpos)
    np.testing.assert_array_equal(estimate.covariance, ekf.P0)
