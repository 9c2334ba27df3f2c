"""MuJoCo dynamics of one estimated or measured state: inverse dynamics, forward dynamics, sensors.

One `Dynamics` per session reuses its own MjData; nothing is allocated per frame but the output
copies handed to the caller::

    dyn = Dynamics(model, outputs=frozenset({"INVERSE_DYNAMICS"}))
    out = dyn.compute(qpos=q, qvel=v, qacc=a, ctrl=None)
    out.qfrc_inverse  # (nv,)
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

__all__ = ["OUTPUTS", "Dynamics", "DynamicsResult"]

OUTPUTS = frozenset({"INVERSE_DYNAMICS", "FORWARD_DYNAMICS", "SENSORS", "FILTER_STATE"})


@dataclass(frozen=True, slots=True)
class DynamicsResult:
    """The dynamics asked for; None where not asked."""

    qfrc_inverse: np.ndarray | None  # (nv,)
    qacc_forward: np.ndarray | None  # (nv,)
    actuator_force: np.ndarray | None  # (nu,)
    sensordata: np.ndarray | None  # (nsensordata,)


class Dynamics:
    """Inverse and forward dynamics of a model at given states, on one reused MjData."""

    def __init__(self, model: mujoco.MjModel, *, outputs: frozenset[str]) -> None:
        unknown = outputs - OUTPUTS
        if unknown:
            raise ValueError(f"outputs must be among {sorted(OUTPUTS)}, got {sorted(unknown)}")
        self._model = model
        self._data = mujoco.MjData(model)
        self._inverse = "INVERSE_DYNAMICS" in outputs
        self._forward = "FORWARD_DYNAMICS" in outputs
        self._sensors = "SENSORS" in outputs and model.nsensordata > 0

    def forward_acceleration(
        self, *, qpos: np.ndarray, qvel: np.ndarray, ctrl: np.ndarray | None, act: np.ndarray | None = None
    ) -> np.ndarray:
        """qacc of mj_forward at (qpos, qvel) under `ctrl` (zero when None); shape (nv,)."""
        self._set_state(qpos, qvel, ctrl, act)
        mujoco.mj_forward(self._model, self._data)
        qacc: np.ndarray = self._data.qacc.copy()  # mujoco's bindings are untyped
        return qacc

    def compute(
        self,
        *,
        qpos: np.ndarray,
        qvel: np.ndarray,
        qacc: np.ndarray,
        ctrl: np.ndarray | None,
        act: np.ndarray | None = None,
    ) -> DynamicsResult:
        """The outputs at one state. `ctrl` (nu,) and `act` (na,) default to zero."""
        model, data = self._model, self._data
        qfrc_inverse = qacc_forward = actuator_force = sensordata = None
        if self._forward or self._sensors:
            self._set_state(qpos, qvel, ctrl, act)
            mujoco.mj_forward(model, data)
            if self._forward:
                qacc_forward = data.qacc.copy()
                actuator_force = data.actuator_force.copy()
            if self._sensors:
                sensordata = data.sensordata.copy()
        if self._inverse:
            self._set_state(qpos, qvel, ctrl, act)
            data.qacc[:] = qacc
            mujoco.mj_inverse(model, data)
            qfrc_inverse = data.qfrc_inverse.copy()
        return DynamicsResult(
            qfrc_inverse=qfrc_inverse,
            qacc_forward=qacc_forward,
            actuator_force=actuator_force,
            sensordata=sensordata,
        )

    def _set_state(
        self, qpos: np.ndarray, qvel: np.ndarray, ctrl: np.ndarray | None, act: np.ndarray | None
    ) -> None:
        data = self._data
        data.qpos[:] = qpos
        data.qvel[:] = qvel
        if ctrl is None:
            data.ctrl[:] = 0.0
        else:
            data.ctrl[:] = ctrl
        if act is None:
            data.act[:] = 0.0
        else:
            data.act[:] = act
