"""What the session runtime needs from a state estimator: the `Estimator` protocol, the frame it
reads (`Measurement`) and the answer it gives (`Estimate`), and the checks every estimator applies
to what it is handed. Sessions drive one estimator a tick at a time::

    estimator.initialise(first)                       # tick 0
    estimate = estimator.predict(ctrl=None)           # a later tick without its frame
    estimator.advance(ctrl=None)                      # a later tick with its frame: advance ...
    estimate = estimator.update(frame)                # ... and answer from the frame

The state layouts of `Estimate.state` are estimation/layout.py's; the settings that make an
estimator are estimation/config.py's, and estimation/factory.py makes one from them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final, Protocol, runtime_checkable

import mujoco
import numpy as np

from jitdyn.errors import InvalidArgument
from jitdyn.vocabulary import Channel

__all__ = [
    "SHARED_WITH_EARLIER",
    "Estimate",
    "Estimator",
    "Measurement",
    "check_measurement",
    "check_vector",
    "read_only",
]


# Metadata of a snapshot's field (a tuple) whose items are shared with the snapshots taken before
# it, as a tuple that only grows by its end is: the memory a snapshot adds to a history is its
# newest item (server/runtime/costs.py snapshot_bytes counts that alone).
SHARED_WITH_EARLIER: Final = "jitdyn_shared_with_earlier"


@dataclass(frozen=True)
class Measurement:
    """One frame's measured channels: qpos (nq,), qvel (nv,), qacc (nv,), ctrl (nu,); None when the
    channel is not measured. Estimators check shapes and finiteness themselves.
    """

    qpos: np.ndarray
    qvel: np.ndarray | None = None
    qacc: np.ndarray | None = None
    ctrl: np.ndarray | None = None


@dataclass(frozen=True)
class Estimate:
    """An estimator's answer for one tick. Every array is a read-only copy.

    qpos (nq,), qvel (nv,), qacc (nv,); state: the estimator's own mean (see estimation/layout.py
    for its layouts); covariance (n, n) in the tangent space, None for dead reckoning; nis:
    normalised innovation squared of the measurement just used, None when none was (or it was not
    finite); reinitialised: the divergence guard restarted the estimator from a measurement;
    adapted: the adaptive noise model changed R or Q by more than a tenth since the last estimate
    that said so; absorbed: the NIS of a window of updates was far outside its interval and the
    filter widened its covariance (and, for a PASSIVE or EXTERNAL filter, started estimating the
    unknown force) to follow the measurements, or the first frame after a gap was past the
    divergence guard's NIS limit and the filter widened its prediction before using it (nis is
    then the NIS against the widened prediction).
    """

    qpos: np.ndarray
    qvel: np.ndarray
    qacc: np.ndarray
    state: np.ndarray
    covariance: np.ndarray | None
    nis: float | None = None
    reinitialised: bool = False
    adapted: bool = False
    absorbed: bool = False
    # Over a gap with Forecast.COMBINED: the weights of the predictors that answered, in
    # estimation/forecast.py's PREDICTORS order; None when the filter answered alone.
    forecast_weights: tuple[float, ...] | None = None
    # The predictors those weights are of, by name (estimation/predictors.py), in their order.
    forecast_predictors: tuple[str, ...] | None = None
    # The scenario of the filter that answered: a PASSIVE session's becomes DRIVEN when a wrong
    # model is absorbed (estimation/switch.py).
    scenario: str = ""


# The ufunc's own reduce, not ndarray.all() and numpy's Python wrapper of it: a measurement's
# channels are checked every tick.
_all_true = np.logical_and.reduce


def check_vector(value: object, size: int, name: str) -> np.ndarray:
    """A private, read-only float64 copy of `value`, which must be finite with shape (size,)."""
    try:
        array = np.array(value, dtype=np.float64)  # a private copy: the caller may reuse its buffer
    except (TypeError, ValueError):
        raise InvalidArgument(f"{name} must be an array of {size} numbers, got {value!r}") from None
    if array.shape != (size,):
        raise InvalidArgument(f"{name} must have shape ({size},), got {array.shape}")
    if not _all_true(np.isfinite(array)):
        raise InvalidArgument(f"{name} must be finite, got {array.tolist()}")
    array.flags.writeable = False
    return array


def check_measurement(m: Measurement, model: mujoco.MjModel, measured: frozenset[str]) -> Measurement:
    """A checked, private, read-only copy of `m`: shapes, finiteness, and every measured state
    channel present (ctrl may be absent: a controller on the server may supply it)."""
    missing = sorted(str(c) for c in measured & {Channel.QVEL, Channel.QACC} if getattr(m, c) is None)
    if missing:
        raise InvalidArgument(f"measurement must have the measured channels {missing}, got None")

    def channel(value: np.ndarray | None, size: int, name: str) -> np.ndarray | None:
        return None if value is None else check_vector(value, size, f"measurement.{name}")

    qpos = check_vector(m.qpos, model.nq, "measurement.qpos")
    return Measurement(
        qpos=qpos,
        qvel=channel(m.qvel, model.nv, "qvel"),
        qacc=channel(m.qacc, model.nv, "qacc"),
        ctrl=channel(m.ctrl, model.nu, "ctrl"),
    )


def read_only(array: np.ndarray) -> np.ndarray:
    """A read-only copy of `array`, to hand out."""
    copy = np.array(array, dtype=np.float64)
    copy.flags.writeable = False
    return copy


@runtime_checkable
class Estimator(Protocol):
    """One session's state estimator, driven one tick at a time from one thread."""

    @property
    def state_dimension(self) -> int:
        """Side of the covariance: 2 nv, or 3 nv in CONTROLLED (tangent space)."""
        ...

    @property
    def state_size(self) -> int:
        """len(Estimate.state): nq + nv, or nq + 2 nv in CONTROLLED."""
        ...

    def initialise(self, m: Measurement) -> None:
        """Start from the first frame: x0 from it, P0 = p0 I."""
        ...

    def predict(self, *, ctrl: np.ndarray | None) -> Estimate:
        """Advance one tick (steps_per_tick physics steps). ctrl (nu,): the control over this tick
        in CONTROLLED (None holds the last one); ignored in the other scenarios."""
        ...

    def advance(self, *, ctrl: np.ndarray | None) -> None:
        """predict() without its answer, for a tick whose frame update() answers next: the same
        state afterwards, without the estimate (and the gap's answer) no one reads."""
        ...

    def update(self, m: Measurement) -> Estimate:
        """Correct the tick just predicted with its frame; may re-initialise (divergence guard)."""
        ...

    def step(self, *, ctrl: np.ndarray | None, m: Measurement) -> Estimate:
        """advance(ctrl=ctrl) then update(m): a tick whose frame is there, the same state and
        estimate as the two calls (in fewer native calls where the engine can)."""
        ...

    def extrapolate(self, seconds: float) -> Estimate:
        """The estimate `seconds` ahead (rounded to physics steps), without changing the estimator;
        0 gives the current estimate."""
        ...

    def glance(self, seconds: float) -> Estimate:
        """The estimate `seconds` ahead at a fraction of extrapolate()'s cost (the mean carried
        alone, the covariance grown by the process noise of that span), without changing the
        estimator: a REALTIME answer for a tick whose frame may still come."""
        ...

    def snapshot(self) -> object:
        """Everything needed to come back to this point (timewarp); immutable, cheap."""
        ...

    def restore(self, snap: object) -> None:
        """Return to a snapshot of this estimator: replaying the same inputs then gives the same
        states, bit for bit."""
        ...
