"""The table of estimator settings, walked: every row is a field of jitdyn.v1.EstimatorSettings
and every field a row, its range holds at its edges, and every reader of settings reads it."""

from __future__ import annotations

import pytest

from jitdyn.errors import InvalidArgument
from jitdyn.estimator_settings import (
    NUMBER_SETTINGS,
    SETTINGS,
    check_for_scenario,
    check_settings,
    settings_markdown,
    steps_per_tick,
)
from jitdyn.v1 import common_pb2
from jitdyn.vocabulary import WORDS, Scenario, WrongModel


def test_rows_are_the_fields_of_the_message() -> None:
    fields = [f.name for f in common_pb2.EstimatorSettings.DESCRIPTOR.fields]
    assert list(SETTINGS) == fields


@pytest.mark.parametrize("name", list(SETTINGS))
def test_a_row_matches_its_field_type(name: str) -> None:
    field = common_pb2.EstimatorSettings.DESCRIPTOR.fields_by_name[name]
    row = SETTINGS[name]
    if row.choices is None:
        assert field.type == field.TYPE_DOUBLE and field.has_presence, f"{name}: an optional double"
    else:
        assert field.enum_type is not None
        assert WORDS[row.choices][1] == field.enum_type.name, f"{name}: the word of {field.enum_type.name}"


@pytest.mark.parametrize("name", NUMBER_SETTINGS)
def test_a_number_row_holds_its_range_at_its_edges(name: str) -> None:
    row = SETTINGS[name]
    for edge, is_open, step in ((row.low, row.low_open, -1e-9), (row.high, row.high_open, 1e-9)):
        if edge is None:
            continue
        if is_open:
            with pytest.raises(InvalidArgument, match=rf"^x.{name} must be"):
                check_settings({name: edge}, argument="x")
        else:
            assert check_settings({name: edge}, argument="x") == {name: edge}
        with pytest.raises(InvalidArgument, match=rf"^x.{name} must be"):
            check_settings({name: edge + step}, argument="x")
    for bad in (float("nan"), float("inf"), "1", True, None):
        with pytest.raises(InvalidArgument, match=rf"^x.{name} must be"):
            check_settings({name: bad}, argument="x")


def test_unknown_names_and_choices_are_named() -> None:
    with pytest.raises(
        InvalidArgument,
        match=r"^open.estimator has unknown setting 'alfa'; expected one of estimator, preset",
    ):
        check_settings({"alfa": 0.5}, argument="open.estimator")
    with pytest.raises(InvalidArgument, match=r"^m.forecast must be one of FILTER, COMBINED, got 'SOON'$"):
        check_settings({"forecast": "SOON"}, argument="m")


def test_wrong_model_driven_is_for_passive_only() -> None:
    check_for_scenario(Scenario.PASSIVE, {"wrong_model": WrongModel.DRIVEN}, argument="open.estimator")
    with pytest.raises(InvalidArgument, match=r"wrong_model DRIVEN .* the scenario is CONTROLLED"):
        check_for_scenario(Scenario.CONTROLLED, {"wrong_model": WrongModel.DRIVEN}, argument="open.estimator")


def test_dt_must_be_a_whole_multiple_of_the_timestep() -> None:
    assert steps_per_tick(0.05, 0.002) == 25
    with pytest.raises(
        InvalidArgument,
        match=r"^open.dt must be a whole multiple \(>= 1\) of the model's timestep 0.002 s, got 0.003",
    ):
        steps_per_tick(0.003, 0.002, argument="open.dt")


def test_the_readme_shows_the_table() -> None:
    from pathlib import Path

    page = Path(__file__).parents[2] / "docs" / "concepts.md"
    if not page.exists():
        pytest.skip("not a checkout")
    assert settings_markdown() in page.read_text(), (
        "docs/concepts.md's settings table is not settings_markdown()"
    )
