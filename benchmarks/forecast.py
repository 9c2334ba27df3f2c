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
"""

from __future__ import annotations

import argparse
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--rounds", type=int, default=7, help="round-robin rounds (default 7)")
    parser.add_argument("--ticks", type=int, default=200, help="ticks per measurement (default 200)")
    args = parser.parse_args(argv)
    if args.rounds < 1 or args.ticks < 1:
        parser.error("--rounds and --ticks must be at least 1")
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
