"""The compiled filter (ukf.cc) behind the surface estimation/fast.py's FastUKF gives
UnscentedFilter, for plain vector states and states on a manifold alike: x, P, Q and R read and written as arrays, predict() and update(z), and what an
update leaves for the adaptive noise (y, K, S, SI). The process model's inputs (activations,
control, the restored force) are handed over before each predict.

    kf = NativeUKF(model, points=points, z_index=slice(0, 4), nstep=2, inputs=Inputs.NONE,
                   fblocks=0, controlled=False)
    kf.x, kf.P = x0, P0
    kf.predict()
    kf.update(z)
"""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np

from jitdyn.errors import InvalidArgument
from jitdyn.server.estimation.manifold import SplitManifold
from jitdyn.server.estimation.native import SingularMatrix, Ukf
from jitdyn.server.estimation.propagate import Inputs
from jitdyn.server.estimation.sigma import MerweScaled, Simplex, UniformSpherical

__all__ = ["NativeUKF"]

_SCHEMES = {MerweScaled: 0, Simplex: 1, UniformSpherical: 2}
_INPUTS = {Inputs.NONE: 0, Inputs.CTRL: 1, Inputs.QFRC: 2}


def _native_array(name: str, *, writable: bool = True) -> Any:
    """A property of NativeUKF that reads (copies out) and writes (copies in) the filter's array."""

    def get(self: NativeUKF) -> np.ndarray:
        return np.asarray(getattr(self._ukf, name))

    def set_(self: NativeUKF, value: np.ndarray) -> None:
        setattr(self._ukf, name, np.asarray(value, dtype=np.float64))

    return property(get, set_ if writable else None)


class NativeUKF:
    """FastUKF's surface over ukf.cc's filter (module docstring). manifold: the state's
    (ball and free joints), whose mean and residual an extrapolation in Python uses."""

    # filterpy's unscented_transform takes these for states on a manifold; a vector state has none.
    x_mean: Any = None
    residual_x: Any = None

    def __init__(
        self,
        model: mujoco.MjModel,
        *,
        points: MerweScaled | Simplex | UniformSpherical,
        z_index: slice | np.ndarray,
        nstep: int,
        inputs: Inputs,
        fblocks: int,
        controlled: bool,
        manifold: SplitManifold | None = None,
    ) -> None:
        scheme = _SCHEMES.get(type(points))
        if scheme is None:
            raise InvalidArgument(
                f"points must be one of {[s.__name__ for s in _SCHEMES]}, got {type(points)}"
            )
        n = int(points.n)
        size = int(model.nq) + n - int(model.nv)  # len(x): qpos, then the tangent's rest
        if isinstance(z_index, slice):
            z = list(range(*z_index.indices(size)))
        else:
            z = [int(i) for i in z_index]
        self._model = model  # the compiled filter holds its pointer: keep it alive
        self._inputs: tuple[np.ndarray | None, ...] = (None, None, None)
        self.Wm, self.Wc = points.Wm, points.Wc
        if manifold is not None:  # for the tangent unscented transform of an extrapolation
            self.x_mean, self.residual_x = manifold.mean, manifold.residual
        self._ukf = Ukf(
            model._address,
            n=n,
            size=size,
            fblocks=fblocks,
            controlled=controlled,
            scheme=scheme,
            scale=float(getattr(points, "_scale", 1.0)),
            unit=points.unit if isinstance(points, Simplex) else np.zeros((0, 0)),
            wm=points.Wm,
            wc=points.Wc,
            z_index=z,
            nstep=nstep,
            inputs=_INPUTS[inputs],
        )

    def set_inputs(self, *, act: np.ndarray, ctrl: np.ndarray, qfrc: np.ndarray) -> None:
        """What acts on the points over the next predict: act (na,), ctrl (nu,), qfrc (nv,).
        Arrays handed over before are not copied again: callers replace their inputs, never
        write into them."""
        u = self._ukf
        if act is not self._inputs[0]:
            u.act = act
        if ctrl is not self._inputs[1]:
            u.ctrl = ctrl
        if qfrc is not self._inputs[2]:
            u.qfrc = qfrc
        self._inputs = (act, ctrl, qfrc)

    def held_act(self, act: np.ndarray) -> None:
        """act (na,) is what the compiled filter holds now (a native tick set it): handed over
        again by set_inputs, it is not copied."""
        self._inputs = (act, self._inputs[1], self._inputs[2])

    @property
    def native(self) -> Ukf:
        """The compiled filter, for native/tick.py."""
        return self._ukf

    def tidy(self) -> bool:
        """Whether x and P are finite; if so P symmetrised, and repaired when indefinite."""
        return bool(self._ukf.tidy())

    def largest_variance(self) -> float:
        return float(self._ukf.largest_variance())

    @property
    def nis(self) -> float:
        """y' S^-1 y of the last update."""
        return float(self._ukf.nis)

    def forward(
        self, qpos: np.ndarray, qvel: np.ndarray, *, act: np.ndarray, ctrl: np.ndarray, qfrc: np.ndarray
    ) -> np.ndarray:
        """qacc (nv,) by mj_forward at (qpos, qvel, act) under ctrl and qfrc_applied."""
        return np.asarray(self._ukf.forward(qpos, qvel, act, ctrl, qfrc))

    @property
    def propagated_act(self) -> np.ndarray:
        """(na,) the weighted mean of the points' activations after the last propagation."""
        return np.asarray(self._ukf.propagated_act)

    @property
    def repairs(self) -> int:
        """Indefinite covariances repaired while drawing sigma points here."""
        return int(self._ukf.repairs)

    def predict(self, **_: Any) -> None:
        self._ukf.predict()

    def update(self, z: np.ndarray, **_: Any) -> None:
        try:
            self._ukf.update(np.asarray(z, dtype=np.float64))
        except SingularMatrix as error:
            raise np.linalg.LinAlgError(str(error)) from None

    def propagate(self, sigmas: np.ndarray, *, nstep: int | None) -> np.ndarray:
        """The process model on a sigma set (count, n), nstep physics steps (None: a tick's)."""
        return np.asarray(self._ukf.propagate(sigmas, self._nstep if nstep is None else nstep))

    @property
    def _nstep(self) -> int:
        return int(self._ukf.nstep)

    x = _native_array("x")
    P = _native_array("P")
    Q = _native_array("Q")
    R = _native_array("R")
    sigmas_f = _native_array("sigmas_f")
    y = _native_array("y", writable=False)
    K = _native_array("K", writable=False)
    S = _native_array("S", writable=False)
    SI = _native_array("SI", writable=False)
