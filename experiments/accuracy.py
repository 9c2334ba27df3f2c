"""What the server's choice of estimator costs in accuracy. For every built-in and myo-sim model,
the estimator a REALTIME session that names none gets (server/runtime/choice.py, from costs timed
here as registration times them) is set against the full UKF (the preset's, with its own sigma
points, run offline however slowly), over 100 ms gaps every 250 ms of (a) the model's own excited
motion and (b) recorded human gait replayed on the hips, knees and ankles of every model whose
joints have those roles, the rest of the model held at rest::

    rows = accuracy_rows(quick=False, progress=True)   # (AccuracyRow, ...), minutes
    row.ratio, row.verdict                              # chosen / full, "met" within BAR

benchmarks/cost_nv.py (--candidates) times every candidate on the same excited motion.
"""

from __future__ import annotations

import dataclasses
import statistics
import sys
import time
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Final

import mujoco
import numpy as np

from jitdyn.errors import ResourceExhausted
from jitdyn.estimator_settings import SettingValue
from jitdyn.experiments.objects import load_source
from jitdyn.experiments.progress import progress_bar
from jitdyn.experiments.recorded import chain_mjcf
from jitdyn.registry import CandidateCost
from jitdyn.registry.info import describe_model
from jitdyn.roles import JointRole, joint_roles
from jitdyn.server.estimation.config import Engine, EstimatorConfig, default_scenario, resolve_config
from jitdyn.server.estimation.factory import make_estimator
from jitdyn.server.estimation.interface import Measurement
from jitdyn.server.estimation.manifold import SplitManifold
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.runtime.choice import CostTable, candidates, measure_costs
from jitdyn.settings import DEFAULTS
from jitdyn.vocabulary import EstimatorKind, Scenario, SigmaScheme

__all__ = [
    "BAR",
    "BUILTIN_RATES",
    "GAITS",
    "MYO_RATE",
    "SHARE",
    "AccuracyRow",
    "Gait",
    "accuracy_rows",
    "candidate_models",
    "excited_motion",
    "gait_frames",
    "gap_run",
]

SHARE: Final = DEFAULTS.max_tick_share  # of dt, the server's default tick budget
BAR: Final = 1.1  # the chosen estimator's error may be at most this many times the full UKF's
GAP: Final = 0.1  # s without frames
EVERY: Final = 0.25  # s from the start of one gap to the next
EXCITED_SECONDS: Final = (2.0, 1.0)  # s of the excited motion: full, quick
# The built-in models at these rates (benchmarks/cost_nv.py's); the myo-sim models at MYO_RATE.
BUILTIN_RATES: Final = {"pendulum_1": 20.0, "pendulum_2": 20.0, "pendulum_3": 20.0, "biped": 200.0}
MYO_RATE: Final = 100.0
# Frames of a wearable: white noise of this many rad (m) on q's tangent, 10 times it in rad/s on qd.
SENSORS: Final = {"perfect": 0.0, "wearable": 0.005}
_QUICK_MODELS: Final = ("pendulum_1",)


@dataclass(frozen=True)
class Gait:
    """A recorded walk of experiments/prior_sources.py: `subject`'s legs, `sides` ("l", "r") in the
    order walking_legs gives them, `seconds` of it replayed (from its start)."""

    subject: str
    title: str
    sides: tuple[str, ...]
    seconds: float


GAITS: Final = (
    # gaitkit's trials: the left leg, then the right (prior_sources._gaitkit_legs).
    Gait("fukuchi", "walking, a healthy adult (Fukuchi et al. 2018): hips, knees, ankles", ("l", "r"), 2.5),
    # iSen: the right leg, then the left (recorded.load_isen); no ankle: the ankles stay at rest.
    Gait("isen", "steady stepping (iSen sensors): hips, knees; ankles at rest", ("r", "l"), 4.0),
)
_QUICK_GAIT: Final = Gait("isen", GAITS[1].title, ("r", "l"), 1.0)


def _load(name: str) -> mujoco.MjModel:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_source(name).compile()


def candidate_models(names: Sequence[str] | None) -> list[tuple[str, mujoco.MjModel, float]]:
    """Every built-in model and every myo-sim model that packs and compiles here (as `jitdyn
    models register --myo` finds them), compiled as the registry compiles them, with its rate;
    names: substrings of the names to keep (None: all)."""
    from jitdyn.client.myo import pack_myo_model, registrable_myo_models

    found = []
    for name, rate in BUILTIN_RATES.items():
        if not names or any(s in name for s in names):
            found.append((name, _load(name), rate))
    for myo in registrable_myo_models():
        if names and not any(s in myo.name for s in names):
            continue
        mjcf, assets = pack_myo_model(myo.name)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            found.append((myo.name, mujoco.MjModel.from_xml_string(mjcf, assets), MYO_RATE))
    return found


def excited_motion(model: mujoco.MjModel, scenario: Scenario, nstep: int, ticks: int) -> list[Measurement]:
    """The model under slow out-of-phase excitations of its actuators (sines for the biped), a frame
    every `nstep` physics steps."""
    d = mujoco.MjData(model)
    mujoco.mj_forward(model, d)
    frames = []
    for k in range(ticks):
        if scenario == Scenario.PASSIVE:
            d.ctrl[:] = 0.0
        elif model.nu and not model.na:
            d.ctrl[:] = 2.0 * np.sin(0.02 * k + np.pi * np.arange(model.nu))
        else:
            d.ctrl[:] = 0.5 + 0.5 * np.sin(0.01 * k * nstep + 0.7 * np.arange(model.nu))
        mujoco.mj_step(model, d, nstep)
        frames.append(Measurement(qpos=d.qpos.copy(), qvel=d.qvel.copy(), ctrl=d.ctrl.copy()))
    return frames


def sensed(model: mujoco.MjModel, frames: Sequence[Measurement], noise: float) -> list[Measurement]:
    """The frames as a sensor gives them, qpos and qvel alone (the excitation is what the
    estimators must not see): Gaussian noise of `noise` rad (or m) on qpos' tangent and
    10 `noise` rad/s on qvel (seeded: the same for every estimator), or the frames themselves."""
    if noise == 0.0:
        return [Measurement(qpos=f.qpos, qvel=f.qvel) for f in frames]  # no ctrl: a DRIVEN session's
    manifold = SplitManifold(model, rest=0)
    rng = np.random.default_rng(0)
    return [
        Measurement(
            qpos=manifold.add(f.qpos, noise * rng.standard_normal(model.nv)),
            qvel=None if f.qvel is None else f.qvel + 10.0 * noise * rng.standard_normal(model.nv),
        )
        for f in frames
    ]


@dataclass(frozen=True)
class GapRun:
    """One estimator over one motion: the mean |q error| of each answer in a gap (rad, m on slides)
    against the truth, and the thread CPU seconds of each cycle on a frame."""

    errors: tuple[float, ...]
    cycles: tuple[float, ...]
    gaps: int


def gap_run(
    model: mujoco.MjModel,
    config: EstimatorConfig,
    frames: Sequence[Measurement],
    sensors: Sequence[Measurement],
    *,
    progress: str | None = None,
) -> GapRun:
    """`config`'s estimator over `frames` (the truth; `sensors`: what it is given), a GAP without
    frames every EVERY: a gap's ticks answered by its prediction, the others by a cycle on the
    frame. progress: the description of a bar on stderr (None: no bar)."""
    period, gap = round(EVERY / config.dt), max(1, round(GAP / config.dt))
    manifold = SplitManifold(model, rest=0)
    errors, cycles, gaps, answered = [], [], 0, False
    with (
        WorkerPool(1) as pool,
        progress_bar(
            total=len(frames), desc=progress or "", unit="tick", enabled=progress is not None
        ) as bar,
    ):
        estimator = make_estimator(model, config, pool=pool)
        estimator.initialise(sensors[0])
        for k in range(1, len(frames)):
            if k > period and k % period < gap:
                gaps += not answered  # the first tick of a gap
                answered = True
                q = estimator.predict(ctrl=None).qpos
                errors.append(float(np.mean(np.abs(manifold.residual(q, frames[k].qpos)))))
            else:
                answered = False
                c0 = time.thread_time()
                estimator.advance(ctrl=None)
                estimator.update(sensors[k])
                cycles.append(time.thread_time() - c0)
            bar.update(1)
    return GapRun(tuple(errors), tuple(cycles), gaps)


# --- recorded gait on a model's legs ------------------------------------------------------------


def _leg_roles(model: mujoco.MjModel) -> dict[str, dict[str, JointRole]]:
    """{side: {kind: role}} of the model's legs: a side with a hip and a knee (as the prior's
    legs_of counts legs), its ankle if it has one."""
    roles = joint_roles(describe_model(model).joints, ())
    by_side: dict[str, dict[str, JointRole]] = {}
    for role in roles:
        by_side.setdefault(role.side, {})[role.kind] = role
    return {side: kinds for side, kinds in by_side.items() if "hip" in kinds and "knee" in kinds}


def _follow_couplings(model: mujoco.MjModel, qpos: np.ndarray, qvel: np.ndarray) -> None:
    """Moves (in place; (T, nq), (T, nv)) every joint that an active joint equality couples to
    another, as the polynomial of the equality says: the knee's translations and rotations of the
    myo-sim legs follow its angle, and the pose is one the model can hold."""
    for e in range(model.neq):
        if model.eq_type[e] != mujoco.mjtEq.mjEQ_JOINT or not model.eq_active0[e] or model.eq_obj2id[e] < 0:
            continue
        j1, j2 = int(model.eq_obj1id[e]), int(model.eq_obj2id[e])
        a1, a2 = int(model.jnt_qposadr[j1]), int(model.jnt_qposadr[j2])
        d1, d2 = int(model.jnt_dofadr[j1]), int(model.jnt_dofadr[j2])
        c = model.eq_data[e, :5]
        x = qpos[:, a2] - model.qpos0[a2]
        qpos[:, a1] = model.qpos0[a1] + c[0] + x * (c[1] + x * (c[2] + x * (c[3] + x * c[4])))
        qvel[:, d1] = (c[1] + x * (2 * c[2] + x * (3 * c[3] + x * 4 * c[4]))) * qvel[:, d2]


def gait_frames(
    model: mujoco.MjModel, legs: Sequence[np.ndarray], sides: Sequence[str], *, rate: float
) -> list[Measurement] | None:
    """Frames at `rate` Hz of a recording's legs ((T, 3) hip flexion, knee flexion, ankle
    dorsiflexion in rad, NaN where not recorded; `sides` their sides) replayed on the model's legs
    by joint role (jitdyn.roles: each joint's sign), within each joint's range; every other joint at
    rest (qpos0, zero velocity) but those a joint equality couples to a replayed one, which follow
    it. A model leg is given the recording's leg of its side; a model with one leg and no side, the
    recording's first. qvel: central differences. None when the model has no leg."""
    model_legs = _leg_roles(model)
    if not model_legs:
        return None
    ticks = min(leg.shape[0] for leg in legs)
    qpos = np.tile(model.qpos0, (ticks, 1))
    replayed = np.zeros((ticks, model.nv))
    for side, kinds in model_legs.items():
        leg = legs[sides.index(side)] if side in sides else legs[0]
        for column, kind in enumerate(("hip", "knee", "ankle")):
            role = kinds.get(kind)
            if role is None or np.isnan(leg[0, column]):
                continue
            joint = int(model.dof_jntid[role.dof])
            low, high = model.jnt_range[joint] if model.jnt_limited[joint] else (-np.inf, np.inf)
            qpos[:, model.jnt_qposadr[joint]] = np.clip(role.sign * leg[:ticks, column], low, high)
    for j in range(model.njnt):
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE:
            a = int(model.jnt_qposadr[j])
            replayed[:, model.jnt_dofadr[j]] = np.gradient(qpos[:, a], 1.0 / rate)
    _follow_couplings(model, qpos, replayed)
    return [Measurement(qpos=qpos[k].copy(), qvel=replayed[k].copy()) for k in range(ticks)]


def _gait_legs(gait: Gait) -> list[np.ndarray]:
    from jitdyn.experiments.prior_sources import RATE, default_cache, fetch_archives, walking_legs

    archives = {} if gait.subject == "isen" else fetch_archives(default_cache())  # isen: biomdp's data
    legs = walking_legs(archives, only=gait.subject)[gait.subject]
    return [leg[: round(gait.seconds * RATE)] for leg in legs]


# --- the table ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Choice:
    """The estimator the server gives a REALTIME session of a model that names none, at a rate,
    from costs timed here; `settings` None: it would refuse the open."""

    settings: dict[str, SettingValue] | None
    full: dict[str, SettingValue]
    full_cost: float  # s of a tick of the full UKF, as timed
    budget: float  # s of a tick the server gives it (--max-tick-share of dt)


def label(settings: dict[str, SettingValue] | None) -> str:
    """ "UKF MERWE", "UKF SIMPLEX", "CONSTANT_VELOCITY"; "refused" for None."""
    if settings is None:
        return "refused"
    estimator = EstimatorKind(str(settings["estimator"])).name
    sigma = settings.get("sigma_points")
    return estimator if sigma is None else f"{estimator} {SigmaScheme(str(sigma)).name}"


def _settings_of(cost: CandidateCost) -> dict[str, SettingValue]:
    settings: dict[str, SettingValue] = {"estimator": EstimatorKind[cost.estimator]}
    if cost.sigma_points:
        settings["sigma_points"] = SigmaScheme[cost.sigma_points]
    return settings


def choose(model: mujoco.MjModel, scenario: Scenario, rate: float) -> Choice:
    """What server/runtime/choice.py gives a REALTIME session of `model` in `scenario` at `rate`
    that names no estimator, with the server's defaults (the native engine, --max-tick-share): each
    candidate timed as registration times it (measure_costs), then CostTable.choose."""
    costs = tuple(measure_costs(model, engine=Engine.NATIVE))
    table = CostTable(costs=costs, timestep=float(model.opt.timestep), share=SHARE)
    dt = 1.0 / rate
    first, sigma = candidates(model, scenario)[0]
    full: dict[str, SettingValue] = {"estimator": first}
    if sigma is not None:
        full["sigma_points"] = sigma
    timed = [c for c in table.of(scenario) if _settings_of(c) == full]
    full_cost = timed[0].at(table.steps(dt)) if timed else float("nan")  # nan: it could not be timed
    try:
        settings: dict[str, SettingValue] | None = table.choose(scenario, dt).settings
    except ResourceExhausted:
        settings = None
    return Choice(settings=settings, full=full, full_cost=full_cost, budget=table.share * dt)


@dataclass(frozen=True)
class AccuracyRow:
    """One model on one motion with one kind of frames: the full UKF's and the chosen estimator's
    mean |q error| over the gaps."""

    model: str
    nv: int
    scenario: Scenario
    rate: float
    motion: str
    sensors: str
    choice: Choice
    full: GapRun
    chosen: GapRun | None  # None: the server would refuse the open

    @property
    def full_error(self) -> float:
        return statistics.fmean(self.full.errors)

    @property
    def chosen_error(self) -> float:
        return float("nan") if self.chosen is None else statistics.fmean(self.chosen.errors)

    @property
    def ratio(self) -> float:
        return self.chosen_error / self.full_error

    @property
    def verdict(self) -> str:
        if self.chosen is None:
            return "refused"
        return "met" if self.ratio <= BAR else f"missed ({self.ratio / BAR:.2f} x the bar)"


def _runs(
    name: str,
    model: mujoco.MjModel,
    rate: float,
    frames: list[Measurement],
    motion: str,
    *,
    choice: Choice,
    progress: bool,
    without: tuple[str, ...] = (),
) -> Iterator[AccuracyRow]:
    scenario, _ = default_scenario(model)
    for sensors_name, noise in SENSORS.items():
        given = sensed(model, frames, noise)
        runs: dict[str, GapRun] = {}
        for settings in (choice.full, choice.settings):
            # The same estimator on the same frames answers the same: the chosen full UKF runs once.
            if settings is None or label(settings) in runs:
                continue
            config = resolve_config(
                model=model, scenario=scenario, dt=1.0 / rate, requested=settings, measured={"qpos", "qvel"}
            )
            # As a session's (server/runtime/opening.py): the roles its prior of human motion matches
            # on, here without the person whose gait is replayed.
            roles = joint_roles(describe_model(model).joints, ())
            config = dataclasses.replace(config, roles=roles, prior_without=without)
            desc = f"{name} {motion} {sensors_name} {label(settings)}" if progress else None
            runs[label(settings)] = gap_run(model, config, frames, given, progress=desc)
        full = runs[label(choice.full)]
        chosen = None if choice.settings is None else runs[label(choice.settings)]
        yield AccuracyRow(
            model=name,
            nv=model.nv,
            scenario=scenario,
            rate=rate,
            motion=motion,
            sensors=sensors_name,
            choice=choice,
            full=full,
            chosen=chosen,
        )


def _say(progress: bool, text: str) -> None:
    if progress:
        print(f"[accuracy] {text}", file=sys.stderr, flush=True)


def accuracy_rows(
    *, quick: bool, progress: bool, names: Sequence[str] | None = None, gaits: Sequence[Gait] | None = None
) -> list[AccuracyRow]:
    """Every model's rows (see the module docstring). quick: pendulum_1's excited motion for 1 s
    and 1 s of the iSen stepping on a hip-knee-ankle chain (experiments/recorded.py's), for CI.
    names: substrings of the model names to keep; gaits: the recordings (default GAITS)."""
    if quick:
        models = [(n, _load(n), BUILTIN_RATES[n]) for n in _QUICK_MODELS]
        models.append(("leg_chain", mujoco.MjModel.from_xml_string(chain_mjcf(name="leg_chain")), MYO_RATE))
    else:
        models = candidate_models(names)
    recordings = [(g, _gait_legs(g)) for g in ([_QUICK_GAIT] if quick else (gaits or GAITS))]
    seconds = EXCITED_SECONDS[1 if quick else 0]
    rows: list[AccuracyRow] = []
    for name, model, rate in models:
        scenario, _ = default_scenario(model)
        started = time.perf_counter()
        choice = choose(model, scenario, rate)
        _say(
            progress,
            f"{name}: {label(choice.settings)} chosen at {rate:g} Hz (full UKF {label(choice.full)}: "
            f"{choice.full_cost * 1e3:.3g} ms a tick, budget {choice.budget * 1e3:.3g} ms; timed in "
            f"{time.perf_counter() - started:.1f} s)",
        )
        if name != "leg_chain":
            steps = round(1.0 / rate / model.opt.timestep)
            frames = excited_motion(model, scenario, steps, ticks=round(seconds * rate))
            rows.extend(_runs(name, model, rate, frames, "excited", choice=choice, progress=progress))
        for gait, legs in recordings:
            replay = gait_frames(model, legs, gait.sides, rate=MYO_RATE)
            if replay is None:
                continue
            if rate != MYO_RATE:  # the recordings are at 100 Hz
                choice = choose(model, scenario, MYO_RATE)
            rows.extend(
                _runs(
                    name,
                    model,
                    MYO_RATE,
                    replay,
                    gait.subject,
                    choice=choice,
                    progress=progress,
                    without=(gait.subject,),
                )
            )
    return rows
