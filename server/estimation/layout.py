"""The layout of an estimator's state in each scenario, and which sigma scheme it allows.

x = [q (nq), qd (nv)] in PASSIVE and EXTERNAL, [q, qd, qdd (nv)] in CONTROLLED, and for the UKF in
DRIVEN [q, qd, f (nv)] (force model RANDOM_WALK) or [q, qd, f, fd (nv)] (INTEGRATED_RANDOM_WALK),
f the unknown generalized force. Covariances live in the tangent space, (k nv, k nv) with k = 2, 3
or 4, which differs from len(x) only for models with ball or free joints (estimation/manifold.py)::

    state_dimension(model, Scenario.DRIVEN, ForceModel.RANDOM_WALK)     # 3 nv
    layout = filter_layout(model, scenario=..., force_model=..., measured=..., linear=False)
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from jitdyn.server.estimation.manifold import has_manifold
from jitdyn.vocabulary import Channel, ForceModel, Scenario

__all__ = [
    "FilterLayout",
    "derivative_order",
    "filter_layout",
    "force_blocks",
    "linear_force_applies",
    "state_dimension",
]


def derivative_order(scenario: Scenario) -> int:
    """How many derivatives of q the state holds per dof: 2 ([q, qd]) or 3 ([q, qd, qdd])."""
    return 3 if scenario == Scenario.CONTROLLED else 2


def force_blocks(scenario: Scenario, force_model: ForceModel = ForceModel.RANDOM_WALK) -> int:
    """How many nv-blocks of unknown force the UKF's state holds: 0, or in DRIVEN 1 (f) or 2 (f, fd)."""
    if scenario != Scenario.DRIVEN:
        return 0
    return 2 if force_model == ForceModel.INTEGRATED_RANDOM_WALK else 1


def state_dimension(
    model: mujoco.MjModel, scenario: Scenario, force_model: ForceModel = ForceModel.RANDOM_WALK
) -> int:
    """The tangent dimension of the UKF's state: 2 nv, 3 nv in CONTROLLED, 3 or 4 nv in DRIVEN."""
    return (derivative_order(scenario) + force_blocks(scenario, force_model)) * int(model.nv)


def linear_force_applies(model: mujoco.MjModel, scenario: Scenario, force_model: ForceModel) -> bool:
    """Whether SIMPLEX_LINEAR_FORCE keeps the force out of the sigma set here (else it is SIMPLEX):
    DRIVEN, the random walk, and a state that is a plain vector (no ball or free joints)."""
    return scenario == Scenario.DRIVEN and force_model == ForceModel.RANDOM_WALK and not has_manifold(model)


@dataclass(frozen=True, eq=False)
class FilterLayout:
    """Where everything sits in one UKF's state and measurement (estimation/layout.py), fixed for
    the filter's life."""

    scenario: Scenario
    nq: int
    nv: int
    na: int
    nu: int
    order: int  # derivative_order: 2 ([q, qd]) or 3 ([q, qd, qdd])
    fblocks: int  # force_blocks: 0, or in DRIVEN 1 (f) or 2 (f, fd)
    n: int  # tangent dimension, the side of P: filterpy's dim_x
    size: int  # len(x)
    z_index: slice | np.ndarray  # the measured entries of x: qpos, then qvel, then qacc
    z_size: int  # how many entries of x the measurement has
    z_tangent: int  # the measurement's tangent dimension
    manifold: bool  # ball or free joints: x lives on a manifold
    linear_force: bool  # SIMPLEX_LINEAR_FORCE keeps the force out of the sigma points
    measured: frozenset[str]

    @property
    def controlled(self) -> bool:
        return self.scenario == Scenario.CONTROLLED

    @property
    def driven(self) -> bool:
        return self.fblocks > 0

    def measures(self, channel: Channel) -> bool:
        """Whether the measurement holds `channel` (qacc only in CONTROLLED: no other state has qdd)."""
        if channel == Channel.QACC:
            return self.controlled and Channel.QACC in self.measured
        return channel in self.measured


def filter_layout(
    model: mujoco.MjModel,
    *,
    scenario: Scenario,
    force_model: ForceModel,
    measured: frozenset[str],
    linear: bool,
) -> FilterLayout:
    """The layout of a UKF on `model` (its process model) measuring the channels `measured`;
    linear: its sigma scheme is SIMPLEX_LINEAR_FORCE."""
    nq, nv = int(model.nq), int(model.nv)
    order = derivative_order(scenario)
    fblocks = force_blocks(scenario, force_model)
    index = list(range(nq))
    z_tangent = nv
    if Channel.QVEL in measured:
        index += range(nq, nq + nv)
        z_tangent += nv
    if scenario == Scenario.CONTROLLED and Channel.QACC in measured:
        index += range(nq + nv, nq + 2 * nv)
        z_tangent += nv
    # A slice when the measured entries are contiguous (qpos and qvel): cheaper than fancy
    # indexing in filterpy's per-point measurement loop.
    contiguous = index == list(range(len(index)))
    return FilterLayout(
        scenario=scenario,
        nq=nq,
        nv=nv,
        na=int(model.na),
        nu=int(model.nu),
        order=order,
        fblocks=fblocks,
        n=(order + fblocks) * nv,
        size=nq + (order - 1 + fblocks) * nv,
        z_index=slice(0, len(index)) if contiguous else np.array(index),
        z_size=len(index),
        z_tangent=z_tangent,
        manifold=has_manifold(model),
        linear_force=linear and linear_force_applies(model, scenario, force_model),
        measured=frozenset(measured),
    )
