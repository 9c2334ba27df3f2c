"""What a late frame's CORRECTED result costs the server when it goes in the due tick's write (one
`results` message, OpenSession.accept_result_batches) against a write of its own, side by side.

    python -m benchmarks.result_batches                    # 8 sessions, frames 2 ticks late, 3 rounds
    python -m benchmarks.result_batches --sessions 16 --late 1 --rounds 5

A `jitdyn serve --processes 1` in its own process; S REALTIME pendulum_2 PASSIVE sessions at 20 Hz
over the raw stubs, every other frame sent `late` ticks (and 5 ms) after its time, the rest on time
(all of them late would read as a clock offset), so that every other tick has a PREDICTED answer at
its deadline and a CORRECTED one when its frame comes. The arms alternate
round by round on the same server; the server's CPU (its process tree, /proc) per answered tick and
the messages a client received per tick are printed, and the ratio of the medians.
"""

from __future__ import annotations

import argparse
import queue
import statistics
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass

import grpc
import numpy as np

from benchmarks.load import cpu_seconds, local_server
from jitdyn.v1 import common_pb2, dynamics_pb2, dynamics_pb2_grpc

DT = 0.05


@dataclass
class _Run:
    ticks: int = 0  # results received (CORRECTED ones included)
    messages: int = 0
    corrected: int = 0
    refused: str = ""


def _session(address: str, *, accept: bool, late: int, ticks: int, run: _Run, lock: threading.Lock) -> None:
    requests: queue.Queue[dynamics_pb2.StreamSessionRequest | None] = queue.Queue()
    with grpc.insecure_channel(address) as channel:
        calls = dynamics_pb2_grpc.DynamicsServiceStub(channel).StreamSession(iter(requests.get, None))
        opening = dynamics_pb2.OpenSession(
            model_name="pendulum_2",
            dt=DT,
            clock=common_pb2.CLOCK_REALTIME,
            scenario=common_pb2.SCENARIO_PASSIVE,
            accept_result_batches=accept,
        )
        requests.put(dynamics_pb2.StreamSessionRequest(open=opening))
        try:
            first = next(calls)
        except grpc.RpcError as error:
            with lock:
                run.refused = error.details() or str(error.code())
            return
        assert first.WhichOneof("payload") == "opened", first
        start = time.monotonic()
        counts = _Run()
        reader = threading.Thread(target=_count, args=(calls, counts))
        reader.start()
        for k in range(ticks):
            time.sleep(max(0.0, start + (k + late * (k % 2)) * DT + 0.005 - time.monotonic()))
            qpos = [0.3 * np.cos(0.2 * k), 0.1 * np.sin(0.3 * k)]
            requests.put(
                dynamics_pb2.StreamSessionRequest(
                    frame=dynamics_pb2.Frame(seq=k, t=k * DT, qpos=qpos, qvel=[0.0, 0.0])
                )
            )
        requests.put(dynamics_pb2.StreamSessionRequest(close=dynamics_pb2.CloseSession()))
        reader.join(timeout=60)
        requests.put(None)
    with lock:
        run.ticks += counts.ticks
        run.messages += counts.messages
        run.corrected += counts.corrected


def _count(calls: object, counts: _Run) -> None:
    for message in calls:  # type: ignore[attr-defined]
        kind = message.WhichOneof("payload")
        results = (
            message.results.results if kind == "results" else [message.result] if kind == "result" else []
        )
        counts.messages += bool(results)
        counts.ticks += len(results)
        counts.corrected += sum(r.source == dynamics_pb2.SOURCE_CORRECTED for r in results)


def _round(
    address: str, pid: int, *, accept: bool, sessions: int, late: int, ticks: int
) -> tuple[float, _Run]:
    run, lock = _Run(), threading.Lock()
    threads = [
        threading.Thread(
            target=_session,
            args=(address,),
            kwargs={"accept": accept, "late": late, "ticks": ticks, "run": run, "lock": lock},
        )
        for _ in range(sessions)
    ]
    cpu = cpu_seconds(pid)
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    used = cpu_seconds(pid) - cpu
    return (1e6 * used / run.ticks if run.ticks else float("nan")), run


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sessions", type=int, default=8, help="REALTIME sessions at once (default 8)")
    parser.add_argument("--late", type=int, default=2, help="ticks every other frame comes late (default 2)")
    parser.add_argument("--ticks", type=int, default=200, help="frames per session (default 200: 10 s)")
    parser.add_argument("--rounds", type=int, default=3, help="rounds of each arm, alternated (default 3)")
    args = parser.parse_args(argv)
    per_tick: dict[bool, list[float]] = {True: [], False: []}
    print(
        f"# {args.sessions} pendulum_2 PASSIVE REALTIME sessions at 20 Hz, every other frame {args.late} ticks late"
    )
    print("round  arm          server us/result  messages/result  results  corrected")
    with local_server(["--processes", "1"]) as (address, pid):
        for r in range(1, args.rounds + 1):
            for accept in (True, False):
                us, run = _round(
                    address, pid, accept=accept, sessions=args.sessions, late=args.late, ticks=args.ticks
                )
                if run.refused:
                    print(f"    {r}  {'batches' if accept else 'one-by-one':<11}  refused: {run.refused}")
                per_tick[accept].append(us)
                share = run.messages / run.ticks if run.ticks else float("nan")
                arm = "batches" if accept else "one-by-one"
                print(f"{r:>5}  {arm:<11}  {us:>16.0f}  {share:>15.2f}  {run.ticks:>7}  {run.corrected:>9}")
    batched, alone = statistics.median(per_tick[True]), statistics.median(per_tick[False])
    print(
        f"median server CPU per result: batches {batched:.0f} us, one-by-one {alone:.0f} us, ratio {batched / alone:.2f}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
