"""One UKF's numeric steps, the interface both engines implement: the native one
(native/filter.py, on MuJoCo's C API) and the Python one here (numpy and filterpy), which the
native one is held to (tests/server/test_native.py). UnscentedFilter (estimation/ukf.py) runs a
tick through these steps and through the steps both engines share (the guard, the adaptive noise,
the forecasts, the estimate: estimation/ukf.py's table says where each is); estimation/parts.py
picks the core of the configured engine.

    core.set_inputs(act=act, ctrl=ctrl, qfrc=qfrc)   # what acts on the points over the tick
    core.predict()                                    # sigma points, propagation, transform
    core.update(z)                                    # the measurement's correction; core.nis
    nis = correct(core, z, size=len(x))               # the same, a singular S a NaN state
    finite = core.tidy()                              # P symmetrised, repaired when indefinite
    qacc = core.forward(qpos, qvel, act=act, ctrl=ctrl, qfrc=qfrc)

| step | Python (PythonCore) | native (ukf.cc) |
|---|---|---|
| sigma points | estimation/sigma.py | Ukf::SigmaPoints |
| propagation | estimation/process.py | Ukf::Propagate |
| unscented transform, update | estimation/fast.py, batched.py (filterpy's) | Ukf::Predict, Ukf::Update |
| tidy, repair | PythonCore.tidy | Ukf::Tidy |
| forward dynamics | PythonCore.forward | Ukf::Forward |

Both take their Q and P0 from estimation/noise.py (UkfNoise), and their adaptive noise from
estimation/adaptive.py or native/adaptive.py.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import mujoco
import numpy as np

from jitdyn.server.estimation.batched import BatchedUKF
from jitdyn.server.estimation.process import SigmaProcess
from jitdyn.server.estimation.sigma import cholesky_upper, nearest_positive_definite

__all__ = ["FilterCore", "PythonCore", "correct"]


class FilterCore(Protocol):
    """The steps of one UKF (module docstring), and its state: x, P, the noises Q and R, the
    propagated sigma points, and what an update leaves for the adaptive noise (y, K, SI)."""

    x: np.ndarray
    P: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    sigmas_f: np.ndarray
    x_mean: Any  # filterpy's mean and residual of x on a manifold, None for a vector state
    residual_x: Any

    @property
    def y(self) -> np.ndarray: ...
    @property
    def K(self) -> np.ndarray: ...
    @property
    def SI(self) -> np.ndarray: ...
    @property
    def nis(self) -> float: ...
    @property
    def propagated_act(self) -> np.ndarray: ...
    @property
    def repairs(self) -> int: ...

    def set_inputs(self, *, act: np.ndarray, ctrl: np.ndarray, qfrc: np.ndarray) -> None: ...
    def predict(self) -> None: ...
    def update(self, z: np.ndarray) -> None: ...
    def tidy(self) -> bool: ...
    def largest_variance(self) -> float: ...
    def forward(
        self, qpos: np.ndarray, qvel: np.ndarray, *, act: np.ndarray, ctrl: np.ndarray, qfrc: np.ndarray
    ) -> np.ndarray: ...


def correct(kf: FilterCore, z: np.ndarray, *, size: int) -> float | None:
    """kf's update with measurement z; its NIS, None when not finite. An innovation covariance
    that cannot be inverted leaves nothing of the update usable: x (size,) turns NaN."""
    try:
        kf.update(z)
        nis = kf.nis
    except np.linalg.LinAlgError:
        kf.x = np.full(size, np.nan)
        nis = float("nan")
    return nis if np.isfinite(nis) else None


def _passed(name: str) -> Any:
    """A property of PythonCore that reads and writes the wrapped filter's attribute."""

    def get(self: PythonCore) -> Any:
        return getattr(self.inner, name)

    def set_(self: PythonCore, value: Any) -> None:
        setattr(self.inner, name, value)

    return property(get, set_)


class PythonCore:
    """FilterCore in Python: `inner`, filterpy's filter (BatchedUKF), its faster FastUKF or the
    LinearForceUKF, predicting with `process`'s propagation; `ut` the unscented transform
    (filterpy's, or the tangent one on a manifold); mj_forward on `data`."""

    def __init__(
        self,
        inner: BatchedUKF,
        *,
        process: SigmaProcess,
        ut: Callable[..., tuple[np.ndarray, np.ndarray]],
        model: mujoco.MjModel,
        data: mujoco.MjData,
    ) -> None:
        self.inner = inner
        self._process = process
        self._ut = ut
        self._model, self._data = model, data
        self._repairs = 0

    x = _passed("x")
    P = _passed("P")
    Q = _passed("Q")
    R = _passed("R")
    sigmas_f = _passed("sigmas_f")
    x_mean = _passed("x_mean")
    residual_x = _passed("residual_x")
    y = _passed("y")
    K = _passed("K")
    SI = _passed("SI")

    @property
    def nis(self) -> float:
        """y' S^-1 y of the last update."""
        y, SI = self.inner.y, self.inner.SI
        return float(y @ SI @ y)

    @property
    def propagated_act(self) -> np.ndarray:
        return self._process.propagated_act

    @property
    def repairs(self) -> int:
        """Indefinite covariances repaired by tidy() (the sigma points' own: RobustCholesky)."""
        return self._repairs

    def set_inputs(self, *, act: np.ndarray, ctrl: np.ndarray, qfrc: np.ndarray) -> None:
        self._process.set_inputs(act=act, ctrl=ctrl, qfrc=qfrc)

    def predict(self) -> None:
        self.inner.predict(UT=self._ut)

    def update(self, z: np.ndarray) -> None:
        self.inner.update(z, UT=self._ut)

    def tidy(self) -> bool:
        """Whether x and P are finite; if so P symmetrised, and repaired when indefinite."""
        kf = self.inner
        finite = bool(np.isfinite(kf.x).all() and np.isfinite(kf.P).all())
        if finite:
            kf.P = np.asarray(0.5 * (kf.P + kf.P.T))
            if cholesky_upper(kf.P) is None:
                self._repairs += 1
                kf.P = nearest_positive_definite(kf.P)
        return finite

    def largest_variance(self) -> float:
        return float(self.inner.P.diagonal().max())

    def forward(
        self, qpos: np.ndarray, qvel: np.ndarray, *, act: np.ndarray, ctrl: np.ndarray, qfrc: np.ndarray
    ) -> np.ndarray:
        """qacc (nv,) by mj_forward at (qpos, qvel, act) under ctrl and qfrc_applied (warm start
        off: no hidden state)."""
        d = self._data
        d.qpos[:], d.qvel[:], d.act[:] = qpos, qvel, act
        d.ctrl[:] = ctrl
        d.qfrc_applied[:] = qfrc
        mujoco.mj_forward(self._model, d)
        return np.array(d.qacc)
