"""A replica on a host of its own (a network namespace, a veth pair, the shared PostgreSQL index
reached across it) answers, and once its link is cut it does not, though the process runs on: new
connections find no route (UNAVAILABLE at once) or silence (DEADLINE_EXCEEDED), and open ones go
quiet, as when a host drops off the network. Later tests cut replicas off this way."""

from __future__ import annotations

import time
from pathlib import Path

import grpc
import pytest
from _cluster import NetnsHost, Replica
from grpc_health.v1 import health_pb2, health_pb2_grpc

pytestmark = pytest.mark.postgres

SESSION_SERVICE = "jitdyn.v1.DynamicsService"


def _health(address: str, *, timeout: float) -> int:
    with grpc.insecure_channel(address) as channel:
        stub = health_pb2_grpc.HealthStub(channel)
        return stub.Check(health_pb2.HealthCheckRequest(service=SESSION_SERVICE), timeout=timeout).status


def test_a_replica_in_its_own_namespace_answers_until_its_link_is_cut(
    netns_host: NetnsHost, index_url: str, tmp_path: Path
) -> None:
    index_across = index_url.replace("127.0.0.1:5432", netns_host.forward(5432))
    # Not a loopback address: jitdyn serve then wants TLS and API keys, or --insecure.
    with Replica.start(
        "cut",
        host=netns_host.peer_ip,
        port=50051,
        data=tmp_path / "cut",
        index_url=index_across,
        prefix=netns_host.prefix,
        extra=["--insecure"],
    ) as replica:
        assert _health(replica.address, timeout=5) == health_pb2.HealthCheckResponse.SERVING

        netns_host.cut()
        started = time.monotonic()
        with pytest.raises(grpc.RpcError) as silent:
            _health(replica.address, timeout=1.0)
        waited = time.monotonic() - started
        print(f"after the cut: {silent.value.code().name} after {waited:.2f} s")
        assert silent.value.code() in (grpc.StatusCode.DEADLINE_EXCEEDED, grpc.StatusCode.UNAVAILABLE)

        netns_host.restore()
        assert _health(replica.address, timeout=5) == health_pb2.HealthCheckResponse.SERVING
