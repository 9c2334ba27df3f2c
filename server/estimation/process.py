"""The UKF's process model in Python: a sigma set carried one tick (or nstep physics steps) through
MuJoCo under the scenario's inputs, in one batched call (estimation/propagate.py). The Python
engines' prediction runs it; so does every engine's extrapolation past the filter.

    process = SigmaProcess(model, data, propagator=propagator, points=points, scenario=..., ...)
    process.set_inputs(act=act, ctrl=ctrl, qfrc=qfrc)   # what acts over the next propagation
    moved = process.propagate(sigmas, nstep=None)       # (nsigma, len x), a tick's steps
    process.propagated_act                              # (na,) the points' mean activation after it

The compiled engine does the same in C++ (native/ukf.cc, Ukf::Propagate); tests/server/test_native.py
holds the two equal.
"""

from __future__ import annotations

import mujoco
import numpy as np

from jitdyn.server.estimation.linear_force import force_response
from jitdyn.server.estimation.propagate import Propagator
from jitdyn.server.estimation.sigma import MerweScaled, Simplex, UniformSpherical

__all__ = ["SigmaProcess"]


class SigmaProcess:
    """The scenario's process model over sigma sets (module docstring). size: len(x); order and
    fblocks: the state's layout (estimation/layout.py)."""

    def __init__(
        self,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        *,
        propagator: Propagator,
        points: MerweScaled | Simplex | UniformSpherical,
        size: int,
        fblocks: int,
        controlled: bool,
        steps_per_tick: int,
    ) -> None:
        self._model, self._data = model, data
        self._propagator = propagator
        self._points = points
        self._nq, self._nv, self._na = int(model.nq), int(model.nv), int(model.na)
        self._size = size
        self._fblocks = fblocks
        self._driven = fblocks > 0
        self._controlled = controlled
        self._steps_per_tick = steps_per_tick
        self._act = np.zeros(self._na)
        self._ctrl = np.zeros(int(model.nu))
        self._qfrc = np.zeros(self._nv)
        self.propagated_act = np.zeros(self._na)

    def set_inputs(self, *, act: np.ndarray, ctrl: np.ndarray, qfrc: np.ndarray) -> None:
        """What acts on the points over the next propagation: act (na,), ctrl (nu,), qfrc (nv,)."""
        self._act, self._ctrl, self._qfrc = act, ctrl, qfrc

    def propagate(self, sigmas: np.ndarray, *, nstep: int | None) -> np.ndarray:
        """The process model on a sigma set (nsigma, len x) -> (nsigma, len x).

        In CONTROLLED, qdd does not enter the dynamics, so points that differ from the first only
        in qdd propagate exactly as it does (with Merwe points and an upper Cholesky factor, the
        last 2 nv of them): each distinct (q, qd) is stepped once and its result shared, which
        gives the same numbers with 2 nv fewer points stepped.
        """
        nq, nv = self._nq, self._nv
        if self._driven:
            return self._propagate_driven(sigmas, nstep=nstep)
        head = sigmas[:, : nq + nv]
        shared: np.ndarray | None = None
        if self._controlled:
            same = (head == head[0]).all(axis=1)
            same[0] = False
            if same.any():
                shared = same
                head = head[~same]
        out = self._propagator(
            head[:, :nq], head[:, nq:], act=self._act, ctrl=self._ctrl, qfrc=self._qfrc, nstep=nstep
        )
        stepped = np.empty((head.shape[0], self._size))
        stepped[:, :nq] = out.qpos
        stepped[:, nq : nq + nv] = out.qvel
        if self._controlled:
            stepped[:, nq + nv :] = out.qacc
        act = out.act
        if shared is None:
            propagated = stepped
        else:
            propagated = np.empty((sigmas.shape[0], self._size))
            propagated[~shared] = stepped
            propagated[shared] = stepped[0]
            if self._na:
                act = np.empty((sigmas.shape[0], self._na))
                act[~shared] = out.act
                act[shared] = out.act[0]
        if self._na:
            self.propagated_act = self._points.Wm @ act
        return propagated

    def _propagate_driven(self, sigmas: np.ndarray, *, nstep: int | None) -> np.ndarray:
        """DRIVEN: every point moves under its own force f (ramping with its rate fd under the
        integrated random walk); f' = f + fd T, fd' = fd (T: the steps' span), or f' = f."""
        nq, nv = self._nq, self._nv
        force = sigmas[:, nq + nv : nq + 2 * nv]
        rate = sigmas[:, nq + 2 * nv : nq + 3 * nv] if self._fblocks == 2 else None
        out = self._propagator(
            sigmas[:, :nq],
            sigmas[:, nq : nq + nv],
            act=self._act,
            qfrc=np.ascontiguousarray(force),
            qfrc_rate=None if rate is None else np.ascontiguousarray(rate),
            nstep=nstep,
        )
        propagated = np.array(sigmas, dtype=np.float64)
        propagated[:, :nq] = out.qpos
        propagated[:, nq : nq + nv] = out.qvel
        if rate is not None:
            span = (self._steps_per_tick if nstep is None else nstep) * float(self._model.opt.timestep)
            propagated[:, nq + nv : nq + 2 * nv] += span * rate
        if self._na:
            self.propagated_act = self._points.Wm @ out.act
        return propagated

    def propagate_linear_force(self, chi: np.ndarray, forces: np.ndarray, *, nstep: int | None) -> np.ndarray:
        """SIMPLEX_LINEAR_FORCE: [q, qd] points (m, 2 nv), each under its own force (m, nv), nstep
        physics steps on -> (m, 2 nv)."""
        nq = self._nq
        out = self._propagator(
            chi[:, :nq], chi[:, nq:], act=self._act, qfrc=np.ascontiguousarray(forces), nstep=nstep
        )
        moved = np.empty_like(chi)
        moved[:, :nq], moved[:, nq:] = out.qpos, out.qvel
        if self._na:
            self.propagated_act = self._points.Wm @ out.act
        return moved

    def force_response(self, s: np.ndarray, f: np.ndarray, *, nstep: int | None) -> np.ndarray:
        """B (2 nv, nv) at s = [q, qd] under force f (estimation/linear_force.py)."""
        steps = self._steps_per_tick if nstep is None else nstep
        return force_response(self._model, self._data, s, f, act=self._act, nstep=steps)
