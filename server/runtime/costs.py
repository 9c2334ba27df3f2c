"""What a session costs, measured to check it against its limits (`limits`): the bytes of one tick of
its history, and the estimated seconds of one tick.

    snapshot_bytes(estimator.snapshot())
    tick_cost(model, nsigma=nsigma, steps_per_tick=steps, state_dimension=n)
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

from jitdyn.server.estimation.interface import SHARED_WITH_EARLIER
from jitdyn.server.estimation.propagate import step_seconds

__all__ = ["snapshot_bytes", "tick_cost"]

# Floating-point work of the filter's linear algebra per second that a tick can count on (numpy on
# one core, measured for the covariance and its square root at state dimensions 50-400).
_FLOPS = 2e9
# Physics steps timed at open to price one step of the model.
_TIMED_STEPS = 10


def snapshot_bytes(snapshot: object) -> int:
    """Bytes of the arrays an estimator snapshot holds (one tick of history)."""
    if isinstance(snapshot, np.ndarray):
        return int(snapshot.nbytes)
    nbytes = getattr(snapshot, "nbytes", None)  # an opaque native snapshot says its own size
    if isinstance(nbytes, int):
        return nbytes
    if dataclasses.is_dataclass(snapshot) and not isinstance(snapshot, type):
        return sum(
            snapshot_bytes(_own(getattr(snapshot, f.name), shared=f.metadata.get(SHARED_WITH_EARLIER, False)))
            for f in dataclasses.fields(snapshot)
        )
    if isinstance(snapshot, (tuple, list)):
        return sum(snapshot_bytes(item) for item in snapshot)
    return 0


def _own(value: object, *, shared: bool) -> object:
    """What of a snapshot's field is its own: of a tuple shared with earlier snapshots, its newest
    item (server/estimation/interface.py SHARED_WITH_EARLIER)."""
    if shared and isinstance(value, tuple):
        return value[-1:]
    return value


def tick_cost(model: mujoco.MjModel, *, nsigma: int, steps_per_tick: int, state_dimension: int) -> float:
    """Estimated seconds of one tick: every sigma point stepped `steps_per_tick` times (one step
    of this model timed here) plus the filter's linear algebra (cubic in the state dimension)."""
    step = step_seconds(model, mujoco.MjData(model), steps=_TIMED_STEPS)
    n = state_dimension
    flops = n**3 + 4.0 * nsigma * n * n
    return nsigma * steps_per_tick * step + flops / _FLOPS
