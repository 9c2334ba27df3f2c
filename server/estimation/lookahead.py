"""A UKF's estimates ahead of its last tick, without changing the filter: extrapolate() (the
sigma set carried and transformed) and glance() (the mean alone, at a fraction of the cost)::

    ahead = Lookahead(parts)
    estimate = ahead.extrapolate(0.1)    # seconds, rounded to physics steps
    estimate = ahead.glance(0.05)
"""

from __future__ import annotations

from typing import Final

import numpy as np

from jitdyn.errors import InvalidArgument
from jitdyn.server.estimation.core import PythonCore
from jitdyn.server.estimation.interface import Estimate
from jitdyn.server.estimation.linear_force import LinearForceUKF
from jitdyn.server.estimation.parts import FilterParts

__all__ = ["Lookahead"]

_SPANS_KEPT: Final = 16  # process noises kept by span: a horizon, and a glance at each tick of a late window


class Lookahead:
    """The extrapolations of one UKF (module docstring); keeps the process noises of the spans
    it was asked for."""

    def __init__(self, parts: FilterParts) -> None:
        self._parts = parts
        self._timestep = float(parts.model.opt.timestep)
        self._noises: dict[int, np.ndarray] = {parts.config.steps_per_tick: parts.Q}

    def extrapolate(self, seconds: float) -> Estimate:
        """The estimate `seconds` ahead: the sigma points of (x, P) propagated and transformed."""
        parts = self._parts
        nstep = self._steps_in(seconds)
        if nstep == 0:
            return parts.answers.estimate()
        Q = self.noise_over(nstep)
        kf, state = parts.kf, parts.state
        parts.process.set_inputs(act=state.act, ctrl=state.ctrl, qfrc=state.qfrc)
        linear = kf.inner if isinstance(kf, PythonCore) else None
        if isinstance(linear, LinearForceUKF):
            sigmas_f = linear.sigmas_f
            x, P = linear.prior(linear.x, linear.P, nstep=nstep)
            linear.sigmas_f = sigmas_f
            P = P + Q
        else:
            sigmas = parts.points.sigma_points(kf.x, kf.P)
            propagated = parts.process.propagate(sigmas, nstep=nstep)
            x, P = parts.ut(propagated, parts.points.Wm, parts.points.Wc, Q, kf.x_mean, kf.residual_x)
        P = symmetric(P)
        act = parts.answers.clip_act(parts.process.propagated_act)
        return parts.answers.make(x, P, act=act)

    def glance(self, seconds: float) -> Estimate:
        """The mean alone carried through the physics (one point for the sigma set's 2n + 1) and P
        grown by the process noise of the span: no unscented transform, no forecast combination.
        For a few ticks, while a late frame may still come, the mean is what the sigma set's would
        be to second order."""
        parts = self._parts
        nstep = self._steps_in(seconds)
        if nstep == 0:
            return parts.answers.estimate()
        layout, state = parts.layout, parts.state
        nq, nv = layout.nq, layout.nv
        x = parts.kf.x
        force = x[nq + nv : nq + 2 * nv] if layout.driven else None
        rate = x[nq + 2 * nv : nq + 3 * nv] if layout.fblocks == 2 else None
        out = parts.propagator(
            x[None, :nq],
            x[None, nq : nq + nv],
            act=state.act,
            ctrl=state.ctrl,
            qfrc=state.qfrc if force is None else force[None, :],
            qfrc_rate=None if rate is None else rate[None, :],
            nstep=nstep,
        )
        ahead = np.array(x, dtype=np.float64)
        ahead[:nq], ahead[nq : nq + nv] = out.qpos[0], out.qvel[0]
        if layout.controlled and out.qacc is not None:
            ahead[nq + nv :] = out.qacc[0]
        if rate is not None:
            ahead[nq + nv : nq + 2 * nv] += nstep * self._timestep * rate
        act = parts.answers.clip_act(out.act[0]) if layout.na else state.act
        return parts.answers.make(ahead, symmetric(parts.kf.P + self.noise_over(nstep)), act=act)

    def noise_over(self, nstep: int) -> np.ndarray:
        """The process noise of nstep physics steps (the adapter's factors applied)."""
        parts = self._parts
        Q = self._noises.get(nstep)
        if Q is None:
            Q = parts.noise.process_noise(nstep * self._timestep)
            if len(self._noises) >= _SPANS_KEPT:
                self._noises = {parts.config.steps_per_tick: parts.Q}
            self._noises[nstep] = Q
        return parts.adapter.q_for(Q) if parts.adapter is not None else Q

    def _steps_in(self, seconds: float) -> int:
        if (
            isinstance(seconds, bool)
            or not isinstance(seconds, (int, float))
            or not 0.0 <= seconds < float("inf")
        ):
            raise InvalidArgument(f"seconds must be finite and >= 0, got {seconds!r}")
        return round(seconds / self._timestep)


def symmetric(P: np.ndarray) -> np.ndarray:
    return np.asarray(0.5 * (P + P.T))
