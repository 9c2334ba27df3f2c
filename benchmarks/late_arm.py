"""Late frames of a small model: a 2-link arm (nv 2, actuated, so DRIVEN when no scenario is
named) at 50 Hz REALTIME, whose frames now and then come 4 ticks late. How many of them a real
`jitdyn serve` CORRECTS, and why it refuses the others, on each engine, run by run alternated.

    python -m benchmarks.late_arm                        # 3 rounds, both engines, DRIVEN
    python -m benchmarks.late_arm --scenario PASSIVE --rounds 5
    python -m benchmarks.late_arm --beside 20            # with 20 pendulum_3 sessions on the server
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import sys
import threading
import time
from collections.abc import Iterator, Sequence

import mujoco
import numpy as np

from benchmarks.load import local_server, run
from jitdyn.client import Client, FrameData, Rejection, SessionOptions, TickResult
from jitdyn.settings import ENGINES

ARM = """
<mujoco model="arm2">
  <option timestep="0.005"/>
  <worldbody>
    <body name="upper">
      <joint name="shoulder" type="hinge" axis="0 1 0" damping="0.1"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="2"/>
      <body name="fore" pos="0.3 0 0">
        <joint name="elbow" type="hinge" axis="0 1 0" damping="0.1"/>
        <geom type="capsule" fromto="0 0 0 0.25 0 0" size="0.025" mass="1.2"/>
      </body>
    </body>
  </worldbody>
  <actuator><motor joint="shoulder"/><motor joint="elbow"/></actuator>
</mujoco>
"""
DT = 0.02  # 50 Hz
TICKS = 150
LATE = set(range(20, TICKS - 10, 15))  # these frames come 4 ticks (and 5 ms) after their time


def truth() -> list[tuple[np.ndarray, np.ndarray]]:
    model = mujoco.MjModel.from_xml_string(ARM)
    data = mujoco.MjData(model)
    data.qpos[:] = [0.5, -0.3]
    states = []
    for k in range(TICKS):
        states.append((data.qpos.copy(), data.qvel.copy()))
        data.ctrl[:] = [0.8 * np.sin(0.1 * k), 0.4 * np.cos(0.13 * k)]
        mujoco.mj_step(model, data, round(DT / model.opt.timestep))
    return states


@contextlib.contextmanager
def beside(address: str, sessions: int) -> Iterator[None]:
    """`sessions` pendulum_3 PASSIVE REALTIME sessions at 20 Hz from the load generator's client
    processes, on the server at `address`, for the arm session's time (none for 0)."""
    if sessions == 0:
        yield
        return
    seconds = TICKS * DT + 8.0  # the generator's own start-up, then the arm's session inside it
    reports = []

    def generate(**kwargs: object) -> None:
        reports.append(run(**kwargs))  # type: ignore[arg-type]

    thread = threading.Thread(
        target=generate,
        kwargs={
            "model": "pendulum_3",
            "scenario": "PASSIVE",
            "rate": 20.0,
            "sessions": sessions,
            "seconds": seconds,
            "clients": 2,
            "server": address,
            "ukf_us": 0.0,
            "floor": False,
        },
        daemon=True,
    )
    thread.start()
    time.sleep(5.0)  # the generator's processes start and open their sessions
    try:
        yield
    finally:
        thread.join(timeout=seconds + 60)
        for report in reports:  # how many of them the server admitted, and how they were answered
            print(f"   beside: {report.line().strip()}", flush=True)


def one_session(engine: str, scenario: str | None, others: int = 0) -> tuple[int, list[str], float]:
    """(late frames CORRECTED, the refusals' messages, median compute us of the on-time answers),
    with `others` pendulum_3 sessions beside it."""
    with (
        local_server(("--engine", engine)) as (address, _),
        beside(address, others),
        Client(address, timeout=30) as client,
    ):
        client.register_model(name="arm2", mjcf=ARM)
        options = SessionOptions(model_name="arm2", dt=DT, clock="REALTIME", scenario=scenario or "")
        with client.open_session(options) as session:
            for _ in range(3):
                session.sync()
                time.sleep(0.005)
            timers = []
            for k, (q, v) in enumerate(truth()):
                time.sleep(max(0.0, k * DT - session.now()))
                frame = FrameData(seq=k, t=k * DT, qpos=q, qvel=v)
                if k in LATE:
                    timer = threading.Timer(4 * DT + 0.005, session.send, args=(frame,))
                    timer.start()
                    timers.append(timer)
                else:
                    session.send(frame)
            for timer in timers:
                timer.join()
            time.sleep(0.2)
            answers = session.poll()
            session.close()
    results = [a for a in answers if isinstance(a, TickResult)]
    corrected = {a.seq for a in results if a.source == "CORRECTED"} & LATE
    # Why the late frames were refused (a frame late for other reasons, the first at start-up, is
    # not one of them).
    refused = [a.message for a in answers if isinstance(a, Rejection) and a.seq in LATE]
    compute = statistics.median(a.compute_us for a in results if a.source == "MEASURED")
    return len(corrected), refused, compute


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--rounds", type=int, default=3, help="sessions per engine, alternated (default 3)")
    parser.add_argument("--engines", nargs="+", choices=ENGINES, default=list(ENGINES))
    parser.add_argument(
        "--beside",
        type=int,
        default=0,
        metavar="N",
        help="N pendulum_3 REALTIME sessions at 20 Hz on the same server meanwhile (default 0)",
    )
    parser.add_argument(
        "--scenario",
        choices=("PASSIVE", "DRIVEN"),
        help="default: none named (DRIVEN, the model is actuated)",
    )
    args = parser.parse_args(argv)
    if args.rounds < 1 or args.beside < 0:
        parser.error(f"--rounds must be >= 1 and --beside >= 0, got {args.rounds} and {args.beside}")
    print(f"{'round':>5} {'engine':>7} {'corrected':>10} {'compute us':>10}  first refusal")
    for round_ in range(1, args.rounds + 1):
        for engine in args.engines:
            corrected, refused, compute = one_session(engine, args.scenario, args.beside)
            first = refused[0] if refused else ""
            print(
                f"{round_:5d} {engine:>7} {corrected:4d} of {len(LATE):<3d} {compute:10.0f}  {first}",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
