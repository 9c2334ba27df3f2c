"""A rehearsal: before a REALTIME session whose fit hangs on what its ticks cost this process is
priced, the process serves such a session alone for a fraction of a second, over real gRPC from a
client process of its own on a loopback port only it listens on, and measures its own CPU per tick
and how many ticks it answered MEASURED on time: the transport, the tick, the record, the event
loop, what no estimate of the filter sees (docs/decisions/0214-a-tick-priced-whole.md). The
session is then discarded.

    marks = Marks(warm=20)                     # the servicer hands them to the rehearsal's stream
    rehearsal = rehearse(rehearser, open_message, model, marks=marks)    # blocking, about a second

The client is a process of its own, as a real client is: in this one it would share the GIL with
the event loop and send its frames late. Its stream carries REHEARSAL_KEY in its metadata, with a
secret of this process: the servicer opens it unadmitted and discards it at its end.
"""

from __future__ import annotations

import base64
import json
import math
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Final

import mujoco

from jitdyn.server.runtime.opening import Rehearsal
from jitdyn.v1 import common_pb2, dynamics_pb2

__all__ = ["REHEARSAL_KEY", "REHEARSAL_SECONDS", "REHEARSAL_TICKS", "Marks", "Rehearser", "rehearse"]

# A rehearsal runs this many ticks, or this long at a slow rate, whichever is shorter: a few hundred
# ticks of a lone session give its CPU per tick to a few percent, and a rehearsal holds its open.
REHEARSAL_TICKS: Final = 200
REHEARSAL_SECONDS: Final = 0.5  # s
REHEARSAL_KEY: Final = "x-jitdyn-rehearsal"
_TIMEOUT: Final = 30.0  # s: a rehearsal that does not end by then is abandoned
# s a frame is sent ahead of its tick, and waits there for it: the server's clock started as
# `opened` left, the client's as it arrived, later by a moment the client does not know (on a loaded
# machine, milliseconds). A tick answered PREDICTED or shed is then the server's doing.
_LEAD: Final = 5e-3
_WARM_UP: Final = 10  # the first tenth of a rehearsal's ticks warm it up: neither timed nor counted

Request = dynamics_pb2.StreamSessionRequest


@dataclass(frozen=True)
class Rehearser:
    """Where this process rehearses: its own loopback port, and the secret that marks the stream."""

    address: str  # "127.0.0.1:PORT"
    secret: str = field(repr=False)


@dataclass
class Marks:
    """The server's side of a rehearsal: this process's clock and CPU at the first tick answered
    past the warm-up and at the last one (`tick`, called by the rehearsal's stream as it answers)."""

    warm: int  # ticks before this one are the warm-up
    first: tuple[float, float] | None = None  # (monotonic s, process CPU s)
    last: tuple[float, float] | None = None

    def tick(self, seq: int) -> None:
        if seq < self.warm:
            return
        self.last = (time.monotonic(), time.process_time())
        if self.first is None:
            self.first = self.last


def ticks_for(dt: float) -> int:
    """How many ticks a rehearsal at `dt` runs."""
    return max(2 * _WARM_UP, min(REHEARSAL_TICKS, math.floor(REHEARSAL_SECONDS / dt)))


def rehearse(
    rehearser: Rehearser, open_message: dynamics_pb2.OpenSession, model: mujoco.MjModel, *, marks: Marks
) -> Rehearsal | None:
    """Run the client of a rehearsal of `open_message`'s session in a process of its own, its
    frames (the model at rest) sent ahead of their ticks; what this process's CPU per tick was
    (from `marks`, which the rehearsal's stream kept) and how many ticks past the warm-up the client
    got MEASURED and on time. None when the rehearsal did not run. Blocking: run it off the event
    loop."""
    count = ticks_for(open_message.dt)
    order = {
        "address": rehearser.address,
        "secret": rehearser.secret,
        "open": base64.b64encode(open_message.SerializeToString()).decode(),
        "qpos": [float(v) for v in model.qpos0],
        "nv": int(model.nv),
        "nu": int(model.nu),
        "ticks": count,
        "warm": marks.warm,
    }
    try:
        child = subprocess.run(
            [sys.executable, "-m", "jitdyn.server.transport.rehearsal"],
            input=json.dumps(order),
            capture_output=True,
            text=True,
            timeout=_TIMEOUT,
            check=False,
        )
        measured = int(json.loads(child.stdout)["measured"])
    except (OSError, subprocess.TimeoutExpired, ValueError, KeyError):
        return None
    if child.returncode != 0 or marks.first is None or marks.last is None:
        return None
    seconds, used = marks.last[0] - marks.first[0], marks.last[1] - marks.first[1]
    if not seconds > 0:
        return None
    # Over the ticks' time, whatever was answered: a process that falls behind skips ticks, which
    # would make those it answered look cheap.
    dt = open_message.dt
    return Rehearsal(
        cost=max(0.0, used) / max(1.0, seconds / dt),
        ticks=count - marks.warm,
        seconds=seconds,
        measured=measured,
    )


def warm_up(dt: float) -> int:
    """Ticks of a rehearsal at `dt` that warm it up."""
    return ticks_for(dt) // _WARM_UP


# ---------------------------------------------------------------------------------------------
# The client, in its own process: python -m jitdyn.server.transport.rehearsal < order.json


def _channels(message: dynamics_pb2.OpenSession) -> list[str]:
    """The frame fields beside qpos that the open's frames carry (unset: qvel, and ctrl in
    CONTROLLED, as the server asks)."""
    names = {
        common_pb2.CHANNEL_QVEL: "qvel",
        common_pb2.CHANNEL_QACC: "qacc",
        common_pb2.CHANNEL_CTRL: "ctrl",
    }
    measured = [names[c] for c in message.measured if c in names]
    if not message.measured:
        measured = ["qvel"]
        if message.scenario == common_pb2.SCENARIO_CONTROLLED:
            measured.append("ctrl")
    return measured


def _requests(
    order: dict[str, object],
    message: dynamics_pb2.OpenSession,
    opened: threading.Event,
    finished: threading.Event,
) -> Iterator[Request]:
    yield Request(open=message)
    if not opened.wait(_TIMEOUT):
        return
    dt, ticks = message.dt, int(order["ticks"])  # type: ignore[call-overload]
    sizes = {"qvel": order["nv"], "qacc": order["nv"], "ctrl": order["nu"]}
    channels = _channels(message)
    started = time.monotonic()
    for k in range(ticks):
        wait = started + k * dt - _LEAD - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        frame = dynamics_pb2.Frame(seq=k, t=k * dt, qpos=order["qpos"])  # type: ignore[arg-type]
        for channel in channels:
            getattr(frame, channel).extend([0.0] * int(sizes[channel]))  # type: ignore[call-overload]
        yield Request(frame=frame)
    # The last tick is answered by its deadline, or never (a process that falls behind skips).
    finished.wait(dt * (ticks // 10 + 2) + _LEAD + 0.5)
    yield Request(close=dynamics_pb2.CloseSession())


def _client() -> int:
    import grpc

    from jitdyn.v1 import dynamics_pb2_grpc

    order = json.loads(sys.stdin.read())
    message = dynamics_pb2.OpenSession.FromString(base64.b64decode(order["open"]))
    ticks, warm = int(order["ticks"]), int(order["warm"])
    opened, finished = threading.Event(), threading.Event()
    results = measured = 0
    with grpc.insecure_channel(order["address"]) as channel:
        stub = dynamics_pb2_grpc.DynamicsServiceStub(channel)
        try:
            for response in stub.StreamSession(
                _requests(order, message, opened, finished),
                metadata=((REHEARSAL_KEY, order["secret"]),),
                timeout=_TIMEOUT,
            ):
                kind = response.WhichOneof("payload")
                if kind == "opened":
                    opened.set()
                elif kind in ("result", "results"):
                    answers = [response.result] if kind == "result" else list(response.results.results)
                    results += len(answers)
                    measured += sum(
                        a.seq >= warm and a.source == dynamics_pb2.SOURCE_MEASURED and not a.late_compute
                        for a in answers
                    )
                    if results >= ticks:
                        finished.set()
        except grpc.RpcError as error:
            print(json.dumps({"error": str(error.code())}))
            return 1
        finally:
            opened.set()
            finished.set()
    print(json.dumps({"measured": measured, "results": results}))
    return 0


if __name__ == "__main__":
    sys.exit(_client())
