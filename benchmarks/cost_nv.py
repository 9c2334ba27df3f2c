"""How a tick's cost grows with the model, and what would make the largest real time.

For each model at its rate, with its default estimator (JITDYN preset): the CPU of one cycle
(predict + update) against its floor, the rollout of the same sigma points over one tick alone
(timed just before and after, on the same pool), and the wall time of a cycle against the tick.
Variants for a model that does not fit: fewer physics steps per tick (the sigma points' physics on
a coarser timestep), and more workers.

    python -m benchmarks.cost_nv                 # every row, ~2 minutes
    python -m benchmarks.cost_nv --rows myolegs  # substrings of the row names

With --candidates, what a user can see before registering a model: every built-in model and every
myo-sim model that compiles here, in the scenario a session of it gets when it names none, at its
rate (the built-ins at the rates above, the myo-sim models at 100 Hz), and for every estimator the
server may choose for it (server/runtime/choice.py, most accurate first): the CPU of a cycle per
tick beside the mean |q error| of its answers over 100 ms gaps every 250 ms of the model's own
excited motion, and that error against the first candidate's (the full UKF's).

    python -m benchmarks.cost_nv --candidates                    # ~10 minutes
    python -m benchmarks.cost_nv --candidates --rows myohand     # substrings of the model names
    python -m benchmarks.cost_nv --candidates --noise 0.005      # frames with a sensor's noise
    python -m benchmarks.cost_nv --candidates --rows myolegs_osl --scenarios driven external
    python -m benchmarks.cost_nv --candidates --rows myolegs_osl --recorded --noise 0.005
    python -m benchmarks.cost_nv --candidates --rows myohand --rate 500 --scenarios external driven
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from jitdyn.experiments.accuracy import candidate_models, excited_motion, gap_run, sensed
from jitdyn.server.estimation.config import resolve_config
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.estimation.ukf import UnscentedFilter
from jitdyn.vocabulary import Scenario

MODELS = Path(__file__).resolve().parents[1] / "models"


def load(name: str) -> mujoco.MjModel:
    if name == "myolegs_osl":  # MyoSuite's legs with the Open Source Leg prosthesis
        import myo_sim

        path = Path(myo_sim.__file__).parent / "models/legacy/osl/myolegs_osl.xml"
        return mujoco.MjModel.from_xml_path(str(path))
    if name.startswith("myo"):
        import myo_sim

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return myo_sim.load_model(name)
    return mujoco.MjModel.from_xml_path(str(MODELS / f"{name}.xml"))


@dataclass(frozen=True)
class Row:
    name: str
    model: str
    scenario: Scenario
    rate: float
    coarsen: int = 1  # the process model's timestep times this (fewer steps per tick)
    workers: int = 1


ROWS = (
    Row("pendulum_3 PASSIVE", "pendulum_3", Scenario.PASSIVE, 20.0),
    Row("biped CONTROLLED", "biped", Scenario.CONTROLLED, 200.0),
    Row("myoElbow DRIVEN (default)", "myoelbow", Scenario.DRIVEN, 500.0),
    Row("myoHand EXTERNAL", "myohand", Scenario.EXTERNAL, 500.0),
    Row("myolegs_osl DRIVEN (default)", "myolegs_osl", Scenario.DRIVEN, 100.0),
    Row("myolegs_osl DRIVEN, 2 workers", "myolegs_osl", Scenario.DRIVEN, 100.0, workers=2),
    Row("myolegs_osl DRIVEN, 5 ms step", "myolegs_osl", Scenario.DRIVEN, 100.0, coarsen=5),
    Row(
        "myolegs_osl DRIVEN, 5 ms step, 2 workers",
        "myolegs_osl",
        Scenario.DRIVEN,
        100.0,
        coarsen=5,
        workers=2,
    ),
    Row("myolegs_osl EXTERNAL", "myolegs_osl", Scenario.EXTERNAL, 100.0),
)


truth = excited_motion  # the model under slow out-of-phase excitations of its actuators


def physics(ukf: UnscentedFilter) -> None:
    """The rollout of this tick's sigma points (as the filter would step them), alone."""
    parts = ukf.parts
    kf, nq, nv, process, state = parts.kf, parts.layout.nq, parts.layout.nv, parts.process, parts.state
    process.set_inputs(act=state.act, ctrl=state.ctrl, qfrc=state.qfrc)
    if parts.layout.linear_force:
        chi = parts.points.sigma_points(kf.x[: nq + nv], kf.P[: 2 * nv, : 2 * nv])
        process.propagate_linear_force(chi, np.repeat(kf.x[None, nq + nv :], chi.shape[0], 0), nstep=None)
    else:
        process.propagate(parts.points.sigma_points(kf.x, kf.P), nstep=None)


def measure(row: Row, rounds: int) -> dict[str, float]:
    model = load(row.model)
    dt = 1.0 / row.rate
    truth_nstep = round(dt / model.opt.timestep)
    frames = truth(model, row.scenario, truth_nstep, ticks=400)
    filter_model = model
    if row.coarsen > 1:
        filter_model = load(row.model)
        filter_model.opt.timestep *= row.coarsen
    controlled = row.scenario == Scenario.CONTROLLED
    measured = {"qpos", "qvel", "ctrl"} if controlled else {"qpos", "qvel"}
    config = resolve_config(
        model=filter_model, scenario=row.scenario, dt=dt, requested={}, model_defaults={}, measured=measured
    )
    out: dict[str, list[float]] = {"cycle_cpu": [], "cycle_wall": [], "physics_cpu": [], "ratio": []}
    with WorkerPool(row.workers) as pool:
        ukf = UnscentedFilter(filter_model, config, pool=pool)
        ukf.initialise(frames[0])
        k = 1
        for _ in range(rounds):
            count = max(3, min(50, int(0.05 / dt)))
            if k + count >= len(frames):
                ukf.initialise(frames[0])
                k = 1
            c0 = time.process_time()
            for _ in range(3):
                physics(ukf)
            before = (time.process_time() - c0) / 3
            c0, w0 = time.process_time(), time.perf_counter()
            for j in range(k, k + count):
                ukf.advance(ctrl=frames[j].ctrl if controlled else None)
                ukf.update(frames[j])
            cpu, wall = (time.process_time() - c0) / count, (time.perf_counter() - w0) / count
            k += count
            c0 = time.process_time()
            for _ in range(3):
                physics(ukf)
            after = (time.process_time() - c0) / 3
            out["cycle_cpu"].append(cpu)
            out["cycle_wall"].append(wall)
            out["physics_cpu"].append(0.5 * (before + after))
            out["ratio"].append(cpu / (0.5 * (before + after)))
        finite = bool(np.isfinite(ukf.parts.kf.x).all())
        error = float(np.max(np.abs(ukf.parts.kf.x[: model.nq] - frames[k - 1].qpos)))
    result = {key: statistics.median(values) for key, values in out.items()}
    result.update(
        nq=model.nq,
        nv=model.nv,
        nu=model.nu,
        n=ukf.state_dimension,
        nsigma=ukf.nsigma,
        steps=config.steps_per_tick,
        dt=dt,
        finite=finite,
        qpos_error=error,
        sigma=str(config.sigma_points),
    )
    return result


def candidate_run(
    model: mujoco.MjModel,
    scenario: Scenario,
    rate: float,
    settings: dict[str, object],
    seconds: float,
    noise: float = 0.0,
    *,
    recorded: bool = False,
) -> tuple[float, float]:
    """(median CPU s of a cycle per tick, mean |q error| over the gaps' ticks against the truth) of
    one candidate on the model's own excited motion (`truth`), a 100 ms gap every 250 ms: a gap's
    ticks answered by the estimator's prediction, the others by a cycle on the frame. The frames
    are perfect, or carry Gaussian noise of `noise` rad (or m) on qpos' tangent and 10 `noise`
    rad/s on qvel (seeded), as benchmarks/linearised.py's `noisy` puts it."""
    dt = 1.0 / rate
    steps = round(dt / model.opt.timestep)
    if recorded:  # iSen's gait on the hips and knees (benchmarks/linearised.py)
        from benchmarks.linearised import gait

        frames = gait(model, dt, seconds)
    else:
        frames = excited_motion(model, scenario, steps, ticks=round(seconds / dt))
    config = resolve_config(
        model=model, scenario=scenario, dt=dt, requested=settings, measured={"qpos", "qvel"}
    )
    run = gap_run(model, config, frames, sensed(model, frames, noise))
    return statistics.median(run.cycles), statistics.fmean(run.errors)


@dataclass(frozen=True)
class CandidateRuns:
    """What --candidates runs: the models (substrings), the motion, and the scenario and rate in
    place of a model's own (None: its default scenario, its rate)."""

    names: list[str] | None
    seconds: float
    noise: float
    scenarios: list[Scenario] | None = None
    rate: float | None = None
    recorded: bool = False


def candidates_table(runs: CandidateRuns) -> None:
    from jitdyn.server.estimation.config import default_scenario
    from jitdyn.server.runtime.choice import candidates

    print(
        "| model | nv / nu / na | scenario, rate | candidate | cycle per tick (us CPU) | cycle / dt "
        "| fits half of dt | mean |q error| over gaps (rad) | error / full UKF's |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for name, model, own_rate in candidate_models(runs.names):
        rate = runs.rate or own_rate
        for scenario in runs.scenarios or [default_scenario(model)[0]]:
            full = None
            for estimator, sigma in candidates(model, scenario):
                settings: dict[str, object] = {"estimator": estimator}
                if sigma is not None:
                    settings["sigma_points"] = sigma
                cycle, error = candidate_run(
                    model, scenario, rate, settings, runs.seconds, runs.noise, recorded=runs.recorded
                )
                full = error if full is None else full
                label = estimator.name if sigma is None else f"{estimator.name} {sigma.name}"
                print(
                    f"| {name} | {model.nv} / {model.nu} / {model.na} | {scenario.name} {rate:g} Hz | {label} "
                    f"| {cycle * 1e6:.0f} | {cycle * rate:.2f} | {'yes' if cycle * rate <= 0.5 else 'no'} "
                    f"| {error:.2e} | {error / full:.2f} |",
                    flush=True,
                )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--rows", nargs="+", help="substrings of row names")
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument(
        "--candidates",
        action="store_true",
        help="every built-in and myo-sim model, every estimator the server may choose: cost and accuracy",
    )
    parser.add_argument(
        "--seconds", type=float, default=2.0, help="of motion per --candidates run (default 2)"
    )
    parser.add_argument(
        "--noise",
        type=float,
        default=0.0,
        help="rad of noise on the frames' qpos (10x on qvel) for --candidates",
    )
    parser.add_argument(
        "--scenarios",
        nargs="+",
        type=lambda name: Scenario[name.upper()],
        help="for --candidates: these scenarios in place of each model's default one",
    )
    parser.add_argument("--rate", type=float, help="for --candidates: this rate (Hz) in place of the models'")
    parser.add_argument(
        "--recorded",
        action="store_true",
        help="for --candidates: recorded human gait on myolegs_osl's hips and knees (100 Hz), not the "
        "model's own excited motion",
    )
    args = parser.parse_args(argv)
    if args.candidates:
        motion = "recorded gait" if args.recorded else "excited motion"
        print(
            f"# {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}; mujoco {mujoco.__version__}; "
            f"{args.seconds:g} s of {motion} a run, noise {args.noise:g}, one thread"
        )
        candidates_table(
            CandidateRuns(
                names=args.rows,
                seconds=args.seconds,
                noise=args.noise,
                scenarios=args.scenarios,
                rate=args.rate,
                recorded=args.recorded,
            )
        )
        return 0
    rows = [r for r in ROWS if not args.rows or any(s in r.name for s in args.rows)]
    print(
        f"# {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}; python {sys.version.split()[0]}, "
        f"mujoco {mujoco.__version__}; medians of {args.rounds} rounds, ratios paired"
    )
    print(
        "| model, scenario | nq / nv / nu | state n | points x steps | physics (us CPU) | cycle (us CPU) "
        "| cycle / physics | cycle wall / dt | posterior |qpos error| |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        r = measure(row, args.rounds)
        print(
            f"| {row.name} | {r['nq']} / {r['nv']} / {r['nu']} | {r['n']} | {r['sigma'].lower()} "
            f"{r['nsigma']} x {r['steps']} | {r['physics_cpu'] * 1e6:.0f} | {r['cycle_cpu'] * 1e6:.0f} "
            f"| {r['ratio']:.2f} | {r['cycle_wall'] / r['dt']:.2f} "
            f"| {r['qpos_error']:.1e}{'' if r['finite'] else ' (NaN)'} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
