"""jitdyn's settings, read in one place: a command-line flag, else an environment variable, else the
default; each parsed and validated once, into one frozen `Settings`::

    settings = resolve(parsed_args, os.environ)      # flags given, then JITDYN_*, then defaults
    settings.workers                                 # an int >= 1, whoever set it

A setting is one field of `Settings`, declared with `setting(...)`: its default, its parser (text to
a typed value, raising ValueError with what was expected), its help, and the commands that take its
flag. Flag and environment variable are derived from the field name (`max_sessions` is
`--max-sessions` and `JITDYN_MAX_SESSIONS`) unless given. `add_arguments(parser, command)` puts the
flags of `command` on an argparse parser with SUPPRESS defaults, so that the same flag may appear on
a group and on its leaf and `resolve` still knows whether it was given. The README's settings table
is `settings_table()`.
"""

from __future__ import annotations

import argparse
import dataclasses
import ipaddress
import os
import re
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final, TypeVar

__all__ = [
    "DEFAULTS",
    "ENV_PREFIX",
    "LIMITS",
    "Setting",
    "SettingError",
    "Settings",
    "add_arguments",
    "argparse_type",
    "checked",
    "default_workers",
    "parse_address",
    "parse_duration",
    "parse_model_reference",
    "parse_seconds",
    "parse_size",
    "positive_int",
    "resolve",
    "settings_for",
    "settings_table",
]

ENV_PREFIX: Final = "JITDYN_"

_V = TypeVar("_V")


class SettingError(ValueError):
    """A setting's value, from a flag or the environment, is not valid; the message names where
    it came from, what was expected and what arrived."""


# -- parsers: text to a typed value, or ValueError saying what was expected --------------------------

_DURATION = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*(us|ms|s)?\s*$")
_DURATION_UNITS: Final = {"us": 1e-6, "ms": 1e-3, "s": 1.0}


def parse_duration(text: str) -> float:
    """'35ms' -> 0.035, '0.5s' -> 0.5, '20us' -> 2e-05 (seconds). A bare number is refused: '35'
    could mean 35 s or 35 ms, and the wrong guess is silent."""
    match = _DURATION.match(text)
    if not match:
        raise ValueError(f"expected a duration with a unit, like 35ms or 0.5s, got {text!r}")
    if match.group(2) is None:
        if float(match.group(1)) == 0.0:
            return 0.0  # nothing is ambiguous about no time at all
        raise ValueError(
            f"a duration needs a unit (us, ms or s): write {match.group(1)}ms or {match.group(1)}s, got {text!r}"
        )
    return float(match.group(1)) * _DURATION_UNITS[match.group(2)]


def parse_seconds(text: str) -> float:
    """A duration of an option that has always taken seconds: '60s', '500ms', '200us' with a unit,
    and a bare number as the seconds it always meant ('60' -> 60.0). Why: docs/decisions/0140."""
    match = _DURATION.match(text)
    if not match:
        raise ValueError(f"expected a duration like 60s, 500ms or 60 (seconds), got {text!r}")
    return float(match.group(1)) * _DURATION_UNITS[match.group(2) or "s"]


def parse_model_reference(text: str) -> tuple[str, str, int]:
    """(model_id, name, version) of 'sha256:<hex>', 'NAME' (the newest version) or 'NAME:VERSION'."""
    if re.fullmatch(r"sha256:[0-9a-f]{64}", text):
        return text, "", 0
    name, colon, version = text.partition(":")
    if not name or (colon and not (version.isdigit() and int(version) >= 1)):
        raise ValueError(
            f"expected a model id (sha256:...), NAME or NAME:VERSION with VERSION a whole number >= 1, got {text!r}"
        )
    return "", name, int(version or 0)


def parse_address(text: str) -> str:
    """HOST:PORT, with an IPv6 host in brackets; port 0..65535."""
    host, sep, port = text.strip().rpartition(":")
    if not sep or not host or not port.isdigit() or int(port) > 65535:
        raise ValueError(f"expected HOST:PORT, like 127.0.0.1:50051, got {text!r}")
    if host.startswith("["):
        try:
            ipaddress.IPv6Address(host.strip("[]"))
        except ValueError:
            raise ValueError(f"expected HOST:PORT with an IPv6 host in brackets, got {text!r}") from None
    return text.strip()


def checked(
    convert: Callable[[str], _V], accept: Callable[[_V], bool], expected: str, *, malformed: str | None = None
) -> Callable[[str], _V]:
    """A parser: `convert` the text, then `accept` the value; otherwise ValueError "expected
    {expected}, got {text!r}" ({malformed} instead where `convert` itself fails)."""

    def parse(text: str) -> _V:
        try:
            value = convert(text)
        except ValueError:
            raise ValueError(f"expected {malformed or expected}, got {text!r}") from None
        if not accept(value):
            raise ValueError(f"expected {expected}, got {text!r}")
        return value

    return parse


_SIZE = re.compile(r"^\s*([0-9]*\.?[0-9]+)\s*([kmg]?)(?:i?b)?\s*$", re.IGNORECASE)
_MIB: Final = 1024 * 1024


def parse_size(text: str) -> int:
    """'64MiB', '2GiB', '512k', '1000' -> bytes (k, M and G are powers of 1024)."""
    match = _SIZE.match(text)
    value = int(float(match.group(1)) * 1024 ** " kmg".index(match.group(2).lower() or " ")) if match else 0
    if value < 1:
        raise ValueError(f"expected a positive size like 64MiB, 2GiB or 1000000, got {text!r}")
    return value


positive_int = checked(int, lambda value: value >= 1, "a whole number >= 1")
_count = checked(int, lambda value: value >= 0, "a whole number >= 0")
_fraction = checked(float, lambda value: 0.0 < value <= 1.0, "a number in (0, 1]")


def _path(text: str) -> Path:
    if not text.strip():
        raise ValueError("expected a path, got an empty string")
    return Path(text).expanduser()


def _text(text: str) -> str:
    if not text.strip():
        raise ValueError("expected a value, got an empty string")
    return text


_TRUE = frozenset({"1", "true", "yes", "on"})
_FALSE = frozenset({"0", "false", "no", "off", ""})


def _boolean(text: str) -> bool:
    if text.strip().lower() in _TRUE:
        return True
    if text.strip().lower() in _FALSE:
        return False
    raise ValueError(f"expected 1/0, true/false, yes/no or on/off, got {text!r}")


ENGINES: Final = ("native", "python")


def _engine(text: str) -> str:
    name = text.strip().lower()
    if name not in ENGINES:
        raise ValueError(f"expected one of {', '.join(ENGINES)}, got {text!r}")
    return name


ESTIMATOR_CHOICES: Final = ("cost", "preset")


def _estimator_choice(text: str) -> str:
    name = text.strip().lower()
    if name not in ESTIMATOR_CHOICES:
        raise ValueError(f"expected one of {', '.join(ESTIMATOR_CHOICES)}, got {text!r}")
    return name


def default_workers(processes: int = 1) -> int:
    """Threads propagating sigma points by default: the CPUs, shared among the server's processes
    (one each at one process per CPU). Why: docs/decisions/0060-one-worker-per-process.md."""
    return max(1, (os.cpu_count() or 1) // max(1, processes))


# -- the declaration of a setting ---------------------------------------------------------------------


@dataclass(frozen=True)
class Setting:
    """What `setting(...)` records on a field of `Settings`."""

    name: str
    parse: Callable[[str], Any]
    help: str
    commands: tuple[str, ...]
    flag: str
    env: str
    metavar: str | None
    is_flag: bool  # a switch: `--insecure` takes no value
    default_text: str | None  # the default as the help says it, when str(default) will not do
    group: str | None  # the heading its flag is listed under in --help, if not the command's own


def setting(
    default: Any = None,
    *,
    parse: Callable[[str], Any],
    help: str,
    commands: tuple[str, ...],
    flag: str | None = None,
    env: str | None = None,
    metavar: str | None = None,
    default_factory: Callable[[], Any] | None = None,
    default_text: str | None = None,
    switch: bool = False,
    group: str | None = None,
) -> Any:
    """A field of `Settings`: see the module docstring. Returns a dataclasses.field."""
    metadata = {
        "jitdyn_setting": {
            "parse": parse,
            "help": help,
            "commands": commands,
            "flag": flag,
            "env": env,
            "metavar": metavar,
            "switch": switch,
            "default_text": default_text,
            "group": group,
        }
    }
    if default_factory is not None:
        return field(default_factory=default_factory, metadata=metadata)
    return field(default=default, metadata=metadata)


def _serve_address(default: str | None, help: str) -> Any:
    """An address `serve` listens on."""
    return setting(default, parse=parse_address, commands=("serve",), metavar="HOST:PORT", help=help)


def _serve_file(help: str) -> Any:
    """A file `serve` reads, none by default."""
    return setting(None, parse=_path, commands=("serve",), metavar="FILE", help=help)


# The limits that protect a server from its clients: per session (server/runtime/limits.py) and per
# model and tenant (registry/limits.py), which take their defaults from these settings. Every refusal
# names the flag that raises its limit.
LIMITS: Final = "limits per session, model and tenant"


def _limit_size(default: int, help: str) -> Any:
    return setting(
        default,
        parse=parse_size,
        commands=("serve",),
        metavar="SIZE",
        default_text=f"{default // _MIB}MiB",
        group=LIMITS,
        help=help,
    )


def _limit_seconds(default: float, help: str) -> Any:
    return setting(
        default,
        parse=checked(
            parse_seconds, lambda value: value > 0, "a duration > 0, like 60s, 500ms or 60 (seconds)"
        ),
        commands=("serve",),
        metavar="DURATION",
        default_text=f"{default:g}s",
        group=LIMITS,
        help=help,
    )


def _quota(help: str) -> Any:
    """A count of open sessions `serve` allows, 0 for no quota."""
    return setting(0, parse=_count, commands=("serve",), metavar="N", default_text="0: no quota", help=help)


@dataclass(frozen=True)
class Settings:
    """Every setting of every command, typed; the defaults are the embedded, loopback set-up."""

    address: str = _serve_address(
        "127.0.0.1:50051",
        "where the server listens (port 0 picks one); a non-loopback address needs "
        "--tls-cert, --tls-key and --api-keys, or --insecure",
    )
    server: str | None = setting(
        None,
        parse=parse_address,
        commands=("models", "demo", "replay", "lsl", "experiments"),
        metavar="HOST:PORT",
        default_text="127.0.0.1:50051 for models; demo, replay, lsl and the experiments start a server in-process",
        help="the jitdyn server to talk to",
    )
    data: Path = setting(
        Path("jitdyn-data"),
        parse=_path,
        commands=("serve", "demo", "replay", "lsl", "sessions"),
        metavar="DIR",
        help="data folder: Parquet frames, model store, the default SQLite index",
    )
    index_url: str | None = setting(
        None,
        parse=_text,
        commands=("serve", "demo", "replay", "lsl", "sessions"),
        flag="--index",
        metavar="URL",
        default_text="index.sqlite in the data folder",
        help="SQL index, e.g. postgresql+psycopg://user@host/db (needs jitdyn[postgres])",
    )
    data_root_uri: str | None = setting(
        None,
        parse=_text,
        commands=("serve",),
        flag="--data-root",
        env="JITDYN_DATA_ROOT",
        metavar="URI",
        default_text="none: sessions stay in the data folder",
        help="where every finished session's Parquet is published, for replicas on several hosts: "
        "s3://BUCKET/PREFIX (endpoint and keys from AWS_ENDPOINT_URL, AWS_REGION, AWS_ACCESS_KEY_ID, "
        "AWS_SECRET_ACCESS_KEY), or a shared folder (file:///PATH or a path); the index then holds "
        "each session's URI",
    )
    workers: int | None = setting(
        None,
        parse=positive_int,
        default_text="the CPU count, shared among --processes (one each at one process per CPU)",
        commands=("serve", "demo", "replay", "lsl"),
        metavar="N",
        help="threads propagating sigma points, shared by all sessions",
    )
    engine: str = setting(
        "native",
        parse=_engine,
        commands=("serve", "demo", "replay", "lsl"),
        metavar="NAME",
        help="what computes the UKF: native (compiled, on MuJoCo's C API) or python (the numpy "
        "engine it is tested against, for comparison and debugging: 1.3-3.5x the CPU of a filter "
        "cycle, benchmarks/RESULTS.md); the THESIS preset always runs filterpy",
    )
    estimator_choice: str = setting(
        "cost",
        parse=_estimator_choice,
        commands=("serve",),
        metavar="RULE",
        help="the estimator of a REALTIME session that names none: cost (the most accurate whose cost, "
        "measured when its model was registered, fits --max-tick-share of the tick; else the open is "
        "refused) or preset (the preset's, whatever it costs)",
    )
    secret_file: Path | None = setting(
        None,
        parse=_path,
        commands=("serve", "demo", "replay", "lsl"),
        metavar="FILE",
        default_text="~/.config/jitdyn/secret.key",
        help="HMAC key of subject pseudonyms, mode 0600, outside the data folder, created at first start; "
        "JITDYN_SECRET=hex in the environment overrides it",
    )
    tls_cert: Path | None = _serve_file("PEM certificate chain, to serve over TLS")
    tls_key: Path | None = _serve_file("PEM private key of --tls-cert")
    api_keys: Path | None = _serve_file(
        "file of `KEY TENANT` lines: every RPC must then carry `authorization: Bearer KEY` and sees "
        "only its tenant's sessions and models"
    )
    insecure: bool = setting(
        False,
        parse=_boolean,
        commands=("serve",),
        switch=True,
        help="allow a non-loopback address without TLS and API keys",
    )
    processes: int = setting(
        parse=positive_int,
        default_factory=lambda: os.cpu_count() or 1,
        default_text="the CPU count",
        commands=("serve",),
        metavar="N",
        help="server processes on the one port (SO_REUSEPORT), each with its own event loop and worker "
        "pool, sharing the data folder and the index",
    )
    tick_budget: float = setting(
        0.75,
        parse=_fraction,
        commands=("serve",),
        metavar="F",
        help="share of one core each process may spend on REALTIME ticks; a session whose measured cost "
        "would exceed it is refused with RESOURCE_EXHAUSTED",
    )
    metrics_address: str | None = _serve_address(None, "serve Prometheus metrics there, e.g. 127.0.0.1:9464")
    health_address: str | None = _serve_address(
        None,
        "serve the kubelet's probes there, e.g. 0.0.0.0:8081: plaintext gRPC health answered off the "
        "event loop, so a loop busy with ticks never fails them. Liveness (no service name) fails only "
        "when the loop has not run for 30 s; readiness (jitdyn.v1.DynamicsService) follows the sessions' "
        "port: NOT_SERVING while draining or stepped down",
    )
    max_sessions: int = _quota(
        "open sessions per process, a quota (REALTIME sessions are admitted by --tick-budget)"
    )
    max_sessions_per_tenant: int = _quota("open sessions per tenant and process, a quota")
    max_state_dimension: int = setting(
        200, parse=positive_int, commands=("serve",), metavar="N", help="largest nv of a session's model"
    )
    lease_ttl: float = setting(
        10.0,
        parse=checked(parse_duration, lambda value: value > 0, "a duration > 0, like 10s"),
        commands=("serve",),
        metavar="DURATION",
        default_text="10s",
        help="with a PostgreSQL index: how long a replica's hold on its open sessions lasts unless "
        "renewed (it renews every third of it); a replica silent that long is taken for dead",
    )
    resume_timeout: float = setting(
        30.0,
        parse=checked(parse_duration, lambda value: value >= 0, "a duration >= 0, like 30s"),
        commands=("serve",),
        metavar="DURATION",
        default_text="30s",
        help="with a PostgreSQL index: a session whose replica died or whose stream ended without a "
        "close, and that nobody resumes within this time after its hold ran out, is stored by a live "
        "replica (RECOVERED or ABANDONED)",
    )
    resume_token_ttl: float = setting(
        600.0,
        parse=checked(parse_duration, lambda value: value > 0, "a duration > 0, like 600s"),
        commands=("serve",),
        metavar="DURATION",
        default_text="600s",
        help="with a PostgreSQL index: how long a session's resume token is good for; a stream hands "
        "its client a fresh one with an answer every half of it, so keep it over twice the longest "
        "time a client may need to resume (the SDK tries for about 121 s)",
    )
    drain_grace: float = setting(
        30.0,
        parse=checked(parse_duration, lambda value: value >= 0, "a duration >= 0, like 30s"),
        commands=("serve",),
        metavar="DURATION",
        default_text="30s",
        help="on SIGTERM: how long the server waits for its open sessions to move to other replicas "
        "(they are told to) before it stops",
    )
    nice: int = setting(
        -10,
        parse=checked(
            int,
            lambda value: -20 <= value <= 19,
            "a nice value from -20 to 19, like -10",
            malformed="a whole number from -20 to 19, like -10",
        ),
        commands=("serve",),
        metavar="N",
        help="CPU priority of the serving processes as nice(1) counts it (lower runs first): ahead of "
        "the batch work started beside the server, which would otherwise take the CPU from admitted "
        "sessions' ticks. Lowering it needs CAP_SYS_NICE (root); without it the server says so and "
        "runs at the priority it was started with",
    )
    max_history_bytes: int = _limit_size(
        256 * _MIB, "memory of one session's late-frame history (ticks x state size)"
    )
    max_clock_offset: float = _limit_seconds(
        5.0, "how far a REALTIME client's clock may be from the session's"
    )
    idle_timeout: float = _limit_seconds(
        60.0, "how long a session may send nothing (no frame, sync or skip) before it is ended"
    )
    max_tick_share: float = setting(
        0.5,
        parse=checked(float, lambda value: value > 0, "a number > 0, like 0.5"),
        commands=("serve",),
        metavar="F",
        group=LIMITS,
        help="largest share of dt a REALTIME tick's cost, estimated at open, may take",
    )
    late_timeout: float = _limit_seconds(
        10.0,
        "how long a REALTIME session told in band that its answers may go late may stay so; then it is "
        "ended and stored, so that the sessions admitted before it are on time again (the first "
        "admitted is never ended)",
    )
    compile_timeout: float = _limit_seconds(
        10.0, "how long a model may take to compile (the whole exchange with the compile worker)"
    )
    max_compiled_bytes: int = _limit_size(64 * _MIB, "memory of one compiled model")
    compile_memory_bytes: int = _limit_size(4096 * _MIB, "address space of a compile worker (RLIMIT_AS)")
    model_cache_bytes: int = _limit_size(
        512 * _MIB, "memory of the compiled models kept (least recently used dropped)"
    )
    max_models_per_tenant: int = setting(
        1000,
        parse=positive_int,
        commands=("serve",),
        metavar="N",
        group=LIMITS,
        help="models (versions) one tenant may register",
    )
    max_tenant_bytes: int = _limit_size(4096 * _MIB, "MJCF and asset bytes one tenant may store")
    stall_report: float = setting(
        0.1,
        parse=checked(parse_duration, lambda value: value >= 0, "a duration >= 0, like 100ms"),
        commands=("serve",),
        metavar="DURATION",
        default_text="100ms",
        help="log every stall of a process's event loop longer than this, with the code it was running "
        "and what its other threads were doing (0: none); the loop's lag is also the metric "
        "jitdyn_loop_lag_seconds",
    )


def _setting(f: dataclasses.Field[Any]) -> Setting:
    spec = f.metadata["jitdyn_setting"]
    return Setting(
        name=f.name,
        parse=spec["parse"],
        help=spec["help"],
        commands=spec["commands"],
        flag=spec["flag"] or "--" + f.name.replace("_", "-"),
        env=spec["env"] or ENV_PREFIX + f.name.upper(),
        metavar=spec["metavar"],
        is_flag=spec["switch"],
        default_text=spec["default_text"],
        group=spec["group"],
    )


SETTINGS: Final[tuple[Setting, ...]] = tuple(_setting(f) for f in dataclasses.fields(Settings))
DEFAULTS: Final = Settings()


def settings_for(command: str) -> Iterator[Setting]:
    """The settings whose flags `command` takes, in declaration order."""
    return (s for s in SETTINGS if command in s.commands)


def _default_text(s: Setting) -> str:
    value = getattr(DEFAULTS, s.name)
    if s.default_text is not None:
        return s.default_text
    if value is None:
        return "none"
    if s.is_flag:
        return "off"
    return str(value)


def add_arguments(parser: argparse.ArgumentParser, command: str) -> None:
    """Put the flags of `command`'s settings on `parser`, defaults SUPPRESSed (see `resolve`); a
    setting of a group under that group's heading."""
    groups: dict[str, argparse._ArgumentGroup] = {}
    for s in settings_for(command):
        text = f"{s.help} (env {s.env}; default {_default_text(s)})".replace("%", "%%")
        target: argparse.ArgumentParser | argparse._ArgumentGroup = parser
        if s.group is not None:
            target = groups.get(s.group) or groups.setdefault(s.group, parser.add_argument_group(s.group))
        if s.is_flag:
            target.add_argument(
                s.flag, dest=s.name, action="store_true", default=argparse.SUPPRESS, help=text
            )
        else:
            target.add_argument(
                s.flag,
                dest=s.name,
                type=argparse_type(s.parse, s.name),
                default=argparse.SUPPRESS,
                metavar=s.metavar,
                help=text,
            )


def argparse_type(parse: Callable[[str], Any], name: str) -> Callable[[str], Any]:
    """`parse` as an argparse `type=`: its ValueError becomes argparse's one-line usage error."""

    def convert(text: str) -> Any:
        try:
            return parse(text)
        except ValueError as error:
            raise argparse.ArgumentTypeError(str(error)) from None

    convert.__name__ = name  # argparse names the type in some messages
    return convert


def resolve(given: argparse.Namespace | Mapping[str, Any] | None, environ: Mapping[str, str]) -> Settings:
    """The settings: each from `given` (parsed flags, already typed) when there, else from its
    environment variable (parsed and checked here), else its default.

    Raises:
      SettingError: an environment variable's value is not valid for its setting.
    """
    values = vars(given) if isinstance(given, argparse.Namespace) else dict(given or {})
    chosen: dict[str, Any] = {}
    for s in SETTINGS:
        if s.name in values:
            chosen[s.name] = values[s.name]
        elif environ.get(s.env) is not None:
            try:
                chosen[s.name] = s.parse(environ[s.env])
            except ValueError as error:
                raise SettingError(f"environment variable {s.env}: {error}") from None
    return Settings(**chosen)


def settings_table() -> str:
    """The settings as a Markdown table: flag, environment variable, default, commands, meaning."""
    lines = ["| flag | environment | default | commands | what it sets |", "|---|---|---|---|---|"]
    for s in SETTINGS:
        lines.append(f"| `{s.flag}` | `{s.env}` | {_default_text(s)} | {', '.join(s.commands)} | {s.help} |")
    return "\n".join(lines)
