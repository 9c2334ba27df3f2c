"""benchmarks/cost_nv.py --candidates on a built-in model: each candidate the server may choose is
run on the model's own motion, and what a gap is answered with shows in its error. The whole table
runs for minutes."""

from __future__ import annotations

from collections.abc import Callable
from types import ModuleType

import pytest

from jitdyn.vocabulary import EstimatorKind, Scenario, SigmaScheme


@pytest.fixture
def cost_nv(benchmark_module: Callable[[str], ModuleType]) -> ModuleType:
    return benchmark_module("cost_nv")


def test_the_ukf_answers_gaps_better_than_dead_reckoning_at_a_price(cost_nv: ModuleType) -> None:
    (name, model, rate), *_ = cost_nv.candidate_models(["pendulum_2"])
    assert (name, rate) == ("pendulum_2", 20.0)
    runs = {
        estimator: cost_nv.candidate_run(model, Scenario.DRIVEN, rate, settings, 2.0)
        for estimator, settings in (
            ("ukf", {"estimator": EstimatorKind.UKF, "sigma_points": SigmaScheme.MERWE}),
            ("reckoning", {"estimator": EstimatorKind.CONSTANT_VELOCITY}),
        )
    }
    (ukf_cycle, ukf_error), (reckoning_cycle, reckoning_error) = runs["ukf"], runs["reckoning"]
    assert 0 < reckoning_cycle < ukf_cycle
    assert 0 < ukf_error < reckoning_error
