"""What late frames cost a REALTIME session: replaying every tick since a late frame's (the timewarp
alone) against waiting for frames that come late (server/runtime/session.py, decision 0007).

The network is emulated in virtual time, as `jitdyn demo` emulates it (latency, jitter, loss,
seeded): frame k reaches the server at k dt + latency + jitter, or never; tick k is answered at its
deadline k dt + grace with what has come. Both runtimes see the same arrivals, in the same order,
on the same worker pool, interleaved session by session so that a slow moment on a shared machine
hits both. Printed per case and mode:

    cpu/tick       thread CPU per tick of the runtime (answers and late frames), median of rounds
    runs/late      ticks of the filter a late frame costs (the timewarp's replay, or the wait's one)
    fit            late frames whose cost fits decision 0001's budget (half a tick, less the tick's
                   own measured cost and `--overhead` for the transport)
    q err          median |q| error of the PREDICTED answers against the truth (rad)

    python -m benchmarks.late_frames                  # biped 100 Hz and pendulum_3 20 Hz, ~1 min
    python -m benchmarks.late_frames --rounds 1 --ticks 300
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import dataclass, field

import mujoco
import numpy as np

from benchmarks.ukf_cycle import CASES, Case, ground_truth, load
from jitdyn.server.estimation.config import resolve_config
from jitdyn.server.estimation.dynamics import Dynamics
from jitdyn.server.estimation.factory import make_estimator
from jitdyn.server.estimation.interface import Measurement
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.runtime.frames import FrameIn
from jitdyn.server.runtime.session import SessionRuntime
from jitdyn.vocabulary import Source


@dataclass(frozen=True)
class Network:
    latency: float
    jitter: float
    loss: float


# (case, dt, network): the biped demo of the README, and a pendulum at 20 Hz two to three ticks late.
SETUPS = [
    ("biped controlled", 0.01, Network(0.020, 0.005, 0.02)),
    ("pendulum_3 passive", 0.05, Network(0.110, 0.020, 0.02)),
]


@dataclass
class Tally:
    cpu: list[float] = field(default_factory=list)  # per round, s per tick
    runs: list[int] = field(default_factory=list)
    fit: int = 0
    late: int = 0
    errors: list[float] = field(default_factory=list)


def _arrivals(ticks: int, dt: float, network: Network, seed: int) -> list[tuple[float, int]]:
    rng = np.random.default_rng(seed)
    out = []
    for k in range(ticks):
        if rng.random() < network.loss:
            continue
        out.append((k * dt + network.latency + rng.uniform(-network.jitter, network.jitter), k))
    return sorted(out)


def _frame(seq: int, dt: float, m: Measurement, arrived: float) -> FrameIn:
    return FrameIn(
        seq=seq,
        t=seq * dt,
        qpos=m.qpos,
        qvel=m.qvel,
        qacc=None,
        ctrl=m.ctrl,
        sensordata=None,
        received=arrived,
    )


def _session(case: Case, model: mujoco.MjModel, dt: float, pool: WorkerPool, *, wait: bool) -> SessionRuntime:
    config = resolve_config(
        model=model, scenario=case.scenario, dt=dt, requested={}, model_defaults={}, measured={"qpos", "qvel"}
    )
    return SessionRuntime(
        model=model,
        estimator=make_estimator(model, config, pool=pool),
        dynamics=Dynamics(model, outputs=frozenset({"INVERSE_DYNAMICS"})),
        dt=dt,
        scenario=case.scenario,
        history=50,
        wait_for_late=wait,
    )


def _run(
    runtime: SessionRuntime,
    truth: list[Measurement],
    arrivals: list[tuple[float, int]],
    dt: float,
    tally: Tally,
    overhead: float,
) -> None:
    """One session through the arrivals; its CPU, the late frames' costs and the answers' errors."""
    grace = dt / 2
    held: dict[int, FrameIn] = {}
    queue = list(arrivals)
    cpu = 0.0
    tick_cost = 0.0
    for seq in range(len(truth)):
        due = seq * dt + grace
        while queue and queue[0][0] <= due:
            arrived, k = queue.pop(0)
            frame = _frame(k, dt, truth[k], arrived)
            if k >= runtime.next_tick:
                held[k] = frame
                continue
            runs = runtime.late_cost(k)
            tally.runs.append(runs)
            tally.late += 1
            tally.fit += runs * tick_cost <= max(0.0, dt / 2 - tick_cost - overhead)
            started = time.thread_time()
            runtime.apply_late(frame)
            cpu += time.thread_time() - started
        started = time.thread_time()
        outcome = runtime.advance(held.pop(seq, None))
        spent = time.thread_time() - started
        cpu += spent
        tick_cost += 0.05 * (spent - tick_cost)
        if outcome.source == Source.PREDICTED and outcome.estimate is not None:
            tally.errors.append(float(np.max(np.abs(outcome.qpos - truth[seq].qpos))))
    tally.cpu.append(cpu / len(truth))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--rounds", type=int, default=3, help="sessions per mode and case (default 3)")
    parser.add_argument("--ticks", type=int, default=600, help="ticks per session (default 600)")
    parser.add_argument(
        "--overhead", type=float, default=1e-3, help="transport CPU per tick for the budget, s (default 1e-3)"
    )
    args = parser.parse_args(argv)
    cases = {case.name: case for case in CASES}
    print(f"{'case':34s} {'mode':7s} {'cpu/tick':>9s} {'runs/late':>9s} {'fit':>6s} {'q err':>9s}")
    with WorkerPool(1) as pool:
        for name, dt, network in SETUPS:
            case = cases[name]
            model, _ = load(case.model)
            truth = ground_truth(model, case, round(dt / model.opt.timestep), args.ticks)
            tallies = {"replay": Tally(), "wait": Tally()}
            for r in range(args.rounds):
                arrivals = _arrivals(args.ticks, dt, network, seed=r)
                for mode, tally in tallies.items():
                    runtime = _session(case, model, dt, pool, wait=mode == "wait")
                    _run(runtime, truth, arrivals, dt, tally, args.overhead)
            label = f"{name} {1 / dt:g} Hz, {network.latency * 1e3:g}+-{network.jitter * 1e3:g} ms"
            for mode, tally in tallies.items():
                print(
                    f"{label:34s} {mode:7s} {1e6 * statistics.median(tally.cpu):7.0f}us "
                    f"{statistics.mean(tally.runs):9.2f} {tally.fit / max(1, tally.late):6.1%} "
                    f"{statistics.median(tally.errors):9.2e}"
                )
            replay, wait = (statistics.median(tallies[m].cpu) for m in ("replay", "wait"))
            print(f"{label:34s} wait/replay cpu per tick {wait / replay:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
