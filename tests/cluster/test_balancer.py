"""Replicas behind one address: sessions opened through HAProxy (deploy/haproxy/haproxy.cfg) or
through gRPC's client-side round_robin spread over the replicas, run to their close with the same
answers a replica gives directly, and a replica killed with -9 is marked down within a second
while new sessions go to the live ones."""

from __future__ import annotations

import json
import time
import uuid
from collections import Counter
from collections.abc import Callable, Sequence
from importlib import resources

import grpc
import numpy as np
import pytest
from _cluster import Balancer, Replica, wait_for

from jitdyn.client import Client, FrameData, Session, SessionOptions, TickResult
from jitdyn.v1 import dynamics_pb2, dynamics_pb2_grpc

pytestmark = pytest.mark.postgres

PENDULUM = (resources.files("jitdyn.models") / "pendulum_2.xml").read_text()


def options() -> SessionOptions:
    """A LOCKSTEP session of the 2-link pendulum, inline, in MJCF of its own (a comment, same
    physics): each session brings content no replica has compiled yet, as a new client's would.
    Models registered through one replica open on the others too (test_registry.py)."""
    return SessionOptions(
        inline_mjcf=f"<!-- {uuid.uuid4()} -->\n{PENDULUM}",
        inline_name="pendulum_2_inline",
        dt=0.05,
        clock="LOCKSTEP",
        outputs=["INVERSE_DYNAMICS"],
    )


TICKS = 20


def frames(ticks: int = TICKS) -> list[FrameData]:
    return [
        FrameData(seq=k, t=k * 0.05, qpos=[0.3 * np.cos(0.2 * k), 0.1 * np.sin(0.3 * k)], qvel=[0.0, 0.0])
        for k in range(ticks)
    ]


def run(session: Session) -> list[TickResult]:
    """Every frame in LOCKSTEP, each answered before the next goes."""
    results = []
    for frame in frames():
        answer = session.send_frame(frame)
        assert isinstance(answer, TickResult), answer
        results.append(answer)
    return results


def replica_of(session_id: str, replicas: Sequence[Replica]) -> str:
    """The replica whose own data folder holds the session's Parquet."""
    holders = [r.name for r in replicas if any(session_id in str(p) for p in r.stored_sessions())]
    assert len(holders) == 1, (session_id, holders)
    return holders[0]


def test_sessions_through_haproxy_spread_over_the_replicas_and_run_to_their_close(
    balancer: Balancer, replicas: list[Replica]
) -> None:
    with Client(replicas[0].address) as direct, direct.open_session(options()) as session:
        reference = run(session)

    with Client(balancer.address) as client:
        sessions = [client.open_session(options()) for _ in range(2 * len(replicas))]
        open_now = {r.name: r.metrics()["jitdyn_open_sessions"] for r in replicas}
        answers = [run(session) for session in sessions]
        summaries = [session.close() for session in sessions]

    where = Counter(replica_of(s.opened.session_id, replicas) for s in sessions)
    print(f"open sessions per replica while open: {open_now}; stored per replica: {dict(where)}")
    assert open_now == {r.name: 2.0 for r in replicas}
    assert where == {r.name: 2 for r in replicas}
    for results, summary in zip(answers, summaries, strict=True):
        assert summary.frames == TICKS and summary.measured == TICKS
        assert [r.seq for r in results] == list(range(TICKS))
        # The balancer carries bytes, nothing else: the same frames, the same forces, to the bit.
        for through, alone in zip(results, reference, strict=True):
            assert through.source == alone.source == "MEASURED"
            np.testing.assert_array_equal(through.qfrc_inverse, alone.qfrc_inverse)
            assert through.qfrc_inverse.shape == (2,) and np.all(np.isfinite(through.qfrc_inverse))


def _raw_session(stub: dynamics_pb2_grpc.DynamicsServiceStub) -> tuple[str, int]:
    """One LOCKSTEP session over the generated stub, pipelined: open, frames, close."""
    requests = [dynamics_pb2.StreamSessionRequest(open=options().to_message())]
    requests += [dynamics_pb2.StreamSessionRequest(frame=f.to_message()) for f in frames()]
    requests.append(dynamics_pb2.StreamSessionRequest(close=dynamics_pb2.CloseSession()))
    responses = list(stub.StreamSession(iter(requests), timeout=60))
    kinds = Counter(r.WhichOneof("payload") for r in responses)
    assert kinds == {"opened": 1, "result": TICKS, "closed": 1}, kinds
    return responses[0].opened.session_id, kinds["result"]


def test_client_side_round_robin_over_the_replicas_addresses_spreads_sessions(
    replicas: list[Replica],
) -> None:
    # The Kubernetes headless-service pattern: one name, every replica's address, round_robin in
    # the client. The SDK's Client takes a target but not channel options, so a raw channel here.
    target = "ipv4:" + ",".join(r.address for r in replicas)
    config = json.dumps({"loadBalancingConfig": [{"round_robin": {}}]})
    with grpc.insecure_channel(target, options=[("grpc.service_config", config)]) as channel:
        grpc.channel_ready_future(channel).result(timeout=10)
        stub = dynamics_pb2_grpc.DynamicsServiceStub(channel)
        ids = [_raw_session(stub)[0] for _ in range(2 * len(replicas))]
    where = Counter(replica_of(session_id, replicas) for session_id in ids)
    print(f"client-side round_robin, stored per replica: {dict(where)}")
    assert set(where) == {r.name for r in replicas}


def test_a_killed_replica_is_down_within_a_second_and_new_sessions_go_to_the_live_one(
    replicas: list[Replica],
    spare_replica: Replica,
    start_balancer: Callable[[Sequence[Replica]], Balancer],
) -> None:
    live, doomed = replicas[0], spare_replica
    balancer = start_balancer([live, doomed])
    with Client(balancer.address) as client:
        # Round robin puts one of two sessions on each replica; the doomed one's gauge says which.
        first = client.open_session(options())
        first_on_doomed = doomed.metrics().get("jitdyn_open_sessions", 0.0) == 1
        second = client.open_session(options())
        on_doomed, on_live = (first, second) if first_on_doomed else (second, first)
        on_doomed.send_frame(frames()[0])

        doomed.kill()
        killed_at = time.monotonic()
        wait_for(lambda: balancer.server_states()[doomed.name].startswith("DOWN"), timeout=5, what="not DOWN")
        down_after = time.monotonic() - killed_at

        # The doomed replica's session resumes on the live one by itself (the SDK's resumption):
        # its next frame is answered there, with no error.
        answer = on_doomed.send_frame(frames()[1])
        assert answer.seq == 1 and len(on_doomed.resumptions) == 1, (answer, on_doomed.resumptions)
        resumed = on_doomed.resumptions[0]
        on_doomed.cancel()
        assert len(run(on_live)) == TICKS
        on_live.close()

        after = [client.open_session(options()) for _ in range(4)]
        for session in after:
            assert len(run(session)) == TICKS
            session.close()
    print(
        f"{doomed.name} marked DOWN {down_after * 1000:.0f} ms after kill -9; its open session resumed "
        f"on the live replica: {resumed}"
    )
    assert down_after < 1.0
    assert {replica_of(s.opened.session_id, [live, doomed]) for s in after} == {live.name}


def test_a_refused_open_through_haproxy_says_what_the_reset_hides_and_the_replica_logs_why(
    start_replica: Callable[..., Replica], start_balancer: Callable[..., Balancer]
) -> None:
    """HAProxy 2.6 (Debian 12) resets a stream the server refused while the client still writes
    (RST_STREAM(CANCEL) after the status, haproxy/haproxy#1219): the client loses the status. The
    SDK then says what the reset likely hides, and the replica's log has the reason. A balancer
    that passes the status on (HAProxy 3.2, nginx) gives the status itself."""
    from jitdyn.errors import JitdynError, NotFound

    replica = start_replica("refuses", "127.0.0.26", extra=["--verbose"])
    balancer = start_balancer([replica])
    with Client(replica.address, timeout=30) as client, pytest.raises(NotFound, match="no_such_model"):
        client.open_session(SessionOptions(model_name="no_such_model", dt=0.05))
    with Client(balancer.address, timeout=30) as client, pytest.raises(JitdynError) as through:
        client.open_session(SessionOptions(model_name="no_such_model", dt=0.05))
    print(f"through HAProxy: {type(through.value).__name__}: {through.value}")
    if not isinstance(through.value, NotFound):
        assert through.value.code == grpc.StatusCode.CANCELLED
        assert "a refusal whose reason the balancer dropped" in str(through.value)
    wait_for(
        lambda: (
            replica.log.read_text().count("an open was refused: NOT_FOUND: no model is named 'no_such_model'")
            == 2
        ),
        timeout=5,
        what="the replica did not log both refusals",
    )
