"""The native engine (server/estimation/native/) against the Python one it mirrors (FAST,
server/estimation/fast.py): one UnscentedFilter each, the same config but the engine, the same
500 noisy frames with gaps, a repeated frame, a frame far off, a late frame's replay, glances and
extrapolations. Everything answered agrees to 1e-9 (absolute, and relative past 1), but where
the adaptive noise amplifies rounding (TOL and its neighbours below say how far)."""

from __future__ import annotations

import dataclasses
from collections import Counter
from pathlib import Path

import mujoco
import numpy as np
import pytest

from jitdyn.server.estimation.config import Engine, EstimatorConfig, resolve_config
from jitdyn.server.estimation.core import PythonCore
from jitdyn.server.estimation.fast import FastUKF
from jitdyn.server.estimation.interface import Estimate, Measurement
from jitdyn.server.estimation.native import Ukf
from jitdyn.server.estimation.native.filter import NativeUKF
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.estimation.ukf import UnscentedFilter
from tests.server.test_ukf import BALL_PENDULUM, config_for, pendulum, simulate, swing

TICKS = 500
# Ticks without their frame: single ticks, gaps of 3 and 12 (the forecast's), every 40 ticks.
SKIPPED = {k for k in range(1, TICKS) if k % 40 in (7, 15, 16, 17) or 25 <= k % 40 <= 30}
REPEATED = {60, 260}  # a second frame for the same tick
FAR_OFF = {150, 151, 152, 153}  # frames OFFSET rad off: the guard's business
OFFSET = 1.0
REPLAYED = {100, 300, 420}  # a late frame: back to the snapshot before its tick, then replay
# |native - python| <= TOL (1 + |python|), entry by entry.
TOL = 1e-9
# The adaptive noise feeds the innovations back into Q and R, and so grows the rounding between
# the engines (Eigen's sums against OpenBLAS's): to 5e-9 over 500 ticks of DRIVEN, and past 1e-7
# on chaotic motion (docs/decisions/0150-native-engine.md).
ADAPTIVE_TOL = 1e-8
CHAOTIC_TOL = 1e-6


def frames_for(
    model: mujoco.MjModel, config: EstimatorConfig, *, swing_scale: float = 0.3
) -> list[Measurement]:
    """A driven double pendulum, measured with noise (seeded): the adaptive noise has work.
    swing_scale 1: a swing the double pendulum turns chaotic under."""
    truth = simulate(
        model,
        TICKS,
        config.steps_per_tick,
        qpos0=swing_scale * np.array([1.0, -0.6]),
        control=lambda k: swing_scale * swing(k)[:2],
    )
    rng = np.random.default_rng(7)
    frames = []
    for k, f in enumerate(truth):
        qpos = f.qpos + rng.normal(0.0, 1e-3, f.qpos.shape)
        if k in FAR_OFF:
            qpos = qpos + OFFSET
        qvel = f.qvel + rng.normal(0.0, 1e-2, f.qvel.shape)
        ctrl = f.ctrl if config.scenario == "CONTROLLED" else None
        frames.append(Measurement(qpos=qpos, qvel=qvel, ctrl=ctrl))
    return frames


def flatten(estimate: Estimate) -> list[np.ndarray]:
    nis = np.nan if estimate.nis is None else estimate.nis
    weights = np.array(estimate.forecast_weights if estimate.forecast_weights is not None else [])
    flags = np.array([estimate.reinitialised, estimate.adapted, estimate.absorbed], dtype=float)
    cov = np.zeros(0) if estimate.covariance is None else np.array(estimate.covariance)
    return [np.array(estimate.state), np.array(estimate.qacc), cov, np.array([nis]), weights, flags]


def run(
    model: mujoco.MjModel, config: EstimatorConfig, frames: list[Measurement]
) -> tuple[list[np.ndarray], Counter[str]]:
    """Every answer of a session, flattened, and how often each branch showed in them."""
    out: list[np.ndarray] = []
    seen: Counter[str] = Counter()

    def answer(estimate: Estimate) -> None:
        out.extend(flatten(estimate))
        seen.update(k for k in ("reinitialised", "adapted", "absorbed") if getattr(estimate, k))
        seen["forecast"] += estimate.forecast_weights is not None

    with WorkerPool(1) as pool:
        f = UnscentedFilter(model, config, pool=pool)
        f.initialise(frames[0])
        snapshot = f.snapshot()
        for k in range(1, len(frames)):
            if k in REPLAYED:  # tick k - 3's frame came late: back before it, and forward again
                f.restore(snapshot)
                for j in range(k - 3, k):
                    f.advance(ctrl=frames[j].ctrl)
                    answer(f.update(frames[j]))
                seen["replayed"] += 1
            if k % 10 == 0:
                answer(f.glance(2 * config.dt))
                answer(f.extrapolate(config.dt))
            if k + 3 in REPLAYED:  # before tick k, whether its frame comes or not
                snapshot = f.snapshot()
                seen["snapshots"] += 1
            if k in SKIPPED:
                answer(f.predict(ctrl=frames[k].ctrl))
                continue
            f.advance(ctrl=frames[k].ctrl)
            answer(f.update(frames[k]))
            if k in REPEATED:
                answer(f.update(frames[k]))
        seen["repairs"] = f.covariance_repairs
    return out, seen


SCHEMES = ("MERWE", "SIMPLEX", "UNIFORM")


@pytest.mark.parametrize("sigma_points", SCHEMES)
@pytest.mark.parametrize("scenario", ["PASSIVE", "CONTROLLED", "EXTERNAL", "DRIVEN"])
def test_native_engine_equals_the_python_engine(scenario: str, sigma_points: str) -> None:
    tol = ADAPTIVE_TOL if scenario == "DRIVEN" else TOL
    assert_engines_agree(scenario, sigma_points, swing_scale=0.3, tol=tol)


@pytest.mark.parametrize("scenario", ["EXTERNAL", "DRIVEN"])
def test_native_engine_follows_the_python_engine_on_chaotic_motion(scenario: str) -> None:
    assert_engines_agree(scenario, "MERWE", swing_scale=1.0, tol=CHAOTIC_TOL)


def assert_engines_agree(scenario: str, sigma_points: str, *, swing_scale: float, tol: float) -> None:
    model = pendulum(2)
    # The preset's settings but the scheme: adaptive noise and the forecast combination in DRIVEN.
    native = config_for(model, scenario, sigma_points=sigma_points)
    assert native.engine == Engine.NATIVE  # the JITDYN preset's
    python = dataclasses.replace(native, engine=Engine.FAST)
    with WorkerPool(1) as pool:
        assert isinstance(UnscentedFilter(model, native, pool=pool)._kf, NativeUKF)
        assert isinstance(UnscentedFilter(model, python, pool=pool)._kf, PythonCore)
        assert isinstance(UnscentedFilter(model, python, pool=pool)._kf.inner, FastUKF)
    frames = frames_for(model, native, swing_scale=swing_scale)
    (got, seen), (expected, seen_python) = run(model, native, frames), run(model, python, frames)
    assert seen == seen_python
    assert len(got) == len(expected)
    for i, (a, b) in enumerate(zip(got, expected, strict=True)):
        np.testing.assert_allclose(
            a, b, rtol=tol, atol=tol, err_msg=f"output {i} ({scenario}, {sigma_points})"
        )
    # The session went through the branches it is meant to hold the engines to.
    assert seen["replayed"] == seen["snapshots"] == len(REPLAYED)
    if scenario in ("CONTROLLED", "EXTERNAL"):
        assert seen["reinitialised"] > 0, seen  # the guard's restart
    if scenario == "DRIVEN":
        assert min(seen["adapted"], seen["absorbed"], seen["forecast"]) > 0, seen


def ball_frames(model: mujoco.MjModel, config: EstimatorConfig) -> list[Measurement]:
    """The ball pendulum swinging and twisting, its orientation and angular velocity measured
    with noise (seeded; the orientation's noise a small rotation, so it stays a unit quaternion)."""
    d = mujoco.MjData(model)
    d.qpos[:] = [np.cos(0.4), np.sin(0.4), 0.0, 0.0]
    d.qvel[:] = [0.0, 0.5, 1.5]
    rng = np.random.default_rng(11)
    frames = []
    for k in range(TICKS):
        qpos = d.qpos.copy()
        mujoco.mj_integratePos(model, qpos, rng.normal(0.0, 1e-3, 3) + (0.5 if k in FAR_OFF else 0.0), 1.0)
        frames.append(Measurement(qpos=qpos, qvel=d.qvel + rng.normal(0.0, 1e-2, 3)))
        mujoco.mj_step(model, d, config.steps_per_tick)
    return frames


@pytest.mark.parametrize("sigma_points", ["MERWE", "SIMPLEX"])
@pytest.mark.parametrize("scenario", ["PASSIVE", "EXTERNAL", "DRIVEN"])
def test_a_ball_joint_on_its_manifold_is_the_python_engines_too(scenario: str, sigma_points: str) -> None:
    """Quaternion states: mj_integratePos and mj_differentiatePos for the points and residuals,
    and the Karcher mean, in C++ as in server/estimation/manifold.py."""
    model = mujoco.MjModel.from_xml_string(BALL_PENDULUM)
    native = config_for(model, scenario, sigma_points=sigma_points)
    python = dataclasses.replace(native, engine=Engine.FAST)
    with WorkerPool(1) as pool:
        assert isinstance(UnscentedFilter(model, native, pool=pool)._kf, NativeUKF)
    frames = ball_frames(model, native)
    (got, seen), (expected, seen_python) = run(model, native, frames), run(model, python, frames)
    assert seen == seen_python
    tol = ADAPTIVE_TOL if scenario == "DRIVEN" else TOL
    for i, (a, b) in enumerate(zip(got, expected, strict=True)):
        np.testing.assert_allclose(
            a, b, rtol=tol, atol=tol, err_msg=f"output {i} ({scenario}, {sigma_points})"
        )
    assert seen["replayed"] == seen["snapshots"] == len(REPLAYED)


def test_the_compiled_filter_names_what_was_wrong() -> None:
    model = pendulum(2)
    with WorkerPool(1) as pool:
        kf = UnscentedFilter(model, config_for(model, "PASSIVE"), pool=pool)._kf
    assert isinstance(kf, NativeUKF)
    with pytest.raises(ValueError, match=r"x must have shape \(4,\), got 3 x 1"):
        kf.x = np.zeros(3)
    with pytest.raises(ValueError, match=r"z must have 4 entries, got 2"):
        kf.update(np.zeros(2))
    spec: dict[str, object] = {
        "n": 4, "size": 4, "fblocks": 0, "controlled": False, "scheme": 0, "scale": 1.0,
        "unit": np.zeros((0, 0)), "wm": np.ones(9) / 9, "wc": np.ones(9) / 9, "z_index": [0, 1],
        "nstep": 1, "inputs": 0,
    }  # fmt: skip
    for changes, message in [
        ({"n": 6, "size": 6}, r"n must be 4, got 6"),
        ({"scheme": 5}, r"scheme must be 0, 1 or 2, got 5"),
        ({"z_index": [1, 0]}, r"z_index must start with qpos"),
        ({"nstep": 0}, r"nstep must be >= 1, got 0"),
    ]:
        with pytest.raises(ValueError, match=message):
            Ukf(model._address, **{**spec, **changes})  # type: ignore[arg-type]


def test_an_innovation_covariance_that_cannot_be_inverted_is_numpys_error() -> None:
    model = pendulum(2)
    with WorkerPool(1) as pool:
        kf = UnscentedFilter(model, config_for(model, "PASSIVE"), pool=pool)._kf
    assert isinstance(kf, NativeUKF)
    kf.x, kf.P, kf.R = np.zeros(4), np.zeros((4, 4)), np.zeros((4, 4))
    kf.sigmas_f = np.zeros((9, 4))
    with pytest.raises(np.linalg.LinAlgError, match="Singular matrix"):
        kf.update(np.zeros(4))


def _lockstep_answers(address: str, frames: list[Measurement], *, scenario: str) -> list[np.ndarray]:
    """A LOCKSTEP session of pendulum_2 over real gRPC, every third tick skipped: its answers."""
    from jitdyn.client import Client, FrameData, SessionOptions, TickResult

    out: list[np.ndarray] = []
    options = SessionOptions(model_name="pendulum_2", dt=0.05, scenario=scenario)
    with Client(address, timeout=30) as client, client.open_session(options) as session:
        for k, f in enumerate(frames):
            if k % 3 == 2:
                result = session.skip(k)
            else:
                result = session.send_frame(FrameData(seq=k, t=k * 0.05, qpos=f.qpos, qvel=f.qvel))
            assert isinstance(result, TickResult), result
            out += [result.qpos, result.qvel, result.qacc, result.qfrc_inverse, result.covariance_diagonal]
        session.close()
    return out


# PASSIVE (10 s) runs with the slow tests (pytest -m slow), to keep CI under 20 minutes.
@pytest.mark.parametrize("scenario", [pytest.param("PASSIVE", marks=pytest.mark.slow), "DRIVEN"])
def test_a_server_on_either_engine_answers_the_same(tmp_path: Path, scenario: str) -> None:
    """`jitdyn serve --engine python` runs the reference, and says so; a LOCKSTEP session through
    it and through a default server gets the same answers to 1e-9 (1e-8 under DRIVEN's adaptive
    noise)."""
    from tests.server._serve import Serve

    model = pendulum(2)
    frames = frames_for(model, config_for(model, scenario))[:120]
    answers = []
    for engine in ("native", "python"):
        server = Serve(tmp_path / engine, "--engine", engine)
        try:
            answers.append(_lockstep_answers(server.address, frames, scenario=scenario))
            announced = "".join(server.lines)  # printed after the address, read meanwhile
            assert ("the UKF runs on the python engine" in announced) == (engine == "python"), announced
        finally:
            server.stop()
    tol = ADAPTIVE_TOL if scenario == "DRIVEN" else TOL
    for i, (a, b) in enumerate(zip(*answers, strict=True)):
        np.testing.assert_allclose(a, b, rtol=tol, atol=tol, err_msg=f"answer {i // 5}")
    # Two engines did answer: they add in different orders, so somewhere the last bits differ.
    assert any(not np.array_equal(a, b) for a, b in zip(*answers, strict=True))


def test_the_engine_setting_reaches_the_filter() -> None:
    model = pendulum(2)
    assert config_for(model, "PASSIVE").engine == Engine.NATIVE
    python = resolve_config(
        model=model, scenario="PASSIVE", dt=0.05, measured={"qpos", "qvel"}, engine=Engine.FAST
    )
    assert python.engine == Engine.FAST
    thesis = resolve_config(
        model=model,
        scenario="PASSIVE",
        dt=0.05,
        measured={"qpos", "qvel"},
        preset="THESIS",
        engine=Engine.FAST,
    )
    assert thesis.engine == Engine.FILTERPY


def test_an_unknown_engine_is_refused_by_name(tmp_path: Path) -> None:
    import subprocess
    import sys

    done = subprocess.run(
        [sys.executable, "-m", "jitdyn.cli", "serve", "--data", str(tmp_path), "--engine", "fortran"],
        check=False,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode != 0
    assert "--engine: expected one of native, python, got 'fortran'" in done.stderr, done.stderr


def test_the_adaptive_noise_in_cpp_is_adaptive_py() -> None:
    """Both adapters fed the same 400 updates (wild ones, non-finite ones, gaps, absorptions, a
    snapshot taken and replayed from): the same verdicts, R, Q and Q over a gap."""
    from jitdyn.server.estimation.adaptive import NoiseAdapter
    from jitdyn.server.estimation.native.adaptive import NativeNoiseAdapter

    rng = np.random.default_rng(3)
    n, m = 6, 4
    q0 = np.diag(rng.uniform(0.01, 1.0, n))
    q0[0, 3] = q0[3, 0] = 0.005
    kwargs = {
        "r0": np.full(m, 0.01),
        "q0": q0,
        "adapt_q": np.array([True] * 4 + [False] * 2),
        "inflate": True,
    }
    python, native = NoiseAdapter(**kwargs), NativeNoiseAdapter(**kwargs)  # type: ignore[arg-type]
    steps = []
    for k in range(400):
        scale = 30.0 if 100 <= k < 130 else 1.0  # a wrong model for a while: absorptions
        y = rng.normal(0.0, 0.1 * scale, m)
        if k == 50:
            y[1] = np.inf
        steps.append(
            {
                "innovation": y,
                "consecutive": k % 17 != 0,
                "gain": rng.normal(0.0, 0.3, (n, m)),
                "nis": None if k % 23 == 5 else float(y @ y / 0.01),
                "noise_share": float(rng.uniform(0.0, 1.2)),
            }
        )

    def drive(adapter: NoiseAdapter | NativeNoiseAdapter, start: int, stop: int) -> list[np.ndarray]:
        out = []
        for k in range(start, stop):
            verdict = adapter.observe(**steps[k])  # type: ignore[arg-type]
            if verdict.absorb:
                adapter.absorbed()
            if k % 11 == 0:
                adapter.observe_gap(nis=float(steps[k]["innovation"] @ steps[k]["innovation"]), m=m)
            out += [np.array([verdict.adapted, verdict.absorb, adapter.window_full], dtype=float)]
            out += [adapter.R, adapter.Q, adapter.Q_gap, adapter.q_for(2.0 * q0)]
        return out

    got_before, expected_before = drive(native, 0, 200), drive(python, 0, 200)
    snapshots = native.snapshot(), python.snapshot()
    got, expected = drive(native, 200, 400), drive(python, 200, 400)
    native.restore(snapshots[0])
    python.restore(snapshots[1])  # type: ignore[arg-type]
    replayed_native, replayed_python = drive(native, 200, 400), drive(python, 200, 400)
    pairs = zip(got_before + got + replayed_native, expected_before + expected + replayed_python, strict=True)
    for i, (a, b) in enumerate(pairs):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15, err_msg=f"output {i}")
    assert sum(float(a[1]) for a in expected_before + expected if a.shape == (3,)) > 0  # absorbed
    for a, b in zip(got, replayed_native, strict=True):
        np.testing.assert_array_equal(a, b)  # a restore replays bit for bit


def test_the_engine_refuses_another_mujoco_in_one_line() -> None:
    """Built against one MuJoCo, handed another's pointers: refused at import, in one line. (The
    other MuJoCo is stood in for by the running one reporting another version.)"""
    import subprocess
    import sys

    code = "import mujoco\nmujoco.mj_version = lambda: 3016000\nimport jitdyn.server.estimation.native\n"
    done = subprocess.run(
        [sys.executable, "-c", code], check=False, capture_output=True, text=True, timeout=60
    )
    assert done.returncode != 0
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith(
        "jitdyn.errors.FailedPrecondition: jitdyn's native engine was built against MuJoCo "
    ), last
    assert "but MuJoCo 3016000" in last and "reinstall jitdyn" in last, last
