"""Storage failures as clients see them: UNAVAILABLE, with a message that names no server path.

    except OSError as error:
        raise storage_failure("session 1234 could not be stored", error) from None

The operating system's message (which names the file, e.g. "[Errno 30] Read-only file system:
'/srv/jitdyn/logs/1234.arrows'") goes to the server log, where an operator needs it; a client only
learns that storage failed and that trying again later may work.
"""

from __future__ import annotations

import logging

from jitdyn.errors import Unavailable

__all__ = ["STORAGE_ERRORS", "storage_failure"]

_log = logging.getLogger(__name__)


def _storage_errors() -> tuple[type[BaseException], ...]:
    import pyarrow as pa
    import sqlalchemy as sa

    return (OSError, sa.exc.SQLAlchemyError, pa.ArrowException)


# What a disk or a database throws when it cannot store: a full or read-only disk, a lost database.
STORAGE_ERRORS: tuple[type[BaseException], ...] = _storage_errors()


def storage_failure(what: str, error: BaseException) -> Unavailable:
    """Log `error` (with its paths) and return the path-free Unavailable for the client."""
    _log.error("%s: %s: %s", what, type(error).__name__, error)
    return Unavailable(
        f"{what}: the server's storage failed (details are in the server log); try again later"
    )
