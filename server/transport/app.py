"""The jitdyn server: building it (`create_server`, which tests bind to port 0) and running it
(`serve`, for `jitdyn serve`), as gRPC's own examples split them::

    server, port, services = await create_server(ServerConfig(address="127.0.0.1:0", data_root=tmp))
    await server.start()
    ...
    await shutdown(server, services)
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import ipaddress
import itertools
import logging
import os
import signal
import urllib.parse
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from jitdyn.errors import FailedPrecondition, InvalidArgument
from jitdyn.key_files import SECRET_ENVIRONMENT, check_ca_file, check_private_file, refuse_placeholder
from jitdyn.mujoco_log import route_mujoco_messages
from jitdyn.registry import DEFAULT_LIMITS, ModelRegistry, RegistryLimits
from jitdyn.server.estimation.config import Engine
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.runtime.admission import Admission
from jitdyn.server.runtime.heap import CollectionPauses, freeze_startup_heap, watch_collections
from jitdyn.server.runtime.limits import DEFAULT_STREAM_LIMITS, StreamLimits
from jitdyn.server.runtime.orphans import finish_orphans
from jitdyn.server.runtime.priority import prioritise
from jitdyn.server.runtime.publishing import publish_pending_loop
from jitdyn.server.runtime.resume import ResumeTokens
from jitdyn.server.runtime.services import DEFAULT_SESSION_LIMITS, Services, SessionLimits
from jitdyn.server.runtime.stalls import BEAT, LoopWatch, Stall
from jitdyn.server.runtime.switch_interval import PROCESS_SWITCH_INTERVAL
from jitdyn.server.transport.auth import ApiKeyInterceptor, load_api_keys
from jitdyn.server.transport.dynamics_service import DynamicsServicer
from jitdyn.server.transport.metrics import metrics, serve_metrics
from jitdyn.server.transport.probes import LOOP_HUNG_AFTER, MirroredHealth, Probes
from jitdyn.server.transport.registry_service import ModelRegistryServicer
from jitdyn.server.transport.session_service import SessionServicer
from jitdyn.server.transport.tally import FLUSH_EVERY, HistogramTally
from jitdyn.settings import Settings, default_workers
from jitdyn.storage.anonymise import DEFAULT_ALLOWED_ATTRIBUTES, Anonymiser, load_or_create_secret
from jitdyn.storage.commit import GroupCommitter
from jitdyn.storage.db import default_index_url, open_index
from jitdyn.storage.index import SessionIndex
from jitdyn.storage.layout import prepare_data_root
from jitdyn.storage.parquet import warm_up as warm_up_storage
from jitdyn.storage.recorder import recover_unfinished
from jitdyn.storage.root import DataRoot, open_data_root
from jitdyn.storage.shared import SharedTier, new_owner_id
from jitdyn.v1 import (
    dynamics_pb2,
    dynamics_pb2_grpc,
    model_registry_pb2,
    model_registry_pb2_grpc,
    session_pb2,
    session_pb2_grpc,
)

__all__ = [
    "MAX_MESSAGE_BYTES",
    "SERVICE_NAMES",
    "ServerConfig",
    "create_server",
    "prepare_data",
    "serve",
    "shutdown",
]

_log = logging.getLogger(__name__)

# Large enough for a MyoSuite hand with its meshes in one RegisterModel request.
MAX_MESSAGE_BYTES = 128 * 1024 * 1024

SERVICE_NAMES = (
    model_registry_pb2.DESCRIPTOR.services_by_name["ModelRegistryService"].full_name,
    dynamics_pb2.DESCRIPTOR.services_by_name["DynamicsService"].full_name,
    session_pb2.DESCRIPTOR.services_by_name["SessionService"].full_name,
)


_DEFAULTS = Settings()


@dataclass(frozen=True)
class ServerConfig:
    """Everything `jitdyn serve` can be told; defaults are jitdyn.settings' (the embedded, loopback
    set-up), so that a server made here and one made by `jitdyn serve` agree."""

    address: str = _DEFAULTS.address
    data_root: Path = _DEFAULTS.data
    index_url: str | None = _DEFAULTS.index_url  # None: a SQLite file in the data root
    index_schema: str | None = None  # PostgreSQL schema (tests isolate runs this way)
    # Where finished sessions' Parquet is published (storage/root.py); None: the data folder only.
    data_root_uri: str | None = _DEFAULTS.data_root_uri
    workers: int = field(default_factory=default_workers)
    # What computes the UKF of the JITDYN preset (--engine): NATIVE, or FAST, its Python reference.
    engine: Engine = Engine.NATIVE
    # How a REALTIME session that names no estimator gets one (--estimator-choice): by its model's
    # stored cost, or the preset's.
    choose_by_cost: bool = True
    secret_file: Path | None = None
    allowed_attributes: frozenset[str] = DEFAULT_ALLOWED_ATTRIBUTES
    registry_limits: RegistryLimits = DEFAULT_LIMITS
    session_limits: SessionLimits = DEFAULT_SESSION_LIMITS
    max_message_bytes: int = MAX_MESSAGE_BYTES
    tls_cert: Path | None = None
    tls_key: Path | None = None
    api_keys: Path | None = None  # `KEY TENANT` lines; None: everyone is the default tenant
    insecure: bool = False
    shutdown_grace: float = 5.0
    environ: dict[str, str] = field(default_factory=lambda: dict(os.environ))
    # What happens once per data folder at start (migrations, recovery, built-ins); the children of
    # `jitdyn serve --processes N` leave it to their parent.
    startup_tasks: bool = True
    reuse_port: bool = False  # SO_REUSEPORT: several processes serve one port
    metrics_address: str | None = None  # HOST:PORT of the Prometheus endpoint; None: none
    # HOST:PORT of the kubelet's probes, answered off the event loop (server/transport/probes.py).
    health_address: str | None = None
    # The server runs inside another program (BackgroundServer: the demo, the experiments, tests):
    # the process's CPU is not all its own, so admission counts only its sessions' estimates.
    shares_process: bool = False
    # Per session: history memory, clock offset, idle time, tick cost (server/runtime/limits.py).
    stream_limits: StreamLimits = DEFAULT_STREAM_LIMITS
    # Replicas sharing a PostgreSQL index: leases, resumption, draining (jitdyn.settings).
    lease_ttl: float = _DEFAULTS.lease_ttl
    resume_timeout: float = _DEFAULTS.resume_timeout
    resume_token_ttl: float = _DEFAULTS.resume_token_ttl
    drain_grace: float = _DEFAULTS.drain_grace
    stall_report: float = _DEFAULTS.stall_report  # s without a beat of the loop that is logged; 0: none
    # The serving processes' CPU priority, a nice value (server/runtime/priority.py); None: left as is.
    nice: int | None = None

    @classmethod
    def from_settings(cls, settings: Settings, **overrides: object) -> ServerConfig:
        """The server `settings` describe (jitdyn.settings.resolve); `overrides` replace fields."""
        values: dict[str, object] = {
            "address": settings.address,
            "data_root": settings.data,
            "index_url": settings.index_url,
            "data_root_uri": settings.data_root_uri,
            "workers": settings.workers if settings.workers is not None else default_workers(),
            "engine": Engine.FAST if settings.engine == "python" else Engine.NATIVE,
            "choose_by_cost": settings.estimator_choice == "cost",
            "secret_file": settings.secret_file,
            "tls_cert": settings.tls_cert,
            "tls_key": settings.tls_key,
            "api_keys": settings.api_keys,
            "insecure": settings.insecure,
            "metrics_address": settings.metrics_address,
            "health_address": settings.health_address,
            "lease_ttl": settings.lease_ttl,
            "resume_timeout": settings.resume_timeout,
            "resume_token_ttl": settings.resume_token_ttl,
            "drain_grace": settings.drain_grace,
            "stall_report": settings.stall_report,
            "nice": settings.nice,
            "stream_limits": StreamLimits(
                max_history_bytes=settings.max_history_bytes,
                max_clock_offset=settings.max_clock_offset,
                idle_timeout=settings.idle_timeout,
                max_tick_share=settings.max_tick_share,
                late_timeout=settings.late_timeout,
            ),
            "registry_limits": dataclasses.replace(
                DEFAULT_LIMITS,
                compile_timeout=settings.compile_timeout,
                max_compiled_bytes=settings.max_compiled_bytes,
                compile_memory_bytes=settings.compile_memory_bytes,
                cache_bytes=settings.model_cache_bytes,
                max_models_per_tenant=settings.max_models_per_tenant,
                max_tenant_bytes=settings.max_tenant_bytes,
            ),
            "session_limits": SessionLimits(
                max_sessions=settings.max_sessions,
                max_sessions_per_tenant=settings.max_sessions_per_tenant,
                max_state_dimension=settings.max_state_dimension,
                tick_budget=settings.tick_budget,
            ),
        }
        values.update(overrides)
        return cls(**values)  # type: ignore[arg-type]


def _shared_tier_tasks(server: grpc.aio.Server, services: Services) -> list[asyncio.Task[None]]:
    """The background work of a replica of a shared tier: sessions nobody resumed, sessions not yet
    on the data root, and stepping down when its leases cannot be renewed."""
    tasks = []
    m = metrics()
    if services.shared is not None:
        claimed = m.claimed.labels(m.process)
        tasks.append(
            asyncio.create_task(
                finish_orphans(services, data_root=services.data_root, on_claimed=claimed.inc)
            )
        )
        stepping = step_down_when_lease_lost(server.dynamics, server.health, services)  # type: ignore[attr-defined]
        tasks.append(asyncio.create_task(stepping))
    if services.root is not None:
        waiting = m.awaiting_upload.labels(m.process)
        tasks.append(asyncio.create_task(publish_pending_loop(services, on_waiting=waiting.set)))
    return tasks


async def step_down_when_lease_lost(
    dynamics: DynamicsServicer, health_servicer: health.aio.HealthServicer, services: Services
) -> None:
    """While this replica's leases are past their renew deadline (checked a few times per TTL): the
    session service NOT_SERVING in health (balancers and readiness send no session here, a resume
    goes elsewhere), and its sessions told to move, again each TTL while it lasts. Until cancelled."""
    if services.shared is None:
        return
    ttl = services.shared.lease_ttl
    service = dynamics_pb2.DESCRIPTOR.services_by_name["DynamicsService"].full_name
    stepped_down = False
    while True:
        await asyncio.sleep(ttl / 4)
        lost = services.committer.lease_lost()
        if lost != stepped_down:
            status = (
                health_pb2.HealthCheckResponse.NOT_SERVING if lost else health_pb2.HealthCheckResponse.SERVING
            )
            await health_servicer.set(service, status)
            stepped_down = lost
        if lost:
            told = await dynamics.step_down()
            if told:
                _log.warning("leases not renewed within their deadline: %d session(s) told to move", told)
                await asyncio.sleep(ttl)


def _is_loopback(address: str) -> bool:
    host = address.rsplit(":", 1)[0].strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _refuse_placeholders(config: ServerConfig) -> None:
    """A Secret applied as shipped holds placeholders: refused here, before anything uses them."""
    for name in SECRET_ENVIRONMENT:
        refuse_placeholder(config.environ.get(name, ""), setting=f"environment variable {name}")
    if config.index_url:
        with contextlib.suppress(ValueError):
            password = urllib.parse.urlsplit(config.index_url).password
            refuse_placeholder(password or "", setting="the password of --index")


def _check_ca_files(config: ServerConfig) -> None:
    """The CA files the index URL (libpq's sslrootcert) and the S3 client (AWS_CA_BUNDLE) are to
    check their servers against: there, readable and PEM, or one line saying which is not."""
    if config.index_url:
        query = urllib.parse.parse_qs(urllib.parse.urlsplit(config.index_url).query)
        for path in query.get("sslrootcert", []):
            if path != "system":  # libpq 16+: the system's CAs
                check_ca_file(Path(path), setting="--index sslrootcert")
    bundle = config.environ.get("AWS_CA_BUNDLE")
    if bundle and config.data_root_uri:
        check_ca_file(Path(bundle), setting="environment variable AWS_CA_BUNDLE")


def _check_security(config: ServerConfig) -> None:
    if ":" not in config.address:
        raise InvalidArgument(f"--address must be HOST:PORT, got {config.address!r}")
    if bool(config.tls_cert) != bool(config.tls_key):
        raise InvalidArgument("--tls-cert and --tls-key must be given together")
    if config.tls_key:
        check_private_file(config.tls_key, setting="--tls-key")
    _refuse_placeholders(config)
    _check_ca_files(config)
    if not _is_loopback(config.address) and not config.insecure and not (config.tls_cert and config.api_keys):
        raise InvalidArgument(
            f"--address {config.address} is not a loopback address: serving beyond this machine needs "
            "--tls-cert, --tls-key and --api-keys (or --insecure, on a network you trust)"
        )


def open_root(config: ServerConfig) -> DataRoot | None:
    """The data root of `config`, checked reachable and writable; None without one. Blocking."""
    if config.data_root_uri is None:
        return None
    return open_data_root(config.data_root_uri, environ=config.environ)


def _recover(*, data_root: Path, index: SessionIndex, root: DataRoot | None) -> None:
    recovered = recover_unfinished(data_root=data_root, index=index, root=root)
    if recovered:
        _log.warning(
            "recovered %d unfinished session(s) to Parquet: %s", len(recovered), ", ".join(recovered)
        )


def prepare_data(config: ServerConfig, *, recover_only: bool = False) -> tuple[Path, str]:
    """What happens once per data folder before serving: the folder, the secret checked, the index
    migrated, sessions a dead server left open recovered (only logs no live process holds), the
    built-in models registered. Returns the data root and the index URL. Blocking."""
    _check_security(config)
    if config.api_keys:
        load_api_keys(config.api_keys)  # refuse a bad key file before touching any data
    root = open_root(config)  # a root that cannot be used stops the start before the folder is made
    data_root = prepare_data_root(config.data_root)
    load_or_create_secret(secret_file=config.secret_file, env=config.environ, data_root=data_root)
    url = config.index_url or default_index_url(data_root)
    engine = open_index(url, schema=config.index_schema)
    try:
        index = SessionIndex(engine)
        _recover(data_root=data_root, index=index, root=root)
        if not recover_only:
            with ModelRegistry(engine=engine, data_root=data_root, limits=config.registry_limits) as registry:
                registry.register_builtins()
    finally:
        engine.dispose()
    return data_root, url


def _bind(config: ServerConfig) -> tuple[grpc.aio.Server, int]:
    """A server bound to `config.address`, with nothing served yet: binding comes before anything
    is created on disk, so that a busy port leaves no trace."""
    options = [
        ("grpc.max_receive_message_length", config.max_message_bytes),
        ("grpc.max_send_message_length", config.max_message_bytes),
        ("grpc.so_reuseport", 1 if config.reuse_port else 0),
        # A client that vanishes without closing its connection (a prosthesis losing power) is
        # found by keepalive pings within about a minute, and its session is stored and released.
        ("grpc.keepalive_time_ms", 30_000),
        ("grpc.keepalive_timeout_ms", 10_000),
        ("grpc.keepalive_permit_without_calls", 1),
        ("grpc.http2.min_ping_interval_without_data_ms", 10_000),
    ]
    interceptors = [ApiKeyInterceptor(load_api_keys(config.api_keys))] if config.api_keys else []
    server = grpc.aio.server(options=options, interceptors=interceptors)
    try:
        if config.tls_cert and config.tls_key:
            credentials = grpc.ssl_server_credentials(
                [(config.tls_key.read_bytes(), config.tls_cert.read_bytes())]
            )
            port = server.add_secure_port(config.address, credentials)
        else:
            port = server.add_insecure_port(config.address)
    except RuntimeError:
        # grpc raises RuntimeError("Failed to bind ...") for a busy or foreign address.
        port = 0
    if port == 0:
        raise FailedPrecondition(
            f"cannot listen on {config.address}: the address is in use (another jitdyn serve?) or not an "
            "address of this machine; choose another with --address HOST:PORT (port 0 picks a free one)"
        )
    return server, port


async def create_server(config: ServerConfig) -> tuple[grpc.aio.Server, int, Services]:
    """Build the server and everything it serves with; not started. Returns the bound port.

    Checks what it can before touching the data folder: the address, TLS and key files, and the
    port (bound first)."""
    route_mujoco_messages()
    warm_up_storage()
    _check_security(config)
    if config.api_keys:
        load_api_keys(config.api_keys)  # refuse a bad key file before touching any data
    server, port = _bind(config)
    try:
        services, health_servicer = await _services(config, server)
    except BaseException:
        await server.stop(None)
        raise
    server.health = health_servicer  # type: ignore[attr-defined]
    if not (config.api_keys or config.shares_process):
        # A loopback port of this process alone (not shared by SO_REUSEPORT with its siblings), for
        # the rehearsals of its opens (server/transport/rehearsal.py). With API keys nothing
        # unauthenticated is served; there sessions are priced without rehearsals.
        private = server.add_insecure_port("127.0.0.1:0")
        if private:
            server.dynamics.rehearse_at(f"127.0.0.1:{private}")  # type: ignore[attr-defined]
    return server, port, services


def _registry_servicer(
    registry: ModelRegistry, config: ServerConfig, admission: Admission
) -> ModelRegistryServicer:
    """The registry's servicer, measuring models' estimator costs as this server's opens use them;
    admission starts its window again after each measurement."""
    return ModelRegistryServicer(
        registry,
        engine=config.engine,
        max_tick_share=config.stream_limits.max_tick_share,
        max_state_dimension=config.session_limits.max_state_dimension,
        measured=admission.start_window,
    )


async def _services(config: ServerConfig, server: grpc.aio.Server) -> tuple[Services, MirroredHealth]:
    root = await asyncio.to_thread(open_root, config)
    data_root = await asyncio.to_thread(prepare_data_root, config.data_root)
    secret = load_or_create_secret(secret_file=config.secret_file, env=config.environ, data_root=data_root)
    engine = await asyncio.to_thread(
        open_index, config.index_url or default_index_url(data_root), schema=config.index_schema
    )
    index = SessionIndex(engine)
    if config.startup_tasks:
        await asyncio.to_thread(_recover, data_root=data_root, index=index, root=root)
    registry = ModelRegistry(engine=engine, data_root=data_root, limits=config.registry_limits)
    if config.startup_tasks:
        await asyncio.to_thread(registry.register_builtins)
    # A PostgreSQL index is shared by replicas on other hosts: the session logs go to it, so that
    # what is acknowledged survives this host (docs/decisions/0120-durable-off-the-host.md).
    shared = (
        SharedTier(engine, owner=new_owner_id(), lease_ttl=config.lease_ttl)
        if engine.dialect.name == "postgresql"
        else None
    )
    services = Services(
        shared=shared,
        resume_tokens=ResumeTokens(secret, ttl=config.resume_token_ttl),
        resume_timeout=config.resume_timeout,
        committer=GroupCommitter(shared=shared),
        registry=registry,
        index=index,
        anonymiser=Anonymiser(secret, allowed_attributes=config.allowed_attributes),
        pool=WorkerPool(config.workers),
        engine=config.engine,
        choose_by_cost=config.choose_by_cost,
        data_root=data_root,
        root=root,
        limits=config.session_limits,
        admission=Admission(
            budget=config.session_limits.tick_budget,
            count_process_cpu=not config.shares_process,
            # A server owns its process's GIL switch interval: short while a fast REALTIME session
            # is open, so that gRPC's poller hands frames to the loop in time.
            switch=PROCESS_SWITCH_INTERVAL,
        ),
    )
    model_registry_pb2_grpc.add_ModelRegistryServiceServicer_to_server(
        _registry_servicer(registry, config, services.admission), server
    )
    dynamics_servicer = DynamicsServicer(services, limits=config.stream_limits)
    server.dynamics = dynamics_servicer  # type: ignore[attr-defined]
    dynamics_pb2_grpc.add_DynamicsServiceServicer_to_server(dynamics_servicer, server)
    session_pb2_grpc.add_SessionServiceServicer_to_server(SessionServicer(index), server)
    health_servicer = MirroredHealth()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    for name in ("", *SERVICE_NAMES):
        await health_servicer.set(name, health_pb2.HealthCheckResponse.SERVING)
    reflection.enable_server_reflection(
        (*SERVICE_NAMES, health_pb2.DESCRIPTOR.services_by_name["Health"].full_name, reflection.SERVICE_NAME),
        server,
    )
    return services, health_servicer


async def shutdown(server: grpc.aio.Server, services: Services, *, grace: float = 5.0) -> None:
    """Stop taking RPCs, let open sessions end within `grace` seconds (they are stored either way)."""
    health_servicer = getattr(server, "health", None)
    if health_servicer is not None:
        await health_servicer.enter_graceful_shutdown()
    await server.stop(grace)
    dynamics = getattr(server, "dynamics", None)
    if dynamics is not None:
        await asyncio.to_thread(dynamics.close)
    await asyncio.to_thread(services.committer.close)
    services.pool.close()
    services.registry.close()
    services.index.engine.dispose()


def watch_loop(admission: Admission, *, stall: float) -> LoopWatch:
    """Watch the running loop: its lag goes to admission and to `jitdyn_loop_lag_seconds`, and a
    stall longer than `stall` seconds (0: none) is logged with what the loop was running."""
    lag = HistogramTally(metrics().loop_lag.labels(metrics().process))
    beats = itertools.count(1)
    every = max(1, round(FLUSH_EVERY / BEAT))

    def on_lag(seconds: float) -> None:
        admission.observe_loop_lag(seconds)
        lag.observe(seconds)
        if next(beats) % every == 0:  # the metric once a window, as a session's (tally.py)
            lag.flush()

    def report(stall: Stall) -> None:
        _log.warning("%s", stall.describe())

    watch = LoopWatch(asyncio.get_running_loop(), on_lag=on_lag, stall=stall or None, report=report)
    watch.start()
    return watch


async def observe_collections(pauses: CollectionPauses, every: float = 1.0) -> None:
    """Move the garbage collector's pauses into `jitdyn_gc_pause_seconds`, every `every` seconds,
    from the loop: never from the collector's callback (server/runtime/heap.py says why)."""

    def observe(generation: int, seconds: float) -> None:
        metrics().gc_pause.labels(metrics().process, str(generation)).observe(seconds)

    while True:
        pauses.drain(observe)
        await asyncio.sleep(every)


def start_probes(
    probes: Probes | None, server: grpc.aio.Server, watch: LoopWatch, stopping: asyncio.Event
) -> None:
    """The kubelet's probes, off the loop: alive while the loop beats (and while the server stops:
    a drain is no hang); ready as the sessions' port's health says."""
    if probes is not None:
        probes.start(alive=lambda: stopping.is_set() or watch.silent() < LOOP_HUNG_AFTER)
        server.health.mirror(probes)  # type: ignore[attr-defined]


async def _create_serving(
    config: ServerConfig, *, probes_here: bool
) -> tuple[grpc.aio.Server, int, Services, Probes | None]:
    """create_server, with the probes' port bound first when this process answers them (a busy
    port stops the start before anything is made on disk)."""
    probes = Probes.bind(config.health_address) if config.health_address and probes_here else None
    try:
        server, port, services = await create_server(config)
    except BaseException:
        if probes is not None:
            probes.stop()
        raise
    return server, port, services, probes


def _announce_start(
    config: ServerConfig, services: Services, port: int, announce: Callable[[str], None]
) -> None:
    host = config.address.rsplit(":", 1)[0]
    announce(f"jitdyn listening on {host}:{port} ({'TLS' if config.tls_cert else 'plaintext'})")
    announce(
        f"data in {services.data_root} (index: {config.index_url or default_index_url(services.data_root)})"
    )
    if services.root is not None:
        announce(f"finished sessions go to the data root {services.root.uri}")


async def observe_commits(committer: GroupCommitter, every: float = 1.0) -> None:
    """Move the committer's counts of commit windows the storage did not take and of sessions
    fenced into `jitdyn_commit_errors_total` and `jitdyn_sessions_fenced_total`, every `every`
    seconds, from the loop (the commit thread never touches the metrics)."""
    m = metrics()
    errors, fenced = m.commit_errors.labels(m.process), m.fenced.labels(m.process)
    seen_errors = seen_fenced = 0
    while True:
        await asyncio.sleep(every)
        now = committer.stats()
        errors.inc(now.errors - seen_errors)
        fenced.inc(now.fenced - seen_fenced)
        seen_errors, seen_fenced = now.errors, now.fenced


async def serve(
    config: ServerConfig, *, announce: Callable[[str], None] = print, process_index: int | None = None
) -> None:
    """Run until SIGINT or SIGTERM, then shut down gracefully. `process_index`: this is one of the
    processes of `jitdyn serve --processes N` (server/transport/processes.py), whose parent serves
    the metrics and the probes."""
    metrics().set_process(process_index or 0)
    # The sessions gauge from the start, at 0: a dashboard sees an idle server as idle, not missing.
    metrics().open_sessions.labels(metrics().process).set(0)
    metrics_served = None
    if config.metrics_address and process_index is None:
        metrics_served = serve_metrics(config.metrics_address)
    server, port, services, probes = await _create_serving(config, probes_here=process_index is None)
    await server.start()
    if config.nice is not None:  # once listening: a server that cannot start says only why
        prioritise(config.nice)
    # After its startup the process's heap is frozen: a full collection of it stops the loop
    # for longer than a tick (server/runtime/heap.py).
    freeze_startup_heap()
    gc_pauses = asyncio.create_task(observe_collections(watch_collections()))
    loop_watch = watch_loop(services.admission, stall=config.stall_report)
    stop = asyncio.Event()
    start_probes(probes, server, loop_watch, stop)
    services.admission.start_window()
    _announce_start(config, services, port, announce)
    if metrics_served is not None:
        announce(f"metrics on http://{metrics_served}/metrics")
    if probes is not None:
        announce(f"health probes on {probes.address} (plaintext gRPC health, off the event loop)")
    loop = asyncio.get_running_loop()
    for signum in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(signum, stop.set)
    waiter = asyncio.create_task(server.wait_for_termination())
    stopper = asyncio.create_task(stop.wait())
    commits = asyncio.create_task(observe_commits(services.committer))
    background = [gc_pauses, commits, *_shared_tier_tasks(server, services)]
    await asyncio.wait({waiter, stopper}, return_when=asyncio.FIRST_COMPLETED)
    stop.set()
    loop_watch.stop()
    for task in background:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    if services.shared is not None:
        announce(f"jitdyn draining: open sessions are told to move (grace {config.drain_grace:g} s)")
        await server.health.enter_graceful_shutdown()  # type: ignore[attr-defined]
        left = await server.dynamics.drain(grace=config.drain_grace)  # type: ignore[attr-defined]
        announce(f"jitdyn drained: {left} session(s) had not moved")
    announce("jitdyn shutting down: open sessions are being stored")
    await shutdown(server, services, grace=config.shutdown_grace)
    if probes is not None:
        probes.stop()
    stopper.cancel()
    waiter.cancel()
