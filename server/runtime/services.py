"""What the servicers share: the registry, the index, the anonymiser, the worker pool, the group
committer of the session logs, the limits, the shared tier of replicas (when there is one).

Built once by server/transport/app.py; `admit` and `release` count open sessions against the limits.
"""

from __future__ import annotations

import secrets
import threading
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from jitdyn.errors import ResourceExhausted
from jitdyn.registry import ModelRegistry
from jitdyn.server.estimation.config import Engine
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.runtime.admission import Admission
from jitdyn.server.runtime.resume import ResumeTokens
from jitdyn.settings import Settings
from jitdyn.storage.anonymise import Anonymiser
from jitdyn.storage.commit import GroupCommitter
from jitdyn.storage.index import SessionIndex
from jitdyn.storage.root import DataRoot
from jitdyn.storage.shared import SharedTier

__all__ = ["DEFAULT_SESSION_LIMITS", "Services", "SessionLimits"]

_DEFAULTS = Settings()


@dataclass(frozen=True)
class SessionLimits:
    """Limits on sessions; each is a setting of `jitdyn serve` (jitdyn.settings), defaults there."""

    # 0: no count limit. REALTIME sessions are admitted by their measured cost against each
    # process's tick budget instead (server/runtime/admission.py), so that one tenant can use the
    # whole machine; these stay for operators who want a quota.
    max_sessions: int = _DEFAULTS.max_sessions
    max_sessions_per_tenant: int = _DEFAULTS.max_sessions_per_tenant
    max_state_dimension: int = _DEFAULTS.max_state_dimension  # nv of a session's model
    tick_budget: float = _DEFAULTS.tick_budget  # of one core, per process


DEFAULT_SESSION_LIMITS = SessionLimits()


@dataclass
class Services:
    registry: ModelRegistry
    index: SessionIndex
    anonymiser: Anonymiser
    pool: WorkerPool
    data_root: Path
    # What computes the JITDYN preset's UKF (--engine): NATIVE, or FAST, its Python reference.
    engine: Engine = Engine.NATIVE
    # A REALTIME session that names no estimator gets the most accurate its model's stored cost
    # fits (server/runtime/choice.py); False (--estimator-choice preset): the preset's.
    choose_by_cost: bool = True
    # Where finished sessions' Parquet is published (storage/root.py); None: the data folder only.
    root: DataRoot | None = None
    limits: SessionLimits = DEFAULT_SESSION_LIMITS
    # One commit thread and one flush to disk per window for every session of this process.
    committer: GroupCommitter = field(default_factory=GroupCommitter)
    admission: Admission = field(default_factory=Admission)
    # Replicas sharing a PostgreSQL index: leases and logs in the shared tier, sessions resumable
    # with a token of `resume_tokens` (keyed from the server secret by app.py; by default from a
    # random one, good in this process only). None: one machine (SQLite, local logs).
    shared: SharedTier | None = None
    resume_tokens: ResumeTokens = field(
        default_factory=lambda: ResumeTokens(secrets.token_bytes(32), ttl=_DEFAULTS.resume_token_ttl)
    )
    resume_timeout: float = _DEFAULTS.resume_timeout
    _open: Counter[str] = field(default_factory=Counter)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def admit(self, tenant: str) -> None:
        """Count a new session, or raise ResourceExhausted naming the limit."""
        with self._lock:
            total = sum(self._open.values())
            if self.limits.max_sessions and total >= self.limits.max_sessions:
                raise ResourceExhausted(
                    f"the server has {total} open sessions, its limit (--max-sessions {self.limits.max_sessions})"
                )
            if (
                self.limits.max_sessions_per_tenant
                and self._open[tenant] >= self.limits.max_sessions_per_tenant
            ):
                raise ResourceExhausted(
                    f"this tenant has {self._open[tenant]} open sessions, the limit per tenant "
                    f"(--max-sessions-per-tenant {self.limits.max_sessions_per_tenant})"
                )
            self._open[tenant] += 1

    def release(self, tenant: str) -> None:
        with self._lock:
            if self._open[tenant] > 0:
                self._open[tenant] -= 1

    @property
    def open_sessions(self) -> int:
        with self._lock:
            return sum(self._open.values())
