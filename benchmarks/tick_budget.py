"""Where a REALTIME tick's server CPU goes, stage by stage, beside the tick's floor, in one run.

It starts `jitdyn serve --processes 1` on a free port, drives REALTIME sessions from separate client
processes (benchmarks/load.py's generator) and, over the steady part of the run, samples the server
with `py-spy record --nonblocking` while reading every thread's CPU from /proc. Each Python thread's
CPU is spread over the stages its samples fall in (STAGES: the first stage whose test a sample's
stack passes); the CPU of threads without Python (gRPC core's event engine and timers) is a stage of
its own. A busy sample whose stack is a wait (select, a lock) is a stack read after its thread's
burst ended (py-spy --nonblocking reads state and stack at two moments): it is left out, counted.
Scaled to the server's CPU per answered tick:

    stage       what the tick spends in it, us of server CPU per answered tick, and its share
    floor       measured in the same run, after the sessions: a bare grpc.aio bidi echo of the same
                sessions, rate and message sizes (server CPU per message), plus the physics the
                filter cannot do without: the sigma points' rollout over one tick and one mj_inverse
    cpu / floor the server's CPU per tick over that floor

    python -m benchmarks.tick_budget                                  # 8 pendulum_3 PASSIVE at 20 Hz
    python -m benchmarks.tick_budget --runs 3 --json budget.json     # medians of 3 fresh servers
    python -m benchmarks.tick_budget --runs 3 --engines native python  # both engines, alternated
    python -m benchmarks.tick_budget --model biped --scenario CONTROLLED --rate 200 --sessions 2

Sessions admission refuses (a busy machine) are said on stderr; the budget is then of those it
admitted. Needs py-spy (in the `dev` extra). Progress goes to stderr, the table to stdout.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import os
import re
import shutil
import statistics
import subprocess
import sys
import sysconfig
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import NoReturn, Self

import numpy as np

from benchmarks.load import (
    RunReport,
    default_config,
    local_server,
    model_source,
    run,
    trajectory,
    ukf_cycle_us,
)
from jitdyn.settings import ENGINES
from jitdyn.vocabulary import Scenario

ROOT = Path(__file__).resolve().parent.parent
SCENARIOS = (Scenario.PASSIVE, Scenario.CONTROLLED, Scenario.EXTERNAL, Scenario.DRIVEN)
MIN_SECONDS = 10.0  # the generator opens sessions over 2 s; the steady window needs the rest


# ---------------------------------------------------------------------------------------------
# A sampled stack, and the stages a tick's CPU is attributed to.


@dataclass(frozen=True)
class Frame:
    """One frame of a py-spy stack."""

    function: str  # qualified, as py-spy prints it: "_Stream.write"
    file: str
    line: int

    @property
    def module(self) -> str | None:
        """The jitdyn file the frame is in, as the repository lays it out ("server/runtime/session.py",
        "jitdyn/checksum.py" for src/jitdyn), whether installed editable or as a wheel; None outside
        jitdyn."""
        path = self.file.replace("\\", "/")
        if "/site-packages/jitdyn/" in path:
            inside = path.split("/site-packages/jitdyn/", 1)[1]
            return inside if inside.split("/", 1)[0] in _FOLDERS else f"jitdyn/{inside}"
        root = f"{ROOT.as_posix()}/"
        if not path.startswith(root) or "/site-packages/" in path:
            return None
        inside = path[len(root) :]
        return inside.removeprefix("src/")


_FOLDERS = frozenset({"server", "storage", "client", "registry", "cli", "models", "experiments"})

Stack = Sequence[Frame]  # innermost frame first
FrameTest = Callable[[Frame], bool]
StackTest = Callable[[Stack], bool]


def in_files(*names: str) -> FrameTest:
    """A frame in one of these jitdyn files, or under one of these folders (names ending in /)."""
    return lambda f: (
        (m := f.module) is not None and any(m.startswith(n) if n.endswith("/") else m == n for n in names)
    )


def in_functions(module: str, *functions: str) -> FrameTest:
    """A frame of one of these functions (qualified names) of one jitdyn file."""
    return lambda f: f.module == module and f.function in functions


def in_library(*fragments: str) -> FrameTest:
    """A frame of a third-party file whose path holds one of these fragments ("/filterpy/")."""
    return lambda f: f.module is None and any(x in f.file.replace("\\", "/") for x in fragments)


def anywhere(*tests: FrameTest) -> StackTest:
    """Some frame of the stack passes one of the tests: the stage includes all it calls."""
    return lambda stack: any(test(f) for f in stack for test in tests)


def innermost(*tests: FrameTest) -> StackTest:
    """The innermost jitdyn frame passes one of the tests: the stage's own lines, and what they call
    outside jitdyn (protobuf, grpc.aio, numpy)."""

    def test(stack: Stack) -> bool:
        frame = next((f for f in stack if f.module is not None), None)
        return frame is not None and any(t(frame) for t in tests)

    return test


def either(*tests: StackTest) -> StackTest:
    return lambda stack: any(t(stack) for t in tests)


def at_top(*tests: FrameTest) -> StackTest:
    """The innermost frame, jitdyn's or not, passes one of the tests."""
    return lambda stack: bool(stack) and any(t(stack[0]) for t in tests)


def called(library: str, *functions: str) -> FrameTest:
    """A frame of one of these functions of a third-party file whose path holds `library`."""
    return lambda f: f.module is None and library in f.file.replace("\\", "/") and f.function in functions


def outside_jitdyn(stack: Stack) -> bool:
    return all(f.module is None for f in stack)


def always(stack: Stack) -> bool:
    return True


@dataclass(frozen=True)
class Stage:
    """A part of the tick: `name`, and the test a sampled stack passes when it is in it. A stage
    that is not `spent` takes no CPU: its samples are left out of the attribution."""

    name: str
    test: StackTest
    spent: bool = True


WAITING = "read in a wait (select, a lock): not spent"
_SERVICE = "server/transport/dynamics_service.py"
_CLOCK_METHODS = (
    "_RealtimeClock.run",
    "_RealtimeClock.due",
    "_RealtimeClock.moved",
    "_Stream.deadline",
    "_Stream.catch_up",
    "_Stream.answer_ready",
    "_Stream.on_deadline",
    "_Stream.replaying",
    "_Stream.horizon",
    "_Stream.frame_delay",
    "DynamicsServicer._pong",
)

# A sample is in the first stage whose test its stack passes: the stages that contain others (the
# forecast steps the physics; the record and the metrics are called from the result's lines) come
# before what they contain.
#
# With --nonblocking, py-spy reads a thread's state and its stack at two moments, the thread
# running on: a thread busy at one read and back in a wait at the other (the event loop runs a
# burst of about half a millisecond several hundred times a second) gives a busy sample whose
# stack is the wait. Those samples are not spent: each thread's CPU goes to its other samples.
STAGES: tuple[Stage, ...] = (
    Stage(
        WAITING,
        at_top(
            called("/selectors.py", "EpollSelector.select", "PollSelector.select", "SelectSelector.select"),
            called("/threading.py", "Condition.wait", "Event.wait", "Semaphore.acquire"),
            called("/concurrent/futures/thread.py", "_worker"),
            called("/queue.py", "Queue.get"),
        ),
        spent=False,
    ),
    Stage(
        "the record (storage: the row, the commit thread)",
        anywhere(in_files("storage/"), in_functions("server/transport/messages.py", "record_tick")),
    ),
    Stage(
        "metrics",
        anywhere(
            in_files("server/transport/metrics.py", "server/transport/tally.py"),
            in_library("/prometheus_client/"),
        ),
    ),
    Stage(
        "admission and the loop's watch",
        anywhere(
            in_files(
                "server/runtime/admission.py", "server/runtime/stalls.py", "server/runtime/switch_interval.py"
            ),
            in_functions(_SERVICE, "_Stream.overload_notice"),
        ),
    ),
    Stage(
        "the forecast (combination, matching, dead reckoning)",
        anywhere(
            in_files(
                "server/estimation/forecast.py",
                "server/estimation/foresight.py",
                "server/estimation/matching.py",
                "server/estimation/deadreckoning.py",
                "server/estimation/gap.py",
            ),
            in_functions("server/estimation/adaptive_steps.py", "observe_gap"),
        ),
    ),
    Stage(
        "the glance ahead (ticks past the filter)",
        anywhere(in_files("server/estimation/lookahead.py")),
    ),
    Stage("the result's dynamics", anywhere(in_files("server/estimation/dynamics.py"))),
    Stage(
        "estimator cycle: the sigma points' physics",
        anywhere(
            in_files("server/estimation/propagate.py", "server/estimation/pool.py"),
            in_library("/mujoco/rollout.py"),
        ),
    ),
    Stage(
        "estimator cycle: the filter's algebra",
        anywhere(in_files("server/estimation/"), in_library("/filterpy/")),
    ),
    Stage(
        "the result message",
        innermost(
            in_files("server/transport/messages.py"),
            in_functions(_SERVICE, "_Stream.record_result", "_Stream.answer"),
        ),
    ),
    Stage("the write", innermost(in_functions(_SERVICE, "_Stream.write", "_RealtimeClock.write"))),
    Stage(
        "frame read and check",
        either(
            anywhere(
                in_files("server/transport/frame_check.py", "server/runtime/frames.py", "jitdyn/checksum.py")
            ),
            innermost(
                in_functions(
                    _SERVICE,
                    "_Stream.on_frame",
                    "_Stream._wait_for_tick",
                    "DynamicsServicer._until_idle",
                    "DynamicsServicer._realtime",
                )
            ),
        ),
    ),
    Stage(
        "the clock",
        either(
            anywhere(in_files("server/runtime/clock.py", "server/runtime/alarm.py")),
            innermost(in_functions(_SERVICE, *_CLOCK_METHODS)),
        ),
    ),
    Stage(
        "the session's bookkeeping",
        innermost(
            in_files("server/runtime/session.py", "jitdyn/mujoco_log.py"),
            in_functions(_SERVICE, "_counting_warnings.<locals>.wrapped"),
        ),
    ),
    Stage(
        "the event loop: asyncio, grpc.aio's Python, its poller",
        either(outside_jitdyn, innermost(in_files("cli/", "server/transport/app.py"))),
    ),
    Stage("other jitdyn", always),
)
NATIVE = "gRPC core's threads (C, no Python)"
UNSAMPLED = "Python threads never sampled busy"


_SPENT = frozenset(stage.name for stage in STAGES if stage.spent)


def classify(stack: Stack, stages: Sequence[Stage] = STAGES) -> str:
    """The name of the first stage whose test `stack` (innermost frame first) passes."""
    return next(stage.name for stage in stages if stage.test(stack))


# ---------------------------------------------------------------------------------------------
# py-spy's raw output, and the threads' CPU.

_FRAME = re.compile(r"^(?P<function>.*) \((?P<file>.*?):(?P<line>\d+)\)$")
_THREAD = re.compile(r"^thread \((?P<id>0x[0-9a-fA-F]+|\d+)\)")


def parse_raw(text: str) -> Counter[tuple[int, str]]:
    """py-spy's `--format raw --threads` output -> samples per (OS thread id, stage)."""
    samples: Counter[tuple[int, str]] = Counter()
    for line in text.splitlines():
        stack_text, _, count = line.rpartition(" ")
        if not stack_text or not count.isdigit():
            continue
        parts = stack_text.split(";")
        thread = _THREAD.match(parts[0])
        tid = int(thread["id"], 0) if thread else 0
        frames = [
            Frame(m["function"], m["file"], int(m["line"]))
            for part in reversed(parts[1:] if thread else parts)
            if (m := _FRAME.match(part))
        ]
        samples[(tid, classify(frames))] += int(count)
    return samples


def thread_cpu(pid: int) -> dict[int, tuple[str, float]]:
    """Every thread of `pid`: its name and user + system CPU so far, in seconds."""
    ticks = os.sysconf("SC_CLK_TCK")
    threads: dict[int, tuple[str, float]] = {}
    for entry in os.listdir(f"/proc/{pid}/task"):
        with contextlib.suppress(OSError):
            stat = Path(f"/proc/{pid}/task/{entry}/stat").read_text()
            name = stat[stat.index("(") + 1 : stat.rindex(")")]
            fields = stat.rsplit(")", 1)[1].split()
            threads[int(entry)] = (name, (int(fields[11]) + int(fields[12])) / ticks)
    return threads


def py_spy() -> str:
    """The py-spy beside this interpreter, else on PATH."""
    beside = Path(sysconfig.get_path("scripts")) / "py-spy"
    found = str(beside) if beside.exists() else shutil.which("py-spy")
    if found is None:
        raise SystemExit("tick_budget: py-spy is not installed; pip install py-spy (it is in the dev extra)")
    return found


def python_threads(spy: str, pid: int) -> set[int]:
    """The OS ids of the threads of `pid` that run Python (py-spy dump)."""
    dump = subprocess.run(
        [spy, "dump", "--pid", str(pid), "--json", "--nonblocking"],
        capture_output=True,
        text=True,
        check=False,
    )
    if dump.returncode != 0:
        raise SystemExit(f"tick_budget: py-spy dump failed: {_last_line(dump.stderr)}")
    return {int(t["os_thread_id"]) for t in json.loads(dump.stdout) if t.get("os_thread_id")}


def _last_line(text: str) -> str:
    return next((line for line in reversed(text.splitlines()) if line.strip()), "(no output)")


@dataclass
class Profile:
    """What the sampler saw over its window: samples per (thread, stage), the threads' CPU."""

    samples: Counter[tuple[int, str]] = field(default_factory=Counter)
    cpu: dict[int, tuple[str, float]] = field(default_factory=dict)  # tid -> (name, seconds)
    python: set[int] = field(default_factory=set)
    error: str = ""

    def threads(self) -> dict[int, tuple[str, float, int]]:
        """tid -> (name, CPU over the window in s, busy samples)."""
        counts: Counter[int] = Counter()
        for (tid, _), n in self.samples.items():
            counts[tid] += n
        return {tid: (name, seconds, counts[tid]) for tid, (name, seconds) in self.cpu.items()}

    def stage_cpu(self) -> dict[str, float]:
        """Server CPU per stage over the window, seconds: each Python thread's CPU spread over its
        samples' stages; threads without Python are NATIVE."""
        out: dict[str, float] = {}

        def add(stage: str, seconds: float) -> None:
            out[stage] = out.get(stage, 0.0) + seconds

        for tid, (_, seconds) in self.cpu.items():
            if tid not in self.python:
                add(NATIVE, seconds)
                continue
            mine = {stage: n for (t, stage), n in self.samples.items() if t == tid and stage in _SPENT}
            total = sum(mine.values())
            if total == 0:
                add(UNSAMPLED, seconds)
                continue
            for stage, n in mine.items():
                add(stage, seconds * n / total)
        return out


class Sampler:
    """py-spy and the threads' CPU over [start, start + seconds] of the server `pid`, in a thread.

    with Sampler(pid, start=..., seconds=..., rate=100) as sampler:
        ...                                     # the load runs
    sampler.profile
    """

    def __init__(
        self, pid: int, *, start: float, seconds: float, rate: int, keep: Path | None = None
    ) -> None:
        self._pid, self._start, self._seconds, self._rate = pid, start, seconds, rate
        self._keep = keep  # where py-spy's raw samples are copied, if anywhere
        self._spy = py_spy()
        self.profile = Profile()
        self._thread = threading.Thread(target=self._run, name="tick-budget-sampler", daemon=True)

    def __enter__(self) -> Self:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._thread.join()

    def _run(self) -> None:
        try:
            time.sleep(max(0.0, self._start - time.monotonic()))
            self._sample()
        except (OSError, SystemExit, ValueError) as error:
            self.profile.error = str(error)

    def _sample(self) -> None:
        with tempfile.TemporaryDirectory(prefix="jitdyn-tick-budget-") as folder:
            output = Path(folder) / "raw.txt"
            self.profile.python = python_threads(self._spy, self._pid)
            before = thread_cpu(self._pid)
            record = subprocess.run(
                [
                    self._spy,
                    "record",
                    "--pid",
                    str(self._pid),
                    "--nonblocking",
                    "--format",
                    "raw",
                    "--full-filenames",
                    "--threads",
                    "--rate",
                    str(self._rate),
                    "--duration",
                    str(round(self._seconds)),
                    "--output",
                    str(output),
                ],
                capture_output=True,
                text=True,
                check=False,
            )
            after = thread_cpu(self._pid)
            if record.returncode != 0 or not output.exists():
                raise SystemExit(f"py-spy record failed: {_last_line(record.stderr)}")
            self.profile.samples = parse_raw(output.read_text())
            if self._keep is not None:
                shutil.copyfile(output, self._keep)
        self.profile.cpu = {
            tid: (name, seconds - before.get(tid, (name, 0.0))[1]) for tid, (name, seconds) in after.items()
        }


# ---------------------------------------------------------------------------------------------
# One run, and the medians of several.


@dataclass(frozen=True)
class Options:
    model: str
    scenario: Scenario
    rate: float
    sessions: int
    seconds: float
    clients: int
    sample_rate: int
    serve_args: tuple[str, ...]
    raw: Path | None = None  # a run's py-spy samples are kept as raw-N.txt in this folder


@dataclass
class Budget:
    """One run's tick budget: us of server CPU per answered tick, by stage, and the floor."""

    cpu_per_tick_us: float
    stages_us: dict[str, float]
    samples: dict[str, int]
    echo_us: float  # a bare grpc.aio bidi echo, server CPU per message
    physics_us: float  # the sigma points' rollout over one tick
    inverse_us: float  # one mj_inverse
    ukf_cycle_us: float  # the filter's predict + update alone, one worker, outside the server
    opened: int
    answered: float
    measured: float
    late_p99_ms: float
    # Each thread over the sampled window: name, CPU (s), busy samples; tid -> (name, s, samples).
    threads: dict[int, tuple[str, float, int]] = field(default_factory=dict)

    @property
    def floor_us(self) -> float:
        return self.echo_us + self.physics_us + self.inverse_us

    @property
    def over_floor(self) -> float:
        return self.cpu_per_tick_us / self.floor_us


def inverse_us(model: str, scenario: Scenario, rate: float, states: dict[str, np.ndarray]) -> float:
    """CPU of one mj_inverse of `model` at the trajectory's states, median of batches, us."""
    import mujoco

    mj, _ = default_config(model, scenario, rate)
    data = mujoco.MjData(mj)
    samples = []
    for k in range(min(len(states["qpos"]), 50)):
        data.qpos[:], data.qvel[:] = states["qpos"][k], states["qvel"][k]
        started = time.process_time()
        for _ in range(200):
            mujoco.mj_inverse(mj, data)
        samples.append((time.process_time() - started) / 200)
    return statistics.median(samples) * 1e6


def window(seconds: float) -> tuple[float, float]:
    """When to sample, from the load's start, s: after every session opened (load.run spreads the
    opens over min(2, seconds / 4) s), and a second before the first closes, a margin each side."""
    spread = min(2.0, seconds / 4)
    return spread + 1.5, seconds - 1.5


def progress(text: str) -> None:
    print(f"# {text}", file=sys.stderr, flush=True)


def register(address: str, model: str) -> None:
    """Registers a model that is not built in before the sampler starts: registration times every
    candidate estimator (seconds of a big model's UKF), which would otherwise fall in the sampled
    window and be charged to the ticks. The load's own registration then finds it, costs stored."""
    from jitdyn.client import Client

    source = model_source(model)
    if not source.builtin:
        with Client(address) as client:
            client.register_model(name=source.name, mjcf=source.mjcf, assets=source.assets)


def one_run(
    options: Options, states: dict[str, np.ndarray], ukf_us: float, *, index: int = 1
) -> Budget | None:
    """A fresh `jitdyn serve --processes 1`, the load, the sampler over its steady part, the floor;
    None when admission refused every session (a busy machine: there was no tick to attribute) or
    the sampler failed."""
    with local_server(("--processes", "1", *options.serve_args)) as (address, pid):
        register(address, options.model)
        begin, end = window(options.seconds)
        progress(
            f"server {address} (pid {pid}); {options.sessions} sessions for {options.seconds:g} s, py-spy "
            f"from {begin:g} to {end:g} s, then the bare grpc.aio echo and the physics"
        )
        keep = options.raw / f"raw-{index}.txt" if options.raw is not None else None
        start = time.monotonic() + begin
        with Sampler(pid, start=start, seconds=end - begin, rate=options.sample_rate, keep=keep) as sampler:
            report = run(
                model=options.model,
                scenario=options.scenario,
                rate=options.rate,
                sessions=options.sessions,
                seconds=options.seconds,
                clients=options.clients,
                server=address,
                states=states,
                ukf_us=ukf_us,
            )
    if sampler.profile.error:
        # py-spy lost the process (it exited, or a read failed mid-dump): this run says nothing.
        progress(f"{sampler.profile.error}; the run is not counted")
        return None
    if report.opened < options.sessions:
        refusal = report.errors[0] if report.errors else "no reason given"
        progress(f"only {report.opened} of {options.sessions} sessions were admitted: {refusal}")
    if report.opened == 0 or report.answered == 0:
        return None
    return budget_of(
        report, sampler.profile, inverse=inverse_us(options.model, options.scenario, options.rate, states)
    )


def budget_of(report: RunReport, profile: Profile, *, inverse: float) -> Budget:
    stage_cpu = profile.stage_cpu()
    total = sum(stage_cpu.values())
    if total <= 0 or not math.isfinite(report.cpu_per_tick_us):
        raise SystemExit("tick_budget: the server spent no CPU in the sampled window; did the sessions run?")
    samples: Counter[str] = Counter()
    for (_, stage), n in profile.samples.items():
        samples[stage] += n
    return Budget(
        cpu_per_tick_us=report.cpu_per_tick_us,
        stages_us={stage: report.cpu_per_tick_us * seconds / total for stage, seconds in stage_cpu.items()},
        samples=dict(samples),
        echo_us=report.floor_grpc_us,
        physics_us=report.physics_us,
        inverse_us=inverse,
        ukf_cycle_us=report.ukf_cycle_us,
        opened=report.opened,
        answered=report.answered,
        measured=report.measured,
        late_p99_ms=report.late_p99_ms,
        threads=profile.threads(),
    )


def median_budget(budgets: Sequence[Budget]) -> Budget:
    """Each figure the median over the runs (a stage missing from a run counts 0 there)."""
    stages = {stage for b in budgets for stage in b.stages_us}
    sampled = {stage for b in budgets for stage in b.samples}

    def med(get: Callable[[Budget], float]) -> float:
        return float(statistics.median(get(b) for b in budgets))

    return Budget(
        cpu_per_tick_us=med(lambda b: b.cpu_per_tick_us),
        stages_us={s: med(lambda b, s=s: b.stages_us.get(s, 0.0)) for s in stages},  # type: ignore[misc]
        samples={s: round(med(lambda b, s=s: b.samples.get(s, 0))) for s in sampled},  # type: ignore[misc]
        echo_us=med(lambda b: b.echo_us),
        physics_us=med(lambda b: b.physics_us),
        inverse_us=med(lambda b: b.inverse_us),
        ukf_cycle_us=med(lambda b: b.ukf_cycle_us),
        opened=round(med(lambda b: b.opened)),
        answered=med(lambda b: b.answered),
        measured=med(lambda b: b.measured),
        late_p99_ms=med(lambda b: b.late_p99_ms),
    )


# ---------------------------------------------------------------------------------------------
# The report.


@dataclass(frozen=True)
class Row:
    stage: str
    us: float
    share: float
    low: float  # the least and most of the runs, us
    high: float
    samples: int


@dataclass(frozen=True)
class Column:
    header: str
    get: Callable[[Row], str]


COLUMNS = (
    Column("stage", lambda r: r.stage),
    Column("us/tick", lambda r: f"{r.us:.0f}"),
    Column("share", lambda r: f"{100 * r.share:.1f} %"),
    Column("runs' range, us", lambda r: f"{r.low:.0f}-{r.high:.0f}"),
    Column("samples", lambda r: str(r.samples)),
)


def rows(median: Budget, budgets: Sequence[Budget]) -> list[Row]:
    """Every stage, those no sample fell in too, most expensive first (median us/tick)."""
    total = sum(median.stages_us.values())
    names = [stage.name for stage in STAGES if stage.spent] + [NATIVE, UNSAMPLED]
    out = [
        Row(
            stage=stage,
            us=us,
            share=us / total if total else 0.0,
            low=min(b.stages_us.get(stage, 0.0) for b in budgets),
            high=max(b.stages_us.get(stage, 0.0) for b in budgets),
            samples=median.samples.get(stage, 0),
        )
        for stage in names
        for us in [median.stages_us.get(stage, 0.0)]
    ]
    return sorted(out, key=lambda r: -r.us)


def table(rows: Sequence[Row], columns: Sequence[Column] = COLUMNS) -> str:
    """A Markdown table, as RESULTS.md holds them."""
    lines = [
        "| " + " | ".join(c.header for c in columns) + " |",
        "|" + "---|" * len(columns),
        *("| " + " | ".join(c.get(r) for c in columns) + " |" for r in rows),
    ]
    return "\n".join(lines)


def summary(options: Options, median: Budget, budgets: Sequence[Budget]) -> str:
    runs = len(budgets)
    ratios = ", ".join(f"{b.over_floor:.2f}" for b in budgets)
    head = (
        f"{options.sessions} x {options.model} {options.scenario} at {options.rate:g} Hz, `jitdyn serve "
        f"--processes 1`, {runs} run{'s' * (runs > 1)} (medians): opened {median.opened}, answered "
        f"{100 * median.answered:.2f} %, MEASURED {100 * median.measured:.2f} %, late p99 "
        f"{median.late_p99_ms:.1f} ms"
    )
    cpu = (
        f"server CPU per answered tick: {median.cpu_per_tick_us:.0f} us (the filter's predict + update "
        f"alone, outside the server: {median.ukf_cycle_us:.0f} us)"
    )
    floor = (
        f"floor: bare grpc.aio echo {median.echo_us:.0f} us/message + sigma points' physics "
        f"{median.physics_us:.0f} us/tick + mj_inverse {median.inverse_us:.1f} us = {median.floor_us:.0f} us"
    )
    waits = (
        f"{median.samples.get(WAITING, 0)} of {sum(median.samples.values())} busy samples (medians) were read "
        "in a wait (select, a lock: py-spy --nonblocking read the stack after the thread's burst); they "
        "are left out, each thread's CPU spread over its other samples"
    )
    ratio = f"cpu/tick / floor: {statistics.median(b.over_floor for b in budgets):.2f} (runs: {ratios})"
    return "\n".join([head, "", table(rows(median, budgets)), "", waits, cpu, floor, ratio])


def side_by_side(medians: dict[str, Budget], budgets: dict[str, list[Budget]]) -> str:
    """Each stage's median us/tick on every engine, and the runs' cpu/tick over the floor."""
    engines = list(medians)
    stages = sorted(
        {stage for m in medians.values() for stage in m.stages_us},
        key=lambda stage: -max(m.stages_us.get(stage, 0.0) for m in medians.values()),
    )
    head = "| stage | " + " | ".join(f"{e} us/tick" for e in engines) + " |"
    lines = [head, "|" + "---|" * (len(engines) + 1)]
    for stage in stages:
        lines.append(
            f"| {stage} | "
            + " | ".join(f"{medians[e].stages_us.get(stage, 0.0):.0f}" for e in engines)
            + " |"
        )
    lines.append(
        "| **server CPU per tick** | "
        + " | ".join(f"**{medians[e].cpu_per_tick_us:.0f}**" for e in engines)
        + " |"
    )
    lines.append("| floor | " + " | ".join(f"{medians[e].floor_us:.0f}" for e in engines) + " |")
    ratios = " | ".join(f"{statistics.median(b.over_floor for b in budgets[e]):.2f}" for e in engines)
    lines.append(f"| cpu/tick / floor (median of runs) | {ratios} |")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# The command.


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: {message} (see --help)\n")


def _positive(kind: type[int | float], least: float, what: str) -> Callable[[str], float]:
    def parse(text: str) -> float:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what}, got {text!r}") from None
        if not value >= least or not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"{what}, got {text!r}")
        return value

    return parse


def parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="python -m benchmarks.tick_budget",
        description=__doc__.splitlines()[0] if __doc__ else None,
        epilog=__doc__.split("\n\n", 1)[1] if __doc__ else None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--model",
        default="pendulum_3",
        help="pendulum_1..3, biped, or any myo-sim model that compiles here, as benchmarks/load.py "
        "offers them (default %(default)s)",
    )
    p.add_argument(
        "--scenario",
        type=Scenario,
        default=Scenario.PASSIVE,
        choices=SCENARIOS,
        help="what moves the model, as the load generator drives it (default %(default)s)",
    )
    p.add_argument(
        "--rate",
        metavar="HZ",
        type=_positive(float, 1e-9, "must be a rate in Hz > 0"),
        default=20.0,
        help="frames per second of every session, Hz (default %(default)s)",
    )
    p.add_argument(
        "--sessions",
        metavar="N",
        type=_positive(int, 1, "must be an integer >= 1"),
        default=8,
        help="REALTIME sessions at once (default %(default)s)",
    )
    p.add_argument(
        "--seconds",
        metavar="S",
        type=_positive(float, MIN_SECONDS, f"must be >= {MIN_SECONDS:g}"),
        default=20.0,
        help="each session's length, s; py-spy samples its steady part (default %(default)s)",
    )
    p.add_argument(
        "--runs",
        metavar="N",
        type=_positive(int, 1, "must be an integer >= 1"),
        default=1,
        help="runs, each on a fresh server; the table holds their medians (default %(default)s)",
    )
    p.add_argument(
        "--clients",
        metavar="N",
        type=_positive(int, 1, "must be an integer >= 1"),
        default=2,
        help="load generator processes (default %(default)s)",
    )
    p.add_argument(
        "--sample-rate",
        metavar="HZ",
        type=_positive(int, 1, "must be an integer in 1..1000"),
        default=200,
        help="py-spy's samples per second (default %(default)s)",
    )
    p.add_argument(
        "--serve-args",
        default="",
        metavar="FLAGS",
        help="more `jitdyn serve` flags, after --processes 1, e.g. '--workers 2'",
    )
    p.add_argument(
        "--engines",
        nargs="+",
        choices=ENGINES,
        default=["native"],
        metavar="ENGINE",
        help="the server's --engine for each run, alternated run by run so that a noisy machine "
        "hits each alike: native, python or both (default native)",
    )
    p.add_argument(
        "--raw",
        type=Path,
        metavar="FOLDER",
        help="also keep each run's py-spy samples (collapsed stacks) here, as raw-N.txt, for a flame graph",
    )
    p.add_argument(
        "--json", type=Path, metavar="PATH", help="also write every run's figures and the medians here"
    )
    return p


def main(argv: Sequence[str] | None = None) -> int:
    p = parser()
    args = p.parse_args(argv)
    if args.sample_rate > 1000:
        p.error(f"argument --sample-rate: must be an integer in 1..1000, got {args.sample_rate}")
    options = Options(
        model=model_source(args.model).name,  # a clear error for an unknown model, before the work
        scenario=args.scenario,
        rate=args.rate,
        sessions=args.sessions,
        seconds=args.seconds,
        clients=args.clients,
        sample_rate=args.sample_rate,
        serve_args=tuple(args.serve_args.split()),
        raw=args.raw,
    )
    if args.raw is not None and not args.raw.is_dir():
        p.error(f"argument --raw: must be an existing folder, got {str(args.raw)!r}")
    py_spy()  # before minutes of work
    progress(
        f"{os.cpu_count()} CPUs; the trajectory and the filter's cycle of {options.model} {options.scenario}"
    )
    ticks = max(2, round(options.seconds * options.rate))
    states = trajectory(options.model, options.scenario, options.rate, ticks)
    ukf_us = ukf_cycle_us(options.model, options.scenario, options.rate, states)
    budgets: dict[str, list[Budget]] = {engine: [] for engine in args.engines}
    for i in range(args.runs):
        for engine in args.engines:
            progress(f"run {i + 1} of {args.runs}, --engine {engine}")
            on_engine = dataclasses.replace(options, serve_args=(*options.serve_args, "--engine", engine))
            budget = one_run(on_engine, states, ukf_us, index=i + 1)
            if budget is None:
                progress(f"run {i + 1}, --engine {engine}: not counted")
                continue
            progress(
                f"run {i + 1}, --engine {engine}: cpu/tick {budget.cpu_per_tick_us:.0f} us, floor "
                f"{budget.floor_us:.0f} us, {budget.over_floor:.2f}x; MEASURED {100 * budget.measured:.2f} %"
            )
            budgets[engine].append(budget)
    empty = [engine for engine, found in budgets.items() if not found]
    if empty:
        raise SystemExit(
            f"tick_budget: no run on --engine {', '.join(empty)} answered a tick (every session refused); "
            "try when the machine is quieter"
        )
    medians = {engine: median_budget(found) for engine, found in budgets.items()}
    for engine, found in budgets.items():
        print(f"## --engine {engine}\n")
        print(summary(options, medians[engine], found), end="\n\n")
    if len(budgets) > 1:
        print(side_by_side(medians, budgets))
    if args.json:
        document = {
            "options": {**asdict(options), "scenario": str(options.scenario), "raw": str(options.raw)},
            # over_floor: the median of the runs' ratios, not the ratio of the medians.
            "engines": {
                engine: {
                    # over_floor: the median of the runs' ratios, not the ratio of the medians.
                    "median": {
                        **asdict(medians[engine]),
                        "floor_us": medians[engine].floor_us,
                        "over_floor": statistics.median(b.over_floor for b in found),
                    },
                    "runs": [
                        {**asdict(b), "floor_us": b.floor_us, "over_floor": b.over_floor} for b in found
                    ],
                }
                for engine, found in budgets.items()
            },
        }
        args.json.write_text(json.dumps(document, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
