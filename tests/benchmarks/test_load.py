"""benchmarks/load.py offers every model a user can register: the built-ins and the myo-sim models
that compile here, and can leave the scenario and the estimator to the server."""

from __future__ import annotations

import re
from collections.abc import Callable
from types import ModuleType

import numpy as np
import pytest

from jitdyn.vocabulary import Scenario


@pytest.fixture
def load(benchmark_module: Callable[[str], ModuleType]) -> ModuleType:
    return benchmark_module("load")


def test_an_unknown_model_is_refused_with_the_models_offered(load: ModuleType) -> None:
    with pytest.raises(
        SystemExit, match=r"^--model must be a built-in model \(pendulum_1, .*myolegs_osl.*got 'nosuch'$"
    ):
        load.model_source("nosuch")


def test_a_myo_sim_model_is_offered_by_any_case_with_its_default_scenario(load: ModuleType) -> None:
    source = load.model_source("myoLegs_OSL")
    assert (source.name, source.builtin) == ("myolegs_osl", False)
    assert load.resolve_scenario("myolegs_osl", load.DEFAULT_SCENARIO) == Scenario.DRIVEN
    assert load.resolve_scenario("pendulum_3", "EXTERNAL") == Scenario.EXTERNAL
    assert load.model_source("biped").builtin


def test_a_model_that_is_no_research_object_moves_under_its_actuators(load: ModuleType) -> None:
    states = load.trajectory("myofinger", Scenario.DRIVEN, 100.0, 30)
    assert states["qpos"].shape[0] == states["qvel"].shape[0] == states["ctrl"].shape[0] == 30
    assert np.ptp(states["qpos"], axis=0).max() > 1e-3  # it moves
    with pytest.raises(SystemExit, match=r"^--rate must make a tick a whole number of myofinger's"):
        load.trajectory("myofinger", Scenario.DRIVEN, 300.0, 3)


def test_a_session_left_to_the_servers_defaults_gets_them(load: ModuleType) -> None:
    # A real `jitdyn serve`, a real client process: the open names neither scenario nor estimator.
    # Admission may refuse it on a busy machine: a few fresh servers are tried, and then the refusal
    # must be admission's (the open itself was valid), not an error.
    for _ in range(3):
        report = load.run(
            model="myofinger",
            scenario=Scenario.DRIVEN,
            name_scenario=False,
            rate=50.0,
            sessions=1,
            seconds=2.0,
            clients=1,
            server=None,
            floor=False,
        )
        if report.opened:
            break
    if not report.opened:
        assert report.refused == 1
        refusal = r"^RESOURCE_EXHAUSTED: this (machine|server process) .* or at a lower rate$"
        assert re.match(refusal, report.errors[0]), report.errors[0]
        return
    assert report.errors == []
    assert report.answered > 0.5
    assert report.opened_with.startswith("SCENARIO_DRIVEN, ESTIMATOR_")
    assert "(ESTIMATOR_CHOICE_BY_COST: chosen by cost" in report.opened_with
