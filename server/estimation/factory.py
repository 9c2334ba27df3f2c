"""Making the estimator a configuration names, and pricing one tick of it. Apart from
`interface.py` and `config.py`, so that the implementations can import those without a cycle.
"""

from __future__ import annotations

import time

import mujoco
import numpy as np

from jitdyn.server.estimation.config import EstimatorConfig, check_against_model
from jitdyn.server.estimation.deadreckoning import DeadReckoning
from jitdyn.server.estimation.interface import Estimator, Measurement
from jitdyn.server.estimation.linearised import LinearisedFilter
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.estimation.switch import SwitchingFilter
from jitdyn.server.estimation.ukf import UnscentedFilter
from jitdyn.vocabulary import Channel, EstimatorKind, Scenario, WrongModel

__all__ = ["make_estimator", "measure_cycle"]


def make_estimator(model: mujoco.MjModel, config: EstimatorConfig, *, pool: WorkerPool) -> Estimator:
    """The estimator `config` names, built whole for `model` on the shared `pool`."""
    check_against_model(model, config)
    if config.estimator == EstimatorKind.UKF:
        if config.scenario == Scenario.PASSIVE and config.wrong_model == WrongModel.DRIVEN:
            return SwitchingFilter(model, config, pool=pool)
        return UnscentedFilter(model, config, pool=pool)
    if config.estimator == EstimatorKind.EKF:
        return LinearisedFilter(model, config)
    return DeadReckoning(model, config)


def measure_cycle(
    model: mujoco.MjModel, config: EstimatorConfig, *, pool: WorkerPool, repeats: int = 3
) -> float:
    """Seconds one tick of `config`'s estimator takes here (predict and update), the fastest of
    `repeats`, on a throwaway estimator started at the model's rest pose: what admission control
    charges a session before its own ticks are measured.

    Timed in this thread's CPU time: opens run in a thread beside the event loop, and the GIL
    handed back and forth around every MuJoCo call would otherwise be counted as the filter's
    (a 0.4 ms cycle measured at 30 ms on a loaded server, refusing sessions it could carry). The
    pool's other threads are not counted; a set small enough to stay on the calling thread, which
    is every model at the default MIN_CHUNK_SECONDS but the largest, is counted whole."""
    estimator = make_estimator(model, config, pool=pool)
    zeros = np.zeros(model.nv)
    measurement = Measurement(
        qpos=model.qpos0.copy(),
        qvel=zeros if Channel.QVEL in config.measured else None,
        qacc=zeros if Channel.QACC in config.measured else None,
        ctrl=np.zeros(model.nu) if Channel.CTRL in config.measured else None,
    )
    estimator.initialise(measurement)
    ctrl = np.zeros(model.nu) if config.scenario == Scenario.CONTROLLED else None
    best = float("inf")
    for _ in range(repeats):
        started = time.thread_time()
        estimator.step(ctrl=ctrl, m=measurement)
        best = min(best, time.thread_time() - started)
    return best
