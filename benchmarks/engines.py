"""The native engine against the Python one (FAST) it mirrors: one UKF cycle (advance + update,
what the server runs for a tick whose frame is there) per model, side by side, round-robin, in
one process and on one worker, with the cycle's physics floor measured in the same run.

    python -m benchmarks.engines                     # every case of benchmarks/ukf_cycle.py, ~1 min
    python -m benchmarks.engines --cases pendulum_3 biped --rounds 9

    python     median microseconds of a FAST cycle
    native     median microseconds of a NATIVE cycle (same config otherwise)
    floor      nsigma x steps per tick x one mj_step of the process model, microseconds
    speedup    python / native;  native/floor  native / floor
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
from collections.abc import Sequence

from benchmarks.ukf_cycle import CASES, Runner, ground_truth, load, step_time
from jitdyn.server.estimation.config import Engine, resolve_config
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.estimation.propagate import process_model
from jitdyn.vocabulary import Channel, Preset, Scenario

CYCLES = 20  # cycles per measurement


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--rounds", type=int, default=7, help="round-robin rounds, each engine once a round (default 7)"
    )
    parser.add_argument("--cases", nargs="+", help="substrings of case names to run (default: all)")
    args = parser.parse_args(argv)
    if args.rounds < 1:
        parser.error(f"--rounds must be >= 1, got {args.rounds}")
    cases = [c for c in CASES if not args.cases or any(s in c.name for s in args.cases)]
    if not cases:
        parser.error(f"no case matches {args.cases}; the cases are {[c.name for c in CASES]}")
    print(
        f"{'case':24} {'n':>3} {'points':>6} {'python us':>10} {'native us':>10} {'floor us':>9} "
        f"{'speedup':>8} {'native/floor':>12}"
    )
    with WorkerPool(1) as pool:
        for case in cases:
            model, _ = load(case.model)
            measured = {Channel.QPOS, Channel.QVEL} | (
                {Channel.CTRL} if case.scenario == Scenario.CONTROLLED else set()
            )
            native = resolve_config(
                model=model, scenario=case.scenario, dt=case.dt, preset=Preset.JITDYN, measured=measured
            )
            python = dataclasses.replace(native, engine=Engine.FAST)
            frames = ground_truth(model, case, native.steps_per_tick, 400)
            runners = {
                "python": Runner(model, python, pool, frames),
                "native": Runner(model, native, pool, frames),
            }
            times: dict[str, list[float]] = {name: [] for name in runners}
            for _ in range(args.rounds):
                for name, runner in runners.items():
                    times[name].append(runner.cycles(CYCLES))
            nsigma = runners["native"].estimator.nsigma  # type: ignore[attr-defined]
            step = step_time(
                process_model(model, scenario=case.scenario), frames, native.steps_per_tick, 50, 0
            )
            floor = nsigma * native.steps_per_tick * step
            py, nat = (statistics.median(times[k]) for k in ("python", "native"))
            n = runners["native"].estimator.state_dimension
            print(
                f"{case.name:24} {n:3d} {nsigma:6d} {py * 1e6:10.0f} {nat * 1e6:10.0f} {floor * 1e6:9.0f} "
                f"{py / nat:8.2f} {nat / floor:12.2f}",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
