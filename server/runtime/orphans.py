"""Sessions nobody resumed: every replica sharing the index looks for them, and the first to find
one takes it over (a new epoch, so its old holder is fenced) and stores it from the shared log.

    task = asyncio.create_task(finish_orphans(services, data_root=services.data_root))
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path

from jitdyn.server.runtime.services import Services
from jitdyn.storage.failures import STORAGE_ERRORS
from jitdyn.storage.recorder import finish_orphan

__all__ = ["finish_orphans", "finish_orphans_once"]

_log = logging.getLogger(__name__)


def finish_orphans_once(services: Services, *, data_root: Path) -> list[str]:
    """Store every session whose hold ran out more than the resume timeout ago. Blocking."""
    shared = services.shared
    finished: list[str] = []
    if shared is None:
        return finished
    while (taken := shared.claim_orphan(resume_timeout=services.resume_timeout)) is not None:
        try:
            finish_orphan(data_root=data_root, shared=shared, taken=taken, root=services.root)
        except Exception:  # noqa: BLE001 (any failure of one session must not stop the others')
            # Left held under this process's new epoch: its lease runs out, and it is tried again.
            _log.exception("session %s could not be stored from the shared log", taken.lease.session_id)
            break
        _log.warning("session %s: nobody resumed it; stored as %s", taken.lease.session_id, taken.ended_as)
        finished.append(taken.lease.session_id)
    return finished


async def finish_orphans(
    services: Services, *, data_root: Path, on_claimed: Callable[[int], None] = lambda count: None
) -> None:
    """Look for sessions nobody resumed, a few times per resume timeout, until cancelled; each
    pass that stored some tells `on_claimed` how many.

    After the index did not answer, this replica waits one lease TTL of answers before it claims
    anything: the owners cut off with it renew their leases first (their commits retry every half
    second), so a session is never taken from a live owner because the outage ended here first."""
    interval = min(1.0, max(0.1, services.resume_timeout / 4))
    ttl = services.shared.lease_ttl if services.shared is not None else 0.0
    answered_since = time.monotonic()  # a fresh start waits for nothing: it was never cut off
    waited_for_owners = True
    while True:
        if waited_for_owners or time.monotonic() - answered_since >= ttl:
            waited_for_owners = True
            try:
                finished = await asyncio.to_thread(finish_orphans_once, services, data_root=data_root)
                if finished:
                    on_claimed(len(finished))
            except STORAGE_ERRORS as error:
                _log.warning("cannot look for sessions nobody resumed: %s", error)
                waited_for_owners = False
                answered_since = math.inf
        else:
            answered_since = await asyncio.to_thread(_answered_at, services, answered_since)
        await asyncio.sleep(interval)


def _answered_at(services: Services, since: float) -> float:
    """`since`, or now if the index answers a trivial question for the first time since it failed;
    math.inf while it does not answer. Blocking."""
    if services.shared is None:
        return since
    try:
        services.shared.ping()
    except STORAGE_ERRORS:
        return math.inf
    return min(since, time.monotonic())
