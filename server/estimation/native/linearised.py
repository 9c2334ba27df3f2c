"""The compiled tick of the linearised filter (linearised.cc) behind PythonTick's surface
(server/estimation/linearised.py): predict and update on arrays the caller holds, the GIL
released while they run.

    tick = NativeTick(process, driven=True, nstep=1, Q=Q, R=R)
    x, P, act = tick.predict(x, P, act, qfrc)
"""

from __future__ import annotations

from typing import Final

import mujoco
import numpy as np

from jitdyn.server.estimation.native import _ukf

__all__ = ["EPS", "FORCE_EPS", "NativeTick"]

# mjd_transitionFD's step, and the force columns' (times max(1, |f_i|)), in both engines: a step
# of 1e-6 (MuJoCo MPC's) made the engines part at 1e-8, the rounding of each difference grown
# through P (docs/decisions/0210-the-linearised-filter-as-a-candidate.md).
EPS: Final = 1e-4
FORCE_EPS: Final = 1e-4


class NativeTick:
    """linearised.cc's Ekf on `model`, the EKF's process model, and `linearised`, what
    mjd_transitionFD differentiates; this keeps both alive (the compiled filter holds pointers)."""

    def __init__(
        self,
        model: mujoco.MjModel,
        *,
        linearised: mujoco.MjModel,
        driven: bool,
        nstep: int,
        Q: np.ndarray,
        R: np.ndarray,
    ) -> None:
        self._models = (model, linearised)
        self._ekf = _ukf.Ekf(
            model._address,
            linearised._address,
            driven=driven,
            nstep=nstep,
            Q=np.asarray(Q, dtype=np.float64),
            R=np.asarray(R, dtype=np.float64),
            eps=EPS,
            force_eps=FORCE_EPS,
        )

    def predict(
        self, x: np.ndarray, P: np.ndarray, act: np.ndarray, qfrc: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self._ekf.predict(x, P, act, qfrc)

    def update(self, x: np.ndarray, P: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        return self._ekf.update(x, P, z)
