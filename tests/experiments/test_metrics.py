"""client.metrics against values computed by hand on tiny arrays."""

from __future__ import annotations

import math

import numpy as np
import pytest

from jitdyn.experiments.metrics import (
    armse,
    chi_square_interval,
    consistency,
    dead_reckon,
    gap_error_profile,
    gap_errors,
    nees,
    rmse,
    ticks_since_frame,
)
from jitdyn.vocabulary import EstimatorKind


def test_rmse_per_joint_and_armse():
    truth = np.zeros((2, 2))
    estimate = np.array([[1.0, 2.0], [-1.0, 2.0]])
    # joint 0: sqrt((1 + 1) / 2) = 1; joint 1: sqrt((4 + 4) / 2) = 2
    np.testing.assert_allclose(rmse(truth, estimate), [1.0, 2.0])
    assert armse(truth, estimate) == pytest.approx(1.5)


def test_rmse_of_one_joint_given_as_a_series():
    np.testing.assert_allclose(rmse([0.0, 0.0, 0.0], [3.0, 0.0, 0.0]), [math.sqrt(3.0)])


def test_rmse_leaves_out_missing_ticks():
    truth = np.zeros((3, 1))
    estimate = np.array([[2.0], [np.nan], [0.0]])
    np.testing.assert_allclose(rmse(truth, estimate), [math.sqrt(2.0)])


def test_rmse_shape_mismatch_is_named():
    with pytest.raises(
        ValueError, match=r"truth and estimate must have the same shape, got \(2, 1\) and \(3, 1\)"
    ):
        rmse(np.zeros((2, 1)), np.zeros((3, 1)))


def test_nees_diagonal_and_full_covariance():
    errors = np.array([[1.0, 2.0], [1.0, 1.0]])
    covariances = np.array([np.diag([1.0, 4.0]), [[2.0, 1.0], [1.0, 2.0]]])
    # 1/1 + 4/4 = 2; [1 1] (1/3 [[2 -1] [-1 2]]) [1 1]^T = 2/3
    np.testing.assert_allclose(nees(errors, covariances), [2.0, 2.0 / 3.0])


def test_nees_singular_covariance_is_inf_not_a_crash():
    assert nees(np.array([[1.0, 0.0]]), np.zeros((1, 2, 2)))[0] == math.inf


def test_nees_covariance_shape_is_named():
    with pytest.raises(
        ValueError, match=r"covariances must have shape \(1, 2, 2\) to match errors \(1, 2\), got \(1, 3, 3\)"
    ):
        nees(np.zeros((1, 2)), np.zeros((1, 3, 3)))


def test_single_sample_interval_is_the_thesis_interval():
    # Table 4.2 prints [0.0506; 7.3778] for dim x = 2 and [0.4844; 11.1433] for dim x = 4.
    two = chi_square_interval(2)
    assert (round(two.low, 4), round(two.high, 4)) == (0.0506, 7.3778)
    four = chi_square_interval(4)
    assert (round(four.low, 4), round(four.high, 4)) == (0.4844, 11.1433)


def test_averaged_interval_divides_the_pooled_quantiles_by_n():
    # N = 2 samples of 2 degrees: chi2(4) quantiles / 2.
    interval = chi_square_interval(2, samples=2)
    assert interval.low == pytest.approx(0.48441855 / 2, rel=1e-6)
    assert interval.high == pytest.approx(11.1432868 / 2, rel=1e-6)


def test_consistency_mean_fraction_and_verdict():
    c = consistency([0.01, 1.0, 2.0, 8.0, np.inf], dof=2)
    assert c.samples == 4  # the inf of a singular P is left out
    assert c.mean == pytest.approx((0.01 + 1.0 + 2.0 + 8.0) / 4)
    assert c.fraction_inside == pytest.approx(0.5)  # 0.01 < 0.0506 and 8 > 7.3778
    assert c.averaged.samples == 4
    assert c.verdict == "consistent" and c.consistent
    assert consistency([1e-4] * 10, dof=2).verdict == "pessimistic"
    assert consistency([1e4] * 10, dof=2).verdict == "optimistic"


def test_consistency_needs_a_finite_sample():
    with pytest.raises(ValueError, match="at least one finite sample, got 1 samples, none finite"):
        consistency([np.nan], dof=2)


def test_dead_reckoning_models():
    state = {"q": np.array([1.0]), "qd": np.array([2.0]), "qdd": np.array([4.0]), "horizon": 0.5}
    expected = {
        EstimatorKind.STATIC: ([1.0], [2.0]),
        EstimatorKind.CONSTANT_VELOCITY: ([2.0], [2.0]),
        # 1 + 2 * 0.5 + 0.5 * 4 * 0.25 = 2.5; 2 + 4 * 0.5 = 4
        EstimatorKind.CONSTANT_ACCELERATION: ([2.5], [4.0]),
    }
    for kind, (q, qd) in expected.items():
        got_q, got_qd = dead_reckon(kind, **state)
        np.testing.assert_allclose(got_q, q)
        np.testing.assert_allclose(got_qd, qd)


def test_ticks_since_frame():
    np.testing.assert_array_equal(
        ticks_since_frame([False, True, False, False, True, False]), [-1, 0, 1, 2, 0, 1]
    )


def test_gap_error_profile_and_gap_lengths():
    received = [False, True, False, False, True, False]
    truth = np.zeros((6, 1))
    estimate = np.array([9.0, 0.0, 1.0, 3.0, 0.0, 2.0])[:, None]
    profile = gap_error_profile(truth, estimate, received)
    # one tick after a frame: ticks 2 and 5 (errors 1 and 2); two ticks after: tick 3 (error 3)
    assert profile == pytest.approx({1: math.sqrt(2.5), 2: 3.0})
    g = gap_errors("UKF", profile, dt=0.05, gaps=(0.035, 0.1, 0.2))
    assert g.ticks == {0.035: 1, 0.1: 2, 0.2: 4}  # 0.1 / 0.05 is 2 ticks, not 3
    assert g.by_gap[0.035] == pytest.approx(math.sqrt(2.5))
    assert g.by_gap[0.1] == pytest.approx(3.0)
    assert math.isnan(g.by_gap[0.2])
