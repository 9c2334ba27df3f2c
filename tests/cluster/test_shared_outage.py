"""The shared tier unreachable for a while (the replica's connection to PostgreSQL cut by
stopping a TCP forward between them for 10 s): the open session keeps answering at once, its
durable_seq stands still and catches up when the database answers again, nothing is lost; a new
session, which needs the index, is refused UNAVAILABLE saying why."""

from __future__ import annotations

import time
from collections.abc import Callable

import grpc
import pyarrow.parquet as pq
import pytest
from _cluster import Replica, TcpForward, free_port
from _raw import RawSession, new_model, open_message, session_row

pytestmark = [pytest.mark.postgres, pytest.mark.slow]

OUTAGE = 10.0  # s


def test_a_cut_to_postgresql_delays_durability_not_answers(
    start_replica: Callable[..., Replica], index_url: str
) -> None:
    port = free_port()
    forward = TcpForward(listen=("127.0.0.1", port), target=("127.0.0.1", 5432))
    replica = start_replica(
        "cut", "127.0.0.19", index_url=index_url.replace("127.0.0.1:5432", f"127.0.0.1:{port}")
    )
    session = RawSession(replica.address, open_message(new_model()))
    k = 0
    for k in range(20):
        session.send(k)
    time.sleep(0.2)
    before = session.send(20).durable_seq
    forward.close()
    cut_at = time.monotonic()
    worst, durable_during, k = 0.0, set(), 21
    refused = None
    while time.monotonic() - cut_at < OUTAGE:
        started = time.monotonic()
        result = session.send(k)
        worst = max(worst, time.monotonic() - started)
        durable_during.add(result.durable_seq)
        k += 1
        if refused is None and time.monotonic() - cut_at > 1.0:
            with pytest.raises(grpc.RpcError) as refused_error:
                RawSession(replica.address, open_message(new_model()))
            refused = refused_error.value
        time.sleep(0.02)
    forward = TcpForward(listen=("127.0.0.1", port), target=("127.0.0.1", 5432))
    try:
        answered_during = k - 21
        restored = time.monotonic()
        caught_up = None
        while caught_up is None and time.monotonic() - restored < 15:
            result = session.send(k)
            if result.durable_seq >= k - 1:
                caught_up = time.monotonic() - restored
            k += 1
            time.sleep(0.02)
        session.close()
        row = session_row(index_url, session.opened.session_id)
    finally:
        forward.close()
    print(
        f"during the {OUTAGE:g} s cut: {answered_during} answers, the slowest in {1e3 * worst:.1f} ms, "
        f"durable_seq held at {sorted(durable_during)}; caught up {caught_up} s after; a new open: "
        f"{refused.code().name if refused else None}: {refused.details() if refused else ''}"
    )
    assert worst < 0.1
    assert durable_during <= {before, before + 1}
    assert caught_up is not None
    assert refused is not None and refused.code() == grpc.StatusCode.UNAVAILABLE
    assert row is not None and row["status"] == "COMPLETE"
    table = pq.read_table(replica.data / str(row["location"]), columns=["kind", "seq"])
    seqs = sorted(
        s
        for kind, s in zip(table["kind"].to_pylist(), table["seq"].to_pylist(), strict=True)
        if kind == "result"
    )
    assert seqs == list(range(k))
