"""DRIVEN under SIMPLEX_LINEAR_FORCE: the sigma points span s = [q, qd] only, each under the force's
mean given its s; what the force has of its own (its covariance given s) acts through B, the
tick's response of [q, qd] to a generalized force, linearised at the mean (`force_response`).
Exact where the force enters linearly (tested against the full simplex on such a model); a third
fewer physics steps. The measurement is linear in the state, so its update is the Kalman filter's
(what the unscented update computes for it).

    kf = LinearForceUKF(motion=2 * nv, propagate_forced=..., response=..., z_index=slice(0, 2 * nv),
                        propagate=..., vector=True, **filterpy_kwargs)
"""

from __future__ import annotations

from typing import Protocol

import mujoco
import numpy as np
from scipy.linalg.lapack import dtrtrs

from jitdyn.server.estimation.batched import BatchedUKF, SigmaPropagation
from jitdyn.server.estimation.sigma import Simplex

__all__ = ["ForceResponse", "ForcedPropagation", "LinearForceUKF", "force_response"]


class ForcedPropagation(Protocol):
    """[q, qd] points (m, 2 nv), each under its own force (m, nv), nstep physics steps on (None: a
    tick's) -> (m, 2 nv)."""

    def __call__(self, chi: np.ndarray, forces: np.ndarray, *, nstep: int | None) -> np.ndarray: ...


class ForceResponse(Protocol):
    """B (2 nv, nv) at s = [q, qd] under force f over nstep physics steps (None: a tick's)."""

    def __call__(self, s: np.ndarray, f: np.ndarray, *, nstep: int | None) -> np.ndarray: ...


class LinearForceUKF(BatchedUKF):
    """x = [s, f], s = [q, qd] (motion = len s), f the force (nv); the points are simplex points of
    s. propagate_forced and response are the process model's; z_index picks the measured entries
    of x."""

    x: np.ndarray
    P: np.ndarray

    def __init__(
        self,
        *,
        motion: int,
        propagate_forced: ForcedPropagation,
        response: ForceResponse,
        z_index: slice | np.ndarray,
        propagate: SigmaPropagation,
        vector: bool,
        **kwargs: object,
    ) -> None:
        super().__init__(propagate=propagate, vector=vector, **kwargs)
        self._k = motion
        self._propagate_forced = propagate_forced
        self._response = response
        self._z_index = z_index

    def prior(self, x: np.ndarray, P: np.ndarray, *, nstep: int | None) -> tuple[np.ndarray, np.ndarray]:
        """Mean (len x) and covariance (n, n) after nstep physics steps, before process noise.

        With U the upper factor of Pss, the force given s is f + G' U^-T (s - s_mean), G = U^-T Psf,
        with covariance Pff - G'G; a simplex point s + U' e carries f + G' e. Its propagation gives
        the part of [s', f] that moves with s; B (Pff - G'G) B' and (Pff - G'G) B' add the rest.
        """
        k = self._k
        s, f = x[:k], x[k:]
        Pss, Psf, Pff = P[:k, :k], P[:k, k:], P[k:, k:]
        U = self.msqrt(Pss)
        G, info = dtrtrs(U, Psf, lower=0, trans=1)
        if info != 0 or not np.all(np.isfinite(U)):
            G = np.full_like(Psf, np.nan)  # a poisoned factor: the divergence guard restarts
        points: Simplex = self.points_fn
        chi = points.from_factor(s, U)
        forces = f + (G.T @ points.unit).T
        moved = self._propagate_forced(chi, forces, nstep=nstep)
        mean = self.Wm @ moved
        spread = moved - mean
        weighted = self.Wc[:, None] * spread
        rest = Pff - G.T @ G
        B = self._response(s, f, nstep=nstep)
        BR = B @ rest
        out = np.empty_like(P)
        out[:k, :k] = spread.T @ weighted + BR @ B.T
        out[:k, k:] = weighted.T @ (forces - f) + BR
        out[k:, :k] = out[:k, k:].T
        out[k:, k:] = Pff
        self.sigmas_f = moved
        return np.concatenate([mean, f]), out

    def predict(self, dt: object = None, UT: object = None, fx: object = None, **fx_args: object) -> None:
        x, P = self.prior(np.asarray(self.x), np.asarray(self.P), nstep=None)
        self.x, self.P = x, P + self.Q
        self.x_prior = np.copy(self.x)
        self.P_prior = np.copy(self.P)

    def update(
        self, z: np.ndarray, R: object = None, UT: object = None, hx: object = None, **hx_args: object
    ) -> None:
        index = self._z_index
        x, P = self.x, self.P
        PHt = P[:, index]
        self.S = PHt[index] + self.R
        self.SI = self.inv(self.S)
        self.K = PHt @ self.SI
        self.y = z - x[index]
        self.x = x + self.K @ self.y
        self.P = P - self.K @ (self.S @ self.K.T)
        self.z = np.array(z)
        self.x_post = self.x.copy()
        self.P_post = self.P.copy()


def force_response(
    model: mujoco.MjModel, data: mujoco.MjData, s: np.ndarray, f: np.ndarray, *, act: np.ndarray, nstep: int
) -> np.ndarray:
    """B = d[q', qd'] / df (2 nv, nv) over nstep physics steps from s = [q, qd] under force f, with
    activations act (na,); `data` is scratch.

    The acceleration's response to a generalized force is H^-1, H = M + J' D J over the
    constraint rows active at s (their Hessian in MuJoCo's primal problem; M alone when none
    is); Euler's implicit damping then maps it through (M + h diag(damping))^-1 M. n
    semi-implicit Euler steps of h with that response held give qd' = n h A f and
    q' = h^2 n (n + 1) / 2 A f."""
    m, d = model, data
    nq, nv = int(m.nq), int(m.nv)
    d.qpos[:], d.qvel[:], d.act[:], d.ctrl[:], d.qfrc_applied[:] = s[:nq], s[nq:], act, 0.0, f
    mujoco.mj_forward(m, d)
    M = np.zeros((nv, nv))
    mujoco.mj_fullM(m, d, M)
    H = M.copy()
    active = np.flatnonzero(d.efc_state == int(mujoco.mjtConstraintState.mjCNSTRSTATE_QUADRATIC))
    if active.size:
        J = _constraint_jacobian(m, d)[active]
        H += J.T @ (d.efc_D[active][:, None] * J)
    A = np.linalg.inv(H)
    h = float(m.opt.timestep)
    damping = m.dof_damping
    if (
        int(m.opt.integrator) == int(mujoco.mjtIntegrator.mjINT_EULER)
        and np.any(damping > 0)
        and not int(m.opt.disableflags) & int(mujoco.mjtDisableBit.mjDSBL_EULERDAMP)
    ):
        A = np.linalg.solve(M + h * np.diag(damping), M @ A)
    B = np.empty((2 * nv, nv))
    B[:nv] = (h * h * nstep * (nstep + 1) / 2.0) * A
    B[nv:] = (nstep * h) * A
    return B


def _constraint_jacobian(m: mujoco.MjModel, d: mujoco.MjData) -> np.ndarray:
    """(nefc, nv) the constraint Jacobian, dense whatever MuJoCo keeps."""
    if not mujoco.mj_isSparse(m):
        return np.asarray(d.efc_J).reshape(d.nefc, m.nv)
    J = np.zeros((d.nefc, m.nv))
    mujoco.mju_sparse2dense(J, d.efc_J, d.efc_J_rownnz, d.efc_J_rowadr, d.efc_J_colind)
    return J
