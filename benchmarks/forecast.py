"""What a tick of the forecast combination (a DRIVEN filter's gap answer) costs against its physics.

A DRIVEN session keeps PROBES forecasts alive, each one single-point rollout of the process model
a tick, stepped together as one `mujoco.batch.Batch` call and scored together
(server/estimation/forecast.py). For each model, measured side by side in one process, round-robin:

    tick        CPU time of combiner.advance() + forecast() + observe(), every probe alive: the
                batched stepping, the predictors' forecasts and the scoring of every probe
    physics     PROBES single mj_step calls of the same process model (one call of count steps)
    alone       the stepping only, each probe set and stepped from Python (the un-batched way)
    tick/physics, alone/physics   medians of ratios paired with the physics measured just before
                and just after (a busy moment on the shared machine weighs on both alike)

tick/physics less alone/physics is what the forecasts and the scores cost beyond the probes'
stepping; alone/physics less 1 is the interpreter's cost per probe that one batched call saves.

    python -m benchmarks.forecast                # pendulum_3 and myoElbow (myoElbow needs jitdyn[myo])
    python -m benchmarks.forecast --rounds 15
    python -m benchmarks.forecast --share        # the forecast's share of a DRIVEN session's cycle

With --share: the whole estimator of a DRIVEN session as the server builds it (JITDYN preset,
native engine, one worker) on a 2-link arm at 50 Hz, myoElbow at 500 Hz and a 3-joint leg whose
joints have roles at 100 Hz (hip, knee, ankle: the prior of human motion among its predictors;
experiments/recorded.py's chain), over the model's own
excited motion with 4 ticks of frames lost every 25, three ways alternated round by round: with the
forecast combination in the native engine (the preset's: native/forecast.cc, motion matching
included), with the Python ForecastCombiner in its place (`native_forecast` False, the same
numbers), and with `forecast` FILTER; thread CPU per tick, medians. The forecast's cost is a
cycle's less FILTER's.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from collections.abc import Callable

import mujoco
import numpy as np

from benchmarks.ukf_cycle import load
from jitdyn.server.estimation.forecast import PROBES, ForecastCombiner
from jitdyn.server.estimation.propagate import process_model


def _thread_seconds(run: Callable[[], None], count: int) -> float:
    began = time.thread_time()
    for _ in range(count):
        run()
    return (time.thread_time() - began) / count


def measure(name: str, dt: float, rounds: int, ticks: int) -> dict[str, float] | None:
    try:
        own, _ = load(name)
    except ImportError:  # myo_sim: the jitdyn[myo] extra
        return None
    process = process_model(own, scenario="DRIVEN")
    combiner = ForecastCombiner(process, dt=dt, steps_per_tick=1, horizon=100)
    act, force = np.full(process.na, 0.3), np.zeros(process.nv)
    qpos0 = process.qpos0.copy()
    k = 0

    def tick() -> None:
        nonlocal k
        k += 1
        q = qpos0 + 0.3 * np.sin(0.01 * k)
        v = np.full(process.nv, 0.003 * np.cos(0.01 * k))
        combiner.advance()
        combiner.forecast()
        combiner.observe(q, v, mean_qpos=q, mean_qvel=v, act=act, force=force, rate=None)

    data = mujoco.MjData(process)
    data.qpos[:] = qpos0

    def physics() -> None:
        mujoco.mj_step(process, data, PROBES)

    alone_data = mujoco.MjData(process)
    starts = np.tile(np.concatenate([qpos0, np.zeros(process.nv)]), (PROBES, 1))

    def alone() -> None:
        for row in starts:
            alone_data.qpos[:] = row[: process.nq]
            alone_data.qvel[:] = row[process.nq :]
            alone_data.act[:] = act
            alone_data.qfrc_applied[:] = force
            mujoco.mj_step(process, alone_data)

    for _ in range(300):  # every probe alive
        tick()
    ratios: dict[str, list[float]] = {"tick": [], "alone": []}
    seconds: dict[str, list[float]] = {"tick": [], "alone": [], "physics": []}
    for _ in range(rounds):
        for label, run in (("tick", tick), ("alone", alone)):
            before = _thread_seconds(physics, ticks)
            spent = _thread_seconds(run, ticks)
            after = _thread_seconds(physics, ticks)
            ratios[label].append(spent / (0.5 * (before + after)))
            seconds[label].append(spent)
            seconds["physics"].extend((before, after))
    return {
        "tick_us": 1e6 * statistics.median(seconds["tick"]),
        "alone_us": 1e6 * statistics.median(seconds["alone"]),
        "physics_us": 1e6 * statistics.median(seconds["physics"]),
        "tick_ratio": statistics.median(ratios["tick"]),
        "alone_ratio": statistics.median(ratios["alone"]),
    }


def _driven_cycle(name: str, rate: float, forecast: str, *, native: bool = True) -> Callable[[int], None]:
    """One tick (k) of a DRIVEN session's estimator of `name` at `rate` Hz: a frame, or none on 4
    ticks of every 25; native: the forecast combination in the native engine (else the Python one)."""
    from benchmarks.cost_nv import load as load_model
    from benchmarks.cost_nv import truth
    from benchmarks.late_arm import ARM
    from jitdyn.experiments.recorded import chain_mjcf
    from jitdyn.registry.info import describe_model
    from jitdyn.roles import joint_roles
    from jitdyn.server.estimation.config import resolve_config
    from jitdyn.server.estimation.factory import make_estimator
    from jitdyn.server.estimation.pool import WorkerPool
    from jitdyn.vocabulary import Scenario

    if name in ("arm2", "leg3"):
        model = mujoco.MjModel.from_xml_string(ARM if name == "arm2" else chain_mjcf())
    else:
        model = load_model(name)
    dt = 1.0 / rate
    config = resolve_config(
        model=model, scenario="DRIVEN", dt=dt, requested={"forecast": forecast}, measured={"qpos", "qvel"}
    )
    roles = joint_roles(describe_model(model).joints, ())  # the leg's: what the registry gives it
    config = dataclasses.replace(config, native_forecast=native, roles=roles)
    frames = truth(model, Scenario.DRIVEN, round(dt / model.opt.timestep), ticks=1000)
    estimator = make_estimator(model, config, pool=WorkerPool(1))
    estimator.initialise(frames[0])

    def tick(k: int) -> None:
        if k % 25 in (10, 11, 12, 13):
            estimator.predict(ctrl=None)
        else:
            estimator.advance(ctrl=None)
            estimator.update(frames[k % len(frames)])

    return tick


def share(rounds: int, ticks: int) -> None:
    """The forecast combination's share of a DRIVEN cycle, native and Python (module docstring)."""
    print(
        "| model | rate (Hz) | cycle, native combination (us) | cycle, Python combination (us) | "
        "cycle, FILTER (us) | the forecast, native (us) | the forecast, Python (us) | Python / native | "
        "native share |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for name, rate in (("arm2", 50.0), ("myoelbow", 500.0), ("leg3", 100.0)):
        try:
            arms = {
                "native": _driven_cycle(name, rate, "COMBINED"),
                "python": _driven_cycle(name, rate, "COMBINED", native=False),
                "filter": _driven_cycle(name, rate, "FILTER"),
            }
        except ImportError:  # myo_sim: the jitdyn[myo] extra
            print(f"| {name} | {rate:g} | not run: myo_sim is not installed |||||||", flush=True)
            continue
        spent: dict[str, list[float]] = {f: [] for f in arms}
        k = 1
        for _ in range(rounds):
            for label, tick in arms.items():
                began = time.thread_time()
                for j in range(k, k + ticks):
                    tick(j)
                spent[label].append((time.thread_time() - began) / ticks * 1e6)
            k += ticks
        native, python, alone = (statistics.median(spent[f]) for f in ("native", "python", "filter"))
        print(
            f"| {name} | {rate:g} | {native:.0f} | {python:.0f} | {alone:.0f} | {native - alone:.0f} | "
            f"{python - alone:.0f} | {(python - alone) / max(native - alone, 1e-9):.1f} | "
            f"{100 * (native - alone) / native:.0f} % |",
            flush=True,
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--rounds", type=int, default=7, help="round-robin rounds (default 7)")
    parser.add_argument("--ticks", type=int, default=200, help="ticks per measurement (default 200)")
    parser.add_argument(
        "--share",
        action="store_true",
        help="the forecast's share of a DRIVEN session's cycle, native and Python, instead",
    )
    args = parser.parse_args(argv)
    if args.rounds < 1 or args.ticks < 1:
        parser.error("--rounds and --ticks must be at least 1")
    if args.share:
        share(args.rounds, args.ticks)
        return 0
    print(f"{PROBES} probes; {args.rounds} rounds of {args.ticks} ticks; mujoco {mujoco.__version__}")
    print()
    print("| model | dt (ms) | physics (us) | tick (us) | tick/physics | alone (us) | alone/physics |")
    print("|---|---|---|---|---|---|---|")
    for name, dt in (("pendulum_3", 0.05), ("myoelbow", 0.002)):
        row = measure(name, dt, args.rounds, args.ticks)
        if row is None:
            print(
                f"| {name} | {1e3 * dt:g} | not run: myo_sim is not installed (pip install 'jitdyn[myo]') |||||",
                flush=True,
            )
            continue
        print(
            f"| {name} | {1e3 * dt:g} | {row['physics_us']:.0f} | {row['tick_us']:.0f} | "
            f"{row['tick_ratio']:.2f} | {row['alone_us']:.0f} | {row['alone_ratio']:.2f} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
