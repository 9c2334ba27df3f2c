"""From a run's trace to the thesis' numbers: aRMSE per component and per joint, average NEES and
NIS against their chi-square intervals, gap errors. Pure functions of a `Trace`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from jitdyn.experiments.metrics import Consistency, armse, consistency, gap_error_profile, nees, rmse
from jitdyn.experiments.runner import Trace

__all__ = ["RunMetrics", "components", "gap_profile", "summarise"]


@dataclass(frozen=True)
class RunMetrics:
    """The numbers of one run. Per-joint arrays are (nv,); None where the run has no such block."""

    label: str
    armse: dict[
        str, float
    ]  # "q", "qd" and, CONTROLLED, "qdd" -> aRMSE (mean over joints of the RMSE over time)
    per_joint: dict[str, np.ndarray]  # the same blocks -> RMSE over time per joint
    settled: dict[str, float]  # the aRMSE of the ticks from `settle` seconds on (the filter's start left out)
    nees: Consistency | None  # None for the dead-reckoning estimators (no covariance)
    nis: Consistency | None  # None when no tick used a measurement
    ticks: int
    reinitialised: int
    mean_compute_us: float
    diverged_at: float | None  # first time (s) the q error passed 1 rad (or m); None if never


def components(trace: Trace) -> tuple[str, ...]:
    return ("q", "qd", "qdd")[: trace.nx // trace.nv]


def summarise(trace: Trace, *, corrected: bool = False, settle: float = 1.0) -> RunMetrics:
    """The metrics of a run over every tick that had an estimate (tick 0 included: x0 = the truth).

    `settled` leaves out the first `settle` seconds (of a shorter run, its first half), where
    P0 = 0.2 I (the filter's belief that it does not know x0) biases the unscented predictions.
    """
    per_joint: dict[str, np.ndarray] = {}
    averages: dict[str, float] = {}
    settled: dict[str, float] = {}
    late = trace.t >= min(settle, trace.t[-1] / 2) - 1e-9
    for block in components(trace):
        truth, estimate = trace.component(block, corrected=corrected)
        per_joint[block] = rmse(truth, estimate)
        averages[block] = armse(truth, estimate)
        settled[block] = armse(truth[late], estimate[late])
    nees_c: Consistency | None = None
    if trace.covariance is not None and not corrected:
        finite = np.all(np.isfinite(trace.estimate), axis=1)
        if finite.any():
            values = nees(trace.truth_state[finite] - trace.estimate[finite], trace.covariance[finite])
            if np.isfinite(values).any():
                nees_c = consistency(values, dof=trace.nx)
    nis_c: Consistency | None = None
    if np.isfinite(trace.nis).any() and trace.measurement_dim > 0:
        nis_c = consistency(trace.nis, dof=trace.measurement_dim)
    q_truth, q_est = trace.component("q", corrected=corrected)
    q_err = np.abs(q_truth - q_est).max(axis=1)
    over = np.nonzero(~(q_err < 1.0))[0]  # NaN (a diverged filter) counts as over
    return RunMetrics(
        label=trace.spec.label,
        armse=averages,
        per_joint=per_joint,
        settled=settled,
        nees=nees_c,
        nis=nis_c,
        ticks=int(trace.t.size),
        reinitialised=trace.reinitialised,
        mean_compute_us=float(np.mean(trace.compute_us[1:])) if trace.t.size > 1 else float("nan"),
        diverged_at=float(trace.t[over[0]]) if over.size else None,
    )


def gap_profile(trace: Trace) -> dict[int, float]:
    """The q error of the answers at the tick against the ticks since the last frame."""
    truth, estimate = trace.component("q")
    return gap_error_profile(truth, estimate, trace.received)
