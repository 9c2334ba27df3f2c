"""The `jitdyn` command line: serve, models, demo, replay, lsl, sessions, experiments.

Every option is accepted wherever a user puts it: `-v` and a group's options (`--server` of
`models`, `--data` of `sessions`) work before or after the action, because each leaf parser takes
them too (argparse `parents=`, defaults SUPPRESSed so that the last one given wins). Settings come
from flags, then environment variables, then defaults, all read by jitdyn.settings.

Exit codes: 0 done; 1 the command could not do it (the server refused, a file is missing, a
needed extra is not installed); 2 a usage error (a bad flag, a bad setting in the environment);
130 interrupted. Every failure a user can cause prints one line on stderr, never a traceback.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import difflib
import logging
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NoReturn

from jitdyn.cli.commands import COMMANDS, Command, ModelRef, OneOf
from jitdyn.cli.extras import MissingExtra, require_extra
from jitdyn.errors import FailedPrecondition, JitdynError, Unavailable
from jitdyn.registry.builtins import BUILTIN_NAMES
from jitdyn.settings import SettingError, Settings, add_arguments, default_workers, resolve
from jitdyn.vocabulary import Clock, Scenario, parse

__all__ = ["DEFAULT_SERVER", "EXIT_ERROR", "EXIT_USAGE", "build_parser", "main"]

EXIT_ERROR = 1
EXIT_USAGE = 2
DEFAULT_SERVER = "127.0.0.1:50051"

_LEAF = "_leaf_parser"
_EPILOG = "exit codes: 0 done, 1 the command failed (one line on stderr says why), 2 usage error"


def _installed_version() -> str:
    """jitdyn's version, as the installed package's metadata says."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("jitdyn")
    except PackageNotFoundError:  # run from a checkout that is not installed
        return "(not installed)"


class _Parser(argparse.ArgumentParser):
    """A parser whose description may be written only when its help is shown (`sessions query`'s
    lists the stored columns, which takes the Parquet stack: parsing loads no numeric library)."""

    lazy_description: Callable[[], str] | None = None

    def format_help(self) -> str:
        if self.lazy_description is not None:
            self.description, self.lazy_description = self.lazy_description(), None
        return super().format_help()


def _common() -> _Parser:
    """Options of every parser, top-level and leaves alike."""
    common = _Parser(add_help=False)
    common.add_argument(
        "-v", "--verbose", action="store_true", default=argparse.SUPPRESS, help="log more (server and client)"
    )
    return common


def _settings_parent(command: str) -> _Parser:
    parent = _Parser(add_help=False)
    add_arguments(parent, command)
    return parent


def build_parser() -> argparse.ArgumentParser:
    """The parser of every command, read from the table in jitdyn.cli.commands."""
    common = _common()
    parser = _Parser(
        prog="jitdyn",
        parents=[common],
        epilog=_EPILOG,
        description="Cloud, just-in-time MuJoCo dynamics of biomechanical models over gRPC, with "
        "Unscented Kalman Filter latency compensation and anonymised Parquet storage.",
    )
    parser.add_argument(
        "--version",
        action="version",
        version=f"jitdyn {_installed_version()}",
        help="print jitdyn's version and exit",
    )
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for command in COMMANDS:
        _add_command(commands, command, command.name, common)
    return parser


def _add_command(
    subparsers: argparse._SubParsersAction[_Parser],
    command: Command,
    group: str,
    common: _Parser,
) -> None:
    """`command`'s parser, with its options, the settings of `group` and its actions' parsers."""
    if command.passthrough:
        rest = subparsers.add_parser(
            command.name, help=command.help, description=str(command.description), add_help=False
        )
        rest.add_argument("rest", nargs=argparse.REMAINDER)
        return
    parser = subparsers.add_parser(
        command.name,
        parents=[common, _settings_parent(group)],
        epilog=_EPILOG,
        help=command.help,
        description=command.description if isinstance(command.description, str) else None,
        formatter_class=argparse.RawDescriptionHelpFormatter
        if command.raw_description
        else argparse.HelpFormatter,
    )
    if callable(command.description):
        parser.lazy_description = command.description
    # The innermost parser reached, so that an option it does not know shows its usage.
    parser.set_defaults(**{_LEAF: parser})
    for entry in command.options:
        if isinstance(entry, OneOf):
            exclusive = parser.add_mutually_exclusive_group(required=entry.required)
            for one in entry.options:
                exclusive.add_argument(*one.flags, **one.kwargs)
        else:
            parser.add_argument(*entry.flags, **entry.kwargs)
    if command.actions:
        actions = parser.add_subparsers(dest=f"{command.name}_command", metavar="ACTION", required=True)
        for action in command.actions:
            _add_command(actions, action, group, common)


def _server_config(settings: Settings, **overrides: Any) -> Any:
    from jitdyn.server.transport.app import ServerConfig

    return ServerConfig.from_settings(settings, **overrides)


def _serve(args: argparse.Namespace, settings: Settings) -> int:
    from jitdyn.server.transport.app import serve

    if settings.workers is None:  # the CPUs shared among the processes (jitdyn.settings.default_workers)
        settings = dataclasses.replace(settings, workers=default_workers(settings.processes))
    config = _server_config(settings)
    if settings.processes > 1:
        from jitdyn.server.transport.processes import run_processes

        run_processes(config, processes=settings.processes, announce=lambda line: print(line, flush=True))
    else:
        asyncio.run(serve(config, announce=lambda line: print(line, flush=True)))
    return 0


def _models(args: argparse.Namespace, settings: Settings) -> int:
    from jitdyn.client import Client
    from jitdyn.client import ModelRef as Registered

    def show(model: Registered) -> None:
        print(
            f"{model.id}  {model.name} v{model.version}  nq={model.nq} nv={model.nv} nu={model.nu} "
            f"timestep={model.timestep:g}s{'  builtin' if model.builtin else ''}  tags={','.join(model.tags)}"
        )

    if args.models_command == "register" and args.myo:
        require_extra("myo_sim", what="myo-sim (MyoSuite models)", extra="myo")
        from jitdyn.client.myo import registrable_myo_models, resolve_myo_name

        if args.myo.strip().lower() == "list":
            for myo in registrable_myo_models():
                print(myo.line())
            return 0
        try:
            args.myo = resolve_myo_name(args.myo)
        except ValueError as error:
            raise SettingError(f"--myo: {error}") from None
    address = settings.server or DEFAULT_SERVER
    with Client(address) as client:
        try:
            if args.models_command == "register":
                return _register(client, args, show)
            if args.models_command == "list":
                for model in client.list_models(name=args.name, tag=args.tag):
                    show(model)
                return 0
            ref: ModelRef = args.model
            message = client.get_model_message(model_id=ref.model_id, name=ref.name, version=ref.version)
        except Unavailable as error:
            raise Unavailable(
                f"no jitdyn server answered at {address} (give --server HOST:PORT or JITDYN_SERVER, or start "
                f"`jitdyn serve`): {error}"
            ) from None
    from google.protobuf import json_format

    # The proto's own field names, and every field, zeros included: a joint's range_lower of 0
    # is a value a reader looks for, not an absence.
    print(
        json_format.MessageToJson(
            message, indent=2, preserving_proto_field_name=True, always_print_fields_with_no_presence=True
        )
    )
    return 0


def _register(client: Any, args: argparse.Namespace, show: Callable[[Any], None]) -> int:
    tags: list[str] = args.tag
    description: str = args.description
    if args.myo:
        from importlib.metadata import version as package_version

        from jitdyn.client.myo import pack_myo_model

        try:
            mjcf, assets = pack_myo_model(args.myo)
        except ValueError as error:
            raise FailedPrecondition(str(error)) from None
        name = args.name or args.myo
        tags = tags or ["myosuite"]
        description = description or f"MyoSuite {args.myo}, packed from myo-sim {package_version('myo-sim')}"
    else:
        from jitdyn.client.assets import read_model_files

        mjcf, assets = read_model_files(args.file, asset_dir=args.asset_dir)
        name = args.name or args.file.stem
    size = len(mjcf.encode()) + sum(len(b) for b in assets.values())
    print(f"registering {name!r}: {len(assets)} assets, {size / 1e6:.1f} MB", file=sys.stderr)
    model, created = client.register_model(
        name=name, mjcf=mjcf, assets=assets, description=description, tags=tags
    )
    if created:
        print("registered", end=": ")
        show(model)
        return 0
    # The registry names each content once (proto: RegisterModel): the stored model comes back as
    # it is. Whatever was asked beyond it is said to be refused, not dropped silently.
    missing_tags = [t for t in tags if t not in model.tags]
    if model.name != name or missing_tags:
        asked = [f"the name {name!r}"] if model.name != name else []
        asked += [f"the tag {t!r}" for t in missing_tags]
        print(
            f"jitdyn models register: not registered: identical content is already registered as "
            f"{model.name} v{model.version} ({model.id}), and {' and '.join(asked)} "
            f"{'was' if len(asked) == 1 else 'were'} not added (the registry keeps one name per content); "
            f"use `jitdyn models show {model.name}:{model.version}`, or change the content",
            file=sys.stderr,
        )
        return EXIT_ERROR
    print("already registered (identical content)", end=": ")
    show(model)
    return 0


def _demo(args: argparse.Namespace, settings: Settings) -> int:
    from jitdyn.experiments.demo import DemoSettings, run_demo
    from jitdyn.experiments.truth import TruthSources

    demo = DemoSettings(
        model=args.model,
        scenario=args.scenario,
        seconds=args.seconds,
        latency=args.latency,
        jitter=args.jitter,
        loss=args.loss,
        seed=args.seed,
        estimator=args.estimator,
        clock=args.clock,
    )
    if not settings.server and (args.mjcf or args.asset_dir):
        raise SettingError(
            "--mjcf and --asset-dir go with --server: the local server's models are in its --data"
        )
    # Against --server, a folder on this machine may hold the model's MJCF (a `jitdyn serve` beside
    # the demo's), or --mjcf names it.
    here = settings.data.resolve() if settings.data.is_dir() else None
    remote = TruthSources(data=here, mjcf=args.mjcf, asset_dir=args.asset_dir)
    _against_server(
        settings,
        args.model,
        lambda address, local: run_demo(
            address,
            demo,
            out=sys.stdout,
            progress=sys.stderr.isatty(),
            local_data=local,
            sources=remote if local is None else None,
        ),
    )
    return 0


def _against_server(settings: Settings, model: str, run: Callable[[str, Path | None], object]) -> None:
    """`run(address, local data folder)` against --server, else a local in-process server on the
    data folder (which must exist for a model that is not built in)."""
    if settings.server:
        run(settings.server, None)
        return
    from jitdyn.server.transport.background import BackgroundServer

    data = settings.data.resolve()
    if model.partition(":")[0] not in BUILTIN_NAMES and not settings.index_url and not data.is_dir():
        raise FailedPrecondition(
            f"no model {model!r} here: {data} does not exist, so only the built-in models "
            f"({', '.join(BUILTIN_NAMES)}) are registered; register it first (jitdyn models register) or "
            "give --data of the folder that holds it"
        )
    config = _server_config(settings, address="127.0.0.1:0")
    print(f"starting a local jitdyn server (data in {data})", flush=True)
    with BackgroundServer(config) as server:
        run(server.address, data)


def _replay(args: argparse.Namespace, settings: Settings) -> int:
    from jitdyn.cli.replay import ReplaySettings, load_trial, run_replay
    from jitdyn.experiments.netem import NetworkProfile

    replay = ReplaySettings(
        file=args.file,
        model=args.model,
        map_file=args.map_file,
        scenario=parse(Scenario, args.scenario, argument="--scenario") if args.scenario else None,
        clock=parse(Clock, args.clock, argument="--clock") if args.clock else None,
        network=NetworkProfile(latency=args.latency, jitter=args.jitter, loss=args.loss),
        seed=args.seed,
        angles=args.angles,
        dt=args.dt,
        start=args.start,
        end=args.end,
    )
    trial = load_trial(replay)  # a file it cannot replay is said before a server starts
    _against_server(
        settings,
        args.model,
        lambda address, local: run_replay(
            address, replay, trial, out=sys.stdout, progress=sys.stderr.isatty(), local_data=local
        ),
    )
    return 0


def _lsl(args: argparse.Namespace, settings: Settings) -> int:
    import signal
    import threading

    from jitdyn.cli.lsl import LslSettings, run_lsl

    require_extra("pylsl", what="pylsl (Lab Streaming Layer)", extra="lab")  # before a server starts

    lsl = LslSettings(
        stream=args.stream_name or args.stream_type,
        by="name" if args.stream_name else "type",
        model=args.model,
        map_file=args.map_file,
        scenario=parse(Scenario, args.scenario, argument="--scenario") if args.scenario else None,
        clock=parse(Clock, args.clock, argument="--clock") if args.clock else None,
        angles=args.angles,
        dt=args.dt,
        seconds=args.seconds,
        wait=args.wait,
        idle=args.idle,
        name=args.publish,
    )
    # Ctrl-C ends the session as the stream's end would: closed, summarised and stored.
    stop = threading.Event()
    previous = signal.signal(signal.SIGINT, lambda *_: stop.set())
    try:
        _against_server(
            settings,
            args.model,
            lambda address, local: run_lsl(
                address, lsl, out=sys.stdout, progress=sys.stderr.isatty(), local_data=local, stop=stop
            ),
        )
    finally:
        signal.signal(signal.SIGINT, previous)
    return 0


def _sessions(args: argparse.Namespace, settings: Settings) -> int:
    from jitdyn.cli.sessions import run_sessions_command

    return run_sessions_command(args, settings)


_HANDLERS: dict[str, Callable[[argparse.Namespace, Settings], int]] = {
    "serve": _serve,
    "models": _models,
    "demo": _demo,
    "replay": _replay,
    "lsl": _lsl,
    "sessions": _sessions,
}


def _experiments(argv: list[str], *, verbose: bool) -> int:
    from jitdyn.experiments.reproduce import main as experiments_main
    from jitdyn.experiments.reproduce import parser

    # Parsed first: `--help` and a usage error need none of the extras, running does.
    parser().parse_args(argv)
    require_extra("matplotlib", what="matplotlib (plots)", extra="experiments")
    require_extra("myo_sim", what="myo-sim (the MyoSuite objects)", extra="experiments")
    return int(experiments_main(argv, verbose=verbose) or 0)


def _action_first(argv: list[str], parser: argparse.ArgumentParser) -> list[str]:
    """`argv` with a group's action moved before the options given ahead of it: `sessions --limit 2
    list` as `sessions list --limit 2`, since argparse reads the action's options only after it."""
    groups = _subcommands(parser)
    for start, word in enumerate(argv):
        if word in groups:
            break
    else:
        return argv
    group = groups[argv[start]]
    actions = _subcommands(group)
    takes_value = {
        option: action.nargs != 0
        for leaf in (group, *actions.values())
        for action in leaf._actions
        for option in action.option_strings
    }
    i = start + 1
    while i < len(argv) and argv[i].startswith("-") and argv[i] != "--":
        i += 2 if takes_value.get(argv[i], False) else 1
    if i == start + 1 or i >= len(argv) or argv[i] not in actions:
        return argv
    return [*argv[: start + 1], argv[i], *argv[start + 1 : i], *argv[i + 1 :]]


def _subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """The parsers of `parser`'s subcommands by name; {} for a leaf."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _did_you_mean(parser: argparse.ArgumentParser, unknown: list[str]) -> str:
    """' (did you mean --latency?)' for a mistyped option the parser has one close to."""
    known = [option for action in parser._actions for option in action.option_strings]
    for word in unknown:
        close = difflib.get_close_matches(word.partition("=")[0], known, n=1)
        if word.startswith("--") and close:
            return f" (did you mean {close[0]}?)"
    return ""


def _fail(command: str, message: str, code: int = EXIT_ERROR) -> NoReturn:
    print(f"jitdyn {command}: {message}", file=sys.stderr)
    raise SystemExit(code)


def _command_name(args: argparse.Namespace) -> str:
    parts = [args.command]
    for attr in ("models_command", "sessions_command"):
        if getattr(args, attr, None):
            parts.append(getattr(args, attr))
    return " ".join(parts)


def _configure_logging(verbose: bool) -> None:
    try:
        from jitdyn.mujoco_log import route_mujoco_messages
    except Exception as error:  # MuJoCo's import reads MUJOCO_GL and loads its renderer
        gl = os.environ.get("MUJOCO_GL")
        if gl is None:
            raise
        raise SettingError(
            f"environment variable MUJOCO_GL={gl}: MuJoCo does not start with it ({error}); install "
            "its library (libosmesa6 for osmesa, libegl1 for egl) or unset MUJOCO_GL"
        ) from None

    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s"
    )
    # Alembic says which migrations it checked at every start of the index: noise for `-v`.
    logging.getLogger("alembic").setLevel(logging.WARNING)
    route_mujoco_messages()


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    # `experiments` has its own parser (jitdyn.experiments): hand it everything after the word.
    leading = 0
    while leading < len(argv) and argv[leading] in ("-v", "--verbose"):
        leading += 1
    if argv[leading : leading + 1] == ["experiments"]:
        try:
            _configure_logging(leading > 0)
        except SettingError as error:
            _fail("experiments", str(error), EXIT_USAGE)
        try:
            return _experiments(argv[leading + 1 :], verbose=leading > 0)
        except MissingExtra as error:
            _fail("experiments", str(error))
        except JitdynError as error:
            _fail("experiments", f"{type(error).__name__}: {error}")
        except OSError as error:
            where = f" {error.filename}" if error.filename else ""
            _fail("experiments", f"{error.strerror or error}:{where}")
        except KeyboardInterrupt:
            return 130
    parser = build_parser()
    args, unknown = parser.parse_known_args(_action_first(argv, parser))
    if unknown:
        leaf: argparse.ArgumentParser = getattr(args, _LEAF, parser)
        leaf.error(f"unrecognized arguments: {' '.join(unknown)}{_did_you_mean(leaf, unknown)}")
    command = _command_name(args)
    try:
        settings = resolve(args, os.environ)
        _configure_logging(getattr(args, "verbose", False))
    except SettingError as error:
        _fail(command, str(error), EXIT_USAGE)
    try:
        return _HANDLERS[args.command](args, settings)
    except SettingError as error:
        _fail(command, str(error), EXIT_USAGE)
    except MissingExtra as error:
        _fail(command, str(error))
    except JitdynError as error:
        _fail(command, f"{type(error).__name__}: {error}")
    except OSError as error:
        where = f" {error.filename}" if error.filename else ""
        _fail(command, f"{error.strerror or error}:{where}")
    except KeyboardInterrupt:
        return 130
