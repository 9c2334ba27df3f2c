"""jitdyn's Python SDK: register models, open sessions, stream frames, read results; sync and async.

    from jitdyn.client import Client, SessionOptions, FrameData
    from jitdyn.client import AsyncClient      # the same over asyncio (grpc.aio)

Value types live in `_models.py`, what both transports share in `_transport.py`, `_session.py` (a
session's state and its steps without I/O) and `_resume.py` (its resume bookkeeping), the sync
transport in `_client.py` and the async one in `aio.py`. It may import the contract (jitdyn.v1, errors, vocabulary, estimator_settings) and
jitdyn.registry (model packing); never the server or the research harness.
"""

from jitdyn.client import _models
from jitdyn.client._client import Client, Session
from jitdyn.client._models import *  # the value types, `_models.__all__`
from jitdyn.client.aio import AsyncClient, AsyncSession

__all__ = ["AsyncClient", "AsyncSession", "Client", "Session"]
__all__ += _models.__all__
