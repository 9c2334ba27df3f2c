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
import textwrap
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

from jitdyn.cli.extras import MissingExtra, require_extra
from jitdyn.errors import FailedPrecondition, JitdynError, Unavailable
from jitdyn.registry.builtins import BUILTIN_NAMES
from jitdyn.settings import (
    SettingError,
    Settings,
    add_arguments,
    argparse_type,
    checked,
    default_workers,
    parse_duration,
    parse_model_reference,
    parse_seconds,
    positive_int,
    resolve,
)
from jitdyn.vocabulary import Clock, EstimatorKind, Scenario, SessionStatus, parse

__all__ = ["DEFAULT_SERVER", "EXIT_ERROR", "EXIT_USAGE", "build_parser", "main"]

EXIT_ERROR = 1
EXIT_USAGE = 2
DEFAULT_SERVER = "127.0.0.1:50051"

_LEAF = "_leaf_parser"
_EPILOG = "exit codes: 0 done, 1 the command failed (one line on stderr says why), 2 usage error"


def _fraction_or_percent(text: str) -> float:
    return float(text.rstrip("%")) / (100.0 if text.endswith("%") else 1.0)


_probability = checked(
    _fraction_or_percent,
    lambda value: 0.0 <= value <= 1.0,
    "a probability in [0, 1]",
    malformed="a probability like 0.05 or 5%",
)
_positive_duration = checked(parse_duration, lambda value: value > 0, "a duration > 0, like 10ms")
_seconds = checked(
    parse_seconds,
    lambda value: value > 0,
    "a duration > 0, like 10s, 2500ms or 10 (seconds)",
)


def _word(kind: type[Any], flag: str, *, lower: bool) -> dict[str, Any]:
    """`type=` and `metavar=` of an option that takes a member of the vocabulary's `kind`, in any
    case, as the SDK takes it (jitdyn.vocabulary.parse); shown in the case the help writes it."""
    names = [member.name.lower() if lower else member.name for member in kind]

    def convert(text: str) -> Any:
        try:
            return parse(kind, text, argument=flag)
        except JitdynError:
            raise argparse.ArgumentTypeError(
                f"expected one of {', '.join(names)} (in any case), got {text!r}"
            ) from None

    convert.__name__ = flag
    return {"type": convert, "metavar": "{" + ",".join(names) + "}"}


@dataclass(frozen=True)
class ModelRef:
    """What `models show` was given: a content id, or a name and a version (0: the newest)."""

    model_id: str = ""
    name: str = ""
    version: int = 0


def _model_ref(text: str) -> ModelRef:
    model_id, name, version = parse_model_reference(text)
    return ModelRef(model_id=model_id, name=name, version=version)


def _installed_version() -> str:
    """jitdyn's version, as the installed package's metadata says."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("jitdyn")
    except PackageNotFoundError:  # run from a checkout that is not installed
        return "(not installed)"


def _common() -> argparse.ArgumentParser:
    """Options of every parser, top-level and leaves alike."""
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "-v", "--verbose", action="store_true", default=argparse.SUPPRESS, help="log more (server and client)"
    )
    return common


def _settings_parent(command: str) -> argparse.ArgumentParser:
    parent = argparse.ArgumentParser(add_help=False)
    add_arguments(parent, command)
    return parent


def build_parser() -> argparse.ArgumentParser:
    common = _common()
    parser = argparse.ArgumentParser(
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

    def leaf(
        subparsers: argparse._SubParsersAction[argparse.ArgumentParser],
        name: str,
        group: str | None = None,
        **kwargs: Any,
    ) -> argparse.ArgumentParser:
        """A command's parser, with the settings of `group` (default: the command itself)."""
        command = subparsers.add_parser(
            name, parents=[common, _settings_parent(group or name)], epilog=_EPILOG, **kwargs
        )
        # The innermost parser reached, so that an option it does not know shows its usage.
        command.set_defaults(**{_LEAF: command})
        return command

    leaf(
        commands,
        "serve",
        help="run the server",
        description="Run the jitdyn server until Ctrl-C or SIGTERM.",
    )

    models = leaf(
        commands,
        "models",
        help="register, list and show models",
        description="The model registry, from the shell.",
    )
    model_commands = models.add_subparsers(dest="models_command", metavar="ACTION", required=True)
    register = leaf(
        model_commands,
        "register",
        "models",
        help="register an MJCF file, or a MyoSuite model with --myo",
        description="Register an MJCF file with the files it names, or a MyoSuite model (--myo). Content "
        "already registered is not registered again: it keeps its name, and a different --name or "
        "--tag is refused (exit 1) rather than dropped silently.",
    )
    what = register.add_mutually_exclusive_group(required=True)
    what.add_argument("file", nargs="?", type=Path, help="the MJCF file")
    what.add_argument(
        "--myo",
        metavar="NAME",
        help="pack the MyoSuite model NAME from myo-sim with its meshes (needs jitdyn[myo]): myoelbow, "
        "myohand, myolegs, myolegs_osl, ...; `--myo list` lists every one that compiles (no server needed)",
    )
    register.add_argument(
        "--name", help="name to register under (default: the file's stem, or the --myo name)"
    )
    register.add_argument(
        "--asset-dir",
        type=Path,
        help="folder of the meshes, textures and included XML the MJCF refers to "
        "(default: the MJCF's folder, only the files it names)",
    )
    register.add_argument("--description", default="", help="free description")
    register.add_argument("--tag", action="append", default=[], help="a tag (repeatable)")
    listing = leaf(model_commands, "list", "models", help="list registered models")
    listing.add_argument("--name", default="", help="only this name")
    listing.add_argument("--tag", default="", help="only models with this tag")
    show = leaf(model_commands, "show", "models", help="show one model (by id, NAME or NAME:VERSION)")
    show.add_argument(
        "model", type=argparse_type(_model_ref, "model"), help="sha256:... id, a name, or name:version"
    )

    demo = leaf(
        commands,
        "demo",
        help="a simulated REALTIME session over an emulated network",
        description="Drive a simulated research object (truth simulated by MuJoCo here) through an emulated "
        "network against a local in-process server (or --server), show progress, and print a summary. A "
        "model whose REALTIME session the server refuses runs LOCKSTEP instead (see --clock).",
    )
    demo.add_argument(
        "--model",
        default="pendulum_3",
        type=argparse_type(lambda text: _model_ref(text) and text, "model"),
        metavar="MODEL",
        help="a registered model: NAME, NAME:VERSION or sha256:ID; a built-in, or one registered in the "
        "data folder (default pendulum_3)",
    )
    demo.add_argument(
        "--mjcf",
        type=Path,
        metavar="FILE",
        help="with --server, the MJCF file --model was registered from, which the demo simulates its truth "
        "with (default: the model's copy in --data, built-ins and MyoSuite models need none)",
    )
    demo.add_argument(
        "--asset-dir",
        type=Path,
        metavar="DIR",
        help="folder of the files --mjcf names, as for `models register` (default: the MJCF's folder)",
    )
    demo.add_argument(
        "--scenario",
        **_word(Scenario, "--scenario", lower=True),
        help="what moves the body, as the filter models it (any case): default passive for a built-in "
        "model, else the server's choice for the model (driven for one with actuators)",
    )
    demo.add_argument(
        "--seconds",
        type=argparse_type(_seconds, "seconds"),
        default=10.0,
        metavar="DURATION",
        help="session length: 10s, 2500ms, or a bare number of seconds (default 10s)",
    )
    _add_network(demo, latency="35ms", jitter="10ms", loss=0.05)
    demo.add_argument(
        "--estimator",
        default=EstimatorKind.UKF,
        **_word(EstimatorKind, "--estimator", lower=False),
        help="what answers a tick whose frame is late or lost (any case): UKF, the Unscented Kalman Filter "
        "on the model's dynamics (default); STATIC, CONSTANT_VELOCITY and CONSTANT_ACCELERATION, dead "
        "reckoning from the last frames, for comparison",
    )
    demo.add_argument(
        "--seed",
        type=int,
        default=0,
        help="seed of the emulated network's latency and loss and of the start state (default 0): the "
        "same seed sends the same frames at the same times",
    )
    demo.add_argument(
        "--clock",
        **_word(Clock, "--clock", lower=True),
        help="realtime: ticks on the server's clock, over the emulated network; lockstep: each frame "
        "answered as it is sent (loss emulated as skipped ticks). Default: realtime, or lockstep, "
        "said so, when the server refuses a realtime session for its cost or its machine's load (a big "
        "MyoSuite model such as myolegs_osl)",
    )

    _add_replay(commands, leaf)
    _add_lsl(commands, leaf)

    sessions = leaf(
        commands,
        "sessions",
        help="list, show, query, export, plot and render stored sessions",
        description="The stored sessions, read from the data folder and the SQL index (no server needed).",
    )
    session_commands = sessions.add_subparsers(dest="sessions_command", metavar="ACTION", required=True)
    slist = leaf(
        session_commands,
        "list",
        "sessions",
        help="list sessions, newest first",
        description="List the stored sessions, newest first, one a line: id, start, status, model, "
        "scenario, clock and the counts of its summary. ticks: distinct ticks answered; measured, "
        "predicted, corrected: answers of each source (a tick answered PREDICTED and then CORRECTED "
        "counts in both); rejected: frames refused, each stored with its reason (see `sessions "
        "query`); late: ticks whose frame came after the tick was answered, so that it was corrected "
        "(results with late_ticks > 0); a frame too late to be used at all is rejected TOO_OLD instead.",
    )
    slist.add_argument(
        "--model",
        type=argparse_type(_model_ref, "model"),
        metavar="MODEL",
        help="only sessions of this model: NAME (every version), NAME:VERSION or sha256:ID",
    )
    slist.add_argument(
        "--status",
        **_word(SessionStatus, "--status", lower=False),
        help="only sessions that ended so (any case)",
    )
    slist.add_argument(
        "--limit",
        type=argparse_type(positive_int, "limit"),
        default=50,
        metavar="N",
        help="at most N (default 50)",
    )
    sshow = leaf(session_commands, "show", "sessions", help="show one session")
    sshow.add_argument("session_id")
    squery = leaf(
        session_commands,
        "query",
        "sessions",
        help="run SQL with DuckDB over the frames (view `frames`) and the index (table `sessions`)",
        description=_query_description(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    squery.add_argument("sql", help='e.g. "SELECT source, count(*) FROM frames GROUP BY source"')
    squery.add_argument(
        "--format",
        choices=("table", "csv", "json"),
        default="table",
        help="an aligned table (default), CSV with a header, or JSON lines (one object per row)",
    )
    squery.add_argument("--out", type=Path, help="write the result to this file instead of stdout")
    sexport = leaf(
        session_commands,
        "export",
        "sessions",
        help="export one session as CSV, OpenSim .sto or MCAP (Foxglove)",
        description="Write one stored session for tools outside jitdyn. csv: every stored row, one "
        "column per array element. sto: OpenSim's storage file, one row per tick (a correction "
        "replaces its prediction). mcap: the file Foxglove opens: joint states, forces, frames, "
        "sources and lateness as time series, and every body's pose at each tick (MuJoCo's forward "
        "kinematics on the stored model) as 3D frame transforms on /tf (needs jitdyn[lab]).",
    )
    sexport.add_argument("session_id")
    sexport.add_argument("--format", choices=("csv", "sto", "mcap"), default="csv")
    sexport.add_argument("--out", type=Path, help="output file (default <session id>.<format>)")
    splot = leaf(
        session_commands,
        "plot",
        "sessions",
        help="draw one session: q measured and answered, forces, lateness, NIS (needs jitdyn[experiments])",
        description="Draw one stored session as one figure on a shared time axis: the source of each "
        "tick's answer; per joint the measured q against the answered q (PREDICTED and CORRECTED ticks "
        "marked, gaps shaded) beside the answered generalized force; the frames' network lateness; the "
        "server's time to answer; the filter's NIS. A PNG, or one self-contained HTML page. Needs "
        "matplotlib (jitdyn[experiments]).",
    )
    splot.add_argument("session_id")
    splot.add_argument(
        "--out", type=Path, help="a .png or .html file, or a folder (default <session id>.png here)"
    )
    splot.add_argument(
        "--joints",
        nargs="+",
        metavar="NAME",
        default=[],
        help="the joints to draw, by name (default: the first 6 of the model)",
    )

    _add_render(session_commands, leaf)

    experiments = commands.add_parser(
        "experiments",
        help="reproduce the thesis experiments (needs jitdyn[experiments])",
        add_help=False,
        description="Reproduce every experiment of the thesis; see `jitdyn experiments --help`.",
    )
    experiments.add_argument("rest", nargs=argparse.REMAINDER)
    return parser


def _query_description() -> str:
    """`sessions query --help`: the tables, then every column of `frames` with its unit."""
    from jitdyn.storage.columns import FRAME_COLUMN_NOTES

    intro = (
        "Run SQL with DuckDB (needs jitdyn[query]) over the stored frames (view `frames`, one row per "
        "answer: a tick answered PREDICTED and later CORRECTED has two rows), the index (table "
        "`sessions`) and the names and units of the arrays' elements (table `coordinates`: session_id, "
        "vector 'qpos' for frame_qpos and qpos or 'dof' for the nv-long arrays, i as DuckDB indexes a "
        "list from 1, name, joint, unit rad or m, force_unit N m or N). Name a joint's values with "
        '"SELECT c.name, f.qfrc_inverse[c.i] FROM frames f JOIN coordinates c USING (session_id) '
        "WHERE c.vector = 'dof'\"."
    )
    width = max(len(name) for name in FRAME_COLUMN_NOTES)
    columns = "\n".join(f"  {name:<{width}}  {note}" for name, note in FRAME_COLUMN_NOTES.items())
    return f"{textwrap.fill(intro, 100)}\n\ncolumns of `frames` (unit: meaning):\n{columns}"


def _add_network(parser: argparse.ArgumentParser, *, latency: str, jitter: str, loss: float) -> None:
    """--latency, --jitter and --loss of the emulated network (experiments/netem.py)."""
    parser.add_argument(
        "--latency",
        type=argparse_type(parse_duration, "duration"),
        default=parse_duration(latency),
        metavar="DURATION",
        help=f"one-way latency of the emulated network, with a unit: 35ms, 0.1s (default {latency})",
    )
    parser.add_argument(
        "--jitter",
        type=argparse_type(parse_duration, "duration"),
        default=parse_duration(jitter),
        metavar="DURATION",
        help=f"latency spread with a unit (default {jitter})",
    )
    parser.add_argument(
        "--loss",
        type=argparse_type(_probability, "probability"),
        default=loss,
        metavar="P",
        help=f"frame loss probability: 0.05 or 5%% (default {loss:g})",
    )


def _clock_option(parser: argparse.ArgumentParser, realtime: str, *, emulated: bool = True) -> None:
    lockstep = "each frame answered as it is sent" + (" (loss emulated as skipped ticks)" if emulated else "")
    parser.add_argument(
        "--clock",
        **_word(Clock, "--clock", lower=True),
        help=f"realtime: ticks on the server's clock, {realtime}; lockstep: {lockstep}. Default: realtime, or "
        "lockstep, said so, when the server refuses a realtime session for its cost or its machine's load (a "
        "big MyoSuite model such as myolegs_osl)",
    )


def _add_replay(
    commands: argparse._SubParsersAction[argparse.ArgumentParser],
    leaf: Callable[..., argparse.ArgumentParser],
) -> None:
    from jitdyn.cli.trials import FORMATS

    replay = leaf(
        commands,
        "replay",
        help="stream a recorded trial's joint angles (.mot, .sto, .c3d, .csv) into a session",
        description="Stream the joint angles of a recorded trial into a session on a registered model, "
        "against a local in-process server (or --server), show progress, and print a summary like the "
        "demo's with the stored session. OpenSim .mot and .sto (degrees or radians as the header's "
        "inDegrees says), C3D (the angle outputs Vicon's Plug-in Gait stores as points, such as "
        "LKneeAngles: x flexion, y varus, z internal rotation; needs jitdyn[lab]) and CSV with a header "
        "(a time column, seconds). A column drives the model's joint of its name; --map FILE links the "
        "rest. Joints without a column are held at rest and columns without a joint are left out, both "
        "said in one line.",
    )
    replay.add_argument("file", type=Path, help=f"the recording: {', '.join(FORMATS)}")
    _add_joint_options(replay, units="as the file says: a .mot's inDegrees, degrees in C3D, radians in CSV")
    for flag, where in (("--start", "first"), ("--end", "last")):
        replay.add_argument(
            flag,
            type=argparse_type(parse_duration, "duration"),
            metavar="T",
            help=f"replay from (--start) or to (--end) this time on the file's clock, with a unit: 1.5s, "
            f"250ms (default: its {where} sample)",
        )
    _clock_option(replay, "each sample sent at its time in the file over the emulated network")
    _add_network(replay, latency="0ms", jitter="0ms", loss=0.0)
    replay.add_argument("--seed", type=int, default=0, help="seed of the emulated network (default 0)")


def _add_joint_options(parser: argparse.ArgumentParser, *, units: str) -> None:
    """--model, --map, --angles, --dt and --scenario of the commands that drive joints from columns."""
    parser.add_argument(
        "--model",
        required=True,
        type=argparse_type(lambda text: _model_ref(text) and text, "model"),
        metavar="MODEL",
        help="the registered model to drive: NAME, NAME:VERSION or sha256:ID (`jitdyn models list`)",
    )
    parser.add_argument(
        "--map",
        dest="map_file",
        type=Path,
        metavar="FILE",
        help="links of columns to joints the names do not make: one `JOINT = COLUMN` a line, "
        "`JOINT = -COLUMN` to flip its sign, # comments",
    )
    parser.add_argument(
        "--angles",
        choices=("deg", "rad"),
        help=f"the rotations are in degrees or radians (default: {units}); slides are metres either way",
    )
    parser.add_argument(
        "--dt",
        type=argparse_type(_positive_duration, "duration"),
        metavar="DURATION",
        help="the session's tick, with a unit: 10ms (default: the recording's step rounded up to a whole "
        "multiple of the model's timestep, as a session's dt must be)",
    )
    parser.add_argument(
        "--scenario",
        **_word(Scenario, "--scenario", lower=True),
        help="default: the server's choice for the model (driven for one with actuators)",
    )


def _add_lsl(
    commands: argparse._SubParsersAction[argparse.ArgumentParser],
    leaf: Callable[..., argparse.ArgumentParser],
) -> None:
    lsl = leaf(
        commands,
        "lsl",
        help="bridge a Lab Streaming Layer stream of joint angles and a session (needs jitdyn[lab])",
        description="Take a Lab Streaming Layer stream of joint angles (by --name or --type) into a session "
        "on a registered model, its sample times mapped onto this machine's LSL clock through the inlet's "
        "time_correction(), and publish the answers as two LSL streams stamped with each tick's time: NAME "
        "(the estimated qpos and qvel, qfrc_inverse and the source: 1 MEASURED, 2 PREDICTED, 3 CORRECTED) "
        "and NAME-lateness (frame_delay and answer_time, s), which LabRecorder stores beside the lab's "
        "other streams. Channels drive joints as in `jitdyn replay`. Runs until --seconds pass, the stream "
        "is silent for --idle, or Ctrl-C; then prints the summary. Needs jitdyn[lab] (pylsl, whose liblsl "
        "needs glibc 2.35 or newer).",
    )
    which = lsl.add_mutually_exclusive_group(required=True)
    which.add_argument("--name", dest="stream_name", metavar="NAME", help="the LSL stream's name")
    which.add_argument(
        "--type", dest="stream_type", metavar="TYPE", help="the LSL stream's type (the first found)"
    )
    _add_joint_options(lsl, units="as the channels' units say: deg, degree or degrees, else radians")
    _clock_option(lsl, "each sample sent as it comes", emulated=False)
    lsl.add_argument(
        "--seconds",
        type=argparse_type(_seconds, "seconds"),
        metavar="DURATION",
        help="end the session after this long on the stream's clock (default: when the stream stops)",
    )
    for flag, default, text in (
        ("--wait", 10.0, "how long to look for the stream, and for its first sample (default 10s)"),
        ("--idle", 2.0, "end the session when the stream sends nothing for this long (default 2s)"),
    ):
        lsl.add_argument(
            flag, type=argparse_type(_seconds, "seconds"), default=default, metavar="DURATION", help=text
        )
    lsl.add_argument(
        "--publish",
        default="jitdyn",
        metavar="NAME",
        help="the name of the answers' LSL stream; the lateness' is NAME-lateness (default jitdyn)",
    )


def _add_render(
    session_commands: argparse._SubParsersAction[argparse.ArgumentParser],
    leaf: Callable[..., argparse.ArgumentParser],
) -> None:
    from jitdyn.cli.render import DEFAULT_GL, FORMATS, GL_BACKENDS

    render = leaf(
        session_commands,
        "render",
        "sessions",
        help="replay one session with MuJoCo's renderer: MP4, GIF or one PNG frame (needs jitdyn[render])",
        description="Replay one stored session with MuJoCo's offscreen renderer: the model moving as the "
        "server answered it, the measured pose beside it as a translucent blue ghost, and the source of "
        "each tick (MEASURED, PREDICTED, CORRECTED when its frame came late) in a caption. Videos play in "
        "real time, decimated to at most 30 (MP4) or 12.5 (GIF, at 3/4 size in 192 colours, for a small file) frames a second. Needs jitdyn[render] and "
        "an offscreen GL library: libosmesa6 (Debian) for osmesa.",
    )
    render.add_argument("session_id")
    render.add_argument(
        "--out", type=Path, required=True, help=f"the file to write: {', '.join(FORMATS)} (one frame)"
    )
    render.add_argument(
        "--frame",
        type=argparse_type(parse_duration, "duration"),
        metavar="T",
        help="the time of the PNG's frame on the session's clock, with a unit: 1.5s, 250ms "
        "(default: the middle of the session)",
    )
    render.add_argument(
        "--gl",
        choices=tuple(GL_BACKENDS),
        help=f"MuJoCo's offscreen GL (default: MUJOCO_GL if set, else {DEFAULT_GL}; egl on a GPU host)",
    )


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
