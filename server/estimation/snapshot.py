"""A UKF's mutable bookkeeping beside its core's x and P (`FilterState`), and the timewarp's
snapshots of the two (`FilterSnapshot`; `NativeSnapshot` where a native tick holds the numbers,
native/tick.py): immutable, cheap, and exact, so that replaying the same inputs from a restored
snapshot gives the same states bit for bit::

    snap = take_snapshot(owner, state, kf, guard=guard, adapter=adapter, foresight=foresight)
    restore_snapshot(snap, state, kf, guard=guard, adapter=adapter, foresight=foresight)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from jitdyn.server.estimation.adaptive import NoiseAdapter, NoiseSnapshot
from jitdyn.server.estimation.core import FilterCore
from jitdyn.server.estimation.forecast import CombinerSnapshot
from jitdyn.server.estimation.foresight import Foresight
from jitdyn.server.estimation.guard import Guard, GuardState
from jitdyn.server.estimation.interface import Measurement, read_only
from jitdyn.server.estimation.native import AdapterState, CombinerState, TickState
from jitdyn.server.estimation.native.adaptive import NativeNoiseAdapter

__all__ = [
    "Bookkeeping",
    "FilterSnapshot",
    "FilterState",
    "NativeSnapshot",
    "bookkeeping",
    "restore_bookkeeping",
    "restore_snapshot",
    "take_snapshot",
]


@dataclass(slots=True)
class FilterState:
    """What a UKF keeps between ticks besides x and P. The arrays are replaced, never written into
    (the native core keeps the inputs it was last handed by identity)."""

    initialised: bool
    act: np.ndarray  # (na,) the muscle activations, the weighted mean of the propagated points'
    ctrl: np.ndarray  # (nu,) the control held over the ticks to come (CONTROLLED)
    qfrc: np.ndarray  # (nv,) the restored force held until the next frame (EXTERNAL)
    last: Measurement | None  # the last frame used
    last_qvel: np.ndarray  # (nv,) its qvel (or the filter's, unmeasured)
    ticks_since_update: int

    @classmethod
    def cleared(cls, na: int, nu: int, nv: int) -> FilterState:
        """The state of a filter not yet initialised."""
        return cls(
            initialised=False,
            act=np.zeros(na),
            ctrl=np.zeros(nu),
            qfrc=np.zeros(nv),
            last=None,
            last_qvel=np.zeros(nv),
            ticks_since_update=0,
        )


@dataclass(frozen=True)
class FilterSnapshot:
    """An UnscentedFilter's whole mutable state; arrays are read-only copies."""

    owner: int  # id() of the filter it came from
    initialised: bool
    x: np.ndarray
    P: np.ndarray
    sigmas_f: np.ndarray  # the prior's sigma points, which update() uses
    act: np.ndarray
    ctrl: np.ndarray
    qfrc: np.ndarray
    last: Measurement | None
    last_qvel: np.ndarray
    ticks_since_update: int
    guard: GuardState
    adapter: NoiseSnapshot | AdapterState | None
    forecasts: CombinerSnapshot | CombinerState | None


@dataclass(frozen=True)
class Bookkeeping:
    """A FilterState's copy, and the guard's, as a snapshot holds them; arrays read-only."""

    initialised: bool
    act: np.ndarray
    ctrl: np.ndarray
    qfrc: np.ndarray
    last: Measurement | None
    last_qvel: np.ndarray
    ticks_since_update: int
    guard: GuardState


def bookkeeping(state: FilterState, guard: Guard) -> Bookkeeping:
    """A read-only copy of `state` and the guard's state."""
    return Bookkeeping(
        initialised=state.initialised,
        act=read_only(state.act),
        ctrl=read_only(state.ctrl),
        qfrc=read_only(state.qfrc),
        last=state.last,  # immutable: check_measurement made it read-only
        last_qvel=read_only(state.last_qvel),
        ticks_since_update=state.ticks_since_update,
        guard=guard.state,
    )


def restore_bookkeeping(kept: Bookkeeping, state: FilterState, guard: Guard) -> None:
    """`state` and the guard back to `kept` (bookkeeping's copy)."""
    state.initialised = kept.initialised
    state.act, state.ctrl, state.qfrc = kept.act.copy(), kept.ctrl.copy(), kept.qfrc.copy()
    state.last = kept.last
    state.last_qvel = kept.last_qvel.copy()
    state.ticks_since_update = kept.ticks_since_update
    guard.restore(kept.guard)


@dataclass(frozen=True)
class NativeSnapshot:
    """An UnscentedFilter's whole mutable state where a native tick holds its numbers: the
    bookkeeping, and x, P, sigmas_f, the adapter's and the combiner's states in one opaque
    TickState (its size: `native.nbytes`)."""

    owner: int  # id() of the filter it came from
    kept: Bookkeeping
    native: TickState


def take_snapshot(
    owner: int,
    state: FilterState,
    kf: FilterCore,
    *,
    guard: Guard,
    adapter: NoiseAdapter | NativeNoiseAdapter | None,
    foresight: Foresight | None,
) -> FilterSnapshot:
    """Everything needed to come back to this point; `owner` the id() of the filter."""
    return FilterSnapshot(
        owner=owner,
        initialised=state.initialised,
        x=read_only(kf.x),
        P=read_only(kf.P),
        sigmas_f=read_only(kf.sigmas_f),
        act=read_only(state.act),
        ctrl=read_only(state.ctrl),
        qfrc=read_only(state.qfrc),
        last=state.last,  # immutable: check_measurement made it read-only
        last_qvel=read_only(state.last_qvel),
        ticks_since_update=state.ticks_since_update,
        guard=guard.state,
        adapter=adapter.snapshot() if adapter is not None else None,
        forecasts=foresight.snapshot() if foresight is not None else None,
    )


def restore_snapshot(
    snap: FilterSnapshot,
    state: FilterState,
    kf: FilterCore,
    *,
    guard: Guard,
    adapter: NoiseAdapter | NativeNoiseAdapter | None,
    foresight: Foresight | None,
) -> None:
    """Back to `snap`, taken by take_snapshot of the same filter."""
    kf.x, kf.P, kf.sigmas_f = snap.x.copy(), snap.P.copy(), snap.sigmas_f.copy()
    state.initialised = snap.initialised
    state.act, state.ctrl, state.qfrc = snap.act.copy(), snap.ctrl.copy(), snap.qfrc.copy()
    state.last = snap.last
    state.last_qvel = snap.last_qvel.copy()
    state.ticks_since_update = snap.ticks_since_update
    guard.restore(snap.guard)
    saved = snap.adapter
    # Each engine's adapter takes its own snapshots (two branches for the type checker).
    if isinstance(adapter, NativeNoiseAdapter) and isinstance(saved, AdapterState):  # noqa: SIM114
        adapter.restore(saved)
    elif isinstance(adapter, NoiseAdapter) and isinstance(saved, NoiseSnapshot):
        adapter.restore(saved)
    if foresight is not None and snap.forecasts is not None:
        foresight.restore(snap.forecasts)
