"""The server's own work for a tick, without the network: a session's frames fed straight to the
servicer's stream (`_Stream.on_frame`: the frame's check, the runtime, the estimator, the result's
dynamics, the record, the metrics, the result message and its serialisation), one thread, CPU time.

    python -m benchmarks.tick_path                                   # pendulum_3, both engines
    python -m benchmarks.tick_path --model biped --scenario CONTROLLED --rate 200
    python -m benchmarks.tick_path --profile 25                      # where it goes, by function
    python -m benchmarks.tick_path --grpc --sessions 8               # the whole tick, by thread
    python -m benchmarks.tick_path --arms native steps static         # a tick in one native call

It opens a LOCKSTEP session on a server built as `jitdyn serve` builds one (not listening), in a
temporary data folder, and feeds it the load generator's trajectory. Per tick it reports the
thread's CPU (time.thread_time: what the other programs of a shared machine do not change) and the
process's (the commit thread's share included), for each engine and for STATIC (no filter: what
the tick costs around it), alternated round by round. gRPC's own read and write are not here:
benchmarks/tick_budget.py sets the whole tick beside a bare echo.

With --grpc the same arms run whole: REALTIME sessions from the load generator's client processes
(benchmarks/load.py) over loopback to a server inside this process (BackgroundServer: it admits by
its sessions' estimates alone, so a busy machine does not refuse them), and each of the server's
threads' CPU per answered tick is read from /proc: the event loop (jitdyn-server), the commit
thread, gRPC core's threads. What the loop spends beyond the tick path above is the transport.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import cProfile
import dataclasses
import os
import pstats
import re
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from benchmarks.load import _frames, run, trajectory
from jitdyn.client import SessionOptions
from jitdyn.server.estimation.config import Engine, EstimatorConfig
from jitdyn.server.estimation.interface import Estimator
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.runtime import opening
from jitdyn.server.runtime.opening import SessionOpener
from jitdyn.server.transport.app import ServerConfig, create_server
from jitdyn.server.transport.background import BackgroundServer
from jitdyn.server.transport.dynamics_service import _Stream
from jitdyn.server.transport.opening import open_request
from jitdyn.v1 import dynamics_pb2
from jitdyn.vocabulary import Clock, Scenario

_ARMS = {
    "native": (Engine.NATIVE, None),
    "steps": (Engine.NATIVE, None),
    "python": (Engine.FAST, None),
    "static": (Engine.NATIVE, "STATIC"),
}


@contextlib.contextmanager
def _native_tick(on: bool) -> Iterator[None]:
    """Sessions opened inside run the native engine's tick in one call (on) or one call a step
    (off: the config's `native_tick` False, their reference; server/estimation/native/tick.py)."""
    if on:
        yield
        return
    built = opening.make_estimator

    def steps(model: mujoco.MjModel, config: EstimatorConfig, *, pool: WorkerPool) -> Estimator:
        return built(model, dataclasses.replace(config, native_tick=False), pool=pool)

    opening.make_estimator = steps
    try:
        yield
    finally:
        opening.make_estimator = built


@dataclass(frozen=True)
class Run:
    thread_us: float  # median over rounds of the feeding thread's CPU per tick
    process_us: float  # the same, of the whole process (the commit thread included)


def _options(
    model: str, scenario: str, rate: float, estimator: str | None, clock: Clock = Clock.LOCKSTEP
) -> SessionOptions:
    from jitdyn.experiments.objects import load_source

    source = load_source(model)
    if not source.builtin:
        raise SystemExit(f"--model {model}: not a built-in model (this benchmark registers none)")
    return SessionOptions(
        model_name=source.name,
        scenario=scenario,
        dt=1.0 / rate,
        clock=clock,
        estimator={"estimator": estimator} if estimator else {},
    )


async def _feed(
    arm: str,
    engine: Engine,
    options: SessionOptions,
    frames: list[dynamics_pb2.Frame],
    folder: Path,
    profile: bool,
    realtime: bool = False,
) -> tuple[float, float, pstats.Stats | None]:
    """Thread and process CPU seconds per tick of one session fed `frames` (the first tenth warms up)."""
    config = ServerConfig(address="127.0.0.1:0", data_root=folder, engine=engine, shares_process=True)
    server, _, services = await create_server(config)
    try:
        with _native_tick(arm != "steps"):
            opened = SessionOpener(services).open_session(open_request(options.to_message(), tenant="bench"))
        stream = _Stream(opened)
        warm = len(frames) // 10
        feed = _realtime_tick if realtime else _lockstep_tick
        for frame in frames[:warm]:
            await feed(stream, frame)
        profiler = cProfile.Profile() if profile else None
        thread, process = time.thread_time(), time.process_time()
        if profiler is not None:
            profiler.enable()
        for frame in frames[warm:]:
            await feed(stream, frame)
        if profiler is not None:
            profiler.disable()
        ticks = len(frames) - warm
        thread, process = (time.thread_time() - thread) / ticks, (time.process_time() - process) / ticks
        opened.recorder.close()
        return thread, process, pstats.Stats(profiler) if profiler is not None else None
    finally:
        await server.stop(None)
        services.committer.close()


class _Wire:
    """Where a stream's responses go in the REALTIME path: serialised, as grpc.aio's write does."""

    async def write(self, response: dynamics_pb2.StreamSessionResponse) -> None:
        response.SerializeToString()


_WIRE = _Wire()


async def _lockstep_tick(stream: _Stream, frame: dynamics_pb2.Frame) -> None:
    for response in stream.on_frame(frame, stream.clock.now()):
        response.SerializeToString()


async def _realtime_tick(stream: _Stream, frame: dynamics_pb2.Frame) -> None:
    """A REALTIME frame that arrives 1 ms before its tick's time, as an on-time client's does: the
    session's clock is set there (server time = client time), and the frame goes the way the
    servicer's request loop sends it: checked, answered at once, written."""
    stream.clock.restart(elapsed=frame.seq * stream.plan.dt - 1e-3)
    responses = stream.on_frame(frame, stream.clock.now())
    await stream.write(_WIRE, *responses)  # type: ignore[arg-type]


def _thread_cpu() -> dict[int, tuple[str, float]]:
    """Every thread of this process: native id -> (name, CPU seconds so far), from /proc."""
    names = {thread.native_id: thread.name for thread in threading.enumerate()}
    tick = os.sysconf("SC_CLK_TCK")
    found = {}
    for task in Path("/proc/self/task").iterdir():
        try:
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
            comm = (task / "comm").read_text().strip()
        except OSError:  # a thread that ended meanwhile
            continue
        tid = int(task.name)
        found[tid] = (names.get(tid, comm), (int(fields[11]) + int(fields[12])) / tick)
    return found


def _over_grpc(arm: str, args: argparse.Namespace, states: dict[str, np.ndarray]) -> dict[str, float]:
    """us of CPU per answered tick, by thread name, of a server in this process serving
    `args.sessions` REALTIME sessions of `arm` from the load generator's client processes."""
    engine, estimator = _ARMS[arm]
    with tempfile.TemporaryDirectory(prefix="jitdyn-tick-path-") as tmp, _native_tick(arm != "steps"):
        server = BackgroundServer(ServerConfig(address="127.0.0.1:0", data_root=Path(tmp), engine=engine))
        try:
            before = _thread_cpu()
            report = run(
                model=args.model,
                scenario=args.scenario,
                rate=args.rate,
                sessions=args.sessions,
                seconds=args.ticks / args.rate,
                clients=2,
                server=server.address,
                states=states,
                ukf_us=0.0,
                estimator=estimator,
                floor=False,
            )
            after = _thread_cpu()
        finally:
            server.close()
    ticks = max(1, round(report.answered * report.ticks_sent))
    by_name: dict[str, float] = {"answered %": 100 * report.answered}
    for tid, (name, cpu) in after.items():
        name = re.sub(r"_\d+$", "", name)  # a pool's threads together
        used = cpu - before.get(tid, (name, 0.0))[1]
        by_name[name] = by_name.get(name, 0.0) + used * 1e6 / ticks
    return by_name


def _grpc_table(args: argparse.Namespace, states: dict[str, np.ndarray]) -> None:
    print(
        f"# {args.model} {args.scenario} at {args.rate:g} Hz, {args.sessions} REALTIME sessions over gRPC "
        f"for {args.ticks / args.rate:g} s, {args.rounds} rounds; us of CPU per answered tick, by thread"
    )
    rows: dict[str, list[dict[str, float]]] = {arm: [] for arm in args.arms}
    for r in range(args.rounds):
        for arm in args.arms:
            rows[arm].append(_over_grpc(arm, args, states))
            shown = ", ".join(f"{k} {v:.0f}" for k, v in rows[arm][-1].items() if v >= 1)
            print(f"  round {r + 1} {arm:7} {shown}", flush=True)
    names = sorted({n for runs in rows.values() for run_ in runs for n in run_ if n != "answered %"})
    print(f"\n{'thread (medians)':28}" + "".join(f"{arm:>10}" for arm in args.arms))
    for name in [*names, "answered %"]:
        cells = [statistics.median(run_.get(name, 0.0) for run_ in rows[arm]) for arm in args.arms]
        if max(cells) < 1.0:
            continue  # a thread idle throughout
        print(f"{name:28}" + "".join(f"{c:10.0f}" for c in cells))
    totals = [
        statistics.median(sum(v for k, v in run_.items() if k != "answered %") for run_ in rows[arm])
        for arm in args.arms
    ]
    print(f"{'the process':28}" + "".join(f"{t:10.0f}" for t in totals))


def _path_table(args: argparse.Namespace, states: dict[str, np.ndarray]) -> None:
    with tempfile.TemporaryDirectory(prefix="jitdyn-tick-path-") as tmp:
        folder = Path(tmp)
        np_path = folder / "frames.npz"
        np.savez(np_path, **states)
        measured = ["qpos", "qvel", "ctrl"] if args.scenario == Scenario.CONTROLLED else ["qpos", "qvel"]
        raw = _frames(_Spec(str(np_path), args.ticks, 1.0 / args.rate), measured)  # type: ignore[arg-type]
        frames = [dynamics_pb2.StreamSessionRequest.FromString(b).frame for b in raw]
        samples: dict[str, list[tuple[float, float]]] = {arm: [] for arm in args.arms}
        clock = Clock.REALTIME if args.realtime else Clock.LOCKSTEP
        stats: dict[str, pstats.Stats | None] = {}
        print(
            f"# {args.model} {args.scenario} at {args.rate:g} Hz, {clock}, {args.ticks} frames, {args.rounds} rounds"
        )
        for r in range(args.rounds):
            for arm in args.arms:
                engine, estimator = _ARMS[arm]
                options = _options(args.model, args.scenario, args.rate, estimator, clock)
                data = folder / f"data-{arm}-{r}"
                last = r == args.rounds - 1
                thread, process, stats[arm] = asyncio.run(
                    _feed(arm, engine, options, frames, data, bool(args.profile) and last, args.realtime)
                )
                samples[arm].append((thread, process))
                print(
                    f"  round {r + 1} {arm:7} thread {thread * 1e6:7.0f} us/tick, process {process * 1e6:7.0f}",
                    flush=True,
                )
    print(f"\n{'arm':8} {'thread us/tick':>15} {'process us/tick':>16}")
    for arm, runs in samples.items():
        thread_us = statistics.median(t for t, _ in runs) * 1e6
        print(f"{arm:8} {thread_us:15.0f} {statistics.median(p for _, p in runs) * 1e6:16.0f}")
    for arm, stat in stats.items():
        if stat is not None:
            print(f"\n## {arm}: cProfile, the last session's {args.ticks - args.ticks // 10} ticks (tottime)")
            stat.sort_stats("tottime").print_stats(args.profile)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.tick_path",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--model", default="pendulum_3", help="a built-in research object (default pendulum_3)"
    )
    parser.add_argument("--scenario", default="PASSIVE", choices=[s.value for s in Scenario])
    parser.add_argument("--rate", type=float, default=20.0, help="frames per second, Hz (default 20)")
    parser.add_argument("--ticks", type=int, default=1000, help="frames per session (default 1000)")
    parser.add_argument("--rounds", type=int, default=3, help="sessions of each arm, alternated (default 3)")
    parser.add_argument(
        "--arms",
        nargs="+",
        choices=sorted(_ARMS),
        default=["native", "python", "static"],
        help="native / python: the UKF on that engine; steps: the native engine one call a step "
        "(native_tick off); static: no filter (default: native, python, static)",
    )
    parser.add_argument(
        "--profile",
        type=int,
        metavar="N",
        default=0,
        help="print cProfile's N costliest functions of each arm's last session",
    )
    parser.add_argument(
        "--realtime",
        action="store_true",
        help="REALTIME sessions instead of LOCKSTEP: each frame 1 ms before its tick's time, answered "
        "at once and written (serialised) as the servicer's request loop does",
    )
    parser.add_argument(
        "--grpc", action="store_true", help="whole REALTIME sessions over gRPC, CPU by thread (see above)"
    )
    parser.add_argument("--sessions", type=int, default=8, help="with --grpc: sessions at once (default 8)")
    args = parser.parse_args(argv)
    if args.ticks < 20 or args.rounds < 1 or args.rate <= 0 or args.sessions < 1:
        parser.error(
            f"--ticks must be >= 20, --rounds and --sessions >= 1 and --rate > 0, got {args.ticks}, "
            f"{args.rounds}, {args.sessions}, {args.rate}"
        )
    if args.grpc and (args.profile or args.realtime):
        parser.error("--profile and --realtime are of the tick path; they do not go with --grpc")
    states = trajectory(args.model, args.scenario, args.rate, args.ticks)
    (_grpc_table if args.grpc else _path_table)(args, states)
    return 0


@dataclass
class _Spec:
    """What benchmarks.load._frames reads of a WorkerSpec."""

    frames_path: str
    ticks: int
    dt: float


if __name__ == "__main__":
    sys.exit(main())
