"""The estimator settings of the wire (jitdyn.v1.EstimatorSettings) to and from the dict keyed by
jitdyn.estimator_settings.SETTINGS' names, for the server's transport and the SDK alike::

    message = settings_message({"alpha": 0.5, "sigma_points": SigmaScheme.SIMPLEX})
    settings_from_message(message, argument="open.estimator")   # the same dict back
"""

from __future__ import annotations

from collections.abc import Mapping

from jitdyn.estimator_settings import SETTINGS, SettingValue
from jitdyn.v1 import common_pb2
from jitdyn.vocabulary import from_proto, parse, to_proto

__all__ = ["settings_from_message", "settings_message"]


def settings_from_message(message: common_pb2.EstimatorSettings, *, argument: str) -> dict[str, SettingValue]:
    """The settings a message sets, in SETTINGS' order: an enum setting as its vocabulary member, a
    number as a float; unset ones left out. An enum value the vocabulary lacks is InvalidArgument
    naming `argument`.name."""
    present = {descriptor.name: value for descriptor, value in message.ListFields()}
    settings: dict[str, SettingValue] = {}
    for name, row in SETTINGS.items():
        if row.choices is not None:
            member = from_proto(row.choices, getattr(message, name), argument=f"{argument}.{name}")
            if member is not None:
                settings[name] = member
        elif name in present:  # the numbers are `optional`: set to 0 is not unset
            settings[name] = float(present[name])
    return settings


def settings_message(settings: Mapping[str, object]) -> common_pb2.EstimatorSettings:
    """The message of settings keyed by SETTINGS' names: an enum setting as its vocabulary member
    or its name, a number as a number."""
    message = common_pb2.EstimatorSettings()
    for name, value in settings.items():
        choices = SETTINGS[name].choices
        if choices is not None:
            setattr(message, name, to_proto(parse(choices, value, argument=f"settings.{name}")))
        else:
            setattr(message, name, value)
    return message
