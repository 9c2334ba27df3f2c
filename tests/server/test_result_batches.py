"""A REALTIME late frame's CORRECTED result waits for the next tick that is due and goes in the
same write: one message (`StreamSessionResponse.results`) for a client that said at open it reads
batches, the two results one after the other for a client that did not (the contract it had)."""

from __future__ import annotations

import queue
import threading
import time
from typing import Any

import grpc
import numpy as np
import pytest

from jitdyn.client import Client, FrameData, SessionOptions, TickResult
from jitdyn.v1 import common_pb2, dynamics_pb2, dynamics_pb2_grpc

DT = 0.05
LATE = 10  # frame 10 is sent after frame 13, three ticks late
TICKS = 20


def _frame(k: int) -> dynamics_pb2.Frame:
    return dynamics_pb2.Frame(
        seq=k, t=k * DT, qpos=[0.3 * np.cos(0.2 * k), 0.1 * np.sin(0.3 * k)], qvel=[0.0, 0.0]
    )


def _session(address: str, *, accept: bool) -> list[dynamics_pb2.StreamSessionResponse]:
    """Frames 0..TICKS-1 sent at their times (5 ms after), frame LATE after frame LATE + 3; every
    message the server wrote, in order."""
    requests: queue.Queue[dynamics_pb2.StreamSessionRequest | None] = queue.Queue()
    with grpc.insecure_channel(address) as channel:
        stub = dynamics_pb2_grpc.DynamicsServiceStub(channel)
        calls = stub.StreamSession(iter(requests.get, None))
        opening = dynamics_pb2.OpenSession(
            model_name="pendulum_2",
            dt=DT,
            clock=common_pb2.CLOCK_REALTIME,
            scenario=common_pb2.SCENARIO_PASSIVE,
            accept_result_batches=accept,
        )
        requests.put(dynamics_pb2.StreamSessionRequest(open=opening))
        received: list[dynamics_pb2.StreamSessionResponse] = []
        first = next(calls)
        assert first.WhichOneof("payload") == "opened", first
        start = time.monotonic()
        reader = threading.Thread(target=lambda: received.extend(calls))
        reader.start()
        order = [k for k in range(TICKS) if k != LATE]
        order.insert(order.index(LATE + 3) + 1, LATE)
        for k in order:
            at = start + max(k, LATE + 3 if k == LATE else k) * DT + 0.005
            time.sleep(max(0.0, at - time.monotonic()))
            requests.put(dynamics_pb2.StreamSessionRequest(frame=_frame(k)))
        time.sleep(3 * DT)
        requests.put(dynamics_pb2.StreamSessionRequest(close=dynamics_pb2.CloseSession()))
        reader.join(timeout=30)
        requests.put(None)
    return received


def _results(message: dynamics_pb2.StreamSessionResponse) -> list[dynamics_pb2.Result]:
    kind = message.WhichOneof("payload")
    if kind == "results":
        return list(message.results.results)
    return [message.result] if kind == "result" else []


@pytest.mark.parametrize("accept", [True, False], ids=["batches", "one-by-one"])
def test_a_corrected_result_goes_with_the_next_due_tick(server: Any, accept: bool) -> None:
    messages = _session(server.address, accept=accept)
    corrected = [
        (i, r)
        for i, m in enumerate(messages)
        for r in _results(m)
        if r.source == dynamics_pb2.SOURCE_CORRECTED
    ]
    assert [r.seq for _, r in corrected] == [LATE], [(r.seq, r.source) for m in messages for r in _results(m)]
    where, _ = corrected[0]
    batches = [m for m in messages if m.WhichOneof("payload") == "results"]
    if accept:
        # One message: the correction, then the tick that was due when it went.
        held = messages[where]
        assert held.WhichOneof("payload") == "results" and batches == [held]
        seqs = [r.seq for r in held.results.results]
        assert seqs[0] == LATE and len(seqs) >= 2 and all(seq > LATE + 3 for seq in seqs[1:]), seqs
    else:
        # No batch: the correction alone, and the next message is the tick that was due.
        assert not batches
        following = _results(messages[where + 1])
        assert messages[where].WhichOneof("payload") == "result"
        assert following and following[0].seq > LATE + 3, following


def test_the_sdk_reads_batches_as_the_results_they_hold(client: Client) -> None:
    """The SDK accepts batches at open and hands out each result alone: the late frame's CORRECTED
    result among them, every tick answered once before it."""
    options = SessionOptions(model_name="pendulum_2", dt=DT, clock="REALTIME", scenario="PASSIVE")
    answers: list[Any] = []
    with client.open_session(options) as session:
        start = session.now()
        order = [k for k in range(TICKS) if k != LATE]
        order.insert(order.index(LATE + 3) + 1, LATE)
        for k in order:
            time.sleep(max(0.0, max(k, LATE + 3 if k == LATE else k) * DT + 0.005 - (session.now() - start)))
            f = _frame(k)
            session.send(FrameData(seq=k, t=f.t, qpos=list(f.qpos), qvel=list(f.qvel)))
            answers.extend(session.poll())
        time.sleep(3 * DT)
        answers.extend(session.poll())
    results = [a for a in answers if isinstance(a, TickResult)]
    corrected = [r.seq for r in results if r.source == "CORRECTED"]
    assert corrected == [LATE], [(r.seq, r.source) for r in results]
    first_answers = [r.seq for r in results if r.source != "CORRECTED"]
    assert first_answers == sorted(set(first_answers)) and set(range(TICKS)) <= set(first_answers)
