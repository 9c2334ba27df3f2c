"""Publishing again, in the background, the finished sessions whose Parquet could not reach the data
root when they ended (it was down): they wait in the data folder, and are published once it answers.

    task = asyncio.create_task(publish_pending_loop(services))
"""

from __future__ import annotations

import asyncio
import logging
from typing import Final

from jitdyn.server.runtime.services import Services
from jitdyn.storage.failures import STORAGE_ERRORS
from jitdyn.storage.publish import publish_pending

__all__ = ["PUBLISH_INTERVAL", "publish_pending_loop"]

_log = logging.getLogger(__name__)

# Seconds between two looks at the data folder for sessions not yet on the data root.
PUBLISH_INTERVAL: Final = 5.0


async def publish_pending_loop(services: Services, *, interval: float = PUBLISH_INTERVAL) -> None:
    """Publish what waits in the data folder, every `interval` seconds, until cancelled."""
    root = services.root
    if root is None:
        return
    while True:
        try:
            await asyncio.to_thread(publish_pending, root, data=services.data_root, index=services.index)
        except STORAGE_ERRORS as error:
            _log.warning(
                "sessions wait in the data folder: the data root %s cannot take them yet (%s: %s)",
                root.uri,
                type(error).__name__,
                " ".join(str(error).split()),
            )
        await asyncio.sleep(interval)
