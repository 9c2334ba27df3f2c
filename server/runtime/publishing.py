"""Publishing again, in the background, the finished sessions whose Parquet could not reach the data
root when they ended (it was down): they wait in the data folder, and are published once it answers;
with a shared index, any replica publishes them from the shared log once their replica lets them be.

    task = asyncio.create_task(publish_pending_loop(services))
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Final

from jitdyn.server.runtime.services import Services
from jitdyn.storage.failures import STORAGE_ERRORS
from jitdyn.storage.publish import awaiting_upload, publish_pending
from jitdyn.storage.recorder import publish_unpublished
from jitdyn.storage.root import DataRoot
from jitdyn.storage.shared import SharedTier

__all__ = ["PUBLISH_INTERVAL", "publish_pending_loop"]

_log = logging.getLogger(__name__)

# Seconds between two looks at the data folder for sessions not yet on the data root.
PUBLISH_INTERVAL: Final = 5.0


def _publish_from_shared_log(shared: SharedTier, *, data: Path, root: DataRoot) -> None:
    """Every session another replica (or this one) ended but could not publish, and let be."""
    while publish_unpublished(data_root=data, shared=shared, root=root) is not None:
        pass


async def publish_pending_loop(
    services: Services,
    *,
    interval: float = PUBLISH_INTERVAL,
    on_waiting: Callable[[int], None] = lambda count: None,
) -> None:
    """Publish what waits in the data folder, every `interval` seconds, until cancelled; after each
    try, `on_waiting` gets how many finished sessions' files still wait there."""
    root = services.root
    if root is None:
        return
    while True:
        try:
            await asyncio.to_thread(publish_pending, root, data=services.data_root, index=services.index)
            if services.shared is not None:
                await asyncio.to_thread(
                    _publish_from_shared_log, services.shared, data=services.data_root, root=root
                )
        except STORAGE_ERRORS as error:
            _log.warning(
                "sessions wait in the data folder: the data root %s cannot take them yet (%s: %s)",
                root.uri,
                type(error).__name__,
                " ".join(str(error).split()),
            )
        on_waiting(await asyncio.to_thread(awaiting_upload, services.data_root))
        await asyncio.sleep(interval)
