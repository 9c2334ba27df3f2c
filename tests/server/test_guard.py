"""The restart policy of the UKF (server/estimation/guard.py), driven alone: NIS values in,
decisions out."""

from __future__ import annotations

import pytest
from scipy.stats import chi2

from jitdyn.server.estimation.guard import (
    ABSORPTIONS_BEFORE_REINIT,
    COVARIANCE_LIMIT,
    DIVERGENCE_TICKS,
    NIS_LIMIT_PER_DIMENSION,
    RESTART_QUANTILE,
    RESTART_UPDATES,
    Guard,
    GuardState,
)

M = 4
FINE = {"finite": True, "largest_variance": 1.0}


def feed(guard: Guard, values: list[float | None]) -> list[bool]:
    decisions = []
    for nis in values:
        guard.count(nis)
        decisions.append(guard.restart_due(**FINE))
    return decisions


def test_a_consistent_nis_never_restarts() -> None:
    guard = Guard(m=M, restart=True, driven=False)
    assert feed(guard, [float(M)] * 100) == [False] * 100


def test_wrong_model_restart_needs_restart_updates_in_a_row_past_the_quantile() -> None:
    far = float(chi2.ppf(RESTART_QUANTILE, M)) * 1.01
    guard = Guard(m=M, restart=True, driven=False)
    assert feed(guard, [far, 1.0, far, 1.0]) == [False] * 4  # never twice in a row
    assert feed(guard, [far] * RESTART_UPDATES) == [False] * (RESTART_UPDATES - 1) + [True]
    # Without wrong_model RESTART the same NIS is left to the divergence guard.
    assert feed(Guard(m=M, restart=False, driven=False), [far] * 20) == [False] * 20


def test_divergence_needs_divergence_ticks_in_a_row_past_the_nis_limit() -> None:
    absurd = NIS_LIMIT_PER_DIMENSION * M * 2
    guard = Guard(m=M, restart=False, driven=False)
    assert guard.far_out(absurd) and not guard.far_out(NIS_LIMIT_PER_DIMENSION * M)
    assert not guard.far_out(None)
    assert feed(guard, [absurd] * (DIVERGENCE_TICKS - 1) + [1.0]) == [False] * DIVERGENCE_TICKS
    # A NIS that is not finite (None) counts as far out.
    assert feed(guard, [None] * DIVERGENCE_TICKS) == [False] * (DIVERGENCE_TICKS - 1) + [True]
    guard.start()
    assert guard.state == GuardState()


@pytest.mark.parametrize(
    ("finite", "largest", "expected"),
    [(True, COVARIANCE_LIMIT, False), (True, COVARIANCE_LIMIT * 10, True), (False, 1.0, True)],
)
def test_a_state_that_is_no_estimate_diverged(finite: bool, largest: float, expected: bool) -> None:
    guard = Guard(m=M, restart=False, driven=False)
    assert guard.diverged(finite=finite, largest_variance=largest) is expected
    assert guard.restart_due(finite=finite, largest_variance=largest) is expected


@pytest.mark.parametrize("driven", [False, True])
def test_absorptions_widen_until_they_restart_a_filter_that_is_not_driven(driven: bool) -> None:
    guard = Guard(m=M, restart=False, driven=driven)
    widen = [guard.absorb() for _ in range(ABSORPTIONS_BEFORE_REINIT)]
    assert widen == [True] * (ABSORPTIONS_BEFORE_REINIT - 1) + [driven]
    assert guard.restart_due(**FINE) is not driven
    guard.settle()  # a window back inside: the absorptions in a row start again
    assert not guard.restart_due(**FINE)


def test_state_restores_and_start_keeps_the_absorptions() -> None:
    guard = Guard(m=M, restart=True, driven=False)
    guard.absorb()
    feed(guard, [None])
    saved = guard.state
    assert saved == GuardState(nis_run=1, far_run=1, absorptions=1)
    guard.start()
    assert guard.state == GuardState(absorptions=1)
    guard.restore(saved)
    assert guard.state == saved
    guard.reset()
    assert guard.state == GuardState()


@pytest.mark.parametrize("restart", [False, True])
def test_quiet_says_when_no_nis_of_the_next_update_can_restart(restart: bool) -> None:
    """Guard.quiet, which lets a native tick observe its posterior: false exactly when some NIS of
    the next update (here the worst, None) would make restart_due true."""
    far = float(chi2.ppf(RESTART_QUANTILE, M)) * 1.01
    absurd = NIS_LIMIT_PER_DIMENSION * M * 2
    for run in ([far] * 3, [absurd] * DIVERGENCE_TICKS, [far, 1.0, absurd, absurd]):
        guard = Guard(m=M, restart=restart, driven=False)
        for nis in run:
            quiet = guard.quiet()
            probe = Guard(m=M, restart=restart, driven=False)
            probe.restore(guard.state)
            probe.count(None)
            assert quiet is not probe.restart_due(**FINE), (run, guard.state)
            guard.count(nis)
    guard = Guard(m=M, restart=restart, driven=False)
    for _ in range(ABSORPTIONS_BEFORE_REINIT):
        guard.absorb()
    assert not guard.quiet()
    assert Guard(m=M, restart=restart, driven=True).quiet()
