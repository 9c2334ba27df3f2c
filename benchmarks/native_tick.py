"""A tick's numeric work in one native call against the same steps one call each: one UKF per
arm, the JITDYN preset on the native engine, `native_tick` on (one call) or off (steps, their
reference), fed the same ground truth as a LOCKSTEP session feeds it: on a frame that is on time
step(), every GAP_EVERY-th tick without its frame predict(), and the timewarp's snapshot after
each tick. Thread CPU per tick, arms alternated round by round in one process (on a shared
machine a slow moment hits both); the ratio is steps / one call.

    python -m benchmarks.native_tick                        # pendulum_3, biped, myoElbow DRIVEN
    python -m benchmarks.native_tick --profile 40           # and every call of a tick, by cost
"""

from __future__ import annotations

import argparse
import cProfile
import dataclasses
import pstats
import statistics
import time
from collections.abc import Sequence

from benchmarks.ukf_cycle import CASES, ground_truth, load
from jitdyn.server.estimation.config import resolve_config
from jitdyn.server.estimation.interface import Measurement
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.estimation.ukf import UnscentedFilter
from jitdyn.vocabulary import Preset, Scenario

_CASES = ("pendulum_3 passive", "biped controlled", "myoElbow driven")
GAP_EVERY = 10  # every tenth tick without its frame: a gap's prediction
_ARMS = {"one call": True, "steps": False}


def _block(f: UnscentedFilter, frames: list[Measurement], start: int, ticks: int, controlled: bool) -> None:
    for k in range(start, start + ticks):
        frame = frames[k]
        ctrl = frame.ctrl if controlled else None
        if k % GAP_EVERY == 0:
            f.predict(ctrl=ctrl)
        else:
            f.step(ctrl=ctrl, m=frame)
        f.snapshot()


def _profile(stats: pstats.Stats, ticks: int, lines: int) -> list[str]:
    """The estimator's own calls (server/estimation, the native module) by time spent in each:
    us a tick (cProfile's, its overhead included) and calls a tick."""
    rows = []
    for (path, line, name), (_, calls, tottime, _, _) in stats.stats.items():  # type: ignore[attr-defined]
        if "estimation" in path or "_ukf" in name:
            where = name if path == "~" else f"{path.split('server/')[-1]}:{line} {name}"
            rows.append((tottime * 1e6 / ticks, calls / ticks, where))
    rows.sort(reverse=True)
    return [f"{us:8.1f} {calls:6.1f}  {where}" for us, calls, where in rows[:lines]]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.native_tick",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--cases", nargs="+", default=list(_CASES), help=f"case names (default {_CASES})")
    parser.add_argument("--rounds", type=int, default=7, help="rounds, arms alternated (default 7)")
    parser.add_argument("--ticks", type=int, default=300, help="ticks a round and arm (default 300)")
    parser.add_argument("--profile", type=int, default=0, help="print this many of each arm's calls")
    args = parser.parse_args(argv)
    cases = {c.name: c for c in CASES}
    print(f"{'case':22} {'one call us':>12} {'steps us':>9} {'steps/one':>10}")
    profiles: list[str] = []
    with WorkerPool(1) as pool:
        for name in args.cases:
            case = cases[name]
            model, _ = load(case.model)
            controlled = case.scenario == Scenario.CONTROLLED
            measured = frozenset({"qpos", "qvel", "ctrl"} if controlled else {"qpos", "qvel"})
            config = resolve_config(
                model=model, scenario=case.scenario, dt=case.dt, preset=Preset.JITDYN, measured=measured
            )
            total = 1 + args.ticks * (args.rounds + 1)
            frames = ground_truth(model, case, config.steps_per_tick, ticks=total)
            filters = {}
            for arm, on in _ARMS.items():
                f = UnscentedFilter(model, dataclasses.replace(config, native_tick=on), pool=pool)
                f.initialise(frames[0])
                _block(f, frames, 1, args.ticks, controlled)  # warm up
                filters[arm] = f
            times: dict[str, list[float]] = {arm: [] for arm in _ARMS}
            for r in range(args.rounds):
                start = 1 + args.ticks * (r + 1)
                for arm, f in filters.items():
                    began = time.thread_time()
                    _block(f, frames, start, args.ticks, controlled)
                    times[arm].append((time.thread_time() - began) / args.ticks)
            one, steps = (statistics.median(times[arm]) * 1e6 for arm in _ARMS)
            print(f"{name:22} {one:12.0f} {steps:9.0f} {steps / one:10.2f}", flush=True)
            if args.profile:
                for arm, f in filters.items():
                    f.initialise(frames[0])
                    profiler = cProfile.Profile()
                    profiler.enable()
                    _block(f, frames, 1, args.ticks, controlled)
                    profiler.disable()
                    profiles.append(
                        f"\n## {name}, {arm}: cProfile of {args.ticks} ticks\n   us/tick calls/tick"
                    )
                    profiles.extend(_profile(pstats.Stats(profiler), args.ticks, args.profile))
    print("\n".join(profiles))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
