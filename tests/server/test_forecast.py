"""The forecast combination of a DRIVEN filter over gaps (estimation/forecast.py): its weights
and its batched probes against plain references, the calls that step them, its answer on a
motion one predictor gets exactly, and what a session reports over real gRPC (issue 10)."""

from __future__ import annotations

import itertools
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import pytest
from scipy.optimize import minimize

from jitdyn.client import FrameData, SessionOptions, TickResult
from jitdyn.server.estimation import forecast
from jitdyn.server.estimation.config import resolve_config
from jitdyn.server.estimation.extrapolators import EXTRAPOLATORS, extrapolate
from jitdyn.server.estimation.forecast import (
    FORGETTING,
    MAX_NOVELTY,
    MIN_SAMPLES,
    NOVELTY,
    PREDICTORS,
    PROBES,
    SURPRISE,
    CombinedForecast,
    ForecastCombiner,
    _min_variance_weights,
)
from jitdyn.server.estimation.interface import Measurement
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.estimation.predictors import FAMILIES, Probes
from jitdyn.server.estimation.propagate import process_model
from jitdyn.server.estimation.ukf import UnscentedFilter

MODELS = Path(__file__).resolve().parents[2] / "models"


def _pendulum(n: int) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(MODELS / f"pendulum_{n}.xml"))


@pytest.mark.parametrize("seed", range(6))
def test_weights_are_the_least_variance_combination_on_the_simplex(seed: int) -> None:
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((4, 7))
    C = A @ A.T / 7 + np.diag(rng.uniform(0, 0.1, 4))
    w = _min_variance_weights(C)
    assert np.all(w >= 0) and abs(w.sum() - 1.0) < 1e-12
    reference = min(
        minimize(
            lambda x: x @ C @ x,
            start,
            bounds=[(0.0, 1.0)] * 4,
            constraints=[{"type": "eq", "fun": lambda x: x.sum() - 1.0}],
            method="SLSQP",
        ).fun
        for start in np.eye(4)
    )
    assert w @ C @ w <= reference * (1 + 1e-6) + 1e-12


def _reference_weights(C: np.ndarray) -> np.ndarray:
    """The least-variance weights as first written: every subset solved on its own."""
    P = C.shape[0]
    scale = float(np.trace(C)) / P
    if not np.isfinite(scale) or scale <= 0.0:
        return np.eye(P)[0]
    C = C + 1e-9 * scale * np.eye(P)
    best_w, best_v = None, np.inf
    for k in range(1, P + 1):
        for subset in itertools.combinations(range(P), k):
            idx = list(subset)
            try:
                x = np.linalg.solve(C[np.ix_(idx, idx)], np.ones(k))
            except np.linalg.LinAlgError:
                continue
            total = float(x.sum())
            if total <= 0.0 or not np.all(x >= 0.0):
                continue
            w = np.zeros(P)
            w[idx] = x / total
            v = float(w @ C @ w)
            if v < best_v:
                best_w, best_v = w, v
    if best_w is None:
        best_w = np.eye(P)[int(np.argmin(np.diag(C)))]
    return best_w


def test_weights_are_those_of_solving_each_subset_alone() -> None:
    rng = np.random.default_rng(3)
    for trial in range(300):
        A = rng.standard_normal((4, int(rng.integers(1, 8)))) * 10 ** rng.uniform(-6, 2, size=(4, 1))
        C = A @ A.T / 3
        if trial % 3 == 0:  # two identical predictors: singular subsets
            C[1], C[:, 1] = C[0], C[:, 0]
        if trial % 7 == 0:
            C = np.ones((4, 4))
        np.testing.assert_array_equal(_min_variance_weights(C), _reference_weights(C))


@dataclass
class _Probe:
    origin: int
    age: int
    keep: bool
    qpos: np.ndarray
    qvel: np.ndarray
    qacc: np.ndarray
    act: np.ndarray
    force: np.ndarray
    rate: np.ndarray | None
    q0: np.ndarray
    v0: np.ndarray
    a0: np.ndarray


class _ReferenceCombiner:
    """The combination as first written: each probe stepped on one MjData from Python and scored
    one at a time (what the batched ForecastCombiner must give, bit for bit)."""

    def __init__(self, process: mujoco.MjModel, *, dt: float, steps_per_tick: int, horizon: int) -> None:
        self.model, self.data = process, mujoco.MjData(process)
        self.dt, self.nstep, self.h = dt, steps_per_tick, float(process.opt.timestep)
        self.horizon = horizon
        self.stride = max(1, -(-horizon // PROBES))
        self.nv = int(process.nv)
        self.tick = 0
        self.probes: list[_Probe] = []
        self.cov = np.zeros((horizon + 1, len(PREDICTORS), len(PREDICTORS)))
        self.count = np.zeros(horizon + 1)
        self.anchor: tuple[np.ndarray, np.ndarray, int] | None = None

    def advance(self) -> None:
        self.tick += 1
        self.probes = [self._step(p) for p in self.probes]

    def observe(self, qpos: np.ndarray, qvel: np.ndarray, *, mean_qpos: np.ndarray, mean_qvel: np.ndarray,
                act: np.ndarray, force: np.ndarray, rate: np.ndarray | None) -> None:  # fmt: skip
        survivors = []
        for p in self.probes:
            if p.keep and 1 <= p.age <= self.horizon:
                errors = self._positions(p) - qpos[None, :]
                if np.all(np.isfinite(errors)):
                    h, sample = p.age, errors @ errors.T / self.nv
                    d = (1.0 - FORGETTING) / (1.0 - FORGETTING ** (self.count[h] + 1))
                    # A regime change: every predictor's error variance above SURPRISE^2 times its
                    # scored past's replaces the past.
                    past = np.diagonal(self.cov[h])
                    if self.count[h] >= MIN_SAMPLES and np.all(
                        np.diagonal(sample) > SURPRISE * SURPRISE * past
                    ):
                        d = 1.0
                    self.cov[h] = (1.0 - d) * self.cov[h] + d * sample
                    self.count[h] += 1
            if p.keep and p.age < self.horizon:
                survivors.append(p)
        previous = self.anchor
        if previous is not None and previous[2] < self.tick:
            a0 = (qvel - previous[1]) / ((self.tick - previous[2]) * self.dt)
        else:
            a0 = np.zeros(self.nv)
        keep = previous is not None and previous[2] == self.tick - 1 and self.tick % self.stride == 0
        self.anchor = (qpos.copy(), qvel.copy(), self.tick)
        zero = np.zeros(self.nv)
        rate = None if rate is None else rate.copy()
        probe = _Probe(self.tick, 0, keep, mean_qpos.copy(), mean_qvel.copy(), zero, act.copy(), force.copy(),
                       rate, qpos.copy(), qvel.copy(), a0)  # fmt: skip
        self.probes = [*survivors, probe]

    def forecast(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        origin = -1 if self.anchor is None else self.anchor[2]
        latest = next((p for p in reversed(self.probes) if p.age > 0 and p.origin == origin), None)
        if latest is None or self.tick - latest.origin > self.horizon:
            return None  # past the scored horizon the filter answers
        h = min(latest.age, self.horizon)
        if self.count[h] < MIN_SAMPLES:
            return None
        t = latest.age * self.dt
        p = latest
        # The extrapolators' formulas are estimation/extrapolators.py's, here as in the combination.
        moved = [extrapolate(kind, p.q0, p.v0, p.a0, t) for kind in EXTRAPOLATORS]
        q = np.stack([p.qpos, *(m[0] for m in moved)])
        v = np.stack([p.qvel, *(m[1] for m in moved)])
        a = np.stack([p.qacc, *(m[2] for m in moved)])
        C = self.cov[h]
        # The novelty guard: a predictor departing from the reference by more than NOVELTY times
        # the RMS departure of its scored past has its errors scaled by the ratio over NOVELTY (by
        # its square for MODEL, below). The
        # reference is STATIC (row 1) moved towards CONSTANT_ACCELERATION (row 3) as far as the
        # last two frames' velocities agree (v0 and v0 - a0 dt: their product over the larger square).
        before = p.v0 - p.a0 * self.dt
        larger = max(float(p.v0 @ p.v0), float(before @ before))
        share = min(max(float(p.v0 @ before) / larger, 0.0), 1.0) if larger > 0.0 else 0.0
        r = np.array([0.0, 1.0 - share, 0.0, share])
        now = np.mean(np.square(q - r @ q), axis=1)
        Cr = C @ r
        limit = NOVELTY * NOVELTY * np.maximum(np.diagonal(C) - 2.0 * Cr + float(r @ Cr), 0.0)
        novel = now > limit
        novel[1] = False
        if novel.any():
            scale = np.ones(len(PREDICTORS))
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = now / limit
                # MODEL (row 0), the model's rollout: the ratio's square.
                factor = np.sqrt(ratio)
                factor[0] = ratio[0]
                scale[novel] = np.minimum(factor[novel], MAX_NOVELTY)
            C = scale[:, None] * C * scale[None, :]
        w = _reference_weights(C)
        return w, w @ q, w @ v, w @ a

    def _positions(self, p: _Probe) -> np.ndarray:
        t = p.age * self.dt
        return np.stack([p.qpos, *(extrapolate(kind, p.q0, p.v0, p.a0, t)[0] for kind in EXTRAPOLATORS)])

    def _step(self, p: _Probe) -> _Probe:
        if p.age >= self.horizon and p.keep:
            return p  # a scoring probe waits at the horizon for the frame that scores it
        m, d = self.model, self.data
        d.qpos[:], d.qvel[:], d.act[:], d.ctrl[:] = p.qpos, p.qvel, p.act, 0.0
        force = p.force
        if p.rate is None:
            d.qfrc_applied[:] = force
            mujoco.mj_step(m, d, self.nstep)
        else:
            for s in range(self.nstep):
                d.qfrc_applied[:] = force + (s + 0.5) * self.h * p.rate
                mujoco.mj_step(m, d)
            force = force + self.nstep * self.h * p.rate
        return _Probe(p.origin, p.age + 1, p.keep, d.qpos.copy(), d.qvel.copy(), d.qacc.copy(), d.act.copy(),
                      force, p.rate, p.q0, p.v0, p.a0)  # fmt: skip


# A muscle on a tendon drives a hinge with a limit: activation state and a constraint.
_MUSCLE_ARM = """
<mujoco>
  <option timestep="0.002"/>
  <worldbody>
    <site name="origin" pos="0 0 0.2"/>
    <body>
      <joint name="elbow" type="hinge" axis="0 1 0" range="-0.4 0.4" limited="true"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="0.5"/>
      <site name="insertion" pos="0.2 0 0.02"/>
    </body>
  </worldbody>
  <tendon><spatial name="t"><site site="origin"/><site site="insertion"/></spatial></tendon>
  <actuator><muscle tendon="t" name="m"/></actuator>
</mujoco>
"""


@pytest.mark.parametrize("ramp", [False, True], ids=["held force", "ramping force"])
@pytest.mark.parametrize(
    ("name", "dt", "horizon"),
    # pendulum_3: RK4, two steps a tick, a probe every tick; the arm: a muscle's activation, a
    # joint limit, one step a tick, a probe every other tick.
    [("pendulum_3", 0.05, 4), ("muscle arm", 0.002, 30)],
)
def test_batched_probes_answer_as_stepping_each_probe_alone(
    name: str, dt: float, horizon: int, ramp: bool
) -> None:
    """The same frames, posteriors and gaps (some longer than the horizon, so that scoring probes
    wait there together), a snapshot restored halfway: every answer bit for bit the reference's."""
    model = _pendulum(3) if name == "pendulum_3" else mujoco.MjModel.from_xml_string(_MUSCLE_ARM)
    process = process_model(model, scenario="DRIVEN")
    nstep = round(dt / process.opt.timestep)
    combiner = ForecastCombiner(process, dt=dt, steps_per_tick=nstep, horizon=horizon)
    reference = _ReferenceCombiner(process, dt=dt, steps_per_tick=nstep, horizon=horizon)
    truth = mujoco.MjData(model)
    truth.qpos[:] = 0.2
    rng = np.random.default_rng(11)
    lost = {k for k in range(8, 400) if k % (3 * horizon) < horizon + 2 + k % 3}
    snap, answers = None, 0
    for k in range(400):
        truth.ctrl[:] = 0.5 + 0.5 * np.sin(0.05 * k + np.arange(model.nu))
        mujoco.mj_step(model, truth, nstep)
        if k == 200:
            snap = (combiner.snapshot(), len(reference.probes))
            combiner.restore(combiner.snapshot())  # a restore at the same point changes nothing
        if k:
            combiner.advance()
            reference.advance()
        got, expected = combiner.forecast(), reference.forecast()
        assert (got is None) == (expected is None), k
        if got is not None and expected is not None:
            answers += 1
            for a, b in zip((got.weights, got.qpos, got.qvel, got.qacc), expected, strict=True):
                np.testing.assert_array_equal(a, b)
        if k not in lost:
            q, v = truth.qpos.copy(), truth.qvel.copy()
            posterior = {
                "mean_qpos": q + 1e-3 * rng.standard_normal(model.nq),
                "mean_qvel": v + 1e-2 * rng.standard_normal(model.nv),
                "act": truth.act.copy(),
                "force": 0.1 * rng.standard_normal(model.nv),
                "rate": rng.standard_normal(model.nv) if ramp else None,
            }
            combiner.observe(q, v, **posterior)
            reference.observe(q, v, **posterior)
    assert answers > 50 and snap is not None


def _myo_model(name: str) -> mujoco.MjModel:
    import myo_sim  # heavy: only the tests that need it pay for it

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "Attaching a spec with an empty prefix": myo_sim's own
        return myo_sim.load_model(name)


@pytest.mark.parametrize("ramp", [False, True], ids=["held", "ramp"])
def test_a_tick_steps_every_probe_in_one_call_per_physics_step(ramp: bool) -> None:
    """myoElbow, the default DRIVEN session of a driven model, with every probe alive: a tick's
    probes are stepped by one batched call per physics step, whatever their number (the interpreter
    costs about one myoElbow step per probe stepped from Python). Counted as the calls the tick
    makes into MuJoCo's bindings; what a tick costs in time is measured by benchmarks/forecast.py,
    not here."""
    steps = 2
    process = process_model(_myo_model("myoelbow"), scenario="DRIVEN")
    combiner = ForecastCombiner(process, dt=0.002 * steps, steps_per_tick=steps, horizon=100)
    act, force = np.full(process.na, 0.3), np.zeros(process.nv)
    rate = np.full(process.nv, 0.5) if ramp else None

    def tick(k: int) -> None:
        q, v = np.array([0.5 + 0.3 * np.sin(0.01 * k)]), np.array([0.003 * np.cos(0.01 * k)])
        combiner.advance()
        combiner.forecast()
        combiner.observe(q, v, mean_qpos=q, mean_qvel=v, act=act, force=force, rate=rate)

    for k in range(300):  # every probe alive
        tick(k)
    calls: list[str] = []

    def into_mujoco(frame: Any, event: str, function: Any) -> None:
        if event == "c_call" and "mujoco" in str(
            getattr(function, "__module__", None) or type(function.__self__).__module__
        ):
            calls.append(function.__name__)

    ticks = 50
    sys.setprofile(into_mujoco)
    try:
        for k in range(300, 300 + ticks):
            tick(k)
    finally:
        sys.setprofile(None)
    assert calls, "the probes were not stepped at all"
    # Held forces: one call steps every probe through the tick; ramping ones: one per physics step.
    assert len(calls) <= ticks * (steps if ramp else 1), (len(calls), sorted(set(calls)))
    assert PROBES >= 8  # so that stepping them one by one would be many times the calls counted


def test_a_motion_of_constant_acceleration_is_answered_by_constant_acceleration() -> None:
    """q = q0 + v0 t + a t^2 / 2 is what CONSTANT_ACCELERATION extrapolates exactly, and the model
    (a pendulum under gravity and no force) does not: after a few scored frames the combination
    answers a gap with CONSTANT_ACCELERATION alone."""
    model = _pendulum(1)
    dt, nstep = 0.05, 10
    combiner = ForecastCombiner(model, dt=dt, steps_per_tick=nstep, horizon=4)

    def truth(k: int) -> tuple[np.ndarray, np.ndarray]:
        t = k * dt
        return np.array([0.1 + 0.2 * t + 0.3 * t * t]), np.array([0.2 + 0.6 * t])

    assert combiner.forecast() is None  # nothing scored yet
    frames = 30
    for k in range(frames):
        if k:
            combiner.advance()
        q, v = truth(k)
        combiner.observe(q, v, mean_qpos=q, mean_qvel=v, act=np.zeros(0), force=np.zeros(1), rate=None)
    for h in range(1, 5):
        combiner.advance()
        answer = combiner.forecast()
        assert answer is not None
        assert answer.weights[PREDICTORS.index("CONSTANT_ACCELERATION")] > 0.999, answer.weights
        q, v = truth(frames - 1 + h)
        # The ridge that keeps weights finite leaves the others about 1e-7 (qvel differs by more
        # between predictors than qpos does over one tick).
        np.testing.assert_allclose(answer.qpos, q, atol=1e-8)
        np.testing.assert_allclose(answer.qvel, v, atol=1e-5)


class _Bouncing:
    """A predictor the combination does not ship, added as a user would add one: a family with a
    name and a prediction from what a probe holds (estimation/predictors.py). It knows the test's
    motion: q0 - v0 t, the velocity reversed."""

    names = ("REVERSED",)
    learned = False

    def predict(self, probes: Probes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        q = probes.q0 - probes.v0 * probes.t
        v = -np.broadcast_to(probes.v0, q.shape)
        return q[:, None, :], v[:, None, :], np.zeros_like(q)[:, None, :]


def test_a_predictor_is_one_family_and_one_registration() -> None:
    """A combiner given one more family weighs it beside the shipped ones, under its name: on a
    motion only it foresees (each frame's velocity points away from where the body goes) it takes
    the weight. Two predictors of one name are refused."""
    model = _pendulum(1)
    dt = 0.05
    families = (*FAMILIES, _Bouncing())
    combiner = ForecastCombiner(model, dt=dt, steps_per_tick=10, horizon=3, families=families)
    assert combiner.predictors == (*PREDICTORS, "REVERSED")

    def truth(k: int) -> tuple[np.ndarray, np.ndarray]:
        # Moves at +0.4 rad/s, while its frames say -0.4: what REVERSED alone extrapolates exactly.
        return np.array([0.1 + 0.4 * k * dt]), np.array([-0.4])

    frames = 30
    for k in range(frames):
        if k:
            combiner.advance()
        q, v = truth(k)
        combiner.observe(q, v, mean_qpos=q, mean_qvel=v, act=np.zeros(0), force=np.zeros(1), rate=None)
    combiner.advance()
    answer = combiner.forecast()
    assert answer is not None and answer.predictors == combiner.predictors
    assert answer.weights[-1] > 0.999, answer.weights
    np.testing.assert_allclose(answer.qpos, truth(frames)[0], atol=1e-6)
    with pytest.raises(ValueError, match="unique"):
        ForecastCombiner(model, dt=dt, steps_per_tick=10, horizon=3, families=(*FAMILIES, *FAMILIES))


def test_a_predictor_departing_far_beyond_its_scored_past_weighs_less_over_a_gap() -> None:
    """A swing (0.2 sin 4t rad) scored for 2 s: CONSTANT_ACCELERATION forecasts it best at every
    horizon and the scored weights are mostly its own. The last frame before the gap has the
    motion jolted (qd 8 rad/s above the swing's, so qdd 160 rad/s^2 from the frame before): it now
    extrapolates 4.8 rad in 200 ms, far beyond any departure from STATIC its scores have seen, and
    the novelty guard weighs it by that. Measured without the guard: STATIC's weight 0.10 at
    200 ms, the answer 4.26 rad from the last frame (0.89 of CONSTANT_ACCELERATION's departure);
    with it, 0.67 and 1.58 rad (0.33)."""
    model = _pendulum(1)
    dt, frames = 0.05, 40
    combiner = ForecastCombiner(model, dt=dt, steps_per_tick=10, horizon=4)
    static = PREDICTORS.index("STATIC")
    jolt = 8.0
    for k in range(frames):
        if k:
            combiner.advance()
        t = k * dt
        q = np.array([0.1 + 0.2 * np.sin(4 * t)])
        v = np.array([0.8 * np.cos(4 * t) + (jolt if k == frames - 1 else 0.0)])
        combiner.observe(q, v, mean_qpos=q, mean_qvel=v, act=np.zeros(0), force=np.zeros(1), rate=None)
    a0 = (v[0] - 0.8 * np.cos(4 * (frames - 2) * dt)) / dt
    for _ in range(4):
        combiner.advance()
        answer = combiner.forecast()
        assert answer is not None
    t = 4 * dt
    constant_acceleration = abs(v[0] * t + 0.5 * a0 * t * t)
    assert answer.weights[static] > 0.5, answer.weights
    assert abs(float(answer.qpos[0] - q[0])) < 0.5 * constant_acceleration, (
        answer.qpos,
        constant_acceleration,
    )


def _onset_answer(*, confirmed: bool, monkeypatch: pytest.MonkeyPatch) -> tuple[CombinedForecast, float]:
    """The swing of the jolted test scored for 2 s, then a real start of motion: 40 rad/s^2 more
    over its last three frames (qd built over them, q integrated with it), then 200 ms of gap:
    the answer and the truth's q at its end; confirmed False: the guard measures from STATIC alone
    (the last two frames' velocities taken as not agreeing)."""
    if not confirmed:
        monkeypatch.setattr(forecast, "_confirmed", lambda *_: 0.0)
    model = _pendulum(1)
    dt, frames, onset, push = 0.05, 40, 36, 40.0

    def motion(t: float) -> tuple[float, float]:
        s = max(0.0, t - onset * dt)
        return 0.1 + 0.2 * np.sin(4 * t) + 0.5 * push * s * s, 0.8 * np.cos(4 * t) + push * s

    combiner = ForecastCombiner(model, dt=dt, steps_per_tick=10, horizon=4)
    for k in range(frames):
        if k:
            combiner.advance()
        q, v = (np.array([x]) for x in motion(k * dt))
        combiner.observe(q, v, mean_qpos=q, mean_qvel=v, act=np.zeros(0), force=np.zeros(1), rate=None)
    for _ in range(4):
        combiner.advance()
        answer = combiner.forecast()
        assert answer is not None
    return answer, motion((frames + 3) * dt)[0]


def test_a_real_start_of_motion_is_not_taken_for_a_glitch(monkeypatch: pytest.MonkeyPatch) -> None:
    """Where the last frames' velocities agree (the motion built its speed over them, as a real
    start does; the jolted frame above has none of its jolt the frame before), the guard measures
    from what they extrapolate, not from STATIC: the answer follows the motion. Measured: STATIC
    0, CONSTANT_VELOCITY 1.0, 0.74 rad short of the truth after 200 ms; measured from STATIC
    alone, STATIC 1.0 and 1.95 rad short."""
    static = PREDICTORS.index("STATIC")
    answer, truth = _onset_answer(confirmed=True, monkeypatch=monkeypatch)
    from_static, _ = _onset_answer(confirmed=False, monkeypatch=monkeypatch)
    assert answer.weights[static] < 0.1, answer.weights
    assert from_static.weights[static] > 0.9, from_static.weights
    assert abs(float(answer.qpos[0]) - truth) < 0.5 * abs(float(from_static.qpos[0]) - truth)


def _scored_covariances(earlier: float, jolt: float) -> np.ndarray:
    """The pooled covariances C_h (h = 1..4) after a swing (0.2 sin 4t rad) scored for 2 s whose
    frames before the last 7 carry `earlier` more (earlier sin 7t: another scored past, the same
    last frames), and whose last frame is displaced by `jolt` rad."""
    model = _pendulum(1)
    dt, frames = 0.05, 40
    combiner = ForecastCombiner(model, dt=dt, steps_per_tick=10, horizon=4)
    for k in range(frames + 1):
        if k:
            combiner.advance()
        t, other = k * dt, earlier if k < frames - 6 else 0.0
        q = np.array([0.1 + 0.2 * np.sin(4 * t) + other * np.sin(7 * t) + (jolt if k == frames else 0.0)])
        v = np.array([0.8 * np.cos(4 * t) + 7 * other * np.cos(7 * t)])
        combiner.observe(q, v, mean_qpos=q, mean_qvel=v, act=np.zeros(0), force=np.zeros(1), rate=None)
    return combiner.snapshot().cov[1:]


def test_a_score_that_surprises_every_predictor_replaces_the_scored_past() -> None:
    """A last frame 0.5 rad off the swing (a landing's impact: a motion none of the predictors
    foresaw) errs every predictor by more than SURPRISE times the RMS of its scored past at every
    horizon: its score replaces the covariances, and two sessions with different pasts but the same
    last frames hold the same ones (without the rule they differ by up to 0.012 rad^2, the past
    weighing FORGETTING). The same frame not displaced surprises none, and the pasts still count."""
    np.testing.assert_array_equal(_scored_covariances(0.0, jolt=0.5), _scored_covariances(0.05, jolt=0.5))
    assert np.abs(_scored_covariances(0.0, jolt=0.0) - _scored_covariances(0.05, jolt=0.0)).max() > 1e-4


def test_the_combination_is_not_used_before_it_has_scores() -> None:
    model = _pendulum(1)
    combiner = ForecastCombiner(model, dt=0.05, steps_per_tick=10, horizon=4)
    q, v = np.array([0.1]), np.array([0.0])
    # Scoring probes start only from a frame that follows a frame: MIN_SAMPLES - 1 scores at h = 1.
    for k in range(MIN_SAMPLES):
        if k:
            combiner.advance()
        combiner.observe(q, v, mean_qpos=q, mean_qvel=v, act=np.zeros(0), force=np.zeros(1), rate=None)
    combiner.advance()
    assert combiner.forecast() is None


def _driven_frames(model: mujoco.MjModel, ticks: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """A pendulum whose motors follow a smooth torque (held over each 50 ms tick)."""
    d = mujoco.MjData(model)
    d.qpos[:] = 0.3
    steps = round(0.05 / model.opt.timestep)
    out = [(d.qpos.copy(), d.qvel.copy())]
    for k in range(1, ticks):
        d.ctrl[:] = 3.0 * np.sin(0.2 * k + np.arange(model.nu))
        mujoco.mj_step(model, d, steps)
        out.append((d.qpos.copy(), d.qvel.copy()))
    return out


def test_over_gaps_the_combination_beats_the_filter_alone_on_a_driven_pendulum() -> None:
    """The same frames and gaps, FORECAST_FILTER against FORECAST_COMBINED: the RMS q error one
    tick into a gap. Measured (deterministic: no noise): 2.03e-3 rad (filter) against 1.63e-3
    (combined)."""
    model = _pendulum(2)
    frames = _driven_frames(model, 200)
    lost = {k for k in range(20, 200) if k % 10 in (0, 1, 2)}
    errors: dict[str, list[float]] = {}
    with WorkerPool(1) as pool:
        for forecast in ("FILTER", "COMBINED"):
            config = resolve_config(
                model=model,
                scenario="DRIVEN",
                dt=0.05,
                requested={"forecast": forecast},
                model_defaults={},
                measured={"qpos", "qvel"},
            )
            ukf = UnscentedFilter(model, config, pool=pool)
            ukf.initialise(Measurement(qpos=frames[0][0], qvel=frames[0][1]))
            first_gap_tick = []
            for k in range(1, len(frames)):
                estimate = ukf.predict(ctrl=None)
                if k in lost:
                    if k % 10 == 0:
                        first_gap_tick.append(float(np.sqrt(np.mean((estimate.qpos - frames[k][0]) ** 2))))
                        assert (estimate.forecast_weights is not None) == (forecast == "COMBINED")
                        np.testing.assert_array_equal(estimate.state[: model.nq], estimate.qpos)
                else:
                    estimate = ukf.update(Measurement(qpos=frames[k][0], qvel=frames[k][1]))
                    assert estimate.forecast_weights is None
            errors[forecast] = first_gap_tick
    filt = float(np.sqrt(np.mean(np.square(errors["FILTER"][1:]))))
    combined = float(np.sqrt(np.mean(np.square(errors["COMBINED"][1:]))))
    assert combined < 0.85 * filt, (combined, filt)


def test_the_default_driven_filter_is_consistent_over_gaps_of_noisy_frames() -> None:
    """The default DRIVEN session (adaptive noise, the combination answering gaps) on a driven
    pendulum with a wearable's noise (0.005 rad, 0.05 rad/s) and 4-tick gaps every 10 ticks: NEES
    over [q, qd] against the truth, per dimension, from the answers' own covariances, after the
    first fifth of the run. Measured: 1.1 on average (gap ticks 2.1, median 1.4; measured ticks
    0.51); before Q followed the NIS and a gap's answer reported the combination's error, 3.3 (gap
    ticks 6.5, median 3.1; measured ticks 1.4)."""
    model = _pendulum(2)
    frames = _driven_frames(model, 300)
    lost = {k for k in range(20, 300) if k % 10 in (0, 1, 2, 3)}
    rng = np.random.default_rng(5)
    config = resolve_config(
        model=model, scenario="DRIVEN", dt=0.05, requested={}, model_defaults={}, measured={"qpos", "qvel"}
    )
    nv = model.nv
    nees: dict[bool, list[float]] = {True: [], False: []}
    with WorkerPool(1) as pool:
        ukf = UnscentedFilter(model, config, pool=pool)
        ukf.initialise(Measurement(qpos=frames[0][0], qvel=frames[0][1]))
        for k in range(1, len(frames)):
            q, v = frames[k]
            if k in lost:
                estimate = ukf.predict(ctrl=None)
            else:
                ukf.advance(ctrl=None)
                noisy = Measurement(
                    qpos=q + 0.005 * rng.standard_normal(nv), qvel=v + 0.05 * rng.standard_normal(nv)
                )
                estimate = ukf.update(noisy)
            assert estimate.covariance is not None
            error = np.concatenate([q - estimate.qpos, v - estimate.qvel])
            P = estimate.covariance[: 2 * nv, : 2 * nv]
            if k >= len(frames) // 5:
                nees[k in lost].append(float(error @ np.linalg.solve(P, error)) / (2 * nv))
    average = float(np.mean(nees[True] + nees[False]))
    assert 0.5 <= average <= 2.0, (average, np.mean(nees[True]), np.mean(nees[False]))
    assert 0.5 <= float(np.median(nees[True])) <= 2.0, np.median(nees[True])


def test_a_default_session_reports_which_predictors_answered_a_gap(client: Any) -> None:
    model = _pendulum(2)
    frames = _driven_frames(model, 60)
    options = SessionOptions(model_name="pendulum_2", dt=0.05, outputs=("FILTER_STATE",))
    with client.open_session(options) as session:
        assert session.opened.scenario == "DRIVEN"
        assert session.opened.estimator["forecast"] == "COMBINED"
        weights = []
        for k, (q, v) in enumerate(frames):
            if k >= 30 and k % 10 in (0, 1):
                result = session.skip(k)
                assert isinstance(result, TickResult) and result.source == "PREDICTED"
                assert result.forecast_weights is not None
                assert len(result.forecast_weights) == len(PREDICTORS) + 1  # and LEARNED
                # The wire names them, in the weights' order.
                assert result.forecast_predictors == (*PREDICTORS, "LEARNED")
                assert abs(sum(result.forecast_weights) - 1.0) < 1e-9
                np.testing.assert_array_equal(result.filter_state[: model.nq], result.qpos)
                weights.append(result.forecast_weights)
            else:
                result = session.send_frame(FrameData(seq=k, t=k * 0.05, qpos=q, qvel=v))
                assert isinstance(result, TickResult) and result.forecast_weights is None
                assert result.forecast_predictors is None
        assert weights


@pytest.mark.parametrize(
    ("scenario", "estimator"),
    [("PASSIVE", {"wrong_model": "KEEP"}), ("EXTERNAL", {}), ("DRIVEN", {"preset": "THESIS"})],
)
def test_the_thesis_scenarios_and_preset_answer_gaps_with_the_filter(
    client: Any, scenario: str, estimator: dict[str, str]
) -> None:
    model = _pendulum(2)
    frames = _driven_frames(model, 40)
    options = SessionOptions(model_name="pendulum_2", scenario=scenario, dt=0.05, estimator=estimator)
    with client.open_session(options) as session:
        assert session.opened.estimator["forecast"] == "FILTER"
        for k, (q, v) in enumerate(frames):
            if k >= 20 and k % 10 in (0, 1):
                result = session.skip(k)
            else:
                result = session.send_frame(FrameData(seq=k, t=k * 0.05, qpos=q, qvel=v))
            assert isinstance(result, TickResult) and result.forecast_weights is None


def test_the_combination_replays_exactly_after_a_snapshot() -> None:
    """The timewarp restores the combiner with the filter: the same inputs give the same answers."""
    model = _pendulum(2)
    frames = _driven_frames(model, 60)
    config = resolve_config(
        model=model, scenario="DRIVEN", dt=0.05, requested={}, model_defaults={}, measured={"qpos", "qvel"}
    )
    with WorkerPool(1) as pool:
        ukf = UnscentedFilter(model, config, pool=pool)
        ukf.initialise(Measurement(qpos=frames[0][0], qvel=frames[0][1]))
        for k in range(1, 40):
            ukf.predict(ctrl=None)
            ukf.update(Measurement(qpos=frames[k][0], qvel=frames[k][1]))
        snap = ukf.snapshot()
        runs = []
        for _ in range(2):
            ukf.restore(snap)
            answers = [ukf.predict(ctrl=None) for _ in range(3)]
            runs.append([(a.state.copy(), a.forecast_weights) for a in answers])
    for (s1, w1), (s2, w2) in itertools.zip_longest(*runs):
        np.testing.assert_array_equal(s1, s2)
        assert w1 == w2 and w1 is not None


def test_scores_that_wait_to_be_reckoned_give_what_reckoning_each_frame_gives() -> None:
    """With the learned predictor the scores of several frames wait and are reckoned together: a
    combiner asked for a forecast every tick (which reckons what waits) and one asked only over
    gaps answer the gaps bit for bit alike, and so does one restored from a snapshot taken while
    scores wait."""
    model = _pendulum(2)
    process = process_model(model, scenario="DRIVEN")
    frames = _driven_frames(model, 240)
    combiners = [
        ForecastCombiner(process, dt=0.05, steps_per_tick=10, horizon=10, learner=True) for _ in range(3)
    ]
    force = np.zeros(model.nv)
    answers: list[list[np.ndarray]] = [[], [], []]
    for k, (q, v) in enumerate(frames):
        gap = k > 60 and k % 25 >= 17
        for i, combiner in enumerate(combiners):
            combiner.advance()
            if i == 0 or gap:
                answer = combiner.forecast()
                if gap and answer is not None:
                    answers[i].append(np.concatenate([answer.weights, answer.qpos, answer.qvel, answer.qacc]))
            if not gap:
                combiner.observe(q, v, mean_qpos=q, mean_qvel=v, act=np.zeros(0), force=force, rate=None)
        if k == 150:  # not a gap: scores wait in the third combiner
            snap = combiners[2].snapshot()
            assert snap.pending
            combiners[2].restore(snap)
    assert len(answers[0]) > 50 and any(a[4] > 0.0 for a in answers[0])  # LEARNED took weight
    for a, b, c in zip(*answers, strict=True):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, c)


def _chain(links: int) -> mujoco.MjModel:
    """A chain of `links` hinged, motor-driven links."""
    body = ""
    for i in range(links):
        body += f'<body pos="0 0 -0.1"><joint name="j{i}" type="hinge" axis="0 1 0"/><geom type="capsule" size="0.01" fromto="0 0 0 0 0 -0.1"/>'
    body += "</body>" * links
    motors = "".join(f'<motor joint="j{i}"/>' for i in range(links))
    return mujoco.MjModel.from_xml_string(
        f"<mujoco><worldbody>{body}</worldbody><actuator>{motors}</actuator></mujoco>"
    )


@pytest.mark.parametrize(("links", "forecast"), [(10, "COMBINED"), (11, "FILTER")])
def test_the_combination_is_jitdyns_driven_default_below_a_large_state(links: int, forecast: str) -> None:
    """DRIVEN's state is 3 nv: 30 for 10 links, 33 (>= LARGE_STATE = 32) for 11, where the filter
    answers gaps (myoHand: the combination's scoring tripled its compute, docs/experiments.md)."""
    model = _chain(links)
    config = resolve_config(
        model=model, scenario="DRIVEN", dt=0.01, requested={}, model_defaults={}, measured={"qpos", "qvel"}
    )
    assert config.forecast == forecast


def test_past_the_scored_horizon_the_filter_answers_and_the_answer_keeps_moving(client: Any) -> None:
    """A gap longer than the combination's horizon (0.5 s: 10 ticks at 50 ms): the last frame's probe
    stops there (it waits to be scored), so the combination's answer would stand still for the rest
    of the gap; past the horizon nothing is scored, and the filter answers, moving on."""
    model = _pendulum(2)
    frames = _driven_frames(model, 60)
    options = SessionOptions(model_name="pendulum_2", dt=0.05)
    with client.open_session(options) as session:
        assert session.opened.estimator["forecast"] == "COMBINED"
        gap: list[TickResult] = []
        for k, (q, v) in enumerate(frames):
            if k < 40 and not (k >= 20 and k % 10 in (0, 1)):  # scored gaps first, as a client's
                result = session.send_frame(FrameData(seq=k, t=k * 0.05, qpos=q, qvel=v))
            else:
                result = session.skip(k)
                if k >= 40:
                    assert isinstance(result, TickResult)
                    gap.append(result)
            assert isinstance(result, TickResult)
    horizon = 10
    assert all(r.forecast_weights is not None for r in gap[:horizon])
    assert all(r.forecast_weights is None for r in gap[horizon:])
    moves = [float(np.max(np.abs(b.qpos - a.qpos))) for a, b in zip(gap[horizon:], gap[horizon + 1 :])]
    assert min(moves) > 1e-6, moves


def test_over_a_gap_the_force_answered_moves_the_model_along_the_forecast(client: Any) -> None:
    """A gap answered by the combination: the unknown force in `filter_state` is the inverse
    dynamics of the forecast q, qd, qdd (so the torques answered agree with the motion answered),
    and it is what `qfrc_inverse` says; not the filter's held force."""
    model = _pendulum(2)
    process = process_model(model, scenario="DRIVEN")
    data = mujoco.MjData(process)
    frames = _driven_frames(model, 60)
    nv = model.nv
    options = SessionOptions(model_name="pendulum_2", dt=0.05, outputs=("FILTER_STATE", "INVERSE_DYNAMICS"))
    answered = 0
    with client.open_session(options) as session:
        for k, (q, v) in enumerate(frames):
            if k >= 30 and k % 10 in (0, 1, 2):
                result = session.skip(k)
                assert isinstance(result, TickResult)
                if result.forecast_weights is None:
                    continue
                data.qpos[:], data.qvel[:], data.qacc[:] = result.qpos, result.qvel, result.qacc
                mujoco.mj_inverse(process, data)
                force = result.filter_state[2 * nv : 3 * nv]
                np.testing.assert_allclose(force, data.qfrc_inverse, rtol=1e-9, atol=1e-9)
                np.testing.assert_allclose(result.qfrc_inverse, force, rtol=1e-9, atol=1e-9)
                answered += 1
            else:
                session.send_frame(FrameData(seq=k, t=k * 0.05, qpos=q, qvel=v))
    assert answered >= 6
