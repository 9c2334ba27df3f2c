"""The kubelet's probes, answered off the tick loop: a plaintext gRPC health server of its own
(`jitdyn serve --health-address HOST:PORT`) on two threads of its own, so that an event loop busy
with ticks never fails liveness. A liveness probe answered on the loop (as it was, on the sessions'
port with a 1 s timeout) gets a loaded pod restarted, and its sessions then land on the other
replicas, which fall behind in turn. Why, and what else was weighed: docs/decisions/0165.

    probes = Probes.bind("0.0.0.0:8081")     # before anything else: a busy port stops the start
    ...
    probes.start(alive=lambda: watch.silent() < LOOP_HUNG_AFTER)
    health.mirror(probes)                    # the sessions' port's health (MirroredHealth), for readiness
    ...
    probes.stop()

- Liveness, service "" (the kubelet's `grpc:` probe without a service): SERVING while `alive()`
  says so: in `jitdyn serve`, while the event loop has run within LOOP_HUNG_AFTER. A loop silent
  that long is hung (a deadlock, a call that never returns), not busy: a tick costs milliseconds.
- Readiness, each service's own name (the session service, jitdyn.v1.DynamicsService): what the
  sessions' port says of it, copied here whenever it changes (NOT_SERVING while the replica drains
  or has stepped down, decision 0163). A loop too busy to change it changes nothing, and admission
  (RESOURCE_EXHAUSTED) is what sheds new sessions off a loaded replica, not its probes.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent import futures
from typing import Any, Final

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc

from jitdyn.errors import FailedPrecondition

__all__ = ["LIVENESS", "LOOP_HUNG_AFTER", "MirroredHealth", "Probes"]

# s without a beat of the event loop after which liveness fails: a tick costs milliseconds and a
# loaded loop beats late by as much; one silent this long is hung, not busy.
LOOP_HUNG_AFTER: Final = 30.0
LIVENESS: Final = ""  # the service name a probe without one asks for
_SERVING: Final = health_pb2.HealthCheckResponse.SERVING
_NOT_SERVING: Final = health_pb2.HealthCheckResponse.NOT_SERVING


class _ProbeHealth(health.HealthServicer):
    """grpc.health.v1 whose service "" is `alive()`, asked at each check; the others as set."""

    def __init__(self) -> None:
        super().__init__()
        self.alive: Callable[[], bool] = lambda: False

    def Check(self, request: health_pb2.HealthCheckRequest, context: Any) -> health_pb2.HealthCheckResponse:
        if request.service == LIVENESS:
            return health_pb2.HealthCheckResponse(status=_SERVING if self.alive() else _NOT_SERVING)
        return super().Check(request, context)


class Probes:
    """The probes' server: bound by `bind`, answering from `start`; `address` is where it listens
    (port 0 picks a free one)."""

    def __init__(self, server: grpc.Server, servicer: _ProbeHealth, address: str) -> None:
        self._server = server
        self._servicer = servicer
        self.address = address

    @classmethod
    def bind(cls, address: str) -> Probes:
        """Bound to `address` (plaintext: the kubelet's probes speak no TLS), answering nothing until
        `start`. FailedPrecondition, in one line, when the address cannot be bound."""
        servicer = _ProbeHealth()
        server = grpc.server(
            futures.ThreadPoolExecutor(max_workers=2, thread_name_prefix="jitdyn-probes"),
            # Not SO_REUSEPORT (grpc's default): a second server on the port is an error, not a sharer.
            options=[("grpc.so_reuseport", 0)],
        )
        health_pb2_grpc.add_HealthServicer_to_server(servicer, server)
        try:
            port = server.add_insecure_port(address)
        except RuntimeError:
            port = 0
        if port == 0:
            raise FailedPrecondition(
                f"cannot serve health probes on {address}: the address is in use or not an address of "
                "this machine; choose another with --health-address HOST:PORT"
            )
        return cls(server, servicer, f"{address.rsplit(':', 1)[0]}:{port}")

    def start(self, *, alive: Callable[[], bool]) -> None:
        """Answer from now on: liveness by `alive()`, asked at each check."""
        self._servicer.alive = alive
        self._server.start()

    def set(self, service: str, status: int) -> None:
        """The readiness of `service`, a HealthCheckResponse.ServingStatus (never liveness: that is
        `alive()`'s)."""
        if service != LIVENESS:
            self._servicer.set(service, status)

    def stop(self) -> None:
        self._server.stop(None)


class MirroredHealth(health.aio.HealthServicer):
    """The sessions' port's health (asyncio), each change copied to `probes` once there are any."""

    def __init__(self) -> None:
        super().__init__()
        self.probes: Probes | None = None
        self._statuses: dict[str, int] = {}
        self._shutting_down = False

    def mirror(self, probes: Probes) -> None:
        """Copy every status set so far to `probes`, and every later change."""
        self.probes = probes
        for service, status in self._statuses.items():
            probes.set(service, status)

    async def set(self, service: str, status: int) -> None:
        await super().set(service, status)
        if self._shutting_down:
            return  # the base class ignores it too
        self._statuses[service] = status
        if self.probes is not None:
            self.probes.set(service, status)

    async def enter_graceful_shutdown(self) -> None:
        await super().enter_graceful_shutdown()
        self._shutting_down = True
        for service in self._statuses:
            self._statuses[service] = _NOT_SERVING
            if self.probes is not None:
                self.probes.set(service, _NOT_SERVING)
