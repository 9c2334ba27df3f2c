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
- `LinearisedFilter`'s own predict at one coarse step a tick: n+1 steps of the process model,
  the columns of the UKF's state (activations are inputs), numpy and the Python around them.

- with --accuracy, the prediction error over 100 ms gaps every 250 ms of the model's own excited
  motion (or, --recorded, of recorded human gait on myolegs_osl's hips and knees): the UKF as the
  server runs it (its filter's prediction alone: forecast FILTER, noise FIXED) against
  `LinearisedFilter`, an EKF of the same algorithm (state, Q, P0, R, process model, restored force,
  divergence guard and wrong_model restart) whose covariance is propagated by the Jacobian of the
  tick, finite-differenced from the same physics (a reference of the algorithm, not of its price).
  Why it is measured before it is chosen: docs/decisions/0189-a-linearised-filter-measured-before-it-is-chosen.md.

    python -m benchmarks.linearised                  # every model, ~1 minute
    python -m benchmarks.linearised --rows myohand   # substrings of the row names
    python -m benchmarks.linearised --accuracy --noise 0.005            # the errors too, ~15 minutes
    python -m benchmarks.linearised --accuracy --noise 0.005 --recorded --rows myolegs
"""

from __future__ import annotations

import argparse
import copy
import os
import statistics
import time

import mujoco
import numpy as np

from benchmarks.cost_nv import ROWS, Row, load, truth
from jitdyn.server.estimation.config import EstimatorConfig, resolve_config
from jitdyn.server.estimation.guard import Guard
from jitdyn.server.estimation.interface import Measurement
from jitdyn.server.estimation.manifold import SplitManifold
from jitdyn.server.estimation.noise import UkfNoise
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.estimation.propagate import process_model
from jitdyn.server.estimation.ukf import UnscentedFilter
from jitdyn.vocabulary import Scenario, WrongModel


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
    reference = float("nan")
    if row.scenario != Scenario.CONTROLLED:  # the reference's own predict, one coarse step a tick
        ekf = LinearisedFilter(original, config, frames[-1], coarsen=steps)
        x0, p0 = ekf.x.copy(), ekf.P.copy()

        def ekf_predict() -> None:
            ekf.x[:], ekf.P = x0, p0
            ekf.predict()

        reference = _cpu(ekf_predict, repeats)
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
        "reference": reference,
    }


class LinearisedFilter:
    """An EKF of the UKF's own state ([q, qd], and f in DRIVEN) on the UKF's own process model
    (estimation/propagate.py; in EXTERNAL the force mj_inverse restores from the frames, held over a
    gap): the mean by the model's steps over the tick, the covariance by the tick's Jacobian,
    finite differences of the same steps, one column a perturbed tangent direction; activations
    carried as inputs, as the UKF does. A state with ball or free joints lives on the UKF's
    manifold (estimation/manifold.py: mj_integratePos and mj_differentiatePos are its + and -).
    `coarsen`: the process model's timestep times this (10 at 1 ms and 100 Hz: one step a tick),
    its integrator implicitfast, as the issue's coarse candidate asks (on myolegs_osl the same
    errors as Euler's: docs/decisions/0200-the-linearised-reference-is-the-ukfs-algorithm.md)."""

    def __init__(
        self, model: mujoco.MjModel, config: EstimatorConfig, first: Measurement, *, coarsen: int = 1
    ) -> None:
        self.model = process_model(model, scenario=config.scenario)  # the UKF's own process model
        self.model.opt.timestep = coarsen * model.opt.timestep
        if coarsen != 1:
            self.model.opt.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
        self.steps, self.dt = round(config.dt / self.model.opt.timestep), config.dt
        self.data = mujoco.MjData(self.model)
        self.external = Scenario(config.scenario) == Scenario.EXTERNAL
        self.qfrc = np.zeros(model.nv)
        noise = UkfNoise.of(model, self.data, config)
        self.n, self.nv, self.nq = noise.n, model.nv, model.nq
        self.manifold = SplitManifold(model, rest=noise.n - model.nv)
        self.Q, self.P0 = noise.process_noise(config.dt), noise.initial_covariance()
        self.R = config.r * np.eye(2 * model.nv)
        # The UKF's own guard (estimation/guard.py): EXTERNAL's wrong_model RESTART starts the
        # filter again from a frame whose NIS stays far out, as the UKF does.
        self.guard = Guard(
            m=2 * model.nv,
            restart=WrongModel(config.wrong_model) == WrongModel.RESTART,
            driven=Scenario(config.scenario) == Scenario.DRIVEN,
        )
        self.restarts = 0
        self.x = np.zeros(self.manifold.dim)  # [qpos (nq), qvel (nv), f (nv, DRIVEN)]
        self.act = np.zeros(model.na)
        self._start_from(first)

    def _start_from(self, frame: Measurement) -> None:
        """x on the frame, P = P0 (estimation/guard_steps.py start_from); DRIVEN keeps its force."""
        self.x[: self.nq + self.nv] = np.concatenate([frame.qpos, frame.qvel])
        self.P = self.P0.copy()
        self.last, self.last_qvel, self.since = frame, np.array(frame.qvel), 0

    def _step(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d, nq, nv = self.data, self.nq, self.nv
        d.qpos[:], d.qvel[:], d.act[:] = x[:nq], x[nq : nq + nv], self.act
        d.qfrc_applied[:] = x[nq + nv :] if self.n > 2 * nv else self.qfrc
        mujoco.mj_step(self.model, d, self.steps)
        out = x.copy()
        out[:nq], out[nq : nq + nv] = d.qpos, d.qvel
        return out, d.act.copy()

    def _scale(self) -> np.ndarray:
        """(n,) each tangent component's size, which its finite difference's step follows."""
        scale = np.abs(self.x[self.nq - self.nv :])
        if self.nq != self.nv:  # a quaternion's component is no tangent one
            scale[: self.nv] = 1.0
        return np.maximum(1.0, scale)

    def predict(self) -> np.ndarray:
        mean, act = self._step(self.x)
        a = np.empty((self.n, self.n))
        eps = 1e-6 * self._scale()
        for i in range(self.n):  # forward differences, scaled to each component's size
            direction = np.zeros(self.n)
            direction[i] = eps[i]
            a[:, i] = (
                self.manifold.residual(self._step(self.manifold.add(self.x, direction))[0], mean) / eps[i]
            )
        self.x, self.act, self.since = mean, act, self.since + 1
        self.P = a @ self.P @ a.T + self.Q
        self.P = 0.5 * (self.P + self.P.T)
        if self.guard.diverged(finite=self._finite(), largest_variance=float(self.P.diagonal().max())):
            self._start_from(self.last)
            self.guard.start()
        return self.x[: self.nq].copy()

    def _finite(self) -> bool:
        return bool(np.all(np.isfinite(self.x)) and np.all(np.isfinite(self.P)))

    def update(self, frame: Measurement) -> None:
        h = np.eye(2 * self.nv, self.n)
        s = h @ self.P @ h.T + self.R
        gain = np.linalg.solve(s, h @ self.P).T
        z = np.concatenate([frame.qpos, frame.qvel])
        y = self.manifold.residual(np.concatenate([z, self.x[self.nq + self.nv :]]), self.x)[: 2 * self.nv]
        nis = float(y @ np.linalg.solve(s, y))
        self.x = self.manifold.add(self.x, gain @ y)
        joseph = np.eye(self.n) - gain @ h
        self.P = joseph @ self.P @ joseph.T + gain @ self.R @ gain.T
        self.guard.count(nis if np.isfinite(nis) else None)
        if self.guard.restart_due(finite=self._finite(), largest_variance=float(self.P.diagonal().max())):
            # As guard_steps.restart: from the frame, the held force kept, the guard as new.
            self.restarts += 1
            self._start_from(frame)
            self.guard.reset()
            return
        if self.external and self.since > 0:  # the force that acted, restored and held, as the UKF does
            d = self.data
            d.qpos[:], d.qvel[:], d.act[:] = frame.qpos, frame.qvel, self.act
            d.qacc[:] = (frame.qvel - self.last_qvel) / (self.since * self.dt)
            mujoco.mj_inverse(self.model, d)
            self.qfrc = np.array(d.qfrc_inverse)
        self.last, self.last_qvel, self.since = frame, np.array(frame.qvel), 0


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
        ekf = LinearisedFilter(model, config, sensed[0], coarsen=row.coarsen)
        manifold = SplitManifold(model, rest=0)
        for k in range(1, len(frames)):
            in_gap = k > period and k % period < gap
            ekf_q = ekf.predict()
            if in_gap:
                ukf_q = ukf.predict(ctrl=None).qpos
                errors["ukf"].append(float(np.mean(np.abs(manifold.residual(ukf_q, frames[k].qpos)))))
                errors["ekf"].append(float(np.mean(np.abs(manifold.residual(ekf_q, frames[k].qpos)))))
            else:
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
        "| EKF algebra us | reference EKF predict, one coarse step, us (n cols) | its / simplex at one step |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        r = measure(row, args.repeats)
        print(
            f"| {row.name.replace(' (default)', '')} | {r['nv']} / {r['na']} | {r['n']}, {r['points']} x {r['steps']} "
            f"| {r['step'] * 1e6:.1f}{' (RK4; FD on Euler)' if r['rk4'] else ''} | {r['simplex'] * 1e6:.0f} | {r['fd'] * 1e6:.0f} ({r['nx']}) "
            f"| {r['ekf'] * 1e6:.0f} | {r['ekf'] / r['simplex']:.2f} | {r['ekf_coarse'] * 1e6:.0f} "
            f"| {r['ekf_coarse'] / r['simplex_coarse']:.2f} | {r['algebra'] * 1e6:.0f} "
            f"| {r['reference'] * 1e6:.0f} ({r['n']}) | {r['reference'] / r['simplex_coarse']:.2f} |",
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
