"""`jitdyn serve`'s flags for the limits that protect a server from its clients: per session
(server/runtime/limits.py) and per model and tenant (registry/limits.py). Every refusal names the
flag that raises its limit."""

from __future__ import annotations

import argparse
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Final

from jitdyn.registry.limits import DEFAULT_LIMITS, RegistryLimits
from jitdyn.server.runtime.limits import DEFAULT_STREAM_LIMITS, StreamLimits
from jitdyn.settings import ENV_PREFIX, SettingError, argparse_type, checked, parse_seconds, positive_int

__all__ = ["add_limit_arguments", "limit_settings"]

_MIB = 1024 * 1024


_SIZE = re.compile(r"^\s*([0-9]*\.?[0-9]+)\s*([kmg]?)(?:i?b)?\s*$", re.IGNORECASE)


def _bytes(text: str) -> int:
    """'64MiB', '2GiB', '512k', '1000' -> bytes."""
    match = _SIZE.match(text)
    value = int(float(match.group(1)) * 1024 ** " kmg".index(match.group(2).lower() or " ")) if match else 0
    if value < 1:
        raise ValueError(f"expected a positive size like 64MiB, 2GiB or 1000000, got {text!r}")
    return value


@dataclass(frozen=True)
class _Unit:
    """How a limit's flag is parsed (ValueError saying what was expected), named in the help
    (metavar), and how its default is written there."""

    parse: Callable[[str], Any]
    metavar: str
    show: Callable[[Any], str]


_BYTES = _Unit(_bytes, "SIZE", lambda value: f"{value // _MIB}MiB")
_SECONDS = _Unit(
    checked(parse_seconds, lambda value: value > 0, "a duration > 0, like 60s, 500ms or 60 (seconds)"),
    "DURATION",
    lambda value: f"{value:g}s",
)
_SHARE = _Unit(
    checked(float, lambda value: value > 0, "a number > 0, like 0.5"), "F", lambda value: f"{value:g}"
)
_COUNT = _Unit(positive_int, "N", str)


@dataclass(frozen=True)
class _Limit:
    """One flag: the field it sets on StreamLimits or RegistryLimits, and what it limits."""

    flag: str
    limits: type[StreamLimits | RegistryLimits]
    field: str
    unit: _Unit
    help: str

    @property
    def dest(self) -> str:
        return self.flag.removeprefix("--").replace("-", "_")

    @property
    def env(self) -> str:
        return ENV_PREFIX + self.dest.upper()

    @property
    def default(self) -> Any:
        return getattr(_DEFAULTS[self.limits], self.field)


_DEFAULTS: Final[dict[type, StreamLimits | RegistryLimits]] = {
    StreamLimits: DEFAULT_STREAM_LIMITS,
    RegistryLimits: DEFAULT_LIMITS,
}

_LIMITS: Final = (
    _Limit(
        "--max-history-bytes",
        StreamLimits,
        "max_history_bytes",
        _BYTES,
        "memory of one session's late-frame history",
    ),
    _Limit(
        "--max-clock-offset",
        StreamLimits,
        "max_clock_offset",
        _SECONDS,
        "how far a REALTIME client's clock may be from the session's",
    ),
    _Limit(
        "--idle-timeout",
        StreamLimits,
        "idle_timeout",
        _SECONDS,
        "how long a session may send nothing before it is ended",
    ),
    _Limit(
        "--max-tick-share",
        StreamLimits,
        "max_tick_share",
        _SHARE,
        "largest share of dt a REALTIME tick's estimated cost may take",
    ),
    _Limit(
        "--late-timeout",
        StreamLimits,
        "late_timeout",
        _SECONDS,
        "how long a REALTIME session told it may go late may stay so before it is ended",
    ),
    _Limit(
        "--compile-timeout",
        RegistryLimits,
        "compile_timeout",
        _SECONDS,
        "how long a model may take to compile",
    ),
    _Limit(
        "--max-compiled-bytes", RegistryLimits, "max_compiled_bytes", _BYTES, "memory of one compiled model"
    ),
    _Limit(
        "--compile-memory-bytes",
        RegistryLimits,
        "compile_memory_bytes",
        _BYTES,
        "address space of a compile worker",
    ),
    _Limit(
        "--model-cache-bytes", RegistryLimits, "cache_bytes", _BYTES, "memory of the compiled models kept"
    ),
    _Limit(
        "--max-models-per-tenant",
        RegistryLimits,
        "max_models_per_tenant",
        _COUNT,
        "models one tenant may register",
    ),
    _Limit(
        "--max-tenant-bytes",
        RegistryLimits,
        "max_tenant_bytes",
        _BYTES,
        "MJCF and asset bytes one tenant may store",
    ),
)


def add_limit_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("limits per session, model and tenant")
    for limit in _LIMITS:
        text = f"{limit.help} (env {limit.env}; default {limit.unit.show(limit.default)})"
        group.add_argument(
            limit.flag,
            dest=limit.dest,
            type=argparse_type(limit.unit.parse, limit.dest),
            default=argparse.SUPPRESS,
            metavar=limit.unit.metavar,
            help=text.replace("%", "%%"),
        )


def limit_settings(args: argparse.Namespace, environ: Mapping[str, str]) -> dict[str, Any]:
    """The ServerConfig fields the limit flags set: each from its flag, else its environment
    variable, else its default.

    Raises:
      SettingError: an environment variable's value is not valid for its limit.
    """

    def value(limit: _Limit) -> Any:
        if limit.dest in args:
            return getattr(args, limit.dest)
        text = environ.get(limit.env)
        if text is None:
            return limit.default
        try:
            return limit.unit.parse(text)
        except ValueError as error:
            raise SettingError(f"environment variable {limit.env}: {error}") from None

    def given(limits: type) -> dict[str, Any]:
        return {limit.field: value(limit) for limit in _LIMITS if limit.limits is limits}

    return {
        "stream_limits": StreamLimits(**given(StreamLimits)),
        "registry_limits": RegistryLimits(**given(RegistryLimits)),
    }
