"""Several sessions' ticks in one native call against one call a session: what the batch could save.

N pendulum_3 PASSIVE filters per arm (the JITDYN preset on the native engine, one native call a
tick), fed the same frames. Each tick, the "one by one" arm calls every filter's native
`Tick.step` in turn (the GIL released and taken back once a session); the "batched" arm hands all N
to `Tick.step_many` (released once). Both take the same tuples back. Thread CPU per session and
tick, arms alternated round by round in one process; the difference is the most a batch of N
sessions' ticks could save a tick, before the cost of bringing their ticks together in time.

    python -m benchmarks.batched_ticks                          # 8 and 20 sessions
    python -m benchmarks.batched_ticks --sessions 60 --rounds 9
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable, Sequence

import numpy as np

from benchmarks.ukf_cycle import CASES, ground_truth, load
from jitdyn.server.estimation.config import resolve_config
from jitdyn.server.estimation.interface import Measurement
from jitdyn.server.estimation.native import _ukf
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.estimation.ukf import UnscentedFilter
from jitdyn.vocabulary import Preset

_CASE = "pendulum_3 passive"


def _filters(count: int, frames: list[Measurement], pool: WorkerPool) -> list[UnscentedFilter]:
    case = next(c for c in CASES if c.name == _CASE)
    model, _ = load(case.model)
    config = resolve_config(
        model=model,
        scenario=case.scenario,
        dt=case.dt,
        preset=Preset.JITDYN,
        measured=frozenset({"qpos", "qvel"}),
    )
    filters = [UnscentedFilter(model, config, pool=pool) for _ in range(count)]
    for f in filters:
        f.initialise(frames[0])
    return filters


def _one_by_one(ticks: list[_ukf.Tick], zs: list[np.ndarray]) -> list[tuple[object, ...]]:
    return [t.step(z, quiet=True, qvel=None) for t, z in zip(ticks, zs, strict=True)]


def _batched(ticks: list[_ukf.Tick], zs: list[np.ndarray]) -> list[tuple[object, ...]]:
    return _ukf.Tick.step_many(ticks, zs, [True] * len(ticks))


_ARMS: dict[str, Callable[[list[_ukf.Tick], list[np.ndarray]], list[tuple[object, ...]]]] = {
    "one by one": _one_by_one,
    "batched": _batched,
}


def measure(sessions: int, *, rounds: int, ticks: int) -> dict[str, list[float]]:
    """Thread CPU per session and tick, us, by arm: one figure a round."""
    case = next(c for c in CASES if c.name == _CASE)
    model, _ = load(case.model)
    frames = ground_truth(model, case, 2, ticks=1 + ticks * (rounds + 1))
    with WorkerPool(1) as pool:
        arms = {arm: _filters(sessions, frames, pool) for arm in _ARMS}
        native = {arm: [f._tick._tick for f in fs] for arm, fs in arms.items()}  # type: ignore[union-attr]
        zs = [fs[0]._z(m) for fs in [arms["batched"]] for m in frames]
        times: dict[str, list[float]] = {arm: [] for arm in _ARMS}
        last: dict[str, list[tuple[object, ...]]] = {}
        for r in range(rounds + 1):
            for arm, call in _ARMS.items():
                began = time.thread_time()
                for k in range(1 + r * ticks, 1 + (r + 1) * ticks):
                    last[arm] = call(native[arm], [zs[k]] * sessions)
                if r > 0:  # the first round warms up
                    times[arm].append(1e6 * (time.thread_time() - began) / (ticks * sessions))
        a, b = (last[arm][-1] for arm in _ARMS)
        if not all(np.array_equal(a[i], b[i]) for i in (8, 9)):  # type: ignore[arg-type]
            raise SystemExit("batched_ticks: the arms' filters differ; the batch is not the same work")
    return times


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.batched_ticks",
        description=__doc__.splitlines()[0] if __doc__ else None,
        epilog=__doc__.split("\n\n", 1)[1] if __doc__ else None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--sessions", type=int, nargs="+", default=[8, 20], help="filters per arm (default 8 20)"
    )
    parser.add_argument("--rounds", type=int, default=7, help="rounds, arms alternated (default %(default)s)")
    parser.add_argument("--ticks", type=int, default=200, help="ticks a round and arm (default %(default)s)")
    args = parser.parse_args(argv)
    if min(args.sessions) < 1 or args.rounds < 1 or args.ticks < 1:
        parser.error("--sessions, --rounds and --ticks must be integers >= 1")
    print(f"{'sessions':>8} {'one by one us':>14} {'batched us':>11} {'saved us':>9} {'batched cheaper':>16}")
    for n in args.sessions:
        times = measure(n, rounds=args.rounds, ticks=args.ticks)
        one, batched = (statistics.median(times[arm]) for arm in _ARMS)
        wins = sum(b < o for o, b in zip(times["one by one"], times["batched"], strict=True))
        print(
            f"{n:8d} {one:14.1f} {batched:11.1f} {one - batched:9.1f} {wins:>10d} of {args.rounds}",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
