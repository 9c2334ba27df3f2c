"""A rehearsal: before a REALTIME session whose fit hangs on what its ticks cost this process is
priced, the process serves such a session alone for a fraction of a second, over real gRPC from a
client thread of its own on a loopback port only it listens on, and measures its CPU per tick:
the transport, the tick, the record, the event loop, what no estimate of the filter sees
(docs/decisions/0214-a-tick-priced-whole.md). The session is then discarded.

    rehearsal = rehearse(Rehearser(address, secret), open_message, dt=0.002)   # blocking, seconds

The rehearsal's stream carries REHEARSAL_KEY in its metadata, with a secret of the process: the
servicer opens it unadmitted and discards it at its end (dynamics_service.DynamicsServicer).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Final

import grpc
import mujoco

from jitdyn.server.runtime.opening import Rehearsal
from jitdyn.v1 import common_pb2, dynamics_pb2, dynamics_pb2_grpc

__all__ = ["REHEARSAL_KEY", "REHEARSAL_SECONDS", "REHEARSAL_TICKS", "Rehearser", "rehearse"]

# A rehearsal runs this many ticks, or this long at a slow rate, whichever is shorter: a few hundred
# ticks of a lone session give its CPU per tick to a few percent, and a rehearsal holds its open.
REHEARSAL_TICKS: Final = 200
REHEARSAL_SECONDS: Final = 0.5  # s
REHEARSAL_KEY: Final = "x-jitdyn-rehearsal"
_TIMEOUT: Final = 30.0  # s: a rehearsal that does not end by then is cancelled
_LEAD: Final = 1e-3  # s a frame is sent ahead of its tick, at most
_WARM_UP: Final = 10  # the first tenth of a rehearsal's ticks warm it up

Request = dynamics_pb2.StreamSessionRequest


@dataclass(frozen=True)
class Rehearser:
    """Where this process rehearses: its own loopback port, and the secret that marks the stream."""

    address: str  # "127.0.0.1:PORT"
    secret: str = field(repr=False)


class _Client:
    """The rehearsal's client: the requests (open, a frame at each tick's time, close) and the CPU
    its threads spent, to take out of the process's."""

    def __init__(self, open_message: dynamics_pb2.OpenSession, model: mujoco.MjModel, *, ticks: int) -> None:
        self._open = open_message
        self._ticks = ticks
        self._qpos = [float(v) for v in model.qpos0]
        self._zeros = {"qvel": [0.0] * model.nv, "qacc": [0.0] * model.nv, "ctrl": [0.0] * model.nu}
        self.opened = threading.Event()
        self.finished = threading.Event()
        self.cpu = 0.0  # s of CPU the request thread spent making and pacing requests
        self.started = math.nan  # monotonic s of the first frame

    def requests(self) -> Iterator[Request]:
        yield Request(open=self._open)
        if not self.opened.wait(_TIMEOUT):
            return
        dt, channels = self._open.dt, _channels(self._open)
        # Each frame leaves a little ahead of its tick: the server's clock started as `opened` left,
        # this one as it arrived, and a frame reaching its tick early is answered as it comes
        # (dynamics_service._EARLY_TOLERANCE). The rehearsal measures the server, not the client's
        # way to it: a tick answered PREDICTED or shed is then the server's doing.
        lead = min(dt / 2, _LEAD)
        self.started = time.monotonic()
        for k in range(self._ticks):
            wait = self.started + k * dt - lead - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            cpu = time.thread_time()
            frame = dynamics_pb2.Frame(seq=k, t=k * dt, qpos=self._qpos)
            for channel in channels:
                getattr(frame, channel).extend(self._zeros[channel])
            self.cpu += time.thread_time() - cpu
            yield Request(frame=frame)
        # The last tick is answered by its deadline, or never (a process that falls behind skips).
        self.finished.wait(dt * (self._ticks // 10 + 2) + 0.5)
        yield Request(close=dynamics_pb2.CloseSession())


def _channels(message: dynamics_pb2.OpenSession) -> list[str]:
    """The frame fields beside qpos that the open says its frames carry (unset: qvel, and ctrl when
    the model is driven by its controls: the server asks for them in CONTROLLED)."""
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


def rehearse(
    rehearser: Rehearser,
    open_message: dynamics_pb2.OpenSession,
    model: mujoco.MjModel,
    *,
    ticks: int | None = None,
) -> Rehearsal | None:
    """Serve `open_message`'s session to a client in this thread for `ticks` ticks (default
    REHEARSAL_TICKS, at most REHEARSAL_SECONDS) at its rate, its frames sent at their ticks' times;
    what this process's CPU per tick was over it, the client's own threads taken out. None when
    the rehearsal did not run (its stream failed). Blocking: run it off the event loop."""
    dt = open_message.dt
    count = ticks or max(1, min(REHEARSAL_TICKS, math.floor(REHEARSAL_SECONDS / dt)))
    client = _Client(open_message, model, ticks=count)
    # The first ticks of a session run cold (its estimator's and MuJoCo's first calls): they are
    # neither timed nor counted, as in a session of thousands of ticks they are not.
    warm = count // _WARM_UP
    results, measured, mark, end = 0, 0, None, None
    with grpc.insecure_channel(rehearser.address) as channel:
        stub = dynamics_pb2_grpc.DynamicsServiceStub(channel)
        try:
            for response in stub.StreamSession(
                client.requests(), metadata=((REHEARSAL_KEY, rehearser.secret),), timeout=_TIMEOUT
            ):
                kind = response.WhichOneof("payload")
                if kind == "opened":
                    client.opened.set()
                elif kind in ("result", "results"):
                    answers = [response.result] if kind == "result" else list(response.results.results)
                    results += len(answers)
                    steady = [a for a in answers if a.seq >= warm]
                    if steady and mark is None:
                        mark = (time.monotonic(), time.process_time(), time.thread_time())
                    measured += sum(
                        a.source == dynamics_pb2.SOURCE_MEASURED and not a.late_compute for a in steady
                    )
                    end = (time.monotonic(), time.process_time(), time.thread_time())
                    if results >= count:
                        client.finished.set()
        except grpc.RpcError:
            return None
        finally:
            client.opened.set()
            client.finished.set()
    if mark is None or end is None or not end[0] > mark[0]:
        return None
    # The process's CPU from the first answer past the warm-up to the last answer, less the client's threads (this one's
    # reading and the request thread's making of frames). gRPC core's threads serve both ends:
    # their client half stays in, on the safe side. Over the ticks' time, whatever was answered:
    # a process that falls behind skips ticks, which would make those it answered look cheap.
    seconds = end[0] - mark[0]
    used = (end[1] - mark[1]) - (end[2] - mark[2]) - client.cpu
    return Rehearsal(
        cost=max(0.0, used) / max(1.0, seconds / dt), ticks=count - warm, seconds=seconds, measured=measured
    )
