"""Every word of jitdyn.vocabulary pinned to its proto enum, both ways: a value added to the proto
and not to the vocabulary (or the other way round) fails here."""

from __future__ import annotations

import enum
import importlib

import pytest

from jitdyn.errors import InvalidArgument
from jitdyn.vocabulary import WORDS, Channel, RejectReason, Scenario, from_proto, parse, to_proto


def _proto_names(kind: type[enum.StrEnum]) -> dict[str, int]:
    module, name, prefix = WORDS[kind]
    wrapper = getattr(importlib.import_module(f"jitdyn.v1.{module}"), name)
    return {
        full.removeprefix(prefix): number
        for full, number in wrapper.items()
        if not full.endswith("_UNSPECIFIED")
    }


@pytest.mark.parametrize("kind", list(WORDS), ids=lambda k: k.__name__)
def test_members_are_the_proto_values(kind: type[enum.StrEnum]) -> None:
    assert {m.name for m in kind} == set(_proto_names(kind)), (
        f"{kind.__name__} and jitdyn.v1.{WORDS[kind][1]} name different values"
    )


@pytest.mark.parametrize("kind", list(WORDS), ids=lambda k: k.__name__)
def test_conversions_round_trip(kind: type[enum.StrEnum]) -> None:
    for name, number in _proto_names(kind).items():
        member = kind[name]
        assert to_proto(member) == number
        assert from_proto(kind, number, argument="x") is member


def test_every_proto_enum_the_code_uses_is_a_word() -> None:
    """The proto's enums, all of them words (a new proto enum needs its word too)."""
    from jitdyn.v1 import common_pb2, dynamics_pb2, model_registry_pb2, session_pb2

    proto_enums = {
        (module.__name__.rsplit(".", 1)[1], name)
        for module in (common_pb2, dynamics_pb2, model_registry_pb2, session_pb2)
        for name in module.DESCRIPTOR.enum_types_by_name
    }
    assert proto_enums == {(module, name) for module, name, _ in WORDS.values()}


def test_unset_is_none_and_an_undefined_value_is_named() -> None:
    assert from_proto(Scenario, 0, argument="open.scenario") is None
    with pytest.raises(
        InvalidArgument, match=r"open.scenario must be one of SCENARIO_PASSIVE, .* got the undefined value 99"
    ):
        from_proto(Scenario, 99, argument="open.scenario")


def test_parse_takes_names_values_and_prefixed_names() -> None:
    assert parse(Channel, "qpos", argument="c") is Channel.QPOS
    assert parse(Channel, "CHANNEL_QVEL", argument="c") is Channel.QVEL
    assert parse(RejectReason, "too_old", argument="r") is RejectReason.TOO_OLD
    with pytest.raises(
        InvalidArgument,
        match=r"^scenario must be one of PASSIVE, CONTROLLED, EXTERNAL, DRIVEN, got 'PASIVE'$",
    ):
        parse(Scenario, "PASIVE", argument="scenario")


def test_a_name_two_kinds_share_keeps_each_kinds_value() -> None:
    """Scenario.DRIVEN and WrongModel.DRIVEN are equal strings with different proto values: a cache
    keyed by the member alone answered whichever was asked first for both."""
    from jitdyn.vocabulary import WrongModel

    assert Scenario.DRIVEN == WrongModel.DRIVEN  # the trap: StrEnum members compare as strings
    for _ in range(2):  # the second time from the cache
        assert to_proto(Scenario.DRIVEN) == 4
        assert to_proto(WrongModel.DRIVEN) == 2
