"""Every command of `jitdyn` and every option it takes, as one table that `build_parser` reads.

A command is a `Command`: its name, help and description, its own options (`Option`, or `OneOf`
for options that exclude each other) and its actions (`models register`, `sessions list`, ...).
Each command also takes the flags of its settings group from jitdyn.settings (the server address,
the data folder, the limits, ...: flag, environment variable and default in one place), which
`build_parser` adds by the group's name: a top-level command's own, an action's its group's.
So an option is declared once, here or there, and `--help` is the table printed.
"""

from __future__ import annotations

import argparse
import textwrap
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from jitdyn.cli.render import DEFAULT_GL, GL_BACKENDS
from jitdyn.cli.render import FORMATS as RENDER_FORMATS
from jitdyn.errors import JitdynError
from jitdyn.settings import (
    argparse_type,
    checked,
    parse_duration,
    parse_model_reference,
    parse_seconds,
    positive_int,
)
from jitdyn.vocabulary import Clock, EstimatorKind, Scenario, SessionStatus, parse

__all__ = ["COMMANDS", "TRIAL_FORMATS", "Command", "ModelRef", "OneOf", "Option"]

# The files `replay` reads (jitdyn.cli.trials, which needs numpy, reads them): named here so that
# parsing the command line loads no numeric stack.
TRIAL_FORMATS: Final = (".mot", ".sto", ".c3d", ".csv")


@dataclass(frozen=True)
class Option:
    """One argument: argparse's `add_argument(*flags, **kwargs)`."""

    flags: tuple[str, ...]
    kwargs: dict[str, Any]


def option(*flags: str, **kwargs: Any) -> Option:
    return Option(flags, kwargs)


@dataclass(frozen=True)
class OneOf:
    """Options of which at most one is given (exactly one if `required`)."""

    options: tuple[Option, ...]
    required: bool = True


@dataclass(frozen=True)
class Command:
    """A command or an action of one: what `--help` says of it, and what it takes."""

    name: str
    help: str
    description: str | Callable[[], str] | None = None
    options: tuple[Option | OneOf, ...] = ()
    actions: tuple[Command, ...] = ()
    raw_description: bool = False  # the description is laid out already (a table of columns)
    # Everything after the command's name goes to a parser of its own (`experiments`).
    passthrough: bool = False


# -- the options' types -----------------------------------------------------------------------------


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
_DURATION: Final = argparse_type(parse_duration, "duration")
_SECONDS: Final = argparse_type(_seconds, "seconds")


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


_MODEL_REF: Final = argparse_type(_model_ref, "model")
# A model reference checked as one, kept as the text the user wrote (the session opens it so).
_MODEL_TEXT: Final = argparse_type(lambda text: _model_ref(text) and text, "model")


# -- options that several commands share ------------------------------------------------------------


def _network(*, latency: str, jitter: str, loss: float) -> tuple[Option, ...]:
    """--latency, --jitter and --loss of the emulated network (experiments/netem.py)."""
    return (
        option(
            "--latency",
            type=_DURATION,
            default=parse_duration(latency),
            metavar="DURATION",
            help=f"one-way latency of the emulated network, with a unit: 35ms, 0.1s (default {latency})",
        ),
        option(
            "--jitter",
            type=_DURATION,
            default=parse_duration(jitter),
            metavar="DURATION",
            help=f"latency spread with a unit (default {jitter})",
        ),
        option(
            "--loss",
            type=argparse_type(_probability, "probability"),
            default=loss,
            metavar="P",
            help=f"frame loss probability: 0.05 or 5%% (default {loss:g})",
        ),
    )


def _clock(realtime: str, *, emulated: bool = True) -> Option:
    lockstep = "each frame answered as it is sent" + (" (loss emulated as skipped ticks)" if emulated else "")
    return option(
        "--clock",
        **_word(Clock, "--clock", lower=True),
        help=f"realtime: ticks on the server's clock, {realtime}; lockstep: {lockstep}. Default: realtime, or "
        "lockstep, said so, when the server refuses a realtime session for its cost or its machine's load (a "
        "big MyoSuite model such as myolegs_osl)",
    )


def _joint_options(*, units: str) -> tuple[Option, ...]:
    """--model, --map, --angles, --dt and --scenario of the commands that drive joints from columns."""
    return (
        option(
            "--model",
            required=True,
            type=_MODEL_TEXT,
            metavar="MODEL",
            help="the registered model to drive: NAME, NAME:VERSION or sha256:ID (`jitdyn models list`)",
        ),
        option(
            "--map",
            dest="map_file",
            type=Path,
            metavar="FILE",
            help="links of columns to joints the names do not make: one `JOINT = COLUMN` a line, "
            "`JOINT = -COLUMN` to flip its sign, # comments",
        ),
        option(
            "--angles",
            choices=("deg", "rad"),
            help=f"the rotations are in degrees or radians (default: {units}); slides are metres either way",
        ),
        option(
            "--dt",
            type=argparse_type(_positive_duration, "duration"),
            metavar="DURATION",
            help="the session's tick, with a unit: 10ms (default: the recording's step rounded up to a whole "
            "multiple of the model's timestep, as a session's dt must be)",
        ),
        option(
            "--scenario",
            **_word(Scenario, "--scenario", lower=True),
            help="default: the server's choice for the model (driven for one with actuators)",
        ),
    )


def _session_id() -> Option:
    return option("session_id", help="the session's id, or a prefix of it that names one session")


# -- the commands -------------------------------------------------------------------------------------

SERVE = Command("serve", "run the server", "Run the jitdyn server until Ctrl-C or SIGTERM.")

MODELS = Command(
    "models",
    "register, list and show models",
    "The model registry, from the shell.",
    actions=(
        Command(
            "register",
            "register an MJCF file, or a MyoSuite model with --myo",
            "Register an MJCF file with the files it names, or a MyoSuite model (--myo). Content already "
            "registered is not registered again: it keeps its name, and a different --name or --tag is "
            "refused (exit 1) rather than dropped silently.",
            options=(
                OneOf(
                    (
                        option("file", nargs="?", type=Path, help="the MJCF file"),
                        option(
                            "--myo",
                            metavar="NAME",
                            help="pack the MyoSuite model NAME from myo-sim with its meshes (needs "
                            "jitdyn[myo]): myoelbow, myohand, myolegs, myolegs_osl, ...; `--myo list` lists "
                            "every one that compiles (no server needed)",
                        ),
                    )
                ),
                option("--name", help="name to register under (default: the file's stem, or the --myo name)"),
                option(
                    "--asset-dir",
                    type=Path,
                    help="folder of the meshes, textures and included XML the MJCF refers to "
                    "(default: the MJCF's folder, only the files it names)",
                ),
                option("--description", default="", help="free description"),
                option("--tag", action="append", default=[], help="a tag (repeatable)"),
            ),
        ),
        Command(
            "list",
            "list registered models",
            options=(
                option("--name", default="", help="only this name"),
                option("--tag", default="", help="only models with this tag"),
            ),
        ),
        Command(
            "show",
            "show one model (by id, NAME or NAME:VERSION)",
            "Show one model (by id, NAME or NAME:VERSION) as JSON: its joints, actuators and metadata, and "
            "what a tick of each estimator a REALTIME session of it may get costs on the server "
            "(estimator_costs, measured once when it was registered, or now for a model that has none yet) "
            "with the estimator the server chooses at a few rates (estimator_choices).",
            options=(option("model", type=_MODEL_REF, help="sha256:... id, a name, or name:version"),),
        ),
    ),
)

DEMO = Command(
    "demo",
    "a simulated REALTIME session over an emulated network",
    "Drive a simulated research object (truth simulated by MuJoCo here) through an emulated network "
    "against a local in-process server (or --server), show progress, and print a summary. A model whose "
    "REALTIME session the server refuses runs LOCKSTEP instead (see --clock).",
    options=(
        option(
            "--model",
            default="pendulum_3",
            type=_MODEL_TEXT,
            metavar="MODEL",
            help="a registered model: NAME, NAME:VERSION or sha256:ID; a built-in, or one registered in the "
            "data folder (default pendulum_3)",
        ),
        option(
            "--mjcf",
            type=Path,
            metavar="FILE",
            help="with --server, the MJCF file --model was registered from, which the demo simulates its "
            "truth with (default: the model's copy in --data, built-ins and MyoSuite models need none)",
        ),
        option(
            "--asset-dir",
            type=Path,
            metavar="DIR",
            help="folder of the files --mjcf names, as for `models register` (default: the MJCF's folder)",
        ),
        option(
            "--scenario",
            **_word(Scenario, "--scenario", lower=True),
            help="what moves the body, as the filter models it (any case): default passive for a built-in "
            "model, else the server's choice for the model (driven for one with actuators)",
        ),
        option(
            "--seconds",
            type=_SECONDS,
            default=10.0,
            metavar="DURATION",
            help="session length: 10s, 2500ms, or a bare number of seconds (default 10s)",
        ),
        *_network(latency="35ms", jitter="10ms", loss=0.05),
        option(
            "--estimator",
            default=None,
            **_word(EstimatorKind, "--estimator", lower=False),
            help="what answers a tick whose frame is late or lost (any case); default: the server's choice, "
            "the most accurate estimator whose cost (measured when the model was registered) fits the tick, "
            "said in the session's first line. UKF, the Unscented Kalman Filter on the model's dynamics; "
            "STATIC, CONSTANT_VELOCITY and CONSTANT_ACCELERATION, dead reckoning from the last frames; "
            "EKF, the filter linearised by MuJoCo (PASSIVE, EXTERNAL and DRIVEN)",
        ),
        option(
            "--seed",
            type=int,
            default=0,
            help="seed of the emulated network's latency and loss and of the start state (default 0): the "
            "same seed sends the same frames at the same times",
        ),
        _clock("over the emulated network"),
    ),
)

REPLAY = Command(
    "replay",
    "stream a recorded trial's joint angles (.mot, .sto, .c3d, .csv) into a session",
    "Stream the joint angles of a recorded trial into a session on a registered model, against a local "
    "in-process server (or --server), show progress, and print a summary like the demo's with the stored "
    "session. OpenSim .mot and .sto (degrees or radians as the header's inDegrees says), C3D (the angle "
    "outputs Vicon's Plug-in Gait stores as points, such as LKneeAngles: x flexion, y varus, z internal "
    "rotation; needs jitdyn[lab]) and CSV with a header (a time column, seconds). A column drives the "
    "model's joint of its name; --map FILE links the rest. Joints without a column are held at rest and "
    "columns without a joint are left out, both said in one line.",
    options=(
        option("file", type=Path, help=f"the recording: {', '.join(TRIAL_FORMATS)}"),
        *_joint_options(units="as the file says: a .mot's inDegrees, degrees in C3D, radians in CSV"),
        *(
            option(
                flag,
                type=_DURATION,
                metavar="T",
                help=f"replay from (--start) or to (--end) this time on the file's clock, with a unit: 1.5s, "
                f"250ms (default: its {where} sample)",
            )
            for flag, where in (("--start", "first"), ("--end", "last"))
        ),
        _clock("each sample sent at its time in the file over the emulated network"),
        *_network(latency="0ms", jitter="0ms", loss=0.0),
        option("--seed", type=int, default=0, help="seed of the emulated network (default 0)"),
    ),
)

LSL = Command(
    "lsl",
    "bridge a Lab Streaming Layer stream of joint angles and a session (needs jitdyn[lab])",
    "Take a Lab Streaming Layer stream of joint angles (by --name or --type) into a session on a "
    "registered model, its sample times mapped onto this machine's LSL clock through the inlet's "
    "time_correction(), and publish the answers as two LSL streams stamped with each tick's time: NAME "
    "(the estimated qpos and qvel, qfrc_inverse and the source: 1 MEASURED, 2 PREDICTED, 3 CORRECTED) and "
    "NAME-lateness (frame_delay and answer_time, s), which LabRecorder stores beside the lab's other "
    "streams. Channels drive joints as in `jitdyn replay`. Runs until --seconds pass, the stream is silent "
    "for --idle, or Ctrl-C; then prints the summary. Needs jitdyn[lab] (pylsl, whose liblsl needs glibc "
    "2.35 or newer).",
    options=(
        OneOf(
            (
                option("--name", dest="stream_name", metavar="NAME", help="the LSL stream's name"),
                option(
                    "--type",
                    dest="stream_type",
                    metavar="TYPE",
                    help="the LSL stream's type (the first found)",
                ),
            )
        ),
        *_joint_options(units="as the channels' units say: deg, degree or degrees, else radians"),
        _clock("each sample sent as it comes", emulated=False),
        option(
            "--seconds",
            type=_SECONDS,
            metavar="DURATION",
            help="end the session after this long on the stream's clock (default: when the stream stops)",
        ),
        option(
            "--wait",
            type=_SECONDS,
            default=10.0,
            metavar="DURATION",
            help="how long to look for the stream, and for its first sample (default 10s)",
        ),
        option(
            "--idle",
            type=_SECONDS,
            default=2.0,
            metavar="DURATION",
            help="end the session when the stream sends nothing for this long (default 2s)",
        ),
        option(
            "--publish",
            default="jitdyn",
            metavar="NAME",
            help="the name of the answers' LSL stream; the lateness' is NAME-lateness (default jitdyn)",
        ),
    ),
)


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


SESSIONS = Command(
    "sessions",
    "list, show, query, export, plot and render stored sessions",
    "The stored sessions, read from the data folder and the SQL index (no server needed).",
    actions=(
        Command(
            "list",
            "list sessions, newest first",
            "List the stored sessions, newest first, one a line: id, start, status, model, scenario, clock "
            "and the counts of its summary. ticks: distinct ticks answered; measured, predicted, corrected: "
            "answers of each source (a tick answered PREDICTED and then CORRECTED counts in both); rejected: "
            "frames refused, each stored with its reason (see `sessions query`); late: ticks whose frame came "
            "after the tick was answered, so that it was corrected (results with late_ticks > 0); a frame too "
            "late to be used at all is rejected TOO_OLD instead.",
            options=(
                option(
                    "--model",
                    type=_MODEL_REF,
                    metavar="MODEL",
                    help="only sessions of this model: NAME (every version), NAME:VERSION or sha256:ID",
                ),
                option(
                    "--status",
                    **_word(SessionStatus, "--status", lower=False),
                    help="only sessions that ended so (any case)",
                ),
                option(
                    "--limit",
                    type=argparse_type(positive_int, "limit"),
                    default=50,
                    metavar="N",
                    help="at most N (default 50)",
                ),
            ),
        ),
        Command("show", "show one session", options=(_session_id(),)),
        Command(
            "query",
            "run SQL with DuckDB over the frames (view `frames`) and the index (table `sessions`)",
            _query_description,
            raw_description=True,
            options=(
                option("sql", help='e.g. "SELECT source, count(*) FROM frames GROUP BY source"'),
                option(
                    "--format",
                    choices=("table", "csv", "json"),
                    default="table",
                    help="an aligned table (default), CSV with a header, or JSON lines (one object per row)",
                ),
                option("--out", type=Path, help="write the result to this file instead of stdout"),
            ),
        ),
        Command(
            "export",
            "export one session as CSV, OpenSim .sto or MCAP (Foxglove)",
            "Write one stored session for tools outside jitdyn. csv: every stored row, one column per array "
            "element. sto: OpenSim's storage file, one row per tick (a correction replaces its prediction). "
            "mcap: the file Foxglove opens: joint states, forces, frames, sources and lateness as time "
            "series, and every body's pose at each tick (MuJoCo's forward kinematics on the stored model) as "
            "3D frame transforms on /tf (needs jitdyn[lab]).",
            options=(
                _session_id(),
                option("--format", choices=("csv", "sto", "mcap"), default="csv"),
                option("--out", type=Path, help="output file (default <session id>.<format>)"),
            ),
        ),
        Command(
            "plot",
            "draw one session: q measured and answered, forces, lateness, NIS (needs jitdyn[experiments])",
            "Draw one stored session as one figure on a shared time axis: the source of each tick's answer; "
            "per joint the measured q against the answered q (PREDICTED and CORRECTED ticks marked, gaps "
            "shaded) beside the answered generalized force; the frames' network lateness; the server's time "
            "to answer; the filter's NIS. A PNG, or one self-contained HTML page. Needs matplotlib "
            "(jitdyn[experiments]).",
            options=(
                _session_id(),
                option(
                    "--out",
                    type=Path,
                    help="a .png or .html file, or a folder (default <session id>.png here)",
                ),
                option(
                    "--joints",
                    nargs="+",
                    metavar="NAME",
                    default=[],
                    help="the joints to draw, by name (default: the first 6 of the model)",
                ),
            ),
        ),
        Command(
            "render",
            "replay one session with MuJoCo's renderer: MP4, GIF or one PNG frame (needs jitdyn[render])",
            "Replay one stored session with MuJoCo's offscreen renderer: the model moving as the server "
            "answered it, the measured pose beside it as a translucent blue ghost, and the source of each "
            "tick (MEASURED, PREDICTED, CORRECTED when its frame came late) in a caption. Videos play in real "
            "time, decimated to at most 30 (MP4) or 12.5 (GIF, at 3/4 size in 192 colours, for a small file) "
            "frames a second. Needs jitdyn[render] and an offscreen GL library: libosmesa6 (Debian) for "
            "osmesa.",
            options=(
                _session_id(),
                option(
                    "--out",
                    type=Path,
                    required=True,
                    help=f"the file to write: {', '.join(RENDER_FORMATS)} (one frame)",
                ),
                option(
                    "--frame",
                    type=_DURATION,
                    metavar="T",
                    help="the time of the PNG's frame on the session's clock, with a unit: 1.5s, 250ms "
                    "(default: the middle of the session)",
                ),
                option(
                    "--gl",
                    choices=tuple(GL_BACKENDS),
                    help=f"MuJoCo's offscreen GL (default: MUJOCO_GL if set, else {DEFAULT_GL}; egl on a GPU "
                    "host)",
                ),
            ),
        ),
    ),
)

EXPERIMENTS = Command(
    "experiments",
    "reproduce the thesis experiments (needs jitdyn[experiments])",
    "Reproduce every experiment of the thesis; see `jitdyn experiments --help`.",
    passthrough=True,
)

COMMANDS: Final = (SERVE, MODELS, DEMO, REPLAY, LSL, SESSIONS, EXPERIMENTS)


# -- the manual's reference, from the same table --------------------------------------------------------


def reference() -> str:
    """Every command's options as Markdown, one table a command: docs/cli.md holds it, and a test
    holds it to this table, so the manual lists what the parser takes."""
    from jitdyn.settings import settings_for

    sections: list[str] = []

    def walk(command: Command, path: str, group: str) -> None:
        if command.passthrough:
            sections.append(
                f"### `{path}`\n\n{command.help[0].upper()}{command.help[1:]}: its options are its own, `{path} --help`."
            )
            return
        if command.actions:
            for action in command.actions:
                walk(action, f"{path} {action.name}", group)
            return
        rows = ["| option | what it takes |", "|---|---|"]
        for entry in command.options:
            ones = entry.options if isinstance(entry, OneOf) else (entry,)
            for one in ones:
                rows.append(f"| {_synopsis(one)} | {_cell(one, isinstance(entry, OneOf))} |")
        flags = [f"`{s.flag}`" for s in settings_for(group)]
        tail = f"\n\nSettings ([below](#settings)): {', '.join(flags)}." if flags else ""
        body = "\n".join(rows) if len(rows) > 2 else "No options of its own."
        sections.append(f"### `{path}`\n\n{command.help[0].upper()}{command.help[1:]}.\n\n{body}{tail}")

    for command in COMMANDS:
        walk(command, f"jitdyn {command.name}", command.name)
    return "\n\n".join(sections)


def _synopsis(one: Option) -> str:
    if not one.flags[0].startswith("-"):
        return f"`{one.kwargs.get('metavar') or one.flags[0].upper()}`"
    metavar = one.kwargs.get("metavar")
    if metavar is None and "choices" in one.kwargs:
        metavar = "{" + ",".join(one.kwargs["choices"]) + "}"
    takes = (
        ""
        if one.kwargs.get("action") in ("store_true", "append_const")
        else " " + (metavar or one.flags[0].lstrip("-").upper().replace("-", "_"))
    )
    return f"`{' '.join(one.flags)}{takes}`"


def _cell(one: Option, exclusive: bool) -> str:
    text = str(one.kwargs.get("help", "")).replace("%%", "%").replace("|", "\\|")
    notes = ["required"] if one.kwargs.get("required") else []
    notes += ["one of these"] if exclusive else []
    return text + (f" ({', '.join(notes)})" if notes else "")
