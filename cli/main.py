"""The `jitdyn` command line: serve, models, demo, sessions, experiments.

Settings come from flags, then environment variables (JITDYN_ADDRESS, JITDYN_SERVER, JITDYN_DATA,
JITDYN_INDEX_URL, JITDYN_SECRET_FILE, JITDYN_WORKERS), then defaults. Every subcommand has --help.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import re
import sys
from collections.abc import Sequence
from pathlib import Path

from jitdyn.cli.limits import add_limit_arguments, limit_settings
from jitdyn.errors import JitdynError

__all__ = ["main", "parse_duration"]

_DURATION = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*(us|ms|s)?\s*$")


def parse_duration(text: str) -> float:
    """'35ms' -> 0.035, '2s' -> 2.0, '0.01' -> 0.01 (seconds)."""
    match = _DURATION.match(text)
    if not match:
        raise argparse.ArgumentTypeError(f"expected a duration like 35ms, 0.5s or 0.035, got {text!r}")
    value = float(match.group(1))
    return value * {"us": 1e-6, "ms": 1e-3, "s": 1.0, None: 1.0}[match.group(2)]


def _probability(text: str) -> float:
    try:
        value = float(text.rstrip("%")) / (100.0 if text.endswith("%") else 1.0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a probability like 0.05 or 5%, got {text!r}") from None
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a probability in [0, 1], got {text!r}")
    return value


def _env(name: str, default: str) -> str:
    return os.environ.get(name, default)


def _data_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--data",
        type=Path,
        default=Path(_env("JITDYN_DATA", "jitdyn-data")),
        help="data folder: Parquet frames, model store, default SQLite index (env JITDYN_DATA; default ./jitdyn-data)",
    )


def _index_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--index",
        default=os.environ.get("JITDYN_INDEX_URL"),
        help="SQL index URL, e.g. postgresql+psycopg://user@host/db (env JITDYN_INDEX_URL; default: "
        "a SQLite file in the data folder)",
    )


def _server_arg(parser: argparse.ArgumentParser, *, help_text: str) -> None:
    parser.add_argument("--server", default=os.environ.get("JITDYN_SERVER"), help=help_text)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jitdyn",
        description="Cloud, just-in-time MuJoCo dynamics of biomechanical models over gRPC, with "
        "Unscented Kalman Filter latency compensation and anonymised Parquet storage.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log more (server and client)")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    serve = commands.add_parser(
        "serve", help="run the server", description="Run the jitdyn server until Ctrl-C or SIGTERM."
    )
    serve.add_argument(
        "--address",
        default=_env("JITDYN_ADDRESS", "127.0.0.1:50051"),
        help="HOST:PORT to listen on (env JITDYN_ADDRESS; default 127.0.0.1:50051; port 0 picks one). "
        "A non-loopback address needs --tls-cert/--tls-key or --insecure",
    )
    _data_arg(serve)
    _index_arg(serve)
    serve.add_argument(
        "--workers",
        type=int,
        default=int(_env("JITDYN_WORKERS", str(os.cpu_count() or 2))),
        help="threads propagating sigma points, shared by all sessions (env JITDYN_WORKERS; default: the CPU count)",
    )
    serve.add_argument(
        "--processes",
        type=int,
        default=int(_env("JITDYN_PROCESSES", str(os.cpu_count() or 1))),
        help="server processes on the one port (SO_REUSEPORT), each with its own event loop and "
        "worker pool, sharing the data folder and index (env JITDYN_PROCESSES; default: the CPU count)",
    )
    serve.add_argument(
        "--secret-file",
        type=Path,
        default=os.environ.get("JITDYN_SECRET_FILE"),
        help="HMAC key for subject pseudonyms, mode 0600, outside the data folder; created at first "
        "start (env JITDYN_SECRET_FILE; default ~/.config/jitdyn/secret.key; JITDYN_SECRET=hex overrides)",
    )
    serve.add_argument("--tls-cert", type=Path, help="PEM certificate chain, to serve over TLS")
    serve.add_argument("--tls-key", type=Path, help="PEM private key of --tls-cert")
    serve.add_argument(
        "--api-keys",
        type=Path,
        help="file of `KEY TENANT` lines: every RPC must then carry "
        "`authorization: Bearer KEY`, and sees only its tenant's sessions and models",
    )
    serve.add_argument(
        "--insecure", action="store_true", help="allow a non-loopback address without TLS and API keys"
    )
    serve.add_argument("--max-sessions", type=int, default=64, help="open sessions in total (default 64)")
    serve.add_argument(
        "--max-sessions-per-tenant", type=int, default=16, help="open sessions per tenant (default 16)"
    )
    serve.add_argument(
        "--max-state-dimension", type=int, default=200, help="largest nv of a session's model (default 200)"
    )
    add_limit_arguments(serve)

    models = commands.add_parser(
        "models", help="register, list and show models", description="The model registry, from the shell."
    )
    _server_arg(models, help_text="server ADDRESS (env JITDYN_SERVER; default 127.0.0.1:50051)")
    model_commands = models.add_subparsers(dest="models_command", metavar="ACTION", required=True)
    register = model_commands.add_parser(
        "register", help="register an MJCF file, or a MyoSuite model with --myo"
    )
    register.add_argument("file", nargs="?", type=Path, help="the MJCF file")
    register.add_argument("--name", help="name to register under (default: the file's stem)")
    register.add_argument(
        "--asset-dir",
        type=Path,
        help="folder of the meshes, textures and included XML the MJCF refers to "
        "(default: the MJCF's folder, only the files it names)",
    )
    register.add_argument(
        "--myo", choices=("myoelbow", "myohand"), help="pack a MyoSuite model from myo-sim with its meshes"
    )
    register.add_argument("--description", default="", help="free description")
    register.add_argument("--tag", action="append", default=[], help="a tag (repeatable)")
    listing = model_commands.add_parser("list", help="list registered models")
    listing.add_argument("--name", default="", help="only this name")
    listing.add_argument("--tag", default="", help="only models with this tag")
    show = model_commands.add_parser("show", help="show one model (by id, NAME or NAME:VERSION)")
    show.add_argument("model", help="sha256:... id, a name, or name:version")

    demo = commands.add_parser(
        "demo",
        help="a simulated REALTIME session over an emulated network",
        description="Drive a simulated research object (truth simulated by MuJoCo here) through an emulated "
        "network against a local in-process server (or --server), show progress, and print a summary.",
    )
    demo.add_argument(
        "--model", default="pendulum_3", help="built-in model: pendulum_1..3 or biped (default pendulum_3)"
    )
    demo.add_argument(
        "--scenario", default="passive", choices=("passive", "controlled", "external"), help="default passive"
    )
    demo.add_argument("--seconds", type=float, default=10.0, help="session length (default 10)")
    demo.add_argument("--latency", type=parse_duration, default=0.035, help="one-way latency (default 35ms)")
    demo.add_argument("--jitter", type=parse_duration, default=0.010, help="latency spread (default 10ms)")
    demo.add_argument("--loss", type=_probability, default=0.05, help="frame loss probability (default 0.05)")
    demo.add_argument(
        "--estimator", default="UKF", choices=("UKF", "STATIC", "CONSTANT_VELOCITY", "CONSTANT_ACCELERATION")
    )
    demo.add_argument("--seed", type=int, default=0, help="seed of the emulated network and the start state")
    _server_arg(demo, help_text="use this server instead of starting one in-process (env JITDYN_SERVER)")
    _data_arg(demo)

    sessions = commands.add_parser(
        "sessions",
        help="list, show, query and export stored sessions",
        description="The stored sessions, read from the data folder and the SQL index.",
    )
    _data_arg(sessions)
    _index_arg(sessions)
    session_commands = sessions.add_subparsers(dest="sessions_command", metavar="ACTION", required=True)
    slist = session_commands.add_parser("list", help="list sessions, newest first")
    slist.add_argument("--model", help="only this model name")
    slist.add_argument("--status", choices=("OPEN", "COMPLETE", "RECOVERED", "FAILED", "ABANDONED"))
    slist.add_argument("--limit", type=int, default=50)
    sshow = session_commands.add_parser("show", help="show one session")
    sshow.add_argument("session_id")
    squery = session_commands.add_parser(
        "query", help="run SQL with DuckDB over the frames (view `frames`) and the index (table `sessions`)"
    )
    squery.add_argument("sql", help='e.g. "SELECT source, count(*) FROM frames GROUP BY source"')
    squery.add_argument("--csv", type=Path, help="write the result as CSV here instead of printing it")
    sexport = session_commands.add_parser("export", help="export one session as CSV or OpenSim .sto")
    sexport.add_argument("session_id")
    sexport.add_argument("--format", choices=("csv", "sto"), default="csv")
    sexport.add_argument("--out", type=Path, help="output file (default <session id>.<format>)")

    experiments = commands.add_parser(
        "experiments",
        help="reproduce the thesis experiments",
        add_help=False,
        description="Reproduce every experiment of the thesis; see `jitdyn experiments --help`.",
    )
    experiments.add_argument("rest", nargs=argparse.REMAINDER)
    return parser


def _serve(args: argparse.Namespace) -> int:
    from jitdyn.server.runtime.services import SessionLimits
    from jitdyn.server.transport.app import ServerConfig, serve

    config = ServerConfig(
        address=args.address,
        data_root=args.data,
        index_url=args.index,
        workers=args.workers,
        secret_file=args.secret_file,
        tls_cert=args.tls_cert,
        tls_key=args.tls_key,
        api_keys=args.api_keys,
        insecure=args.insecure,
        session_limits=SessionLimits(
            max_sessions=args.max_sessions,
            max_sessions_per_tenant=args.max_sessions_per_tenant,
            max_state_dimension=args.max_state_dimension,
        ),
        **limit_settings(args),
    )
    if args.processes > 1:
        from jitdyn.server.transport.processes import run_processes

        run_processes(config, processes=args.processes, announce=lambda line: print(line, flush=True))
    else:
        asyncio.run(serve(config, announce=lambda line: print(line, flush=True)))
    return 0


def _models(args: argparse.Namespace) -> int:
    from jitdyn.client.sdk import Client, ModelRef

    def show(model: ModelRef) -> None:
        print(
            f"{model.id}  {model.name} v{model.version}  nq={model.nq} nv={model.nv} nu={model.nu} "
            f"timestep={model.timestep:g}s{'  builtin' if model.builtin else ''}  tags={','.join(model.tags)}"
        )

    with Client(args.server or "127.0.0.1:50051") as client:
        if args.models_command == "register":
            if args.myo:
                from jitdyn.client.myo import pack_myo_model

                mjcf, assets = pack_myo_model(args.myo)
                name = args.name or args.myo
                from importlib.metadata import version as package_version

                args.tag = args.tag or ["myosuite"]
                args.description = (
                    args.description
                    or f"MyoSuite {args.myo}, packed from myo-sim {package_version('myo-sim')}"
                )

            else:
                if args.file is None:
                    raise SystemExit("jitdyn models register: give an MJCF FILE or --myo NAME")
                from jitdyn.client.assets import read_model_files

                mjcf, assets = read_model_files(args.file, asset_dir=args.asset_dir)
                name = args.name or args.file.stem
            size = len(mjcf.encode()) + sum(len(b) for b in assets.values())
            print(f"registering {name!r}: {len(assets)} assets, {size / 1e6:.1f} MB", file=sys.stderr)
            model, created = client.register_model(
                name=name, mjcf=mjcf, assets=assets, description=args.description, tags=args.tag
            )
            print("registered" if created else "already registered (identical content)", end=": ")
            show(model)
        elif args.models_command == "list":
            for model in client.list_models(name=args.name, tag=args.tag):
                show(model)
        else:
            text = args.model
            if text.startswith("sha256:"):
                message = client.get_model_message(model_id=text)
            else:
                name, _, version = text.partition(":")
                message = client.get_model_message(name=name, version=int(version or 0))
            from google.protobuf import json_format

            print(json_format.MessageToJson(message, indent=2))
    return 0


def _demo(args: argparse.Namespace) -> int:
    from jitdyn.experiments.demo import DemoSettings, run_demo

    settings = DemoSettings(
        model=args.model,
        scenario=args.scenario,
        seconds=args.seconds,
        latency=args.latency,
        jitter=args.jitter,
        loss=args.loss,
        seed=args.seed,
        estimator=args.estimator,
    )
    if args.server:
        run_demo(args.server, settings, out=sys.stdout)
        return 0
    from jitdyn.server.transport.app import ServerConfig
    from jitdyn.server.transport.background import BackgroundServer

    print(f"starting a local jitdyn server (data in {args.data.resolve()})", flush=True)
    with BackgroundServer(ServerConfig(address="127.0.0.1:0", data_root=args.data)) as server:
        run_demo(server.address, settings, out=sys.stdout)
    return 0


def _sessions(args: argparse.Namespace) -> int:
    from jitdyn.cli.sessions import run_sessions_command

    return run_sessions_command(args)


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["experiments"]:
        from jitdyn.experiments import main as experiments_main

        return int(experiments_main(argv[1:]) or 0)
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s"
    )
    try:
        handler = {"serve": _serve, "models": _models, "demo": _demo, "sessions": _sessions}[args.command]
        return handler(args)
    except JitdynError as error:
        print(f"jitdyn {args.command}: {type(error).__name__}: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
