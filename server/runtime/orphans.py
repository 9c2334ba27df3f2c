"""Sessions nobody resumed: every replica sharing the index looks for them, and the first to find
one takes it over (a new epoch, so its old holder is fenced) and stores it from the shared log.

    task = asyncio.create_task(finish_orphans(services, data_root=services.data_root))
"""

from __future__ import annotations

import asyncio
import logging
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


async def finish_orphans(services: Services, *, data_root: Path) -> None:
    """Look for sessions nobody resumed, a few times per resume timeout, until cancelled."""
    interval = min(1.0, max(0.1, services.resume_timeout / 4))
    while True:
        try:
            await asyncio.to_thread(finish_orphans_once, services, data_root=data_root)
        except STORAGE_ERRORS as error:
            _log.warning("cannot look for sessions nobody resumed: %s", error)
        await asyncio.sleep(interval)
