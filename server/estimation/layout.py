"""The layout of an estimator's state in each scenario, and which sigma scheme it allows.

x = [q (nq), qd (nv)] in PASSIVE and EXTERNAL, [q, qd, qdd (nv)] in CONTROLLED, and for the UKF in
DRIVEN [q, qd, f (nv)] (force model RANDOM_WALK) or [q, qd, f, fd (nv)] (INTEGRATED_RANDOM_WALK),
f the unknown generalized force. Covariances live in the tangent space, (k nv, k nv) with k = 2, 3
or 4, which differs from len(x) only for models with ball or free joints (estimation/manifold.py)::

    state_dimension(model, Scenario.DRIVEN, ForceModel.RANDOM_WALK)     # 3 nv
"""

from __future__ import annotations

import mujoco

from jitdyn.server.estimation.manifold import has_manifold
from jitdyn.vocabulary import ForceModel, Scenario

__all__ = ["derivative_order", "force_blocks", "linear_force_applies", "state_dimension"]


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
