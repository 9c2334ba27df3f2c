"""A UKF's answers: the estimate it hands out, and the dynamics at single states they need
(mj_forward for qacc, mj_inverse for a restored or a forecast's force), on the filter's own
mjData::

    answers = Answers(layout, model=model, data=data, kf=kf, state=state, dt=0.05)
    estimate = answers.estimate(nis=nis)                   # from the core's x and P
    qfrc = answers.inverse(qpos, qvel, qacc)               # (nv,)
"""

from __future__ import annotations

import mujoco
import numpy as np

from jitdyn.server.estimation.core import FilterCore
from jitdyn.server.estimation.interface import Estimate, Measurement, read_only
from jitdyn.server.estimation.layout import FilterLayout
from jitdyn.server.estimation.snapshot import FilterState
from jitdyn.vocabulary import Scenario

__all__ = ["Answers", "activation_bounds"]


def activation_bounds(model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    """(na,) lower and upper bounds of each activation; -inf, inf where unlimited."""
    low = np.full(model.na, -np.inf)
    high = np.full(model.na, np.inf)
    for i in range(model.nu):
        adr = int(model.actuator_actadr[i])
        if adr < 0:
            continue
        num = int(model.actuator_actnum[i])
        limited = bool(model.actuator_actlimited[i]) or int(model.actuator_dyntype[i]) == int(
            mujoco.mjtDyn.mjDYN_MUSCLE
        )
        if limited:
            # Muscles clamp their activation to [0, 1] in MuJoCo whatever actlimited says.
            bounds = model.actuator_actrange[i] if model.actuator_actlimited[i] else (0.0, 1.0)
            low[adr : adr + num], high[adr : adr + num] = bounds
    return low, high


class Answers:
    """The estimate of one UKF, and its dynamics at single states (module docstring). Reads the
    core's x and P and the filter's `state`; dt: the tick's seconds."""

    def __init__(
        self,
        layout: FilterLayout,
        *,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        kf: FilterCore,
        state: FilterState,
        dt: float,
    ) -> None:
        self._layout = layout
        self._model, self._data = model, data
        self._kf = kf
        self._state = state
        self._dt = dt
        self._act_bounds = activation_bounds(model)
        self._no_ctrl, self._no_force = np.zeros(layout.nu), np.zeros(layout.nv)

    def clip_act(self, act: np.ndarray) -> np.ndarray:
        # Negative Merwe weights can put a weighted mean of activations outside their range.
        return np.clip(act, *self._act_bounds) if self._layout.na else act

    def inverse(self, qpos: np.ndarray, qvel: np.ndarray, qacc: np.ndarray) -> np.ndarray:
        """The generalized force (nv,) that gives qacc at (qpos, qvel) and the held activations."""
        d = self._data
        d.qpos[:], d.qvel[:], d.qacc[:], d.act[:] = qpos, qvel, qacc, self._state.act
        mujoco.mj_inverse(self._model, d)
        return np.array(d.qfrc_inverse)

    def forward(
        self, qpos: np.ndarray, qvel: np.ndarray, act: np.ndarray, *, force: np.ndarray | None = None
    ) -> np.ndarray:
        """qacc at a state under the scenario's inputs (warm start is off: no hidden state);
        DRIVEN: under `force`, the estimated unknown force."""
        state = self._state
        ctrl = state.ctrl if self._layout.controlled else self._no_ctrl
        if force is None:
            force = state.qfrc if self._layout.scenario == Scenario.EXTERNAL else self._no_force
        return self._kf.forward(qpos, qvel, act=act, ctrl=ctrl, qfrc=force)

    def restored_force(self, m: Measurement, qvel: np.ndarray) -> np.ndarray:
        """EXTERNAL: the generalized force that produced the frame's motion (mj_inverse)."""
        state = self._state
        if m.qacc is not None:
            qacc = m.qacc
        elif state.ticks_since_update > 0:
            qacc = (qvel - state.last_qvel) / (state.ticks_since_update * self._dt)
        else:
            return state.qfrc  # a second frame for the same tick: nothing new to difference
        force = self.inverse(m.qpos, qvel, qacc)
        return force if np.all(np.isfinite(force)) else state.qfrc

    def estimate(
        self,
        *,
        nis: float | None = None,
        reinitialised: bool = False,
        adapted: bool = False,
        absorbed: bool = False,
    ) -> Estimate:
        """The estimate of the filter as it stands."""
        return self.make(
            self._kf.x,
            self._kf.P,
            act=self._state.act,
            nis=nis,
            reinitialised=reinitialised,
            adapted=adapted,
            absorbed=absorbed,
        )

    def make(
        self,
        x: np.ndarray,
        P: np.ndarray,
        *,
        act: np.ndarray,
        nis: float | None = None,
        reinitialised: bool = False,
        adapted: bool = False,
        absorbed: bool = False,
        qacc: np.ndarray | None = None,
    ) -> Estimate:
        """The estimate of mean x and covariance P, with activations act; qacc by forward(), or
        the one given (a native tick's, computed the same way)."""
        nq, nv = self._layout.nq, self._layout.nv
        state = read_only(x)
        qpos, qvel = state[:nq], state[nq : nq + nv]  # views of a read-only copy are read-only
        if self._layout.controlled:
            qacc = state[nq + nv :]
        elif qacc is not None:
            qacc = read_only(qacc)
        elif np.isfinite(state).all():
            force = state[nq + nv : nq + 2 * nv] if self._layout.driven else None
            qacc = read_only(self.forward(qpos, qvel, act, force=force))
        else:
            qacc = read_only(np.full(nv, np.nan))
        return Estimate(
            qpos=qpos,
            qvel=qvel,
            qacc=qacc,
            state=state,
            covariance=read_only(P),
            nis=nis,
            reinitialised=reinitialised,
            adapted=adapted,
            absorbed=absorbed,
            scenario=self._layout.scenario.value,
        )
