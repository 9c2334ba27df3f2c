"""What operators see: a Prometheus endpoint (`jitdyn serve --metrics-address HOST:PORT`).

Every series carries the serving process's index (`process`), so that a process falling behind is
visible on its own. With `--processes N` the children write their values to a shared folder
(prometheus-client's multiprocess mode, PROMETHEUS_MULTIPROC_DIR, set by the parent before they
start) and the parent serves them all from one endpoint.

    jitdyn_open_sessions{process}                          sessions open now
    jitdyn_ticks_total{process,model,source}               results sent (MEASURED, PREDICTED, CORRECTED)
    jitdyn_shed_ticks_total{process,model}                 ticks answered without the estimator (late_compute)
    jitdyn_rejections_total{process,reason}                frames rejected, by reason
    jitdyn_admission_refusals_total{process}               sessions refused by the tick budget
    jitdyn_tick_lateness_seconds{process,model}            deadline to send of ticks answered at their deadline
    jitdyn_tick_compute_seconds{process,model}             estimator and dynamics time per tick
    jitdyn_durable_lag_ticks{process}                      ticks between a result and the newest durable one
    jitdyn_process_load_cores{process}                     the admission's view of the process's load
    jitdyn_loop_lag_seconds{process}                       how late the event loop ran what fell due

With replicas sharing a PostgreSQL index and a data root (deploy/):

    jitdyn_sessions_resumed_total{process}                 resumes taken over here
    jitdyn_sessions_fenced_total{process}                  sessions taken over elsewhere, refused here
    jitdyn_sessions_claimed_total{process}                 sessions nobody resumed, stored here
    jitdyn_commit_errors_total{process}                    commit windows the storage did not take
    jitdyn_files_awaiting_upload{process}                  finished Parquet not yet on the data root
"""

from __future__ import annotations

import os
from typing import Final

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, start_http_server
from prometheus_client import multiprocess as prometheus_multiprocess

from jitdyn.errors import InvalidArgument
from jitdyn.vocabulary import RejectReason

__all__ = ["MULTIPROCESS_ENV", "Metrics", "metrics", "serve_metrics"]

MULTIPROCESS_ENV: Final = "PROMETHEUS_MULTIPROC_DIR"

_LATENESS_BUCKETS: Final = (0.0005, 0.001, 0.002, 0.003, 0.005, 0.01, 0.025, 0.05, 0.1, 0.5, 1.0)
_COMPUTE_BUCKETS: Final = (0.0001, 0.00025, 0.0005, 0.001, 0.002, 0.004, 0.008, 0.016, 0.05, 0.1)
_LAG_BUCKETS: Final = (0, 1, 2, 5, 10, 20, 50, 100, 1000)


class Metrics:
    """The server's metrics, one set per process (prometheus-client registers them globally)."""

    def __init__(self) -> None:
        self.process = "0"
        self.open_sessions = Gauge(
            "jitdyn_open_sessions", "Sessions open now.", ["process"], multiprocess_mode="livesum"
        )
        self.ticks = Counter("jitdyn_ticks", "Results sent, by source.", ["process", "model", "source"])
        self.shed = Counter(
            "jitdyn_shed_ticks", "Ticks answered without the estimator (late_compute).", ["process", "model"]
        )
        self.restarts = Counter(
            "jitdyn_filter_restarts",
            "Ticks whose estimator restarted (a divergence, a wrong model, a resume).",
            ["process", "model"],
        )
        self.rejections = Counter("jitdyn_rejections", "Frames rejected, by reason.", ["process", "reason"])
        self.refusals = Counter(
            "jitdyn_admission_refusals", "Sessions refused by the tick budget.", ["process"]
        )
        self.lateness = Histogram(
            "jitdyn_tick_lateness_seconds",
            "From a tick's deadline to its result's send, for ticks answered at their deadline.",
            ["process", "model"],
            buckets=_LATENESS_BUCKETS,
        )
        self.compute = Histogram(
            "jitdyn_tick_compute_seconds",
            "Estimator and dynamics time per tick.",
            ["process", "model"],
            buckets=_COMPUTE_BUCKETS,
        )
        self.durable_lag = Histogram(
            "jitdyn_durable_lag_ticks",
            "Ticks between a result and the newest durable one when it was sent.",
            ["process"],
            buckets=_LAG_BUCKETS,
        )
        self.loop_lag = Histogram(
            "jitdyn_loop_lag_seconds",
            "How late the event loop ran what fell due (a beat every 5 ms): the lag of every deadline then.",
            ["process"],
            buckets=_LATENESS_BUCKETS,
        )
        self.gc_pause = Histogram(
            "jitdyn_gc_pause_seconds",
            "Garbage collections of the process (the event loop stops for each), by generation.",
            ["process", "generation"],
            buckets=_LATENESS_BUCKETS,
        )
        self.load = Gauge(
            "jitdyn_process_load_cores",
            "The process's load as admission sees it (cores).",
            ["process"],
            multiprocess_mode="livemax",
        )
        self._fleet()

    def _fleet(self) -> None:
        """What replicas sharing a PostgreSQL index and a data root count."""
        self.resumed = Counter(
            "jitdyn_sessions_resumed", "Resumes taken over here: a client's stream moved in.", ["process"]
        )
        self.fenced = Counter(
            "jitdyn_sessions_fenced",
            "Sessions whose writes were refused here because another stream took them over.",
            ["process"],
        )
        self.claimed = Counter(
            "jitdyn_sessions_claimed",
            "Sessions nobody resumed (their replica died), claimed and stored by this one.",
            ["process"],
        )
        self.commit_errors = Counter(
            "jitdyn_commit_errors",
            "Commit windows the storage did not take: a log's write or sync failed, or the shared "
            "index did not answer (its rows are retried).",
            ["process"],
        )
        self.awaiting_upload = Gauge(
            "jitdyn_files_awaiting_upload",
            "Finished sessions' Parquet files in the data folder that the data root does not hold yet.",
            ["process"],
            multiprocess_mode="livemax",  # the processes of one server share one data folder
        )

    def set_process(self, index: int) -> None:
        """This process's index. Its counters of rare events start at 0: rate() needs a sample
        before an increment to see it, so a series born at 1 hides the process's first refusal
        (or rejection of a reason, or collection of a generation) from the dashboard."""
        self.process = str(index)
        self.refusals.labels(self.process)
        for counter in (self.resumed, self.fenced, self.claimed, self.commit_errors):
            counter.labels(self.process)
        self.awaiting_upload.labels(self.process).set(0)
        for reason in RejectReason:
            self.rejections.labels(self.process, reason)
        for generation in ("0", "1", "2"):
            self.gc_pause.labels(self.process, generation)


_metrics: Metrics | None = None


def metrics() -> Metrics:
    """This process's metrics (made at first use, after PROMETHEUS_MULTIPROC_DIR is set)."""
    global _metrics
    if _metrics is None:
        _metrics = Metrics()
    return _metrics


def serve_metrics(address: str) -> str:
    """Serve /metrics on `address` (HOST:PORT) from a daemon thread: this process's metrics, or
    every process's when PROMETHEUS_MULTIPROC_DIR is set. Returns the address served (port 0 asks
    for a free one)."""
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit():
        raise InvalidArgument(f"--metrics-address must be HOST:PORT, got {address!r}")
    registry = None
    if os.environ.get(MULTIPROCESS_ENV):
        registry = CollectorRegistry()
        prometheus_multiprocess.MultiProcessCollector(registry)  # type: ignore[no-untyped-call]
    try:
        if registry is None:
            http, _ = start_http_server(int(port), addr=host.strip("[]"))
        else:
            http, _ = start_http_server(int(port), addr=host.strip("[]"), registry=registry)
    except OSError as exc:
        raise InvalidArgument(f"cannot serve metrics on {address}: {exc.strerror}") from None
    return f"{host}:{http.server_port}"
