"""The adaptive noise's steps inside a UKF's update (the adapter itself is estimation/adaptive.py,
or native/adaptive.cc): what the frame that ends a gap was worth, the widened second correction
of a frame far out after a gap, and the adapter's verdict on each update::

    prior = gap_prior(parts)                      # before the correction
    observe_gap(parts, gap_nis, nis)              # after it
    adapted, absorbed = adapt(parts, nis, finite=finite)
"""

from __future__ import annotations

import numpy as np

from jitdyn.server.estimation.core import correct
from jitdyn.server.estimation.parts import FilterParts

__all__ = ["adapt", "correct_widened", "gap_prior", "observe_gap", "verdict_taken"]


def gap_prior(parts: FilterParts) -> tuple[np.ndarray, np.ndarray] | None:
    """A copy of the prior (x, P) when this frame ends a gap and the noise adapts, else None."""
    if parts.adapter is None or parts.state.ticks_since_update <= 1:
        return None
    return parts.kf.x.copy(), parts.kf.P.copy()


def observe_gap(parts: FilterParts, gap_nis: float | None, nis: float | None) -> None:
    """The adaptive noise learns from the frame that ends a gap: its NIS against the gap's last
    answer (`gap_nis`, the combination's), or against the filter's prediction (`nis`)."""
    if parts.adapter is None:
        return
    gap_nis = nis if parts.foresight is None or gap_nis is None else gap_nis
    if gap_nis is not None:
        parts.adapter.observe_gap(nis=gap_nis, m=parts.layout.z_tangent)


def correct_widened(parts: FilterParts, z: np.ndarray, prior: tuple[np.ndarray, np.ndarray]) -> float | None:
    """The frame that ends a gap, past the divergence guard's NIS limit, used again against the
    prior widened as an absorption widens it: [q, qd] follow the frame, the force its evidence
    (docs/decisions/0022-widen-after-a-gap.md)."""
    x, P = prior
    k = parts.layout.order * parts.layout.nv
    P[:k, :k] += parts.P0[:k, :k]
    parts.kf.x, parts.kf.P = x, P
    if not parts.layout.linear_force:
        parts.kf.sigmas_f = parts.points.sigma_points(x, P)  # what filterpy's update uses
    return correct(parts.kf, z, size=parts.layout.size)


def adapt(parts: FilterParts, nis: float | None, *, finite: bool) -> tuple[bool, bool]:
    """The adaptive noise learns from this update (finite: x and P are): whether it adapted, and
    whether its NIS window asked for an absorption (which widens P on [q, qd] while the guard
    allows)."""
    adapter = parts.adapter
    if adapter is None or not finite or nis is None:
        return False, False
    kf = parts.kf
    verdict = adapter.observe(
        innovation=np.asarray(kf.y),
        consecutive=parts.state.ticks_since_update == 1,
        gain=np.asarray(kf.K),
        nis=nis,
        noise_share=float(np.diagonal(kf.SI) @ np.diagonal(kf.R)) / parts.layout.z_tangent,
    )
    return verdict_taken(parts, adapted=verdict.adapted, absorb=verdict.absorb)


def verdict_taken(parts: FilterParts, *, adapted: bool, absorb: bool) -> tuple[bool, bool]:
    """What the guard makes of the adapter's verdict on an update (adapt's second half, which a
    native tick runs after its observation): whether it adapted, and whether it absorbed."""
    adapter, kf = parts.adapter, parts.kf
    if adapter is None:
        raise RuntimeError("unreachable: a verdict comes from an adapter")
    if not absorb:
        if adapter.window_full:
            parts.guard.settle()
        return adapted, False
    if parts.guard.absorb():
        # The model is wrong, not the noise: forget what P says was known, and let Q follow
        # the corrections the filter has to make. Only q and qd widen: a force spread as wide
        # as P0 throws the sigma points of a pendulum over (measured, docs/experiments.md).
        k = parts.layout.order * parts.layout.nv
        P = np.array(kf.P)
        P[:k, :k] += parts.P0[:k, :k]
        kf.P = P
        adapter.absorbed()
    return adapted, True
