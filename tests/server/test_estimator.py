"""Estimator settings (presets, precedence, checks), the factory, and LOCKSTEP-like skip sequences
driven straight on the estimators against MuJoCo's ground truth (server/estimation/config.py,
interface.py)."""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import mujoco
import numpy as np
import pytest

from jitdyn.errors import InvalidArgument
from jitdyn.estimator_settings import SETTINGS
from jitdyn.server.estimation.config import (
    SETTING_FIELDS,
    EstimatorConfig,
    is_pendulum_like,
    preset_values,
    resolve_config,
)
from jitdyn.server.estimation.deadreckoning import DeadReckoning
from jitdyn.server.estimation.factory import make_estimator
from jitdyn.server.estimation.interface import Estimator, Measurement
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.estimation.ukf import UnscentedFilter
from jitdyn.vocabulary import Preset, Scenario

MODELS = Path(__file__).resolve().parents[2] / "models"


def pendulum(n: int) -> mujoco.MjModel:
    """models/pendulum_<n>.xml when it is there, else the same pendulum inline: n rods of radius
    0.05 m, length 1 m, mass 1 kg, frictionless hinges about y, motors of gear 1, timestep 0.01 s."""
    path = MODELS / f"pendulum_{n}.xml"
    if path.exists():
        return mujoco.MjModel.from_xml_path(str(path))
    bodies = "".join(
        f'<body pos="0 0 {0 if i == 0 else -1}"><joint name="j{i}" type="hinge" axis="0 1 0"/>'
        '<geom type="capsule" fromto="0 0 0 0 0 -1" size="0.05" mass="1" contype="0" conaffinity="0"/>'
        for i in range(n)
    )
    motors = "".join(f'<motor joint="j{i}" gear="1"/>' for i in range(n))
    return mujoco.MjModel.from_xml_string(
        f'<mujoco><option timestep="0.01"/><worldbody>{bodies}{"</body>" * n}</worldbody>'
        f"<actuator>{motors}</actuator></mujoco>"
    )


# The thesis' biped, in miniature: slides and hinges, contact with the ground, 1 ms timestep.
BIPED = """
<mujoco>
  <option timestep="0.001"/>
  <worldbody>
    <geom type="plane" size="10 10 0.1"/>
    <body pos="0 0 1.1">
      <joint name="x" type="slide" axis="1 0 0"/>
      <joint name="z" type="slide" axis="0 0 1"/>
      <geom type="sphere" size="0.1" mass="1"/>
      <body>
        <joint name="left_hip" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.05" mass="0.5"/>
        <body pos="0 0 -0.5">
          <joint name="left_knee" type="slide" axis="0 0 1" stiffness="100" damping="5"/>
          <geom type="capsule" fromto="0 0 0 0 0 -0.45" size="0.05" mass="0.5"/>
        </body>
      </body>
      <body>
        <joint name="right_hip" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.05" mass="0.5"/>
        <body pos="0 0 -0.5">
          <joint name="right_knee" type="slide" axis="0 0 1" stiffness="100" damping="5"/>
          <geom type="capsule" fromto="0 0 0 0 0 -0.45" size="0.05" mass="0.5"/>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor joint="left_hip"/><motor joint="left_knee"/><motor joint="right_hip"/><motor joint="right_knee"/>
  </actuator>
</mujoco>
"""


def load_myo(name: str) -> mujoco.MjModel:
    import myo_sim  # heavy: only the tests that need it pay for it

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "Attaching a spec with an empty prefix": myo_sim's own
        return myo_sim.load_model(name)


def resolve(
    model: mujoco.MjModel, scenario: str, preset: str = "JITDYN", **kwargs: object
) -> EstimatorConfig:
    return resolve_config(
        model=model,
        scenario=scenario,
        dt=kwargs.pop("dt", 0.05),  # type: ignore[arg-type]
        requested=kwargs.pop("requested", {}),  # type: ignore[arg-type]
        model_defaults=kwargs.pop("model_defaults", {}),  # type: ignore[arg-type]
        preset=preset,
        measured=kwargs.pop("measured", {"qpos", "qvel"}),  # type: ignore[arg-type]
    )


# -- presets --------------------------------------------------------------------------------------


@pytest.mark.parametrize("n", [1, 2, 3])
@pytest.mark.parametrize(
    ("scenario", "q_var", "derivatives"), [("PASSIVE", 0.1, 2), ("CONTROLLED", 0.2, 3), ("EXTERNAL", 50.0, 2)]
)
def test_thesis_preset_is_the_table_for_the_pendulums(
    n: int, scenario: str, q_var: float, derivatives: int
) -> None:
    config = resolve(pendulum(n), scenario, "THESIS")
    assert (config.estimator, config.sigma_points) == ("UKF", "MERWE")
    assert (config.alpha, config.beta, config.p0, config.r, config.q_var) == (0.001, 2.0, 0.2, 0.01, q_var)
    assert config.kappa == 3 - derivatives * n  # 3 - 2n passive and external, 3 - 3n controlled
    assert (config.dt, config.steps_per_tick) == (0.05, round(0.05 / pendulum(n).opt.timestep))


@pytest.mark.parametrize(
    ("model", "scenario", "dt", "q_var"),
    [
        ("biped", "CONTROLLED", 0.005, 5.0),
        ("biped", "EXTERNAL", 0.005, 50.0),
        ("myoelbow", "EXTERNAL", 0.002, 50.0),
        ("myohand", "EXTERNAL", 0.002, 50.0),
    ],
)
def test_thesis_preset_for_contact_and_muscle_models(
    model: str, scenario: str, dt: float, q_var: float
) -> None:
    mj_model = mujoco.MjModel.from_xml_string(BIPED) if model == "biped" else load_myo(model)
    assert not is_pendulum_like(mj_model)
    config = resolve(mj_model, scenario, "THESIS", dt=dt)
    assert (config.alpha, config.beta, config.kappa, config.p0, config.r, config.q_var) == (
        0.001,
        2.0,
        0.0,
        0.2,
        0.01,
        q_var,
    )
    assert config.sigma_points == "MERWE"


def test_jitdyn_preset_is_the_thesis_noise_with_sound_weights() -> None:
    for n, scenario, kappa in [(1, "PASSIVE", 1.0), (1, "CONTROLLED", 0.0), (3, "EXTERNAL", 0.0)]:
        config = resolve(pendulum(n), scenario)
        assert (config.alpha, config.beta, config.kappa, config.sigma_points) == (1.0, 2.0, kappa, "MERWE")
        thesis = resolve(pendulum(n), scenario, "THESIS")
        assert (config.p0, config.q_var, config.r) == (thesis.p0, thesis.q_var, thesis.r)
    hand = resolve(load_myo("myohand"), "EXTERNAL", dt=0.002)
    assert (hand.sigma_points, hand.alpha, hand.kappa) == ("SIMPLEX", 1.0, 0.0)
    biped = resolve(mujoco.MjModel.from_xml_string(BIPED), "CONTROLLED", dt=0.005)
    assert (biped.sigma_points, biped.q_var) == ("MERWE", 5.0)


def test_request_beats_model_defaults_beats_preset() -> None:
    model = pendulum(2)
    config = resolve(
        model,
        "PASSIVE",
        "THESIS",
        requested={"r": 0.5, "sigma_points": "UNIFORM"},
        model_defaults={"r": 0.2, "q_var": 3.0, "alpha": 0.5},
    )
    assert (config.r, config.q_var, config.alpha, config.sigma_points, config.kappa) == (
        0.5,
        3.0,
        0.5,
        "UNIFORM",
        -1.0,
    )
    assert resolve(model, "PASSIVE", requested={"estimator": "STATIC"}).estimator == "STATIC"
    assert preset_values("JITDYN", model=model, scenario="PASSIVE")["kappa"] == 0.0


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"requested": {"gamma": 1.0}}, r"^requested has unknown settings \['gamma'\]; expected some of \["),
        ({"model_defaults": {"R": 1.0}}, r"^model_defaults has unknown settings \['R'\]"),
        ({"requested": {"r": "small"}}, r"^r must be a number, got 'small'$"),
        (
            {"requested": {"estimator": "PARTICLE"}},
            r"^estimator must be one of UKF, STATIC, CONSTANT_VELOCITY, CONSTANT_ACCELERATION, EKF, got 'PARTICLE'$",
        ),
        (
            {"requested": {"sigma_points": "CUBATURE"}},
            r"^sigma_points must be one of MERWE, SIMPLEX, UNIFORM, SIMPLEX_LINEAR_FORCE, got 'CUBATURE'$",
        ),
        (
            {"dt": 0.055},
            r"^dt must be a whole multiple \(>= 1\) of the model's timestep 0.025 s, got 0.055 \(2.2 timesteps\)$",
        ),
        ({"dt": 0.0}, r"^dt must be a positive number of seconds, got 0.0$"),
        ({"measured": {"qvel"}}, r"^measured must include 'qpos', got \['qvel'\]$"),
        (
            {"measured": {"qpos", "torque"}},
            r"^measured must be a subset of \['ctrl', 'qacc', 'qpos', 'qvel'\], got \['qpos', 'torque'\]$",
        ),
        ({"measured": "qpos"}, r"^measured must be a set of channel names, got the string 'qpos'$"),
    ],
)
def test_settings_are_checked_with_messages_naming_the_field(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(InvalidArgument, match=message):
        resolve(pendulum(1), "PASSIVE", **kwargs)


def test_unknown_scenario_and_preset_are_refused() -> None:
    with pytest.raises(
        InvalidArgument,
        match=r"^scenario must be one of PASSIVE, CONTROLLED, EXTERNAL, DRIVEN, got 'IDLE'$",
    ):
        resolve(pendulum(1), "IDLE")
    with pytest.raises(InvalidArgument, match=r"^preset must be one of JITDYN, THESIS, got 'PAPER'$"):
        resolve(pendulum(1), "PASSIVE", "PAPER")


def test_config_is_frozen_and_checked_against_the_model_by_the_factory() -> None:
    config = resolve(pendulum(1), "PASSIVE")
    with pytest.raises(AttributeError):
        config.r = 1.0  # type: ignore[misc]
    wrong_steps = EstimatorConfig(**{**config.__dict__, "steps_per_tick": 4})
    with (
        WorkerPool(1) as pool,
        pytest.raises(InvalidArgument, match=r"^steps_per_tick must be dt / timestep = 2, got 4$"),
    ):
        make_estimator(pendulum(1), wrong_steps, pool=pool)


@pytest.mark.parametrize("kind", ["UKF", "STATIC", "CONSTANT_VELOCITY", "CONSTANT_ACCELERATION"])
def test_factory_builds_the_named_estimator(kind: str) -> None:
    model = pendulum(2)
    config = resolve(model, "CONTROLLED", requested={"estimator": kind}, measured={"qpos", "qvel", "ctrl"})
    with WorkerPool(1) as pool:
        estimator = make_estimator(model, config, pool=pool)
        assert isinstance(estimator, Estimator)
        assert isinstance(estimator, UnscentedFilter if kind == "UKF" else DeadReckoning)
        assert (estimator.state_dimension, estimator.state_size) == (6, 6)
        estimator.initialise(Measurement(qpos=np.zeros(2), qvel=np.zeros(2), ctrl=np.zeros(2)))
        estimate = estimator.predict(ctrl=np.ones(2))
        assert estimate.state.shape == (6,)
        assert (estimate.covariance is None) == (kind != "UKF")


@pytest.mark.parametrize(
    ("kind", "scenario", "requested"),
    [
        ("UKF", "DRIVEN", {}),  # the forecast combination's answer is what advance leaves out
        ("UKF", "CONTROLLED", {}),
        ("UKF", "PASSIVE", {"wrong_model": "DRIVEN"}),  # the switching filter, switched halfway
        ("CONSTANT_ACCELERATION", "EXTERNAL", {}),
        ("EKF", "DRIVEN", {}),  # the linearised filter (estimation/linearised.py)
        ("EKF", "EXTERNAL", {}),
    ],
)
def test_advance_then_update_is_predict_then_update(
    kind: str, scenario: str, requested: dict[str, str]
) -> None:
    """A tick with its frame: advance() leaves the estimator where predict() does (the server
    drops predict()'s answer on such a tick), so every later answer is the same bit for bit."""
    model = pendulum(2)
    measured = {"qpos", "qvel", "ctrl"} if scenario == "CONTROLLED" else {"qpos", "qvel"}
    config = resolve(model, scenario, requested={"estimator": kind, **requested}, measured=measured)
    d = mujoco.MjData(model)
    d.qpos[:] = 0.4
    frames = []
    for k in range(60):
        d.ctrl[:] = 3.0 * np.sin(0.2 * k + np.arange(model.nu))
        mujoco.mj_step(model, d, config.steps_per_tick)
        frames.append(Measurement(qpos=d.qpos.copy(), qvel=d.qvel.copy(), ctrl=d.ctrl.copy()))
    lost = {k for k in range(20, 60) if k % 10 in (0, 1, 2)}
    runs = []
    with WorkerPool(1) as pool:
        for advance in (False, True):
            estimator = make_estimator(model, config, pool=pool)
            estimator.initialise(frames[0])
            answers = []
            for k in range(1, len(frames)):
                ctrl = frames[k].ctrl
                if k in lost:
                    answers.append(estimator.predict(ctrl=ctrl))
                    continue
                if advance:
                    estimator.advance(ctrl=ctrl)
                else:
                    estimator.predict(ctrl=ctrl)
                answers.append(estimator.update(frames[k]))
            runs.append(answers)
    for a, b in zip(*runs, strict=True):
        np.testing.assert_array_equal(a.state, b.state)
        assert a.covariance is None or np.array_equal(a.covariance, b.covariance)  # type: ignore[arg-type]
        assert (a.forecast_weights, a.absorbed, a.scenario) == (b.forecast_weights, b.absorbed, b.scenario)
    if requested.get("wrong_model") == "DRIVEN":
        assert runs[1][-1].scenario == "DRIVEN"  # the driven pendulum was absorbed
    if scenario == "DRIVEN" and kind == "UKF":
        assert any(a.forecast_weights is not None for a in runs[1])


# -- skip sequences against the truth --------------------------------------------------------------


def skip_pattern(ticks: int, seed: int) -> set[int]:
    """Seeded LOCKSTEP skips: lone ones and bursts of 2-5 ticks, about a third of all ticks."""
    rng = np.random.default_rng(seed)
    skipped: set[int] = set()
    k = 2
    while k < ticks:
        if rng.random() < 0.25:
            burst = int(rng.integers(1, 6))
            skipped.update(range(k, min(k + burst, ticks)))
            k += burst + 1
        else:
            k += 1
    return skipped


def drive(estimator: Estimator, frames: list[Measurement], skipped: set[int]) -> np.ndarray:
    """Run the sequence; the qpos error against the truth on every skipped tick (rad)."""
    estimator.initialise(frames[0])
    errors = []
    for k in range(1, len(frames)):
        estimate = estimator.predict(ctrl=frames[k].ctrl)
        if k in skipped:
            errors.append(np.max(np.abs(estimate.qpos - frames[k].qpos)))
        else:
            estimator.update(frames[k])
    return np.array(errors)


def truth(model: mujoco.MjModel, ticks: int, nstep: int, qpos0: np.ndarray) -> list[Measurement]:
    d = mujoco.MjData(model)
    d.qpos[:] = qpos0
    frames = []
    for _ in range(ticks):
        frames.append(Measurement(qpos=d.qpos.copy(), qvel=d.qvel.copy()))
        for _ in range(nstep):
            mujoco.mj_step(model, d)
    return frames


@pytest.mark.parametrize("n", [1, 2, 3])
@pytest.mark.parametrize("preset", ["JITDYN", "THESIS"])
def test_passive_pendulum_predictions_stay_close_to_the_truth_and_far_below_dead_reckoning(
    n: int, preset: str
) -> None:
    model = pendulum(n)
    ukf_config = resolve(model, "PASSIVE", preset)
    cv_config = resolve(model, "PASSIVE", requested={"estimator": "CONSTANT_VELOCITY"})
    frames = truth(model, 200, ukf_config.steps_per_tick, qpos0=np.array([1.2, -0.6, 0.4])[:n])
    skipped = skip_pattern(len(frames), seed=n)
    assert 40 < len(skipped) < 100
    with WorkerPool(2) as pool:
        ukf_errors = drive(make_estimator(model, ukf_config, pool=pool), frames, skipped)
        cv_errors = drive(make_estimator(model, cv_config, pool=pool), frames, skipped)
    rms_ukf = float(np.sqrt(np.mean(ukf_errors**2)))
    rms_cv = float(np.sqrt(np.mean(cv_errors**2)))
    # Measured: max 0.002-0.010 rad, RMS 0.3-0.5 % of constant velocity's.
    assert ukf_errors.max() < 0.03  # rad, over bursts of up to 5 ticks (0.25 s)
    assert rms_ukf < 0.02 * rms_cv, (rms_ukf, rms_cv)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_controlled_and_external_pendulums_track_through_skips(n: int) -> None:
    model = pendulum(n)
    d = mujoco.MjData(model)
    d.qpos[:] = np.array([0.5, -0.3, 0.2])[:n]
    frames = [Measurement(qpos=d.qpos.copy(), qvel=d.qvel.copy(), ctrl=np.zeros(n))]
    for k in range(1, 150):
        d.ctrl[:] = 3.0 * np.sin(0.2 * k + np.arange(n))
        for _ in range(round(0.05 / model.opt.timestep)):
            mujoco.mj_step(model, d)
        frames.append(Measurement(qpos=d.qpos.copy(), qvel=d.qvel.copy(), ctrl=d.ctrl.copy()))
    skipped = skip_pattern(len(frames), seed=10 + n)
    with WorkerPool(2) as pool:
        controlled = resolve(model, "CONTROLLED", measured={"qpos", "qvel", "ctrl"})
        external = resolve(model, "EXTERNAL")
        cv = resolve(model, "EXTERNAL", requested={"estimator": "CONSTANT_VELOCITY"})
        errors = {
            name: drive(make_estimator(model, config, pool=pool), frames, skipped)
            for name, config in (("controlled", controlled), ("external", external), ("cv", cv))
        }
    # Knowing the control, the prediction is as good as the passive one's (measured: < 0.003 rad).
    assert errors["controlled"].max() < 0.01
    # Holding the restored force is a constant-acceleration guess: better than constant velocity.
    assert np.mean(errors["external"]) < np.mean(errors["cv"])


@pytest.mark.parametrize("preset", list(Preset))
@pytest.mark.parametrize("scenario", list(Scenario))
@pytest.mark.parametrize("model", ["pendulum", "biped", "ball"])
def test_the_settings_table_is_the_config_and_every_preset_fills_it(
    preset: Preset, scenario: Scenario, model: str
) -> None:
    """Every row of jitdyn.estimator_settings.SETTINGS but the preset is a field of EstimatorConfig
    and a setting of every preset for every scenario, and the presets' values pass the table."""
    mj_model = {
        "pendulum": pendulum(2),
        "biped": mujoco.MjModel.from_xml_string(BIPED),
        "ball": mujoco.MjModel.from_xml_string(
            '<mujoco><worldbody><body><joint name="b" type="ball"/><geom size="0.1" mass="1"/></body>'
            '</worldbody><actuator><motor joint="b" gear="1 0 0 0 0 0"/></actuator></mujoco>'
        ),
    }[model]
    fields = {f.name for f in dataclasses.fields(EstimatorConfig)}
    assert set(SETTING_FIELDS) == set(SETTINGS) - {"preset"}
    assert set(SETTING_FIELDS) <= fields
    values = preset_values(preset, model=mj_model, scenario=scenario)
    assert set(values) == set(SETTING_FIELDS)
    for name, value in values.items():
        assert SETTINGS[name].check(value, argument=name) == value
