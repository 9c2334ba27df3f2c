"""Must-have 6: a soak of mixed honest and abusive clients against one `jitdyn serve`. RSS, threads
and descriptors stay flat; no frame a client saw acknowledged (durable_seq) is lost.

Slow (30 minutes by default; JITDYN_SOAK_SECONDS sets it); not in the default run:

    JITDYN_SOAK_SECONDS=1800 chrt -i 0 .venv/bin/pytest -q -m slow tests/hostile/test_soak.py -s
"""

from __future__ import annotations

import os
import random
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import grpc
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest
from _hostile import (
    Request,
    Resources,
    Served,
    chain,
    close,
    frame,
    hfield,
    logs,
    open_request,
    register,
    settle,
    stored,
)

from jitdyn.v1 import dynamics_pb2, session_pb2

SECONDS = float(os.environ.get("JITDYN_SOAK_SECONDS", "1800"))
WARM_UP = min(60.0, SECONDS / 5)


@dataclass
class Ledger:
    """What the honest clients saw acknowledged: session id -> highest durable seq."""

    durable: dict[str, int] = field(default_factory=dict)
    sessions: int = 0
    frames: int = 0
    abuses: dict[str, int] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def abused(self, kind: str) -> None:
        with self.lock:
            self.abuses[kind] = self.abuses.get(kind, 0) + 1


def _honest_lockstep(served: Served, ledger: Ledger, rng: random.Random, *, abandon: bool) -> None:
    ticks = rng.randint(20, 200)
    gate = threading.Event()
    cut = rng.randint(5, ticks) if abandon else ticks

    def requests() -> Iterator[Request]:
        yield open_request()
        for k in range(cut):
            yield frame(k)
        if not abandon:
            yield close()
        gate.wait(30)

    call = served.dynamics.StreamSession(requests(), timeout=120)
    session_id = ""
    durable = -1
    answered = 0
    for response in call:
        kind = response.WhichOneof("payload")
        if kind == "opened":
            session_id = response.opened.session_id
        elif kind == "result":
            answered += 1
            if response.result.HasField("durable_seq"):
                durable = max(durable, response.result.durable_seq)
            if abandon and answered == cut:
                call.cancel()
                break
        elif kind == "closed":
            durable = max(durable, cut - 1)  # closed: all of it is stored
            break
    gate.set()
    with ledger.lock:
        ledger.sessions += 1
        ledger.frames += answered
        if durable >= 0:
            ledger.durable[session_id] = durable


def _honest(served: Served, ledger: Ledger, stop: threading.Event, pause: threading.Event, seed: int) -> None:
    rng = random.Random(seed)
    while not stop.is_set():
        if pause.is_set():
            time.sleep(0.1)
            continue
        try:
            _honest_lockstep(served, ledger, rng, abandon=rng.random() < 0.3)
        except grpc.RpcError as error:
            if error.code() == grpc.StatusCode.RESOURCE_EXHAUSTED:
                time.sleep(0.2)  # slots taken by abusers being released: an honest client retries
                continue
            ledger.errors.append(f"honest: {error.code()} {error.details()}")


def _abuse(served: Served, ledger: Ledger, stop: threading.Event, pause: threading.Event, seed: int) -> None:
    rng = random.Random(seed)
    kinds: list[Callable[[], None]] = []

    def held(requests: list[Request], *, cancel_after: float | None) -> None:
        gate = threading.Event()

        def stream() -> Iterator[Request]:
            yield from requests
            gate.wait(30)

        call = served.dynamics.StreamSession(stream(), timeout=30)
        if cancel_after is not None:
            time.sleep(cancel_after)
            call.cancel()
        try:
            for _ in call:
                if cancel_after is not None:
                    break
        except grpc.RpcError:
            pass
        gate.set()

    def cancel_during_open() -> None:
        held([open_request()], cancel_after=rng.random() * 0.005)

    def cancel_after_opened() -> None:
        held([open_request()], cancel_after=0.02)

    def idle() -> None:
        held([open_request(clock=rng.choice(["LOCKSTEP", "REALTIME"]))], cancel_after=None)

    def clock_leap() -> None:
        leap = rng.choice([1e5, -1e5])
        held(
            [
                open_request(clock="REALTIME"),
                Request(sync=dynamics_pb2.SyncPing(id=1, client_send_time=leap)),
                Request(
                    sync=dynamics_pb2.SyncPing(
                        id=2, client_send_time=leap, previous_id=1, previous_receive_time=leap
                    )
                ),
            ],
            cancel_after=None,
        )

    def garbage_frames() -> None:
        requests = [open_request()]
        for _ in range(50):
            seq = rng.choice([0, 1, 2**63, rng.randint(0, 10**6)])
            requests.append(
                Request(frame=dynamics_pb2.Frame(seq=seq, qpos=[float("nan")] * rng.randint(0, 3)))
            )
        requests.append(close())
        held(requests, cancel_after=None)

    def bomb() -> None:
        try:
            register(served, f"bomb{rng.randint(0, 10**9)}", hfield(5000))
        except grpc.RpcError:
            pass

    def heavy_history() -> None:
        held([open_request(model="chain100", dt=0.005, history=10000)], cancel_after=None)

    def second_open() -> None:
        held([open_request(), frame(0), open_request()], cancel_after=None)

    kinds = [
        cancel_during_open,
        cancel_after_opened,
        idle,
        clock_leap,
        garbage_frames,
        bomb,
        heavy_history,
        second_open,
    ]
    weights = [5, 5, 1, 2, 3, 0.3, 1, 2]
    while not stop.is_set():
        if pause.is_set():
            time.sleep(0.1)
            continue
        chosen = rng.choices(kinds, weights)[0]
        try:
            chosen()
        except grpc.RpcError:
            pass
        ledger.abused(chosen.__name__)


@pytest.mark.timeout(SECONDS + 900)
def test_soak_of_honest_and_abusive_clients(serve: Callable[..., Served]) -> None:
    served = serve("--idle-timeout", "3", "--workers", "1")
    register(served, "chain100", chain(100))
    ledger = Ledger()
    stop, pause = threading.Event(), threading.Event()
    threads = [
        threading.Thread(target=_honest, args=(served, ledger, stop, pause, i), daemon=True) for i in range(3)
    ]
    threads += [
        threading.Thread(target=_abuse, args=(served, ledger, stop, pause, 100 + i), daemon=True)
        for i in range(3)
    ]

    def quiet() -> Resources:
        """The server's resources with no session open (clients paused, everything stored)."""
        assert settle(lambda: stored(served, "OPEN") == [] and logs(served) == [], timeout=60)
        time.sleep(2.0)
        return served.resources()

    started = time.monotonic()
    for thread in threads:
        thread.start()
    samples: list[tuple[float, Resources]] = []
    baseline: Resources | None = None
    while time.monotonic() - started < SECONDS:
        time.sleep(min(10.0, SECONDS / 20))
        assert served.alive(), served.text()[-3000:]
        if baseline is None and time.monotonic() - started >= WARM_UP:
            pause.set()
            time.sleep(1.0)
            baseline = quiet()
            print(f"baseline after {WARM_UP:.0f} s of warm-up, no session open: {baseline}", flush=True)
            pause.clear()
        samples.append((time.monotonic() - started, served.resources()))
        print(f"t={samples[-1][0]:7.1f}s {samples[-1][1]}", flush=True)
    stop.set()
    for thread in threads:
        thread.join(120)
    final = quiet()
    assert baseline is not None
    during = [s for t, s in samples if t >= WARM_UP]
    print(
        f"\nsoak {time.monotonic() - started:.0f} s: {ledger.sessions} honest sessions, {ledger.frames} honest "
        f"frames, abuses {sum(ledger.abuses.values())} {ledger.abuses}\n"
        f"no session open, after warm-up -> at the end: RSS {baseline.rss_mb:.1f} -> {final.rss_mb:.1f} MB, "
        f"threads {baseline.threads} -> {final.threads}, fds {baseline.fds} -> {final.fds}, "
        f"data fds {baseline.data_fds} -> {final.data_fds}\n"
        f"under load after warm-up: RSS {min(s.rss_mb for s in during):.1f}..{max(s.rss_mb for s in during):.1f} MB, "
        f"threads {min(s.threads for s in during)}..{max(s.threads for s in during)}, "
        f"fds {min(s.fds for s in during)}..{max(s.fds for s in during)}"
    )
    assert ledger.errors == []
    # Zero acknowledged frames lost: every session's stored Parquet holds each result up to the
    # highest durable_seq its client saw.
    lost = 0
    for session_id, durable in ledger.durable.items():
        session = served.sessions.GetSession(session_pb2.GetSessionRequest(session_id=session_id), timeout=30)
        table = pq.read_table(served.data / session.session.location, columns=["kind", "seq"])
        seqs = set(table.filter(pc.equal(table["kind"], "result"))["seq"].to_pylist())
        lost += len(set(range(durable + 1)) - seqs)
    print(f"acknowledged frames checked in {len(ledger.durable)} sessions; lost: {lost}")
    assert lost == 0
    # Flat: with no session open, memory within 50 MB of where it stood after the warm-up, threads
    # and descriptors back, no log held.
    assert final.rss_mb - baseline.rss_mb < 50
    assert final.threads <= baseline.threads + 4 and final.fds <= baseline.fds + 4
    assert final.data_fds == 0


pytestmark = pytest.mark.slow
