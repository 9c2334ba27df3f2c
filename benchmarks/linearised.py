"""What an EKF linearised by MuJoCo would cost a tick, against the sigma points it would replace.

MuJoCo MPC's Kalman estimator propagates its covariance with the transition Jacobian that
`mjd_transitionFD` finite-differences (one call, skipping the stages a perturbation cannot change).
It perturbs 2nv+na state columns, where the spherical simplex set steps n+2 points: measure before
assuming that the EKF is cheaper. For each model of benchmarks/cost_nv.py at its rate,
on the state its own excitation reaches, the CPU of:

- the simplex points' physics over one tick: points x steps mj_step (the UKF's floor), and at one
  coarse step a tick (points x 1 mj_step, the step's own price taken at the model's timestep);
- the EKF's Jacobians over one tick: one mjd_transitionFD a step, chained (A = A_k ... A_1), or one
  at a single coarse step of the whole tick (`coarse`: the model's timestep set to dt);
- the EKF's algebra in numpy: A P A' + Q and an update measuring qpos and qvel;
- the linearised filter's own tick (server/estimation/linearised.py) at one coarse step a tick:
  the mean, mjd_transitionFD's Jacobian of [q, qd] (and DRIVEN's force columns, forward
  differences of the step) and A P A' + Q, in its Python reference and compiled (native).

- with --accuracy, the prediction error over 100 ms gaps every 250 ms of the model's own excited
  motion (or, --recorded, of recorded human gait on myolegs_osl's hips and knees): the UKF as the
  server runs it (its filter's prediction alone: forecast FILTER, noise FIXED) against
  `LinearisedFilter` (native), the EKF of the same algorithm (state, Q, P0, R, process model,
  restored force, divergence guard and wrong_model restart) whose covariance is propagated by the
  tick's Jacobian. Why it was measured before it was chosen:
  docs/decisions/0189-a-linearised-filter-measured-before-it-is-chosen.md; where it is chosen:
  docs/decisions/0210-the-linearised-filter-as-a-candidate.md.

    python -m benchmarks.linearised                  # every model, ~1 minute
    python -m benchmarks.linearised --rows myohand   # substrings of the row names
    python -m benchmarks.linearised --accuracy --noise 0.005            # the errors too, ~15 minutes
    python -m benchmarks.linearised --accuracy --noise 0.005 --recorded --rows myolegs
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import os
import statistics
import time

import mujoco
import numpy as np

from benchmarks.cost_nv import ROWS, Row, load, truth
from jitdyn.server.estimation.config import Engine, EstimatorConfig, resolve_config
from jitdyn.server.estimation.interface import Measurement
from jitdyn.server.estimation.linearised import LinearisedFilter
from jitdyn.server.estimation.manifold import SplitManifold
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.estimation.ukf import UnscentedFilter
from jitdyn.vocabulary import EstimatorKind, Forecast, NoiseModel, Scenario, WrongModel


def _cpu(work: object, repeats: int) -> float:
    """Median CPU seconds of `work()` over `repeats` calls, after one to warm it."""
    assert callable(work)
    work()
    times = []
    for _ in range(repeats):
        c0 = time.process_time()
        work()
        times.append(time.process_time() - c0)
    return statistics.median(times)


def ekf_config(config: EstimatorConfig, *, engine: Engine = Engine.NATIVE) -> EstimatorConfig:
    """The linearised filter's settings beside the UKF's `config`: the same noise, fixed, the
    filter's own forecast, and PASSIVE's wrong_model RESTART (the switch to DRIVEN is the UKF's),
    as resolve_config gives an EKF session."""
    wrong_model = WrongModel.RESTART if config.wrong_model == WrongModel.DRIVEN else config.wrong_model
    return dataclasses.replace(
        config,
        estimator=EstimatorKind.EKF,
        noise_model=NoiseModel.FIXED,
        forecast=Forecast.FILTER,
        wrong_model=wrong_model,
        engine=engine,
    )


def measure(row: Row, repeats: int) -> dict[str, float]:
    model = load(row.model)
    dt = 1.0 / row.rate
    steps = round(dt / model.opt.timestep)
    frames = truth(model, row.scenario, steps, ticks=60)
    config = resolve_config(
        model=model, scenario=row.scenario, dt=dt, requested={}, model_defaults={}, measured={"qpos", "qvel"}
    )
    with WorkerPool(1) as pool:
        ukf = UnscentedFilter(model, config, pool=pool)
        points, n = ukf.nsigma, ukf.state_dimension
    d = mujoco.MjData(model)
    d.qpos[:], d.qvel[:], d.ctrl[:] = frames[-1].qpos, frames[-1].qvel, frames[-1].ctrl
    mujoco.mj_forward(model, d)
    start = mujoco.MjData(model)
    mujoco.mj_copyData(start, model, d)

    def one_step() -> None:
        mujoco.mj_copyData(d, model, start)
        mujoco.mj_step(model, d)

    step = _cpu(one_step, repeats * 20)
    original = model
    rk4 = model.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4
    if rk4:  # mjd_transitionFD refuses RK4: the Jacobian of a semi-implicit Euler step instead
        model = copy.copy(model)
        model.opt.integrator = mujoco.mjtIntegrator.mjINT_EULER
    nx = 2 * model.nv + model.na
    a = np.zeros((nx, nx))

    def jacobian() -> None:
        mujoco.mj_copyData(d, model, start)
        mujoco.mjd_transitionFD(model, d, 1e-6, False, a, None, None, None)

    fd = _cpu(jacobian, repeats)
    coarse = copy.copy(model)
    coarse.opt.timestep = steps * model.opt.timestep
    dc = mujoco.MjData(coarse)
    mujoco.mj_copyData(dc, coarse, start)

    def coarse_jacobian() -> None:
        mujoco.mjd_transitionFD(coarse, dc, 1e-6, False, a, None, None, None)

    fd_coarse = _cpu(coarse_jacobian, repeats)
    rng = np.random.default_rng(0)
    p = np.cov(rng.standard_normal((nx, 4 * nx)))
    h = np.eye(2 * model.nv, nx)
    r = 1e-4 * np.eye(2 * model.nv)

    def algebra() -> None:
        prior = a @ p @ a.T + 1e-6 * np.eye(nx)
        s = h @ prior @ h.T + r
        gain = np.linalg.solve(s, h @ prior).T
        prior - gain @ s @ gain.T

    chain = _cpu(lambda: a @ a, repeats * 5) * (steps - 1)
    predicts = {Engine.FAST: float("nan"), Engine.NATIVE: float("nan")}
    if row.scenario != Scenario.CONTROLLED:  # the filter's own predict, one coarse step a tick
        for engine in predicts:
            ekf = LinearisedFilter(original, ekf_config(config, engine=engine), coarsen=steps)
            ekf.initialise(frames[-1])
            start_ekf = ekf.snapshot()

            def ekf_predict(ekf: LinearisedFilter = ekf, start_ekf: object = start_ekf) -> None:
                ekf.restore(start_ekf)
                ekf.advance(ctrl=None)

            predicts[engine] = _cpu(ekf_predict, repeats)
    return {
        "nv": model.nv,
        "na": model.na,
        "n": n,
        "nx": nx,
        "points": points,
        "steps": steps,
        "step": step,
        "simplex": points * steps * step,
        "fd": fd,
        "ekf": steps * fd + chain,
        "ekf_coarse": fd_coarse,
        "simplex_coarse": points * step,
        "algebra": _cpu(algebra, repeats),
        "rk4": rk4,
        "reference": predicts[Engine.FAST],
        "native": predicts[Engine.NATIVE],
    }


# The reference takes PASSIVE, EXTERNAL and DRIVEN, not CONTROLLED's [q, qd, qdd]. A row whose
# `coarsen` is not 1 runs the EKF at fewer, longer steps (the UKF as the server runs it).
ACCURACY_ROWS = (
    Row("pendulum_3 PASSIVE", "pendulum_3", Scenario.PASSIVE, 20.0),
    Row("myoElbow DRIVEN", "myoelbow", Scenario.DRIVEN, 500.0),
    Row("myoElbow EXTERNAL", "myoelbow", Scenario.EXTERNAL, 500.0),
    Row("myoHand EXTERNAL", "myohand", Scenario.EXTERNAL, 500.0),
    Row("myoHand DRIVEN", "myohand", Scenario.DRIVEN, 500.0),
    Row("myolegs_osl DRIVEN", "myolegs_osl", Scenario.DRIVEN, 100.0),
    Row("myolegs_osl DRIVEN, EKF one step a tick", "myolegs_osl", Scenario.DRIVEN, 100.0, coarsen=10),
    Row("myolegs_osl EXTERNAL", "myolegs_osl", Scenario.EXTERNAL, 100.0),
    Row("myolegs_osl EXTERNAL, EKF two steps a tick", "myolegs_osl", Scenario.EXTERNAL, 100.0, coarsen=5),
    Row("myolegs_osl EXTERNAL, EKF one step a tick", "myolegs_osl", Scenario.EXTERNAL, 100.0, coarsen=10),
)

# iSen's columns (experiments/recorded.py load_isen) onto myolegs_osl's joints: hips and knees.
GAIT_JOINTS = ("hip_flexion_r", "osl_knee_angle_r", "hip_flexion_l", "knee_angle_l")


def gait(model: mujoco.MjModel, dt: float, seconds: float) -> list[Measurement]:
    """iSen's recorded gait (experiments/recorded.py, 100 Hz) replayed on the model's hips and
    knees, clipped to their ranges; every other joint held at rest (qpos0) but for the ones a joint
    equality couples to a knee, which follow it; qvel the central difference of the poses."""
    from jitdyn.experiments.recorded import load_isen

    angles = load_isen("isen_gait")
    if abs(dt - 0.01) > 1e-12:
        raise ValueError(f"the recorded gait is replayed at 100 Hz, got dt {dt}")
    ticks = min(len(angles), round(seconds / dt))
    poses = np.tile(model.qpos0, (ticks, 1))
    for column, name in enumerate(GAIT_JOINTS):
        joint = model.joint(name)
        poses[:, joint.qposadr[0]] = np.clip(angles[:ticks, column], *joint.range)
    for e in range(model.neq):  # joint equalities: q1 - q1_0 = poly(q2 - q2_0)
        if model.eq_type[e] == mujoco.mjtEq.mjEQ_JOINT and model.eq_obj2id[e] >= 0:
            a1, a2 = model.jnt_qposadr[model.eq_obj1id[e]], model.jnt_qposadr[model.eq_obj2id[e]]
            dq = poses[:, a2] - model.qpos0[a2]
            poses[:, a1] = model.qpos0[a1] + sum(c * dq**i for i, c in enumerate(model.eq_data[e][:5]))
    manifold = SplitManifold(model, rest=0)
    velocities = np.gradient(
        np.cumsum(np.vstack([np.zeros(model.nv), manifold.residual(poses[1:], poses[:-1])]), 0), dt, axis=0
    )
    return [Measurement(qpos=q, qvel=v) for q, v in zip(poses, velocities, strict=True)]


def swing(model: mujoco.MjModel, steps: int, ticks: int) -> list[Measurement]:
    """A passive body let go from a pose 0.8 rad off its rest in every joint (seeded)."""
    d = mujoco.MjData(model)
    d.qpos[:] = model.qpos0 + 0.8 * np.random.default_rng(0).uniform(-1.0, 1.0, model.nq)
    frames = []
    for _ in range(ticks):
        mujoco.mj_step(model, d, steps)
        frames.append(Measurement(qpos=d.qpos.copy(), qvel=d.qvel.copy()))
    return frames


def noisy(model: mujoco.MjModel, frames: list[Measurement], std: float, seed: int = 0) -> list[Measurement]:
    """The frames as a sensor would give them: Gaussian noise of `std` rad (or m) on each of qpos'
    tangent components (a quaternion stays one) and 10 `std` rad/s on qvel (seeded)."""
    rng = np.random.default_rng(seed)
    manifold = SplitManifold(model, rest=0)
    return [
        Measurement(
            qpos=manifold.add(f.qpos, std * rng.standard_normal(model.nv)),
            qvel=f.qvel + 10.0 * std * rng.standard_normal(f.qvel.shape),
        )
        for f in frames
    ]


def gap_errors(
    row: Row, seconds: float, noise: float = 0.0, *, recorded: bool = False
) -> tuple[float, float]:
    """Mean |q error| (in the tangent space: mj_differentiatePos) against the true motion over the
    ticks of 100 ms gaps every 250 ms, the filters fed frames with `noise` (see `noisy`); the
    truth the model's own excited motion, or (`recorded`) the recorded gait (`gait`): (UKF, EKF)."""
    model = load(row.model)
    dt = 1.0 / row.rate
    steps = round(dt / model.opt.timestep)
    if recorded:
        frames = gait(model, dt, seconds)
    elif row.scenario == Scenario.PASSIVE:  # a passive body left at rest would not move: let it swing
        frames = swing(model, steps, ticks=round(seconds / dt))
    else:
        frames = truth(model, row.scenario, steps, ticks=round(seconds / dt))
    config = resolve_config(
        model=model,
        scenario=row.scenario,
        dt=dt,
        requested={"forecast": "FILTER", "noise_model": "FIXED"},
        model_defaults={},
        measured={"qpos", "qvel"},
    )
    sensed = noisy(model, frames, noise) if noise else frames
    period, gap = round(0.25 / dt), max(1, round(0.1 / dt))
    errors: dict[str, list[float]] = {"ukf": [], "ekf": []}
    with WorkerPool(1) as pool:
        ukf = UnscentedFilter(model, config, pool=pool)
        ukf.initialise(sensed[0])
        ekf = LinearisedFilter(model, ekf_config(config), coarsen=row.coarsen)
        ekf.initialise(sensed[0])
        manifold = SplitManifold(model, rest=0)
        for k in range(1, len(frames)):
            in_gap = k > period and k % period < gap
            if in_gap:
                ekf_q = ekf.predict(ctrl=None).qpos
                ukf_q = ukf.predict(ctrl=None).qpos
                errors["ukf"].append(float(np.mean(np.abs(manifold.residual(ukf_q, frames[k].qpos)))))
                errors["ekf"].append(float(np.mean(np.abs(manifold.residual(ekf_q, frames[k].qpos)))))
            else:
                ekf.advance(ctrl=None)
                ukf.advance(ctrl=None)
                ukf.update(sensed[k])
                ekf.update(sensed[k])
    return statistics.fmean(errors["ukf"]), statistics.fmean(errors["ekf"])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--rows", nargs="+", help="substrings of row names")
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--accuracy", action="store_true", help="also the errors over gaps (slow)")
    parser.add_argument("--seconds", type=float, default=4.0, help="of motion for --accuracy (default 4)")
    parser.add_argument(
        "--noise",
        type=float,
        default=0.0,
        help="rad of noise on the frames' qpos (10x on qvel) for --accuracy",
    )
    parser.add_argument(
        "--recorded",
        action="store_true",
        help="for --accuracy: myolegs_osl's rows on the recorded gait, not its simulated motion",
    )
    args = parser.parse_args(argv)
    seen: set[tuple[str, Scenario]] = set()
    rows = []
    for row in ROWS:  # the models and scenarios of cost_nv, without its pool and timestep variants
        if (row.model, row.scenario) not in seen and (not args.rows or any(s in row.name for s in args.rows)):
            seen.add((row.model, row.scenario))
            rows.append(row)
    print(
        f"# {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}; mujoco {mujoco.__version__}; "
        f"medians of {args.repeats} calls, CPU time, one thread"
    )
    print(
        "| model, scenario | nv / na | UKF n, points x steps | mj_step us | simplex physics us/tick "
        "| FD us/step (2nv+na cols) | EKF Jacobians us/tick | EKF / simplex | one coarse FD us | its / simplex at one step "
        "| EKF algebra us | reference EKF predict, one coarse step, us (n cols) | its / simplex at one step "
        "| native EKF predict us | its / simplex at one step |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        r = measure(row, args.repeats)
        print(
            f"| {row.name.replace(' (default)', '')} | {r['nv']} / {r['na']} | {r['n']}, {r['points']} x {r['steps']} "
            f"| {r['step'] * 1e6:.1f}{' (RK4; FD on Euler)' if r['rk4'] else ''} | {r['simplex'] * 1e6:.0f} | {r['fd'] * 1e6:.0f} ({r['nx']}) "
            f"| {r['ekf'] * 1e6:.0f} | {r['ekf'] / r['simplex']:.2f} | {r['ekf_coarse'] * 1e6:.0f} "
            f"| {r['ekf_coarse'] / r['simplex_coarse']:.2f} | {r['algebra'] * 1e6:.0f} "
            f"| {r['reference'] * 1e6:.0f} ({r['n']}) | {r['reference'] / r['simplex_coarse']:.2f} "
            f"| {r['native'] * 1e6:.0f} | {r['native'] / r['simplex_coarse']:.2f} |",
            flush=True,
        )
    if args.accuracy:
        print("\n| model, scenario | UKF mean |q error| over gaps (rad) | EKF | EKF / UKF |")
        print("|---|---|---|---|")
        for row in ACCURACY_ROWS:
            if args.rows and not any(s in row.name for s in args.rows):
                continue
            if args.recorded and row.model != "myolegs_osl":
                continue
            ukf, ekf = gap_errors(row, args.seconds, args.noise, recorded=args.recorded)
            print(
                f"| {row.name.replace(' (default)', '')} | {ukf:.2e} | {ekf:.2e} | {ekf / ukf:.2f} |",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
