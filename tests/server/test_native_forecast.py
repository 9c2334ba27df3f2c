"""The forecast combination in the native engine (native/forecast.cc, matching.cc, prior.cc)
against estimation/forecast.py's ForecastCombiner, its reference: the same sessions fed to both
give the same answers to 1e-9 (weights, qpos, qvel, qacc, var_q, var_qd), with and without the
prior of human motion, and so does a DRIVEN session's whole estimator with either combiner."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import pytest

from jitdyn.experiments.recorded import chain_mjcf
from jitdyn.registry.info import describe_model
from jitdyn.roles import joint_roles
from jitdyn.server.estimation import forecast
from jitdyn.server.estimation.config import Engine
from jitdyn.server.estimation.factory import make_estimator
from jitdyn.server.estimation.forecast import CombinedForecast, ForecastCombiner
from jitdyn.server.estimation.interface import Measurement
from jitdyn.server.estimation.native import _ukf
from jitdyn.server.estimation.native import combiner as native_combiner
from jitdyn.server.estimation.native.combiner import NativeCombiner
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.estimation.predictors import PRIOR
from jitdyn.server.estimation.prior import PriorMatcher, legs_of, library
from jitdyn.server.estimation.propagate import process_model
from jitdyn.server.estimation.ukf import UnscentedFilter
from jitdyn.server.runtime.costs import snapshot_bytes
from tests.server.test_native import ADAPTIVE_TOL, REPLAYED, frames_for, run
from tests.server.test_ukf import config_for, pendulum

MODELS = Path(__file__).resolve().parents[2] / "models"
TOLERANCE = 1e-9
DT = 0.05
# A tick whose posterior force sends its probe to NaN; one whose posterior q (1e160 rad) its
# rollout keeps, finite, with squared errors past the largest float.
DIVERGING, WILD = 304, 216


def _process(links: int = 2) -> mujoco.MjModel:
    model = mujoco.MjModel.from_xml_path(str(MODELS / f"pendulum_{links}.xml"))
    return process_model(model, scenario="DRIVEN")


def _frames(model: mujoco.MjModel, ticks: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """A pendulum under a smooth torque whose pattern repeats (motion matching finds it), with a
    little noise on the frames."""
    rng = np.random.default_rng(seed)
    d = mujoco.MjData(model)
    d.qpos[:] = 0.3
    steps = round(DT / model.opt.timestep)
    out = []
    for k in range(ticks):
        d.qfrc_applied[:] = 2.0 * np.sin(0.3 * k + np.arange(model.nv))
        mujoco.mj_step(model, d, steps)
        out.append(
            (d.qpos + 1e-3 * rng.standard_normal(model.nv), d.qvel + 1e-2 * rng.standard_normal(model.nv))
        )
    return out


def _answer(a: CombinedForecast | None) -> np.ndarray | None:
    if a is None:
        return None
    return np.concatenate([a.weights, a.qpos, a.qvel, a.qacc, a.var_q, a.var_qd])


@dataclass
class _Log:
    answers: list[np.ndarray | None]
    weights: list[np.ndarray]  # of the answers given


def _session(
    combiner: Any,
    model: mujoco.MjModel,
    *,
    ramp: bool,
    ticks: int = 520,
    seed: int = 0,
    frames: list[tuple[np.ndarray, np.ndarray]] | None = None,
    early: bool = False,
) -> _Log:
    """A session with gaps of 1 to 14 ticks, a second frame in some ticks, frames far off the motion
    (a landing's impact), a jolted last frame before some gaps, a probe under a force that diverges,
    and the noise of the frames taken out of some answers; frames: the motion's (q, qd) per tick,
    else a pendulum's (_frames); early: gaps in the first 50 ticks too, while horizons have fewer
    than MIN_SAMPLES scores and LEARNED fewer than LEARNED_SAMPLES."""
    frames = _frames(model, ticks, seed) if frames is None else frames[:ticks]
    rng = np.random.default_rng(seed + 1)
    nv = model.nv
    gaps = {
        k: length for k, length in zip(range(60, ticks, 23), [1, 3, 7, 14, 2, 5, 11, 4, 9] * 5, strict=False)
    }
    if early:
        gaps |= {6: 4, 15: 9, 30: 14, 47: 6}
    log = _Log([], [])
    gap_left, ended = 0, False

    def ask(**kwargs: Any) -> None:
        a = combiner.forecast(**kwargs)
        log.answers.append(_answer(a))
        if a is not None:
            log.weights.append(np.asarray(a.weights))

    for k, (q, v) in enumerate(frames):
        if k:
            combiner.advance()
        gap_left = gaps.get(k, gap_left)
        if gap_left:
            gap_left, ended = gap_left - 1, True
            noisy = k % 2 == 0
            ask(noise_q=np.full(nv, 1e-6) if noisy else None, noise_qd=np.full(nv, 1e-4) if noisy else None)
            continue
        if ended:
            ask(ended=True)
            ended = False
        q = q + (2.0 if k % 61 == 50 else 0.0)  # far off the motion: a regime change
        if k + 1 in gaps and k % 2 == 0:
            v = v + 6.0  # a jolted last frame: the novelty guard
        force = 0.5 * np.sin(0.1 * k + np.arange(nv))
        if k == DIVERGING:
            force = np.full(nv, np.inf)
        rate = 0.3 * np.cos(0.1 * k + np.arange(nv)) if ramp else None
        mean = (q + 1e-3 * rng.standard_normal(nv), v + 1e-2 * rng.standard_normal(nv))
        if k == WILD:
            mean = (np.full(nv, 1e160), mean[1])
        act = np.full(model.na, 0.5 + 0.3 * np.sin(0.2 * k))
        for second in (False, True) if k % 41 == 7 else (False,):  # a second frame in some ticks
            combiner.observe(
                q + (1e-3 if second else 0.0), v, mean_qpos=mean[0], mean_qvel=mean[1], act=act,
                force=force, rate=rate,
            )  # fmt: skip
        if k % 3 == 0:
            ask()
    return log


def _pair(model: mujoco.MjModel, horizon: int) -> tuple[ForecastCombiner, NativeCombiner]:
    return (
        ForecastCombiner(model, dt=DT, steps_per_tick=10, horizon=horizon, learner=True),
        NativeCombiner(model, dt=DT, steps_per_tick=10, horizon=horizon),
    )


def _assert_equal(a: _Log, b: _Log) -> None:
    assert len(a.answers) == len(b.answers)
    for k, (x, y) in enumerate(zip(a.answers, b.answers, strict=True)):
        assert (x is None) == (y is None), k
        if x is not None and y is not None:
            np.testing.assert_allclose(y, x, rtol=0.0, atol=TOLERANCE, err_msg=f"answer {k}")


@pytest.mark.parametrize("ramp", [False, True], ids=["held", "ramped"])
@pytest.mark.parametrize("horizon", [10, 25])
def test_the_native_combination_answers_as_the_python_one(ramp: bool, horizon: int) -> None:
    model = _process()
    python, native = _pair(model, horizon)
    a, b = _session(python, model, ramp=ramp), _session(native, model, ramp=ramp)
    _assert_equal(a, b)
    given = a.weights
    assert len(given) > 100
    assert any(w[4] > 0.01 for w in given)  # LEARNED took weight
    assert any(w[0] > 0.01 for w in given)  # and MODEL


@pytest.mark.parametrize(("rule", "off"), [("SURPRISE", 1e100), ("NOVELTY", 1e100)])
def test_the_session_takes_the_regime_change_and_the_novelty_guard(
    monkeypatch: pytest.MonkeyPatch, rule: str, off: float
) -> None:
    """The sessions above go through both rules: the Python combiner with the rule unable to fire
    answers otherwise, and the native one (the rule in C++) answers as the Python one with it."""
    model = _process()
    python, native = _pair(model, 10)
    expected = _session(python, model, ramp=False)
    monkeypatch.setattr(forecast, rule, off)
    without = _session(
        ForecastCombiner(model, dt=DT, steps_per_tick=10, horizon=10, learner=True), model, ramp=False
    )
    differs = [
        x is not None and y is not None and not np.allclose(x, y, rtol=0.0, atol=1e-6)
        for x, y in zip(expected.answers, without.answers, strict=True)
    ]
    assert sum(differs) > 5, sum(differs)
    _assert_equal(expected, _session(native, model, ramp=False))


@pytest.mark.parametrize("leg", [False, True], ids=["pendulum", "leg-with-prior"])
def test_a_late_frames_replay_is_the_first_run_and_the_python_ones(leg: bool) -> None:
    """Snapshot, run on, restore, run again: the native combiner answers as it did the first time
    and as the Python one does through the same replay (with the prior: its ring of frames too);
    reset forgets the scores alike."""
    if leg:
        model, python, native, signs = _leg_pair(chain_mjcf(), 10)
        frames, pair = _walk(model.nv, signs, 200, seed=3), (python, native)
    else:
        model = _process()
        frames, pair = _frames(model, 200, seed=3), _pair(model, 10)
    runs: list[list[np.ndarray | None]] = []
    for combiner in pair:
        answers: list[np.ndarray | None] = []

        def tick(k: int, c: Any = combiner, out: list[np.ndarray | None] = answers) -> None:
            c.advance()
            if k % 17 in (5, 6, 7, 8):
                out.append(_answer(c.forecast(noise_q=np.full(model.nv, 1e-6))))
                return
            if k % 17 == 9:  # the frame that ends a gap
                out.append(_answer(c.forecast(ended=True)))
            q, v = frames[k]
            force, rate = np.full(model.nv, np.sin(0.1 * k)), 0.2 * np.cos(0.1 * k + np.arange(model.nv))
            c.observe(q, v, mean_qpos=q, mean_qvel=v, act=np.zeros(0), force=force, rate=rate)

        for k in range(100):
            tick(k)
        snap = combiner.snapshot()
        assert snapshot_bytes(snap) > 8 * 5 * 5 * 11  # a session's history counts its covariances at least
        first = len(answers)
        for k in range(100, 160):
            tick(k)
        once = answers[first:]
        combiner.restore(snap)
        del answers[first:]
        for k in range(100, 160):
            tick(k)
        assert sum(a is not None for a in once) > 10
        for a, b in zip(once, answers[first:], strict=True):
            assert (a is None) == (b is None)
            if a is not None and b is not None:
                np.testing.assert_array_equal(a, b)
        combiner.reset()
        for k in range(160, 200):
            tick(k)
        runs.append(answers)
    _assert_equal(_Log(runs[0], []), _Log(runs[1], []))


def test_a_driven_estimator_answers_alike_with_either_combiner() -> None:
    """A DRIVEN session's whole estimator (the JITDYN preset: native engine, adaptive noise, the
    forecast combination), with the native combiner and with the Python one (`native_forecast`
    False): the same states, covariances, NIS, weights and flags over 500 ticks of noisy frames
    with gaps, repeated frames and late frames' replays, to the adaptive noise's tolerance."""
    model = pendulum(2)
    native = config_for(model, "DRIVEN")
    assert native.engine == Engine.NATIVE
    python = dataclasses.replace(native, native_forecast=False)
    with WorkerPool(1) as pool:
        for config, kind in ((native, NativeCombiner), (python, ForecastCombiner)):
            built = make_estimator(model, config, pool=pool)
            assert isinstance(built, UnscentedFilter)
            assert built._parts.foresight is not None
            assert isinstance(built._parts.foresight.combiner, kind)
    frames = frames_for(model, native)
    (got, seen), (expected, seen_python) = run(model, native, frames), run(model, python, frames)
    assert seen == seen_python
    assert seen["forecast"] > 50 and seen["replayed"] == len(REPLAYED), seen
    assert len(got) == len(expected)
    for i, (a, b) in enumerate(zip(got, expected, strict=True)):
        # The combiners agree to 1e-9 tick by tick (the tests above); here the adaptive noise feeds
        # each tick's rounding back into Q and R, and over 500 ticks it grows to 3.6e-9 on a qacc
        # of 0.6, as it does between the engines themselves (test_native's ADAPTIVE_TOL).
        np.testing.assert_allclose(a, b, rtol=ADAPTIVE_TOL, atol=ADAPTIVE_TOL, err_msg=f"output {i}")


def test_a_leg_estimator_answers_alike_with_either_combiner() -> None:
    """The same for a leg whose joints have roles, the prior among the predictors: a DRIVEN
    session's whole estimator with the native combiner and with the Python one, 500 ticks with
    gaps and late frames' replays."""
    legs = mujoco.MjModel.from_xml_string(chain_mjcf())
    roles = joint_roles(describe_model(legs).joints, ())
    native = dataclasses.replace(config_for(legs, "DRIVEN", dt=LEG_DT), roles=roles)
    python = dataclasses.replace(native, native_forecast=False)
    signs = {d: s for leg in legs_of(roles) for d, s in zip(leg.dofs, leg.signs, strict=True) if d >= 0}
    frames = [Measurement(qpos=q, qvel=v) for q, v in _walk(legs.nv, signs, 500, seed=9)]
    (got, seen), (expected, seen_python) = run(legs, native, frames), run(legs, python, frames)
    assert seen == seen_python
    assert seen["forecast"] > 50 and seen["replayed"] == len(REPLAYED), seen
    for i, (a, b) in enumerate(zip(got, expected, strict=True)):
        np.testing.assert_allclose(a, b, rtol=ADAPTIVE_TOL, atol=ADAPTIVE_TOL, err_msg=f"output {i}")


def test_the_fast_engine_keeps_the_python_combiner_and_the_prior_goes_native() -> None:
    """The FAST engine combines in Python; the NATIVE engine combines natively for a model whose
    joints have leg roles too, the prior of human motion among its predictors."""
    model = pendulum(2)
    fast = dataclasses.replace(config_for(model, "DRIVEN"), engine=Engine.FAST)
    legs = mujoco.MjModel.from_xml_string(chain_mjcf())
    roles = joint_roles(describe_model(legs).joints, ())
    native = dataclasses.replace(config_for(legs, "DRIVEN"), roles=roles)
    assert native.engine == Engine.NATIVE and legs_of(roles)
    with WorkerPool(1) as pool:
        for m, config, kind in ((model, fast, ForecastCombiner), (legs, native, NativeCombiner)):
            built = make_estimator(m, config, pool=pool)
            assert isinstance(built, UnscentedFilter) and built._parts.foresight is not None
            assert isinstance(built._parts.foresight.combiner, kind)
            assert (PRIOR.names[0] in built._parts.foresight.combiner.predictors) == (m is legs)


def test_a_filled_window_matches_alike() -> None:
    """fill_window records motion matching's whole window and scores nothing, in either combiner;
    the session after it answers alike, and the combiners say the same of themselves."""
    model = _process()
    python, native = _pair(model, 10)
    assert native.predictors == python.predictors
    assert (native.horizon, native.nv, native.na) == (python.horizon, python.nv, python.na)

    def frame(tick: int) -> tuple[np.ndarray, np.ndarray]:
        t = tick * DT
        return 0.3 * np.sin(t + np.arange(model.nv)), 0.3 * np.cos(t + np.arange(model.nv))

    assert native.fill_window(frame) == python.fill_window(frame) == 400  # 20 s at 50 ms
    _assert_equal(
        _session(python, model, ramp=False, ticks=200), _session(native, model, ramp=False, ticks=200)
    )


ACTIVATED = """
<mujoco>
  <option timestep="0.005"/>
  <worldbody>
    <body><joint name="a" type="hinge" axis="0 1 0" damping="0.1"/>
      <geom type="capsule" size="0.02" fromto="0 0 0 0 0 -0.3" mass="1"/>
      <body pos="0 0 -0.3"><joint name="b" type="hinge" axis="0 1 0" damping="0.1"/>
        <geom type="capsule" size="0.02" fromto="0 0 0 0 0 -0.3" mass="1"/></body></body>
  </worldbody>
  <actuator>
    <general joint="a" dyntype="filter" dynprm="0.05" gainprm="5"/>
    <general joint="b" dyntype="integrator" gainprm="3"/>
  </actuator>
</mujoco>
"""


def test_a_model_with_activations_carries_them_alike() -> None:
    """Activations (na = 2) travel with each probe's state, in the columns before its force (the
    process model's actuation is off, so they move no joint: a column out of place would move the
    force, the rate and the anchor instead), over a session at another timestep."""
    model = process_model(mujoco.MjModel.from_xml_string(ACTIVATED), scenario="DRIVEN")
    assert model.na == 2
    python, native = _pair(model, 10)
    _assert_equal(
        _session(python, model, ramp=True, ticks=300), _session(native, model, ramp=True, ticks=300)
    )


# Two legs and a joint of neither: the right one with hip, knee and ankle; the left one without an
# ankle and its knee's positive direction extension (sign -1); the trunk's joint no role's.
LEGS = """
<mujoco>
  <option timestep="0.002"/>
  <worldbody>
    <body name="trunk" pos="0 0 1"><joint name="lumbar" type="hinge" axis="1 0 0" damping="1"/>
      <geom type="box" size="0.1 0.1 0.1" mass="10"/>
      <body name="thigh_r" pos="0 -0.1 -0.1"><joint name="hip_flexion_r" type="hinge" axis="0 -1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.42" size="0.06" mass="10"/>
        <body pos="0 0 -0.42"><joint name="knee_flexion_r" type="hinge" axis="0 1 0"/>
          <geom type="capsule" fromto="0 0 0 0 0 -0.43" size="0.04" mass="3"/>
          <body pos="0 0 -0.43"><joint name="ankle_flexion_r" type="hinge" axis="0 -1 0"/>
            <geom type="capsule" fromto="0 0 0 0.25 0 0" size="0.03" mass="1"/></body></body></body>
      <body name="thigh_l" pos="0 0.1 -0.1"><joint name="hip_flexion_l" type="hinge" axis="0 -1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.42" size="0.06" mass="10"/>
        <body pos="0 0 -0.42"><joint name="knee_extension_l" type="hinge" axis="0 -1 0"/>
          <geom type="capsule" fromto="0 0 0 0 0 -0.43" size="0.04" mass="3"/></body></body>
    </body>
  </worldbody>
</mujoco>
"""
LEG_DT = 0.01
LEFT_OUT = "moore"  # whose walk the sessions replay, left out of their prior


def _walk(nv: int, signs: dict[int, float], ticks: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """LEFT_OUT's walk as the library holds it, at LEG_DT: dof d of the model takes joint column
    d % 3 of the walk, half a stride later on every other leg, times signs[d]; dofs of no leg a
    third of the hip's swing (the whole motion repeats, so motion matching finds it: without a
    match LEARNED answers as CONSTANT_VELOCITY, and the weights between two equal predictors are
    the solver's rounding); a little noise on the frames."""
    full = library()
    rows = np.flatnonzero(full.subject == full.subjects.index(LEFT_OUT))
    q = np.nan_to_num(full.q[rows])
    v = np.gradient(q, LEG_DT, axis=0)
    rng = np.random.default_rng(seed)
    out = []
    for k in range(ticks):
        qk, vk = np.zeros(nv), np.zeros(nv)
        for d in range(nv):
            if d in signs:
                j = (k + 55 * (d // 3)) % q.shape[0]
                qk[d], vk[d] = signs[d] * q[j, d % 3], signs[d] * v[j, d % 3]
            else:
                j = k % q.shape[0]
                qk[d], vk[d] = 0.3 * q[j, 0], 0.3 * v[j, 0]
        out.append((qk + 1e-3 * rng.standard_normal(nv), vk + 1e-2 * rng.standard_normal(nv)))
    return out


def _leg_pair(
    xml: str, horizon: int
) -> tuple[mujoco.MjModel, ForecastCombiner, NativeCombiner, dict[int, float]]:
    """A leg model's process model, the Python and the native combiner with the prior (its walker
    left out), and the sign of each leg's dof."""
    model = mujoco.MjModel.from_xml_string(xml)
    legs = legs_of(joint_roles(describe_model(model).joints, ()))
    assert legs
    chosen = library((LEFT_OUT,))
    process = process_model(model, scenario="DRIVEN")

    def prior() -> PriorMatcher:
        return PriorMatcher(chosen, legs=legs, nv=model.nv, dt=LEG_DT)

    signs = {d: s for leg in legs for d, s in zip(leg.dofs, leg.signs, strict=True) if d >= 0}
    return (
        process,
        ForecastCombiner(process, dt=LEG_DT, steps_per_tick=5, horizon=horizon, learner=True, prior=prior()),
        NativeCombiner(process, dt=LEG_DT, steps_per_tick=5, horizon=horizon, prior=prior()),
        signs,
    )


@pytest.mark.parametrize(
    ("xml", "horizon"),
    [(chain_mjcf(), 10), (chain_mjcf(), 25), (LEGS, 25)],
    ids=["leg-10", "leg-25", "two-legs"],
)
def test_the_native_prior_answers_as_the_python_one(xml: str, horizon: int) -> None:
    """A leg model's session (a walk its prior does not hold, with the gaps, far-off frames, jolts
    and diverging probes of _session) answers alike tick by tick from both combiners with the prior:
    its matches, its continuations, its weight of its own before MIN_SAMPLES, and PRIOR's weight 0
    on a probe without a match."""
    process, python, native, signs = _leg_pair(xml, horizon)
    assert native.predictors == python.predictors and native.predictors[-1] == PRIOR.names[0]
    frames = _walk(process.nv, signs, 600, seed=5)
    a = _session(python, process, ramp=False, ticks=600, frames=frames, early=True)
    b = _session(native, process, ramp=False, ticks=600, frames=frames, early=True)
    _assert_equal(a, b)
    given = np.array(a.weights)
    assert len(given) > 100
    # PRIOR took weight (which it has only on a probe with a match of it).
    assert (given[:, -1] > 0.05).sum() >= 3
    # The first gap (ticks 6-9, asked at each) is answered at every tick: at its last, 4 ticks on,
    # the horizon has fewer than MIN_SAMPLES scores, and only the predictors the prior's scores
    # cover weigh (not MODEL, not LEARNED).
    first_gap = a.answers[2:6]
    assert all(x is not None for x in first_gap)
    last = first_gap[-1]
    assert last is not None and last[0] == 0.0 and last[4] == 0.0


def _onset(nv: int, ticks: int, start: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """A motion that is not gait: a slow small swing, and from tick `start` a movement that builds
    its speed and comes to rest (0.8 s^2 e^-s, s in seconds from the start), larger on every later
    dof; a little noise on the frames."""
    rng = np.random.default_rng(seed)
    scale = 1.0 + 0.3 * np.arange(nv)
    out = []
    for k in range(ticks):
        t = k * LEG_DT
        s = max(0.0, t - start * LEG_DT)
        swing = np.arange(nv) + 2.0 * t
        q = 0.02 * np.sin(swing) + 0.8 * s * s * np.exp(-s) * scale
        v = 0.04 * np.cos(swing) + 0.8 * (2.0 * s - s * s) * np.exp(-s) * scale
        out.append((q + 1e-4 * rng.standard_normal(nv), v + 1e-3 * rng.standard_normal(nv)))
    return out


@pytest.mark.parametrize("rule", ["settled", "agreement"])
def test_a_start_of_motion_after_a_slow_start_answers_alike(
    monkeypatch: pytest.MonkeyPatch, rule: str
) -> None:
    """A leg session with the prior on a motion that is not gait (_onset, from tick 10) goes through
    both rules of a short past: the prior's scores counted as far as the session's agree with them,
    and before SETTLED scores the novelty guard judging the reference's own predictors by their share
    not the reference's. The Python combiner without the rule answers otherwise, and the native one
    (the rule in C++) answers as the Python one with it
    (docs/decisions/0222-a-short-past-does-not-judge-a-start-of-motion.md)."""
    process, python, native, _ = _leg_pair(chain_mjcf(), 25)
    frames = _onset(process.nv, 600, 10, seed=5)

    def session(combiner: Any) -> _Log:
        return _session(combiner, process, ramp=False, ticks=600, frames=frames, early=True)

    expected = session(python)
    if rule == "settled":
        monkeypatch.setattr(forecast, "SETTLED", 0)
    else:
        monkeypatch.setattr(ForecastCombiner, "_agreement", lambda self, h: 1.0)
    without = session(_leg_pair(chain_mjcf(), 25)[1])
    differs = [
        x is not None and y is not None and not np.allclose(x, y, rtol=0.0, atol=1e-6)
        for x, y in zip(expected.answers, without.answers, strict=True)
    ]
    assert sum(differs) >= 2, sum(differs)
    _assert_equal(expected, session(native))


def test_a_prior_that_does_not_fit_is_refused() -> None:
    """A prior matcher of another dt, and a leg whose table, dofs and signs disagree, are refused
    with errors that say what is wrong."""
    model = mujoco.MjModel.from_xml_string(chain_mjcf())
    legs = legs_of(joint_roles(describe_model(model).joints, ()))
    process = process_model(model, scenario="DRIVEN")
    other = PriorMatcher(library((LEFT_OUT,)), legs=legs, nv=3, dt=0.02)
    with pytest.raises(ValueError, match=r"the prior's matcher has dt 0.02, the combiner 0.01"):
        NativeCombiner(process, dt=LEG_DT, steps_per_tick=5, horizon=10, prior=other)
    table = native_combiner.prior_table(library((LEFT_OUT,)), np.array([0, 1, 2]))
    with pytest.raises(ValueError, match=r"a prior leg's table, dofs and signs disagree in their sizes"):
        _ukf.Combiner(
            process._address, dt=LEG_DT, steps_per_tick=5, horizon=10, legs=[(table, [0, 1], [1.0, 1.0])]
        )
    with pytest.raises(ValueError, match=r"a prior leg's dof must be in \[0, 3\), got 7"):
        _ukf.Combiner(
            process._address, dt=LEG_DT, steps_per_tick=5, horizon=10, legs=[(table, [0, 1, 7], [1.0] * 3)]
        )
    with pytest.raises(
        ValueError, match=r"the prior's scores must have horizon \+ 1 = 11 covariances each, got 2"
    ):
        _ukf.Combiner(
            process._address, dt=LEG_DT, steps_per_tick=5, horizon=10, legs=[(table, [0, 1, 2], [1.0] * 3)],
            prior_cov=[np.eye(4)] * 2, prior_cov_v=[np.eye(4)] * 2,
        )  # fmt: skip
