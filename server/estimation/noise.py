"""The UKF's noise model: its process noise Q over any span, its initial covariance P0, and which
components of Q the adaptive noise may scale, for one session's model and settings::

    noise = UkfNoise.of(model, data, config)      # the mass matrix's diagonal read once, at qpos0
    Q = noise.process_noise(config.dt)              # (n, n)
    P0 = noise.initial_covariance()

[q, qd] (and qdd in CONTROLLED) take filterpy's discrete white noise, a block per dof; in DRIVEN the
unknown force f is a random walk, f' = f + w with Var w = force_var m_ii^2 dt (m_ii the dof's mass
matrix diagonal), or an integrated random walk of (f, fd) with the same intensity on fd.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

import mujoco
import numpy as np
from filterpy.common import Q_discrete_white_noise

from jitdyn.server.estimation.config import EstimatorConfig
from jitdyn.server.estimation.layout import derivative_order, force_blocks
from jitdyn.vocabulary import Scenario

__all__ = ["FORCE_P0_ACCELERATION", "FORCE_RATE_P0_JERK", "UkfNoise", "process_noise"]

# DRIVEN's initial uncertainty of the unknown force (and its rate), as the acceleration it would
# give each dof alone: 10 rad/s^2 (or m/s^2), 100 rad/s^3; scaled by the mass matrix's diagonal.
FORCE_P0_ACCELERATION: Final = 10.0
FORCE_RATE_P0_JERK: Final = 100.0


def process_noise(*, order: int, dt: float, var: float, nv: int) -> np.ndarray:
    """filterpy's discrete white-noise Q, one block per dof, in jitdyn's layout.

    filterpy's order_by_dim=True lays a dof's derivatives together, [q0, qd0, q1, qd1, ...];
    jitdyn's state is [q0, q1, ..., qd0, qd1, ...], which is filterpy's order_by_dim=False (its
    "order by derivative" permutation). Returns (order nv, order nv).
    """
    return np.asarray(
        Q_discrete_white_noise(dim=order, dt=dt, var=var, block_size=nv, order_by_dim=False), dtype=np.float64
    )


def mass_diagonal(model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
    """(nv,) the mass matrix's diagonal at qpos0 (kg, kg m^2): the scale of a dof's force. Leaves
    `data` at qpos0, at rest."""
    data.qpos[:] = model.qpos0
    data.qvel[:] = 0.0
    mujoco.mj_forward(model, data)
    full = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, full)
    return np.asarray(np.diagonal(full).copy())


@dataclass(frozen=True)
class UkfNoise:
    """Q and P0 of one session's UKF, in the tangent layout (n = (order + fblocks) nv)."""

    nv: int
    order: int  # derivatives of q per dof in the state: 2, or 3 in CONTROLLED
    fblocks: int  # DRIVEN: 1 (f) or 2 (f, fd); else 0
    q_var: float
    force_var: float
    p0: float
    mass: np.ndarray  # (nv,) the mass matrix's diagonal at qpos0

    @classmethod
    def of(cls, model: mujoco.MjModel, data: mujoco.MjData, config: EstimatorConfig) -> UkfNoise:
        scenario = Scenario(config.scenario)
        return cls(
            nv=int(model.nv),
            order=derivative_order(scenario),
            fblocks=force_blocks(scenario, config.force_model),
            q_var=config.q_var,
            force_var=config.force_var,
            p0=config.p0,
            mass=mass_diagonal(model, data),
        )

    @property
    def n(self) -> int:
        return (self.order + self.fblocks) * self.nv

    def adapt_q_mask(self) -> np.ndarray:
        """(n,) the components whose Q adapts: all but the unknown force's. The force's corrections
        are its real changes, large for a driven body; a Q matched to them spreads the sigma points
        so wide that the predicted mean leaves the motion's path (measured: docs/experiments.md)."""
        return np.full(self.n, self.fblocks == 0, dtype=bool)

    def process_noise(self, dt: float) -> np.ndarray:
        """Q over dt (n, n): the discrete white-noise blocks of [q, qd] (and qdd), then the unknown
        force's (DRIVEN)."""
        base = process_noise(order=self.order, dt=dt, var=self.q_var, nv=self.nv)
        if self.fblocks == 0:
            return base
        nv, k = self.nv, self.order * self.nv
        Q = np.zeros((self.n, self.n))
        Q[:k, :k] = base
        intensity = self.force_var * self.mass**2
        f = np.arange(k, k + nv)
        if self.fblocks == 1:
            Q[f, f] = intensity * dt
        else:
            fd = f + nv
            Q[f, f] = intensity * dt**3 / 3.0
            Q[f, fd] = Q[fd, f] = intensity * dt**2 / 2.0
            Q[fd, fd] = intensity * dt
        return Q

    def initial_covariance(self) -> np.ndarray:
        """P0: p0 I on [q, qd] (and qdd); in DRIVEN the force's uncertainty as an acceleration of
        FORCE_P0_ACCELERATION (its rate's as FORCE_RATE_P0_JERK) on each dof alone."""
        diagonal = np.full(self.n, self.p0)
        k, nv = self.order * self.nv, self.nv
        if self.fblocks:
            diagonal[k : k + nv] = (FORCE_P0_ACCELERATION * self.mass) ** 2
            if self.fblocks == 2:
                diagonal[k + nv :] = (FORCE_RATE_P0_JERK * self.mass) ** 2
        return np.diag(diagonal)
