"""Making the estimator a configuration names. Apart from `estimator.py`, which only declares the
interface and its settings, so that the implementations can import the interface without a cycle.
"""

from __future__ import annotations

import mujoco

from jitdyn.server.estimation.deadreckoning import DeadReckoning
from jitdyn.server.estimation.estimator import Estimator, EstimatorConfig, EstimatorKind, check_against_model
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.estimation.ukf import UnscentedFilter

__all__ = ["make_estimator"]


def make_estimator(model: mujoco.MjModel, config: EstimatorConfig, *, pool: WorkerPool) -> Estimator:
    """The estimator `config` names, built whole for `model` on the shared `pool`."""
    check_against_model(model, config)
    if config.estimator == EstimatorKind.UKF:
        return UnscentedFilter(model, config, pool=pool)
    return DeadReckoning(model, config)
