"""How long one UKF cycle (predict + update) takes per model, against the floor of its physics.

For each of the thesis' experiments (passive pendulums, controlled pendulum_3, controlled biped,
externally controlled myoElbow and myoHand), with jitdyn's default settings (the JITDYN preset),
both propagation back-ends and 1 and 2 workers:

    cycle   median wall time of estimator.advance(ctrl) + estimator.update(frame), what the
            server runs for a tick whose frame is there
    floor   nsigma x steps per tick x one mj_step (measured in the same run, on the filter's own
            process model, along the same trajectory) / workers
    ratio   cycle / floor     (target <= 1.5; and cycle < dt for every model)

In CONTROLLED the filter steps fewer points than nsigma (points that differ only in qdd share one
propagation; server/estimation/ukf.py): the floor still counts every sigma point, and the table says how many
were stepped. mj_step is the process model's (server/estimation/propagate.py: warm start and sensors off;
in EXTERNAL actuators off and inert tendons dropped); the model's own is printed beside it.

Everything is measured side by side, round-robin, in one process: on a machine shared with other
work, a slow moment then hits every configuration alike. Ground truth is MuJoCo itself, driven
as the thesis drove it; models come from models/*.xml and from myo_sim.

    python benchmarks/ukf_cycle.py                   # full run, ~2 minutes
    python benchmarks/ukf_cycle.py --quick           # fewer rounds
"""

from __future__ import annotations

import argparse
import statistics
import sys
import threading
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from jitdyn.server.estimation.config import EstimatorConfig, resolve_config
from jitdyn.server.estimation.factory import make_estimator
from jitdyn.server.estimation.interface import Measurement
from jitdyn.server.estimation.pool import Backend, WorkerPool
from jitdyn.server.estimation.propagate import process_model
from jitdyn.vocabulary import Preset, Scenario, SigmaScheme

MODELS = Path(__file__).resolve().parents[1] / "models"


def load(name: str) -> tuple[mujoco.MjModel, str]:
    """The model and where it came from."""
    if name.startswith("myo"):
        import myo_sim  # heavy: only when a myo model is benchmarked

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "Attaching a spec with an empty prefix": myo_sim's own
            return myo_sim.load_model(name), "myo_sim"
    path = MODELS / f"{name}.xml"
    return mujoco.MjModel.from_xml_path(str(path)), str(path.relative_to(MODELS.parent))


@dataclass(frozen=True)
class Case:
    name: str
    model: str
    scenario: Scenario
    dt: float
    control: Callable[[mujoco.MjModel, int], np.ndarray]


def _sines(model: mujoco.MjModel, k: int) -> np.ndarray:
    return 2.0 * np.sin(0.2 * k + np.arange(model.nu))


def _gait(model: mujoco.MjModel, k: int) -> np.ndarray:
    return 5.0 * np.sin(0.02 * k + np.pi * np.arange(model.nu))


def _excitation(model: mujoco.MjModel, k: int) -> np.ndarray:
    # Gradual raising and lowering (myoElbow), alternate bending (myoHand): slow, out-of-phase waves.
    return 0.5 + 0.5 * np.sin(0.01 * k + 0.7 * np.arange(model.nu))


def _none(model: mujoco.MjModel, k: int) -> np.ndarray:
    return np.zeros(model.nu)


CASES = [
    Case("pendulum_1 passive", "pendulum_1", Scenario.PASSIVE, 0.05, _none),
    Case("pendulum_2 passive", "pendulum_2", Scenario.PASSIVE, 0.05, _none),
    Case("pendulum_3 passive", "pendulum_3", Scenario.PASSIVE, 0.05, _none),
    Case("pendulum_3 controlled", "pendulum_3", Scenario.CONTROLLED, 0.05, _sines),
    Case("biped controlled", "biped", Scenario.CONTROLLED, 0.005, _gait),
    Case("myoElbow external", "myoelbow", Scenario.EXTERNAL, 0.002, _excitation),
    Case("myoHand external", "myohand", Scenario.EXTERNAL, 0.002, _excitation),
    # What a MyoSuite session that names no scenario gets: the unknown force in the state.
    Case("myoElbow driven", "myoelbow", Scenario.DRIVEN, 0.002, _excitation),
    Case("myoHand driven", "myohand", Scenario.DRIVEN, 0.002, _excitation),
]


def ground_truth(model: mujoco.MjModel, case: Case, nstep: int, ticks: int) -> list[Measurement]:
    d = mujoco.MjData(model)
    if case.model.startswith("pendulum"):
        d.qpos[:] = 0.5
    mujoco.mj_forward(model, d)
    frames = []
    for k in range(ticks):
        d.ctrl[:] = case.control(model, k)
        for _ in range(nstep):
            mujoco.mj_step(model, d)
        frames.append(Measurement(qpos=d.qpos.copy(), qvel=d.qvel.copy(), ctrl=d.ctrl.copy()))
    return frames


class Runner:
    """One estimator on one pool, stepping through its ground truth a few cycles at a time."""

    def __init__(
        self, model: mujoco.MjModel, config: EstimatorConfig, pool: WorkerPool, frames: list[Measurement]
    ):
        self.estimator = make_estimator(model, config, pool=pool)
        self.frames = frames
        self.estimator.initialise(frames[0])
        self.next = 1
        self.controlled = config.scenario == Scenario.CONTROLLED

    def cycles(self, count: int) -> float:
        """Run `count` cycles; seconds per cycle."""
        estimator, frames = self.estimator, self.frames
        if self.next + count > len(frames):
            estimator.initialise(frames[0])
            self.next = 1
        start = time.perf_counter()
        for k in range(self.next, self.next + count):
            frame = frames[k]
            estimator.advance(ctrl=frame.ctrl if self.controlled else None)
            estimator.update(frame)
        elapsed = time.perf_counter() - start
        self.next += count
        return elapsed / count


def step_time(model: mujoco.MjModel, frames: list[Measurement], nstep: int, ticks: int, start: int) -> float:
    """Seconds per mj_step of the process model along the ground truth (states set per tick)."""
    d = mujoco.MjData(model)
    elapsed = 0.0
    for k in range(start, start + ticks):
        frame = frames[k % len(frames)]
        d.qpos[:], d.qvel[:] = frame.qpos, frame.qvel
        if frame.ctrl is not None:
            d.ctrl[:] = frame.ctrl
        t0 = time.perf_counter()
        mujoco.mj_step(model, d, nstep)
        elapsed += time.perf_counter() - t0
    return elapsed / (ticks * nstep)


def parallel_speedup(model: mujoco.MjModel, steps: int) -> float:
    """How much faster two threads step this model than one, right now (2.0: a free second core
    and no contention for caches or memory between the two).

    Each thread loops mj_step on its own MjData (mj_step releases the GIL); the same work is done
    once on one thread and once split across two.
    """
    datas = [mujoco.MjData(model) for _ in range(2)]

    def run(d: mujoco.MjData, n: int) -> None:
        mujoco.mj_step(model, d, n)

    start = time.perf_counter()
    run(datas[0], 2 * steps)
    one = time.perf_counter() - start
    other = threading.Thread(target=run, args=(datas[1], steps))
    start = time.perf_counter()
    other.start()
    run(datas[0], steps)
    other.join()
    two = time.perf_counter() - start
    return one / two


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--rounds", type=int, default=15, help="round-robin rounds (default 15)")
    parser.add_argument(
        "--seconds", type=float, default=0.05, help="target time per measurement (default 0.05 s)"
    )
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--preset", type=Preset, default=Preset.JITDYN, choices=list(Preset))
    parser.add_argument("--cases", nargs="+", help="substrings of case names to run")
    parser.add_argument("--quick", action="store_true", help="5 rounds")
    args = parser.parse_args(argv)
    rounds = 5 if args.quick else args.rounds
    cases = [c for c in CASES if not args.cases or any(s in c.name for s in args.cases)]

    pools = {(b, w): WorkerPool(w, backend=b) for b in Backend for w in args.workers}
    setups = []
    for case in cases:
        model, source = load(case.model)
        measured = {"qpos", "qvel", "ctrl"} if case.scenario is Scenario.CONTROLLED else {"qpos", "qvel"}
        config = resolve_config(
            model=model,
            scenario=case.scenario,
            dt=case.dt,
            preset=args.preset,
            measured=measured,
        )
        frames = ground_truth(model, case, config.steps_per_tick, ticks=4000)
        runners = {key: Runner(model, config, pool, frames) for key, pool in pools.items()}
        some = next(iter(runners.values())).estimator
        nsigma = int(getattr(some, "nsigma", 1))  # a UKF, or the switching filter around one
        stepped = (
            nsigma - 2 * model.nv
            if case.scenario is Scenario.CONTROLLED and config.sigma_points == SigmaScheme.MERWE
            else nsigma
        )
        # Calibrate the cycles per measurement on the slowest configuration (one worker).
        probe = runners[Backend.ROLLOUT, min(args.workers)].cycles(5)
        count = max(3, min(500, int(args.seconds / probe)))
        setups.append((case, model, source, config, frames, runners, nsigma, count, stepped))

    cycle: dict[tuple[str, Backend, int], list[float]] = {}
    step: dict[str, list[float]] = {}
    own_step: dict[str, list[float]] = {}
    speedups: dict[str, list[float]] = {}
    processes = {case.name: process_model(model, scenario=case.scenario) for case, model, *_ in setups}
    # Ratios are paired: each cycle measurement is divided by the floor measured just before and
    # just after it, so that a busy moment on the shared machine weighs on both alike.
    ratio: dict[tuple[str, Backend, int], list[float]] = {}
    rollout_over_threads: dict[tuple[str, int], list[float]] = {}
    for r in range(rounds):
        for case, model, _, config, frames, runners, nsigma, count, _ in setups:
            ticks = max(20, count * nsigma // config.steps_per_tick)
            process = processes[case.name]
            speedups.setdefault(case.name, []).append(
                parallel_speedup(process, steps=ticks * config.steps_per_tick)
            )
            own_step.setdefault(case.name, []).append(
                step_time(model, frames, config.steps_per_tick, ticks=max(5, ticks // 4), start=r * 37)
            )
            here: dict[tuple[Backend, int], float] = {}
            for (backend, workers), runner in runners.items():
                before = step_time(process, frames, config.steps_per_tick, ticks=ticks, start=r * 37)
                seconds = runner.cycles(count)
                after = step_time(process, frames, config.steps_per_tick, ticks=ticks, start=r * 37)
                mj = 0.5 * (before + after)
                step.setdefault(case.name, []).append(mj)
                cycle.setdefault((case.name, backend, workers), []).append(seconds)
                floor = nsigma * config.steps_per_tick * mj / workers
                ratio.setdefault((case.name, backend, workers), []).append(seconds / floor)
                here[backend, workers] = seconds
            for workers in args.workers:
                rollout_over_threads.setdefault((case.name, workers), []).append(
                    here[Backend.ROLLOUT, workers] / here[Backend.THREADS, workers]
                )

    print(
        f"preset {args.preset}; {rounds} rounds; medians (ratios: median of paired ratios); "
        f"python {sys.version.split()[0]}, mujoco {mujoco.__version__}"
    )
    print("2 threads: how much faster two threads stepped the model than one, in the same run: the")
    print("parallelism the machine had to give (2.00 would be a free second core, uncontended).")
    print()
    print(
        "| case | model | dt (ms) | points x steps (stepped) | mj_step process / own (us) | 2 threads "
        "| workers | floor (us) | rollout (us) | ratio | threads (us) | ratio | faster | cycle < dt |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for case, _, source, config, _, _, nsigma, _, stepped in setups:
        mj = statistics.median(step[case.name])
        own = statistics.median(own_step[case.name])
        for workers in args.workers:
            floor = nsigma * config.steps_per_tick * mj / workers
            roll = statistics.median(cycle[case.name, Backend.ROLLOUT, workers])
            thr = statistics.median(cycle[case.name, Backend.THREADS, workers])
            roll_ratio = statistics.median(ratio[case.name, Backend.ROLLOUT, workers])
            thr_ratio = statistics.median(ratio[case.name, Backend.THREADS, workers])
            best = min(roll, thr)
            relative = statistics.median(rollout_over_threads[case.name, workers])
            faster = f"rollout {1 / relative:.2f}x" if relative <= 1 else f"threads {relative:.2f}x"
            print(
                f"| {case.name} | {source} | {case.dt * 1e3:g} | {config.sigma_points.lower()} {nsigma} x "
                f"{config.steps_per_tick} ({stepped}) | {mj * 1e6:.1f} / {own * 1e6:.1f} "
                f"| {statistics.median(speedups[case.name]):.2f}x | {workers} "
                f"| {floor * 1e6:.0f} "
                f"| {roll * 1e6:.0f} | {roll_ratio:.2f} | {thr * 1e6:.0f} | {thr_ratio:.2f} "
                f"| {faster} | {'yes' if best < case.dt else 'NO'} ({best / case.dt:.0%}) |"
            )
    for pool in pools.values():
        pool.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
