"""What a UKF does when it starts from a frame: the first frame (initialise), and the restarts
estimation/guard.py decides on, after a prediction that diverged or an update::

    start_from(parts, m, qvel_fallback=np.zeros(nv))   # x from the frame, P = P0
    reinitialise(parts, m)                             # the divergence guard's restart
    restart(parts, m)                                  # after an update: noise and guard as new
"""

from __future__ import annotations

import numpy as np

from jitdyn.server.estimation.interface import Measurement
from jitdyn.server.estimation.parts import FilterParts

__all__ = ["reinitialise", "restart", "start_from"]


def start_from(parts: FilterParts, m: Measurement, *, qvel_fallback: np.ndarray) -> None:
    """x from the measurement (unmeasured qvel: qvel_fallback), P = P0."""
    layout, kf, state = parts.layout, parts.kf, parts.state
    nq, nv = layout.nq, layout.nv
    qvel = m.qvel if m.qvel is not None else qvel_fallback
    x = np.empty(layout.size)
    x[:nq] = m.qpos
    x[nq : nq + nv] = qvel
    if layout.controlled:
        x[nq + nv :] = m.qacc if m.qacc is not None else parts.answers.forward(m.qpos, qvel, state.act)
    if layout.driven:
        # The force that would give the frame's qacc (none measured: hold the body still);
        # a re-initialisation keeps the force it had, when that is still finite.
        previous = kf.x[nq + nv :] if state.initialised else None
        if previous is not None and np.all(np.isfinite(previous)):
            x[nq + nv :] = previous
        else:
            qacc = m.qacc if m.qacc is not None else np.zeros(nv)
            x[nq + nv :] = 0.0
            x[nq + nv : nq + 2 * nv] = parts.answers.inverse(m.qpos, qvel, qacc)
    kf.x = x
    kf.P = parts.P0.copy()
    if layout.linear_force:  # the points span [q, qd]
        k = 2 * nv
        kf.sigmas_f = parts.points.sigma_points(kf.x[: nq + nv], kf.P[:k, :k])
    else:
        kf.sigmas_f = parts.points.sigma_points(kf.x, kf.P)
    state.last = m
    state.last_qvel = np.array(qvel)
    state.ticks_since_update = 0
    parts.guard.start()


def reinitialise(parts: FilterParts, m: Measurement) -> None:
    """The divergence guard: back to the measurement, with what is still finite of the rest."""
    layout, state = parts.layout, parts.state
    qvel = parts.kf.x[layout.nq : layout.nq + layout.nv]
    fallback = qvel.copy() if np.all(np.isfinite(qvel)) else np.zeros(layout.nv)
    if not np.all(np.isfinite(state.act)):
        state.act = np.zeros_like(state.act)
    if not np.all(np.isfinite(state.ctrl)):
        state.ctrl = np.zeros_like(state.ctrl)
    if not np.all(np.isfinite(state.qfrc)):
        state.qfrc = np.zeros_like(state.qfrc)
    start_from(parts, m, qvel_fallback=fallback)


def restart(parts: FilterParts, m: Measurement) -> None:
    """The guard's restart after an update: from this frame, the noise and the guard as new."""
    reinitialise(parts, m)
    if parts.adapter is not None:
        parts.adapter.reset()
    parts.guard.reset()
