"""Real time under load: N concurrent REALTIME sessions against one `jitdyn serve`.

The load comes from separate client processes (`--clients`, default 2), each holding its share of
the sessions on one grpc.aio channel and sending every frame on its tick time, pre-serialised, so
the generator spends as little of the shared CPU as it can. Over every tick of every session it
reports:

    answered    ticks with at least one result / ticks sent
    measured    ticks whose first result is MEASURED / ticks sent
    late p50/p99/max   the first result's arrival after the tick's deadline (k dt + grace on the
                client's session clock; loopback transit included), ms; early answers count as 0
    cpu/tick    server CPU (user + system of every server process) / ticks answered, us
    ukf cycle   the same model's predict + update, measured in this run on one worker, us
    floor       what a tick cannot cost less than, measured after the run, in the same process:
                a bare grpc.aio tick (an echo servicer, same sessions, rate, frame and result
                sizes as the run's) + the tick's physics (the rollout of the model's sigma points
                alone, on a pool of one worker as each default server process has); printed as
                cpu/tick / floor

    python -m benchmarks.load --model pendulum_3 --rate 20 --sessions 100 --seconds 20
    python -m benchmarks.load --sweep                 # the four targets of RESULTS.md, largest N each
    python -m benchmarks.load --server 127.0.0.1:50051 --model biped --scenario CONTROLLED --rate 200 --sessions 6
    python -m benchmarks.load --sessions 16 --estimator STATIC --floor   # what a tick costs without the filter
    python -m benchmarks.load --model myolegs_osl --scenario DEFAULT --rate 100 --sessions 1 --seconds 60

--model is a built-in model or any myo-sim model that compiles here (as `jitdyn models register
--myo NAME` takes them), registered inline by the generator. The pendulums, the biped, myoElbow and
myoHand move as the experiments move them; any other model under slow out-of-phase excitations of
its actuators (experiments/accuracy.py's excited motion). --scenario DEFAULT names no scenario in
the open: the session gets the server's default for the model, and with no --estimator the
server's choice of estimator by the model's stored cost (each printed with the report).

Without --server it starts `jitdyn serve` with default settings on a free port and a temporary
data folder, and stops it after each run (a fresh server per trial in a sweep).

The generator stands for clients on other machines, so it runs at the server's priority (`--nice`,
default -10 as `jitdyn serve`'s): below it, the server's own work on a burst of opens took the CPU
from the generator's admitted sessions, whose frames then reached the server late (400 offered:
94.9-96.8 % of the admitted ticks MEASURED with the generator at nice 0, 99.9-100 % at -10;
benchmarks/RESULTS.md, Round 12).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import functools
import gc
import json
import math
import multiprocessing as mp
import os
import queue as queue_module
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from jitdyn.server.runtime.alarm import Alarm
from jitdyn.server.runtime.priority import set_priority
from jitdyn.server.runtime.stalls import LoopWatch
from jitdyn.settings import Settings
from jitdyn.vocabulary import Clock, Preset, Scenario

GRACE_FRACTION = 0.5  # the server's default grace, dt / 2
TARGET_P99_MS = 5.0
TARGET_MEASURED = 0.99


@dataclass(frozen=True)
class Target:
    """One row of the load targets: `sessions` of `model` in `scenario` at `rate` Hz."""

    model: str
    scenario: Scenario
    rate: float
    sessions: int
    aim: int
    seconds: float


TARGETS = (
    Target("pendulum_3", Scenario.PASSIVE, 20.0, 100, 200, 20.0),
    Target("biped", Scenario.CONTROLLED, 200.0, 6, 12, 20.0),
    Target("myoelbow", Scenario.EXTERNAL, 500.0, 6, 12, 20.0),
    Target("myohand", Scenario.EXTERNAL, 500.0, 1, 1, 60.0),
)


# ---------------------------------------------------------------------------------------------
# The trajectory every session replays.


# The research objects of the experiments, which move as the experiments move them.
OBJECTS = ("pendulum_1", "pendulum_2", "pendulum_3", "biped", "myoelbow", "myohand")
BUILTINS = ("pendulum_1", "pendulum_2", "pendulum_3", "biped")
# --scenario DEFAULT: the open names no scenario, and the server gives the model's default.
DEFAULT_SCENARIO = "DEFAULT"


def model_source(name: str) -> Any:
    """The `ModelSource` of `name`: a built-in model (the server knows it by name) or any myo-sim
    model that compiles here (registered inline), matched ignoring case; SystemExit naming the
    choices otherwise."""
    from jitdyn.client.myo import pack_myo_model, registrable_myo_models
    from jitdyn.experiments.objects import ModelSource, load_source

    if name in BUILTINS:
        return load_source(name)
    myo = {m.name.lower(): m.name for m in registrable_myo_models()}
    if name.lower() not in myo:
        raise SystemExit(
            f"--model must be a built-in model ({', '.join(BUILTINS)}) or a myo-sim model that compiles "
            f"here ({', '.join(sorted(myo.values()))}), got {name!r}"
        )
    mjcf, assets = pack_myo_model(myo[name.lower()])
    return ModelSource(name=myo[name.lower()], mjcf=mjcf, assets=assets, builtin=False)


def resolve_scenario(model: str, scenario: str) -> Scenario:
    """`scenario`, or for DEFAULT the scenario the server gives a session of `model` that names none."""
    if scenario != DEFAULT_SCENARIO:
        return Scenario(scenario)
    from jitdyn.server.estimation.config import default_scenario

    return default_scenario(model_source(model).compile())[0]


def _excited(model: str, scenario: str, rate: float, ticks: int) -> dict[str, np.ndarray]:
    """A model that is no research object, under experiments/accuracy.py's excitations."""
    from jitdyn.experiments.accuracy import excited_motion

    mj = model_source(model).compile()
    steps = round(1.0 / rate / float(mj.opt.timestep))
    if steps < 1 or abs(steps * float(mj.opt.timestep) * rate - 1.0) > 1e-6:
        raise SystemExit(
            f"--rate must make a tick a whole number of {model}'s {float(mj.opt.timestep) * 1e3:g} ms "
            f"timesteps, got {rate:g} Hz"
        )
    # DRIVEN is how the filter models the unknown force: the body moves as in EXTERNAL.
    motion = Scenario.EXTERNAL if scenario == Scenario.DRIVEN else Scenario(scenario)
    frames = excited_motion(mj, motion, steps, ticks)
    return {
        "qpos": np.array([f.qpos for f in frames]),
        "qvel": np.array([f.qvel for f in frames]),
        "ctrl": np.array([f.ctrl for f in frames]),
    }


def trajectory(model: str, scenario: str, rate: float, ticks: int) -> dict[str, np.ndarray]:
    """qpos, qvel, ctrl of `model` at `rate`: a research object driven as the experiments drive it,
    any other model under slow excitations of its actuators."""
    from jitdyn.experiments import objects

    dt = 1.0 / rate
    kinds = {
        "pendulum_1": (objects.Pendulum, (1,)),
        "pendulum_2": (objects.Pendulum, (2,)),
        "pendulum_3": (objects.Pendulum, (3,)),
        "biped": (objects.Biped, ()),
        "myoelbow": (objects.MyoElbow, ()),
        "myohand": (objects.MyoHand, ()),
    }
    if model not in kinds:
        return _excited(model, scenario, rate, ticks)
    cls, args = kinds[model]
    # DRIVEN is how the filter models the unknown force: the body moves as in EXTERNAL.
    motion = Scenario.EXTERNAL if scenario == Scenario.DRIVEN else Scenario(scenario)
    obj = cls(*args, motion, dt=dt)
    states = [obj.reset(seed=0)]
    for _ in range(ticks - 1):
        # CONTROLLED: the object's controller, fed the truth (a client's own controller would be).
        now = states[-1]
        ctrl = obj.control(now.t, now.qpos, now.qvel) if scenario == Scenario.CONTROLLED else None
        states.append(obj.step(ctrl))
    return {
        "qpos": np.array([s.qpos for s in states]),
        "qvel": np.array([s.qvel for s in states]),
        "ctrl": np.array([s.ctrl for s in states]),
    }


# ---------------------------------------------------------------------------------------------
# Client processes.


@dataclass
class WorkerSpec:
    address: str
    open_bytes: bytes
    frames_path: str
    sessions: int
    dt: float
    ticks: int
    start_spread: float
    index: int
    first: int = 0  # the global number of this process's first session
    total: int = 1  # sessions over every client process

    def start_delay(self, j: int) -> float:
        """When this process's session j opens: spread over `start_spread`, and at a tick phase of its
        own (k/total of dt for session k), as independent devices are. Spread alone put a 20 Hz
        run's 12 sessions on 3 phases, so frames came in bursts of 4 that queued on the loop."""
        g = self.first + j
        spread = self.start_spread * g / max(1, self.total)
        return spread - spread % self.dt + self.dt * g / max(1, self.total)


@dataclass
class WorkerResult:
    ticks_sent: int = 0
    answered: int = 0
    measured: int = 0
    lateness_ms: list[float] = field(default_factory=list)
    opened: int = 0
    refused: list[str] = field(default_factory=list)
    # Sessions the server ended while they ran (RESOURCE_EXHAUSTED: still late --late-timeout after
    # it told them they may go late), each its status details.
    ended: list[str] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    # What the server opened the first session with: its scenario, estimator and why.
    opened_with: str = ""
    cpu_seconds: float = 0.0
    shed: int = 0  # answers flagged late_compute
    late_frames: int = 0  # frames that came after their tick was answered (CORRECTED)
    rejected: int = 0
    reject_reasons: dict[str, int] = field(default_factory=dict)  # reason -> count
    reject_example: str = ""  # one rejection's message, to say why
    arrivals: list[float] = field(default_factory=list)  # monotonic time of each first answer
    # Monotonic tick time of each answered tick whose first answer was not MEASURED: when in the
    # run the misses came (the opens of the surplus, a stall, the end).
    unmeasured_at: list[float] = field(default_factory=list)
    server_late_ms: list[float] = field(default_factory=list)  # deadline to send, server clock
    # When each frame reached the server's loop after its tick time (Result.frame_delay), ms:
    # past the grace, its tick was answered PREDICTED.
    frame_delay_ms: list[float] = field(default_factory=list)
    frame_bytes: int = 0  # a serialised frame request, as sent
    result_bytes: int = 0  # a serialised result response, as received (the largest seen)
    # How late the load generator's own loop ran what fell due, ms: an answer it read late by
    # this much was not late at the server (a stall of the generator, not of the server).
    generator_lag_ms: list[float] = field(default_factory=list)


def _frames(spec: WorkerSpec, measured: Sequence[str]) -> list[bytes]:
    from jitdyn.checksum import frame_checksum
    from jitdyn.v1 import dynamics_pb2

    with np.load(spec.frames_path) as npz:  # each npz[key] reads the whole array again: once
        data = {key: npz[key] for key in npz.files}
    out = []
    for k in range(spec.ticks):
        channels = {
            "qpos": data["qpos"][k],
            "qvel": data["qvel"][k] if "qvel" in measured else np.empty(0),
            "qacc": np.empty(0),
            "ctrl": data["ctrl"][k] if "ctrl" in measured else np.empty(0),
            "sensordata": np.empty(0),
        }
        t = k * spec.dt
        frame = dynamics_pb2.Frame(
            seq=k,
            t=t,
            qpos=channels["qpos"].tolist(),
            qvel=channels["qvel"].tolist(),
            ctrl=channels["ctrl"].tolist(),
            checksum=frame_checksum(seq=k, t=t, **channels),
        )
        out.append(dynamics_pb2.StreamSessionRequest(frame=frame).SerializeToString())
    return out


def _opened_with(opened: Any) -> str:
    from jitdyn.v1 import common_pb2, dynamics_pb2

    estimator = common_pb2.Estimator.Name(opened.estimator.estimator)
    sigma = opened.estimator.sigma_points  # resolved for every estimator: a UKF's points only
    ukf = opened.estimator.estimator == common_pb2.ESTIMATOR_UKF
    scheme = f" {common_pb2.SigmaPoints.Name(sigma)}" if sigma and ukf else ""
    return (
        f"{common_pb2.Scenario.Name(opened.scenario)}, {estimator}{scheme} "
        f"({dynamics_pb2.EstimatorChoice.Name(opened.estimator_choice)}: {opened.estimator_reason})"
    )


async def _session(
    stub_call: object, spec: WorkerSpec, frames: list[bytes], delay: float, result: WorkerResult
) -> None:
    import grpc

    from jitdyn.v1 import dynamics_pb2

    await asyncio.sleep(delay)
    call = stub_call(wait_for_ready=True)  # type: ignore[operator]
    try:
        await call.write(spec.open_bytes)
        first = dynamics_pb2.StreamSessionResponse.FromString(await call.read())
    except grpc.aio.AioRpcError as error:
        text = f"{error.code().name}: {error.details()}"
        (result.refused if error.code() == grpc.StatusCode.RESOURCE_EXHAUSTED else result.errors).append(text)
        return
    if not first.HasField("opened"):
        result.errors.append(f"first answer is not `opened`: {first.WhichOneof('payload')}")
        return
    result.opened += 1
    result.opened_with = result.opened_with or _opened_with(first.opened)
    start = time.monotonic()
    grace = first.opened.grace or spec.dt * GRACE_FRACTION
    first_answer: dict[int, tuple[float, int, bool, int]] = {}
    probe = 0
    last_probe: tuple[int, float] | None = None

    async def read() -> None:
        nonlocal last_probe
        while True:
            raw = await call.read()
            if raw is grpc.aio.EOF:
                return
            now = time.monotonic()
            response = dynamics_pb2.StreamSessionResponse.FromString(raw)
            kind = response.WhichOneof("payload")
            if kind == "result":
                result.result_bytes = max(result.result_bytes, len(raw))
                seq = response.result.seq
                r = response.result
                if r.frame_received:
                    result.frame_delay_ms.append(r.frame_delay * 1e3)
                if seq not in first_answer:
                    first_answer[seq] = (now - start, r.source, r.late_compute, r.receive_to_send_us)
            elif kind == "sync":
                last_probe = (response.sync.id, now - start)
            elif kind == "closed":
                result.late_frames += response.closed.summary.late
            elif kind == "rejected":
                result.rejected += 1
                reason = dynamics_pb2.RejectReason.Name(response.rejected.reason)
                result.reject_reasons[reason] = result.reject_reasons.get(reason, 0) + 1
                result.reject_example = result.reject_example or response.rejected.message

    async def ping() -> None:
        nonlocal probe
        probe += 1
        message = dynamics_pb2.SyncPing(id=probe, client_send_time=time.monotonic() - start)
        if last_probe is not None:
            message.previous_id, message.previous_receive_time = last_probe
        await call.write(dynamics_pb2.StreamSessionRequest(sync=message).SerializeToString())

    reader = asyncio.create_task(read())
    try:
        await ping()
        next_sync = 1.0
        # Frames leave on their tick times to within a fraction of a millisecond: asyncio.sleep
        # is 0.65 ms late at the median (its epoll timeout is whole milliseconds, rounded up),
        # which is most of a 500 Hz tick's 1 ms grace spent before the frame leaves.
        alarm = Alarm.of(asyncio.get_running_loop())
        for k, frame in enumerate(frames):
            await alarm.sleep_until(start + k * spec.dt)
            try:
                await call.write(frame)
            except asyncio.InvalidStateError:  # the server ended the call
                reader.cancel()
                await asyncio.gather(reader, return_exceptions=True)
                text = f"{(await call.code()).name}: {await call.details()}"
                ended = await call.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
                (result.ended if ended else result.errors).append(text)
                frames = frames[:k]  # the ticks sent
                break
            if k * spec.dt >= next_sync:
                await ping()
                next_sync += 1.0
        else:
            # Let the last tick's deadline pass before closing (close answers pending ticks at once).
            await asyncio.sleep(
                max(0.0, start + (len(frames) - 1) * spec.dt + grace + 0.05 - time.monotonic())
            )
            await call.write(
                dynamics_pb2.StreamSessionRequest(close=dynamics_pb2.CloseSession()).SerializeToString()
            )
            await call.done_writing()
            await asyncio.wait_for(reader, timeout=30)
    except (grpc.aio.AioRpcError, TimeoutError) as error:
        result.errors.append(repr(error)[:200])
        reader.cancel()
    result.ticks_sent += len(frames)
    measured_source = dynamics_pb2.SOURCE_MEASURED
    for k in range(len(frames)):
        answer = first_answer.get(k)
        if answer is None:
            continue
        result.answered += 1
        arrived, source, shed, server_late_us = answer
        result.server_late_ms.append(server_late_us / 1e3)
        result.measured += source == measured_source
        if source != measured_source:
            result.unmeasured_at.append(start + k * spec.dt)
        result.shed += shed
        result.lateness_ms.append(max(0.0, (arrived - (k * spec.dt + grace)) * 1e3))
        result.arrivals.append(start + arrived)


async def _worker_main(spec: WorkerSpec, measured: Sequence[str]) -> WorkerResult:
    import grpc

    frames = _frames(spec, measured)
    result = WorkerResult(frame_bytes=max(len(f) for f in frames))
    cpu_started = time.process_time()
    # One connection per session, as every device has its own: the kernel spreads connections, not
    # streams, over the server's processes (SO_REUSEPORT). gRPC shares one connection between
    # channels of the same target and arguments (its global subchannel pool): without a local pool
    # every session of a client process went over one connection to one server process.
    options = [("grpc.max_receive_message_length", 64 * 1024 * 1024), ("grpc.use_local_subchannel_pool", 1)]
    channels = [grpc.aio.insecure_channel(spec.address, options=options) for _ in range(spec.sessions)]
    # The generator's heap frozen, as the server's is (docs/decisions/0006), and its own loop
    # watched, so that its stalls are told apart from the server's.
    gc.collect()
    gc.freeze()
    watch = LoopWatch(asyncio.get_running_loop(), on_lag=lambda s: result.generator_lag_ms.append(1e3 * s))
    watch.start()
    try:
        tasks = [
            _session(
                channel.stream_stream(
                    "/jitdyn.v1.DynamicsService/StreamSession",
                    request_serializer=None,
                    response_deserializer=None,
                ),
                spec,
                frames,
                spec.start_delay(i),
                result,
            )
            for i, channel in enumerate(channels)
        ]
        await asyncio.gather(*tasks)
    finally:
        watch.stop()
        for channel in channels:
            await channel.close()
    result.cpu_seconds = time.process_time() - cpu_started
    return result


def _worker(spec: WorkerSpec, measured: Sequence[str], queue: mp.Queue) -> None:  # type: ignore[type-arg]
    try:
        queue.put(asdict(asyncio.run(_worker_main(spec, measured))))
    except BaseException as error:  # noqa: BLE001 - reported to the parent, which fails the run
        queue.put({"fatal": repr(error)})


# ---------------------------------------------------------------------------------------------
# The server and its CPU.


def _process_tree(pid: int) -> list[int]:
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            with contextlib.suppress(OSError):
                fields = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()
                children.setdefault(int(fields[1]), []).append(int(entry))
    tree, todo = [], [pid]
    while todo:
        current = todo.pop()
        tree.append(current)
        todo.extend(children.get(current, []))
    return tree


def cpu_seconds(pid: int) -> float:
    """User + system CPU of `pid` and its descendants so far, in seconds."""
    ticks = os.sysconf("SC_CLK_TCK")
    total = 0
    for p in _process_tree(pid):
        with contextlib.suppress(OSError):
            fields = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
            total += int(fields[11]) + int(fields[12])
    return total / ticks


@contextlib.contextmanager
def local_server(extra: Sequence[str] = (), log: list[str] | None = None) -> Iterator[tuple[str, int]]:
    """`jitdyn serve` on a free port and a temporary data folder: (address, pid). What it prints goes
    to `log` line by line, read all along: a pipe nobody reads fills, and a server writing to it
    stops (its warnings, a stall's report, would hang it)."""
    with tempfile.TemporaryDirectory(prefix="jitdyn-load-") as data:
        env = dict(os.environ, JITDYN_SECRET="ab" * 32)
        process = subprocess.Popen(
            [sys.executable, "-m", "jitdyn.cli", "serve", "--address", "127.0.0.1:0", "--data", data, *extra],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env=env,
        )
        assert process.stdout is not None
        address = None
        for line in process.stdout:
            if line.startswith("jitdyn listening on"):
                address = line.split()[3]
                break
        if address is None:
            process.wait()
            raise SystemExit("jitdyn serve did not start")
        lines = log if log is not None else []
        reader = threading.Thread(target=lambda: lines.extend(process.stdout or ()), daemon=True)
        reader.start()
        try:
            yield address, process.pid
        finally:
            process.terminate()
            try:
                process.wait(timeout=60)
            except subprocess.TimeoutExpired:
                process.kill()
            reader.join(timeout=5)
            process.stdout.close()


def stall_reports(log: Sequence[str]) -> list[str]:
    """The server's reports of event-loop stalls (`jitdyn serve --stall-report`), each its lines."""
    reports: list[str] = []
    for line in log:
        if "the event loop stalled" in line:
            reports.append(line)
        elif reports and line.startswith("  "):
            reports[-1] += line
    return reports


def _server_pid(address: str) -> int | None:
    """The pid listening on `address` (for --server), from /proc/net/tcp; None if not ours to see."""
    port = int(address.rsplit(":", 1)[1])
    inodes = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with contextlib.suppress(OSError):
            for line in Path(table).read_text().splitlines()[1:]:
                parts = line.split()
                if int(parts[1].rsplit(":", 1)[1], 16) == port and parts[3] == "0A":
                    inodes.add(parts[9])
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            with contextlib.suppress(OSError):
                for fd in os.listdir(f"/proc/{entry}/fd"):
                    link = os.readlink(f"/proc/{entry}/fd/{fd}")
                    if link.startswith("socket:[") and link[8:-1] in inodes:
                        return _serve_root(int(entry))
    return None


def _serve_root(pid: int) -> int:
    """The `jitdyn serve` process whose tree `pid` is in: with --processes N every child listens
    on the port, and the server's CPU is the whole tree's (one child alone read 0 us per tick)."""
    while True:
        try:
            parent = int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
            command = Path(f"/proc/{parent}/cmdline").read_bytes().split(b"\0")
        except (OSError, ValueError, IndexError):
            return pid
        # `python -m jitdyn.cli serve`, or the `jitdyn serve` console script: a parent that is
        # neither (a shell, the console script's caller) is not the server's.
        names = {os.path.basename(arg) for arg in command}
        if b"serve" not in command or not names & {b"jitdyn.cli", b"jitdyn"}:
            return pid
        pid = parent


# ---------------------------------------------------------------------------------------------
# The floor: what grpc.aio alone costs per tick, measured in the same run.


def _floor_server(queue: mp.Queue, seconds: float, dt: float, response_bytes: int) -> None:  # type: ignore[type-arg]
    import grpc

    response = b"x" * response_bytes  # the run's result size; nobody parses it

    transit: list[float] = []  # s from the client's write to this read (one monotonic clock)

    async def handler(requests: object, context: grpc.aio.ServicerContext) -> None:  # type: ignore[type-arg]
        started = time.monotonic()
        for k in range(round(seconds / dt)):
            frame = await context.read()  # the frame, stamped with its send time
            transit.append(time.monotonic() - struct.unpack_from("d", frame)[0])  # type: ignore[arg-type]
            wait = started + k * dt - time.monotonic()
            if wait > 0:
                await asyncio.sleep(wait)
            await context.write(response)

    async def main() -> None:
        server = grpc.aio.server()
        handlers = grpc.method_handlers_generic_handler(
            "floor.Floor",
            {
                "S": grpc.stream_stream_rpc_method_handler(
                    handler, request_deserializer=None, response_serializer=None
                )
            },
        )
        server.add_generic_rpc_handlers((handlers,))
        port = server.add_insecure_port("127.0.0.1:0")
        await server.start()
        queue.put(port)
        cpu = time.process_time()
        await asyncio.sleep(seconds + 2.0)
        queue.put((time.process_time() - cpu, transit))
        await server.stop(0)

    asyncio.run(main())


async def _floor_clients(port: int, sessions: int, seconds: float, dt: float, frame_bytes: int) -> None:
    import grpc

    padding = b"x" * max(0, frame_bytes - 8)  # the run's frame size, its send time first
    alarm = Alarm.of(asyncio.get_running_loop())
    options = [("grpc.use_local_subchannel_pool", 1)]  # a connection each, as the sessions have

    async def one(i: int) -> None:
        async with grpc.aio.insecure_channel(f"127.0.0.1:{port}", options=options) as channel:
            call = channel.stream_stream(
                "/floor.Floor/S", request_serializer=None, response_deserializer=None
            )()
            started = time.monotonic() + dt * i / sessions  # a phase of its own
            for k in range(round(seconds / dt)):
                await alarm.sleep_until(started + k * dt)
                await call.write(struct.pack("d", time.monotonic()) + padding)
                await call.read()

    await asyncio.gather(*(one(i) for i in range(sessions)))


@dataclass(frozen=True)
class Floor:
    """CPU per tick of a bare grpc.aio bidirectional stream, no jitdyn at all, us."""

    server_us: float  # read a frame, wait for the tick, write a result
    client_us: float  # write a frame on the tick, read the result: a Python client's least
    transit_p50_ms: float  # from the client's write to the server's read
    transit_p99_ms: float
    over_grace: float  # share of frames whose transit alone passed the grace (dt/2)

    def cores(self, sessions: int, rate: float) -> float:
        """What `sessions` at `rate` Hz cost both sides of the bare stream, in cores."""
        return sessions * rate * (self.server_us + self.client_us) / 1e6


def transport_floor(
    sessions: int, rate: float, seconds: float = 5.0, *, frame_bytes: int = 200, result_bytes: int = 120
) -> Floor:
    """Server and client CPU per tick of a bare grpc.aio stream, `sessions` streams at `rate` Hz,
    frames and results of these sizes (bytes, serialised)."""
    context = mp.get_context("spawn")
    queue = context.Queue()
    server = context.Process(target=_floor_server, args=(queue, seconds, 1.0 / rate, result_bytes))
    server.start()
    port = queue.get()
    client_cpu = time.process_time()
    asyncio.run(_floor_clients(port, sessions, seconds, 1.0 / rate, frame_bytes))
    client_cpu = time.process_time() - client_cpu
    cpu, transit = queue.get()
    server.join()
    ticks = sessions * round(seconds * rate)
    delays = np.array(transit) * 1e3
    return Floor(
        server_us=float(cpu) / ticks * 1e6,
        client_us=client_cpu / ticks * 1e6,
        transit_p50_ms=float(np.percentile(delays, 50)),
        transit_p99_ms=float(np.percentile(delays, 99)),
        over_grace=float(np.mean(delays > 1e3 * GRACE_FRACTION / rate)),
    )


# ---------------------------------------------------------------------------------------------
# One run.


def per_tick_us(cpu_seconds: float, ticks: float) -> float:
    """CPU per answered tick, us; nan when nothing was answered (printed as nan, not as the whole
    CPU of the run charged to one tick)."""
    return cpu_seconds / ticks * 1e6 if ticks else math.nan


@dataclass
class RunReport:
    model: str
    scenario: str
    rate: float
    sessions: int
    opened: int
    refused: int
    errors: list[str]
    ticks_sent: int
    answered: float
    measured: float
    late_p50_ms: float
    late_p99_ms: float
    late_max_ms: float
    cpu_per_tick_us: float
    ukf_cycle_us: float
    client_cpu_per_tick_us: float
    ended: int = 0  # sessions the server ended while they ran, still late after --late-timeout
    floor_grpc_us: float = math.nan  # bare grpc.aio server CPU per tick, same sizes, after the run
    physics_us: float = math.nan  # the rollout of the tick's sigma points alone, CPU
    frame_bytes: int = 0
    result_bytes: int = 0

    @property
    def over_floor(self) -> float:
        """Server CPU per tick / (bare grpc.aio tick + the tick's physics)."""
        return self.cpu_per_tick_us / (self.floor_grpc_us + self.physics_us)

    shed: float = 0.0  # share of ticks answered late_compute
    late_frames: float = 0.0  # share of frames that came after their tick was answered
    rejected: int = 0
    reject_reasons: dict[str, int] = field(default_factory=dict)
    reject_example: str = ""
    measured_of_answered: float = 0.0  # of the admitted sessions' answered ticks
    unmeasured_by_second: dict[str, int] = field(default_factory=dict)  # second of the run -> ticks
    frame_delay_p50_ms: float = 0.0  # a frame's arrival on the server's loop after its tick time
    frame_delay_p99_ms: float = 0.0
    server_late_p99_ms: float = 0.0  # deadline to send on the server's clock (Result.receive_to_send_us)
    stalls: list[str] = field(default_factory=list)  # the server's stall reports (a local server only)
    generator_lag_p99_ms: float = 0.0  # the load generator's own loop lag
    generator_lag_max_ms: float = 0.0
    opened_with: str = ""  # the first session's scenario and estimator, as `opened` gave them

    def meets(self) -> bool:
        return (
            self.opened == self.sessions
            and not self.errors
            and self.answered >= 1.0
            and self.measured >= TARGET_MEASURED
            and self.late_p99_ms <= TARGET_P99_MS
        )

    def line(self) -> str:
        verdict = "MEETS" if self.meets() else "misses"
        if self.opened == 0:
            # Nothing ran: no lateness or CPU per tick to report (they would read nan and inf).
            return (
                f"{self.sessions:4d} x {self.model:10s} {self.scenario:10s} {self.rate:5.0f} Hz | "
                f"opened    0 refused {self.refused:3d} | nothing ran (ukf {self.ukf_cycle_us:5.0f} us) | {verdict}"
            )
        return (
            (
                f"{self.sessions:4d} x {self.model:10s} {self.scenario:10s} {self.rate:5.0f} Hz | "
                f"opened {self.opened:4d} refused {self.refused:3d} ended {self.ended:2d} | answered {100 * self.answered:6.2f} % "
                f"measured {100 * self.measured:6.2f} % shed {100 * self.shed:5.2f} % late frames "
                f"{100 * self.late_frames:5.2f} % rejected {self.rejected} | late p50 {self.late_p50_ms:6.2f} p99 {self.late_p99_ms:7.2f} "
                f"max {self.late_max_ms:8.2f} ms (server {self.server_late_p99_ms:5.2f}) | cpu/tick {self.cpu_per_tick_us:6.0f} us "
                f"(ukf {self.ukf_cycle_us:5.0f} us, +{self.cpu_per_tick_us - self.ukf_cycle_us:5.0f}; "
                f"load generator {self.client_cpu_per_tick_us:4.0f} us) | {verdict}"
            )
            + self._floor()
            + self._rejections()
            + (f"\n      opened with {self.opened_with}" if self.opened_with else "")
        )

    def _floor(self) -> str:
        if math.isnan(self.floor_grpc_us):
            return ""
        return (
            f"\n      floor: bare grpc.aio {self.floor_grpc_us:.0f} us ({self.frame_bytes} B frames, "
            f"{self.result_bytes} B results) + physics {self.physics_us:.0f} us = "
            f"{self.floor_grpc_us + self.physics_us:.0f} us; cpu/tick / floor = {self.over_floor:.2f}"
        )

    def _rejections(self) -> str:
        text = (
            f"\n      frames reached the server's loop {self.frame_delay_p50_ms:.2f} ms (p50), "
            f"{self.frame_delay_p99_ms:.2f} ms (p99) after their tick time; grace "
            f"{1e3 * GRACE_FRACTION / self.rate:g} ms; the load generator's own loop lag "
            f"{self.generator_lag_p99_ms:.2f} (p99) / {self.generator_lag_max_ms:.1f} ms (max)"
        )
        if self.unmeasured_by_second:
            seconds = ", ".join(f"{s} s: {n}" for s, n in self.unmeasured_by_second.items())
            text += (
                f"\n      {100 * self.measured_of_answered:.2f} % of the answered ticks MEASURED; the others "
                f"by second of the run: {seconds}"
            )
        if self.stalls:
            longest = max(self.stalls, key=lambda r: float(r.split("stalled ")[1].split(" ms")[0]))
            text += f"\n      the server logged {len(self.stalls)} stalls of its loop; the longest:\n{longest.rstrip()}"
        if not self.reject_reasons:
            return text
        reasons = ", ".join(f"{reason} {count}" for reason, count in sorted(self.reject_reasons.items()))
        return text + f"\n      rejected frames: {reasons}; for example: {self.reject_example[:160]}"


def default_config(model: str, scenario: str, rate: float) -> tuple[Any, Any]:
    """The compiled model and the default JITDYN estimator config of a session at `rate` Hz."""
    from jitdyn.server.estimation.config import resolve_config

    mj = model_source(model).compile()
    measured = {"qpos", "qvel", "ctrl"} if scenario == Scenario.CONTROLLED else {"qpos", "qvel"}
    config = resolve_config(
        model=mj,
        scenario=scenario,
        dt=1.0 / rate,
        requested={},
        model_defaults={},
        preset=Preset.JITDYN,
        measured=measured,
    )
    return mj, config


# The UKF's cycle and the physics are sampled at most this long, once this many samples are taken.
_SAMPLING_SECONDS = 5.0
_FEWEST_SAMPLES = 20


def ukf_cycle_us(model: str, scenario: str, rate: float, states: dict[str, np.ndarray]) -> float:
    """Median predict + update of the default estimator for `model`, one worker, this process."""
    from jitdyn.server.estimation.factory import make_estimator
    from jitdyn.server.estimation.interface import Measurement
    from jitdyn.server.estimation.pool import WorkerPool

    mj, config = default_config(model, scenario, rate)
    with WorkerPool(1) as pool:
        estimator = make_estimator(mj, config, pool=pool)

        def measurement(k: int) -> Measurement:
            return Measurement(
                qpos=states["qpos"][k],
                qvel=states["qvel"][k],
                ctrl=states["ctrl"][k] if scenario == Scenario.CONTROLLED else None,
            )

        estimator.initialise(measurement(0))
        samples: list[float] = []
        n = min(len(states["qpos"]), 400)
        for k in range(1, n):
            if len(samples) >= _FEWEST_SAMPLES and sum(samples) > _SAMPLING_SECONDS:
                break  # a big model's UKF (tens of ms a cycle): a median of what fits
            ctrl = states["ctrl"][k] if scenario == Scenario.CONTROLLED else None
            started = time.perf_counter()
            estimator.predict(ctrl=ctrl)
            estimator.update(measurement(k))
            samples.append(time.perf_counter() - started)
    return statistics.median(samples) * 1e6


def tick_physics_us(model: str, scenario: str, rate: float, states: dict[str, np.ndarray]) -> float:
    """CPU per tick of the physics alone: the rollout of the default estimator's sigma points
    (drawn from its posterior along the trajectory) over one tick, on a pool of one worker, us."""
    from jitdyn.server.estimation.factory import make_estimator
    from jitdyn.server.estimation.interface import Measurement
    from jitdyn.server.estimation.pool import WorkerPool
    from jitdyn.server.estimation.ukf import UnscentedFilter

    mj, config = default_config(model, scenario, rate)
    controlled = scenario == Scenario.CONTROLLED
    with WorkerPool(1) as pool:
        estimator = make_estimator(mj, config, pool=pool)
        ukf = getattr(estimator, "_first", estimator)  # a SwitchingFilter's filter, before a switch
        if not isinstance(ukf, UnscentedFilter):
            raise SystemExit(f"the default estimator of {model} {scenario} is not a UKF")
        samples: list[float] = []
        n = min(len(states["qpos"]), 200)
        for k in range(n):
            if len(samples) >= _FEWEST_SAMPLES and 5 * sum(samples) > _SAMPLING_SECONDS:
                break
            frame = Measurement(
                qpos=states["qpos"][k], qvel=states["qvel"][k], ctrl=states["ctrl"][k] if controlled else None
            )
            if k == 0:
                ukf.initialise(frame)
                continue
            parts = ukf.parts
            kf, state, layout = parts.kf, parts.state, parts.layout
            if controlled:
                state.ctrl = np.array(states["ctrl"][k])
            parts.process.set_inputs(act=state.act, ctrl=state.ctrl, qfrc=state.qfrc)
            if layout.linear_force:  # SIMPLEX_LINEAR_FORCE: points over [q, qd], the force carried along
                head = layout.nq + layout.nv
                chi = parts.points.sigma_points(kf.x[:head], kf.P[: 2 * layout.nv, : 2 * layout.nv])
                force = np.repeat(kf.x[None, head:], chi.shape[0], 0)
                rollout = functools.partial(parts.process.propagate_linear_force, chi, force, nstep=None)
            else:
                sigmas = parts.points.sigma_points(kf.x, kf.P)
                rollout = functools.partial(parts.process.propagate, sigmas, nstep=None)
            started = time.process_time()  # the pool's threads included
            for _ in range(5):
                rollout()
            samples.append((time.process_time() - started) / 5)
            ukf.advance(ctrl=frame.ctrl)
            ukf.update(frame)
    return statistics.median(samples) * 1e6


def run(
    *,
    model: str,
    scenario: str,
    rate: float,
    sessions: int,
    seconds: float,
    clients: int,
    server: str | None,
    serve_args: Sequence[str] = (),
    states: dict[str, np.ndarray] | None = None,
    ukf_us: float | None = None,
    estimator: str | None = None,
    floor: bool = True,
    name_scenario: bool = True,
) -> RunReport:
    """`sessions` REALTIME sessions of `model` (a built-in or myo-sim name) for `seconds`; the open
    names `scenario` unless `name_scenario` is False, when the server gives the model's default
    (which `scenario` must then be: the trajectory and the UKF's figures are of it)."""
    from jitdyn.client import Client, SessionOptions

    dt = 1.0 / rate
    ticks = max(2, round(seconds * rate))
    if states is None:
        states = trajectory(model, scenario, rate, ticks)
    if ukf_us is None:
        ukf_us = ukf_cycle_us(model, scenario, rate, states)
    server_log: list[str] = []
    with contextlib.ExitStack() as stack:
        if server is None:
            address, pid = stack.enter_context(local_server(serve_args, server_log))
        else:
            address, found = server, _server_pid(server)
            if found is None:
                raise SystemExit(f"cannot see the process serving {server}; run the server as this user")
            pid = found
        folder = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="jitdyn-load-frames-")))
        frames_path = folder / "frames.npz"
        np.savez(frames_path, **states)
        options: dict[str, object] = {"dt": dt, "clock": Clock.REALTIME}
        if name_scenario:
            options["scenario"] = scenario
        source = model_source(model)
        with Client(address) as client:
            if source.builtin:
                options["model_name"] = source.name
            else:
                info, _ = client.register_model(name=source.name, mjcf=source.mjcf, assets=source.assets)
                options["model_id"] = info.id
        if estimator is not None:
            options["estimator"] = {"estimator": estimator}
        open_message = SessionOptions(**options)  # type: ignore[arg-type]
        measured = ["qpos", "qvel", "ctrl"] if scenario == Scenario.CONTROLLED else ["qpos", "qvel"]
        from jitdyn.v1 import dynamics_pb2

        open_bytes = dynamics_pb2.StreamSessionRequest(open=open_message.to_message()).SerializeToString()
        per_client = [sessions // clients + (1 if i < sessions % clients else 0) for i in range(clients)]
        context = mp.get_context("spawn")
        queue = context.Queue()
        spread = min(2.0, seconds / 4)
        workers = [
            context.Process(
                target=_worker,
                args=(
                    WorkerSpec(
                        address,
                        open_bytes,
                        str(frames_path),
                        n,
                        dt,
                        ticks,
                        spread,
                        i,
                        sum(per_client[:i]),
                        sessions,
                    ),
                    measured,
                    queue,
                ),
            )
            for i, n in enumerate(per_client)
            if n
        ]
        # Server CPU over the steady part of the run: every session open, before the first closes.
        started = time.monotonic()
        window = (started + spread + 1.0, started + max(spread + 2.0, seconds - 1.0))
        for worker in workers:
            worker.start()
        samples: dict[int, tuple[float, float]] = {}
        results: list[dict[str, object]] = []
        for i, at in enumerate(window):
            while time.monotonic() < at and len(results) < len(workers):
                with contextlib.suppress(queue_module.Empty):
                    results.append(queue.get(timeout=min(0.2, max(0.01, at - time.monotonic()))))
            samples[i] = (time.monotonic(), cpu_seconds(pid))
        while len(results) < len(workers):
            results.append(queue.get())
        for worker in workers:
            worker.join()
    (t1, cpu1), (t2, cpu2) = samples[0], samples[1]
    fatal = [r["fatal"] for r in results if "fatal" in r]
    if fatal:
        raise SystemExit(f"a client process failed: {fatal[0]}")
    merged = WorkerResult()
    for r in results:
        merged.shed += r["shed"]
        merged.late_frames += r["late_frames"]
        merged.rejected += r["rejected"]
        for reason, count in r["reject_reasons"].items():
            merged.reject_reasons[reason] = merged.reject_reasons.get(reason, 0) + count
        merged.reject_example = merged.reject_example or r["reject_example"]
        merged.arrivals.extend(r["arrivals"])
        merged.unmeasured_at.extend(r["unmeasured_at"])
        merged.server_late_ms.extend(r["server_late_ms"])
        merged.frame_delay_ms.extend(r["frame_delay_ms"])
        merged.ticks_sent += r["ticks_sent"]
        merged.answered += r["answered"]
        merged.measured += r["measured"]
        merged.lateness_ms.extend(r["lateness_ms"])
        merged.opened += r["opened"]
        merged.refused.extend(r["refused"])
        merged.ended.extend(r["ended"])
        merged.errors.extend(r["errors"])
        merged.opened_with = merged.opened_with or r["opened_with"]
        merged.cpu_seconds += r["cpu_seconds"]
        merged.generator_lag_ms.extend(r["generator_lag_ms"])
    expected = sessions * ticks
    floor_grpc = physics = math.nan
    frame_bytes = max((r["frame_bytes"] for r in results), default=0)
    result_bytes = max((r["result_bytes"] for r in results), default=0)
    if floor and result_bytes:
        measured_floor = transport_floor(
            min(sessions, 50), rate, frame_bytes=frame_bytes, result_bytes=result_bytes
        )
        floor_grpc = measured_floor.server_us
        physics = tick_physics_us(model, scenario, rate, states)
    late = np.array(merged.lateness_ms or [math.inf])

    def percentile(values: list[float], q: float) -> float:
        # Nothing ran: inf, not numpy's nan (and its warning) from interpolating between infinities.
        return float(np.percentile(values, q)) if values else math.inf

    return RunReport(
        model=model,
        scenario=scenario,
        rate=rate,
        sessions=sessions,
        opened=merged.opened,
        refused=len(merged.refused),
        ended=len(merged.ended),
        errors=merged.errors[:5] + merged.refused[:2] + merged.ended[:1],
        ticks_sent=merged.ticks_sent,
        answered=merged.answered / expected,
        measured=merged.measured / expected,
        measured_of_answered=merged.measured / max(1, merged.answered),
        unmeasured_by_second={
            str(second): count
            for second, count in sorted(Counter(int(at - started) for at in merged.unmeasured_at).items())
        },
        late_p50_ms=percentile(merged.lateness_ms, 50),
        late_p99_ms=percentile(merged.lateness_ms, 99),
        late_max_ms=float(late.max()),
        cpu_per_tick_us=per_tick_us(cpu2 - cpu1, sum(t1 <= a < t2 for a in merged.arrivals)),
        shed=merged.shed / expected,
        late_frames=merged.late_frames / expected,
        rejected=merged.rejected,
        reject_reasons=merged.reject_reasons,
        reject_example=merged.reject_example,
        server_late_p99_ms=percentile(merged.server_late_ms, 99),
        frame_delay_p50_ms=percentile(merged.frame_delay_ms, 50),
        frame_delay_p99_ms=percentile(merged.frame_delay_ms, 99),
        ukf_cycle_us=ukf_us,
        client_cpu_per_tick_us=per_tick_us(merged.cpu_seconds, merged.answered),
        floor_grpc_us=floor_grpc,
        physics_us=physics,
        frame_bytes=frame_bytes,
        result_bytes=result_bytes,
        stalls=stall_reports(server_log),
        generator_lag_p99_ms=percentile(merged.generator_lag_ms, 99),
        generator_lag_max_ms=max(merged.generator_lag_ms, default=0.0),
        opened_with=merged.opened_with,
    )


def sweep(
    target: Target, *, clients: int, server: str | None, serve_args: Sequence[str], seconds: float | None
) -> list[RunReport]:
    """The largest N meeting the targets: the required N first, then up towards the aim, or down."""
    length = seconds or target.seconds
    ticks = max(2, round(length * target.rate))
    states = trajectory(target.model, target.scenario, target.rate, ticks)
    ukf_us = ukf_cycle_us(target.model, target.scenario, target.rate, states)
    floor_n = min(target.sessions, 50)
    floor = transport_floor(floor_n, target.rate)
    least = target.sessions * target.rate * ukf_us / 1e6 + floor.cores(target.sessions, target.rate)
    print(
        f"# {target.model} {target.scenario} {target.rate:g} Hz: UKF cycle {ukf_us:.0f} us; bare grpc.aio "
        f"per tick ({floor_n} streams): {floor.server_us:.0f} us of server CPU, {floor.client_us:.0f} us of "
        f"client CPU; so {target.sessions} sessions need at least {least:.2f} cores (the UKF and bare "
        f"gRPC on both sides, nothing else) of this machine's {os.cpu_count()}. A bare frame's transit "
        f"p50 / p99 {floor.transit_p50_ms:.2f} / {floor.transit_p99_ms:.2f} ms, {100 * floor.over_grace:.1f} % "
        "of frames past the grace on transit alone",
        flush=True,
    )
    reports: list[RunReport] = []

    def trial(n: int) -> RunReport:
        report = run(
            model=target.model,
            scenario=target.scenario,
            rate=target.rate,
            sessions=n,
            seconds=length,
            clients=clients,
            server=server,
            serve_args=serve_args,
            states=states,
            ukf_us=ukf_us,
        )
        print(report.line(), flush=True)
        reports.append(report)
        return report

    n = target.sessions
    if trial(n).meets():
        while n < target.aim:
            bigger = min(target.aim, max(n + 1, round(n * 1.5)))
            if not trial(bigger).meets():
                break
            n = bigger
    else:
        while n > 1:
            n = max(1, n // 2)
            if trial(n).meets():
                break
    return reports


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0],
        epilog=__doc__.split("\n\n", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--model",
        default="pendulum_3",
        help="pendulum_1..3, biped, or any myo-sim model that compiles here (myoelbow, myohand, "
        "myolegs_osl, ...; as `jitdyn models register --myo NAME` takes them)",
    )
    parser.add_argument(
        "--scenario",
        default=Scenario.PASSIVE,
        choices=(Scenario.PASSIVE, Scenario.CONTROLLED, Scenario.EXTERNAL, Scenario.DRIVEN, DEFAULT_SCENARIO),
        help=f"{DEFAULT_SCENARIO}: name none in the open, and get the server's default for the model "
        "(default %(default)s)",
    )
    parser.add_argument("--rate", type=float, default=20.0, help="frames per second (Hz)")
    parser.add_argument("--sessions", type=int, default=10)
    parser.add_argument(
        "--seconds", type=float, default=None, help="session length (default 20; 60 for myohand in a sweep)"
    )
    parser.add_argument("--clients", type=int, default=2, help="client processes generating the load")
    parser.add_argument("--server", help="ADDRESS of a running server (default: start `jitdyn serve`)")
    parser.add_argument("--serve-args", default="", help="extra `jitdyn serve` flags, e.g. '--processes 1'")
    parser.add_argument("--sweep", action="store_true", help="find the largest N of each target")
    parser.add_argument(
        "--targets", nargs="*", default=None, help="with --sweep: models to sweep (default all four)"
    )
    parser.add_argument(
        "--estimator",
        choices=("UKF", "STATIC", "CONSTANT_VELOCITY", "CONSTANT_ACCELERATION"),
        help="the sessions' estimator (default: the server's, chosen by the model's stored cost); STATIC measures what a tick "
        "costs around the filter, with no filter",
    )
    parser.add_argument("--json", type=Path, help="also write every report here")
    parser.add_argument(
        "--nice",
        type=int,
        default=Settings().nice,
        metavar="N",
        help="the load generator's CPU priority, as nice(1) counts it (default: the server's default, "
        "%(default)s): it stands for clients on other machines, not behind the server or batch work here",
    )
    parser.add_argument(
        "--floor",
        action="store_true",
        help="also measure bare grpc.aio's server CPU per tick at the same load",
    )
    args = parser.parse_args(argv)
    if not -20 <= args.nice <= 19:
        parser.error(f"--nice must be a nice value from -20 to 19, got {args.nice}")
    serve_args = args.serve_args.split()
    problem = set_priority(args.nice)
    print(
        f"# {os.cpu_count()} CPUs; server {'at ' + args.server if args.server else 'started per run'} "
        f"{' '.join(serve_args)}; {args.clients} client processes at nice {os.getpriority(os.PRIO_PROCESS, 0)}"
        + (f" ({problem})" if problem else ""),
        flush=True,
    )
    if args.sweep and args.estimator:
        parser.error("--estimator is for single runs: the targets are the default estimator's")
    if args.sweep:
        reports = []
        for target in TARGETS:
            if args.targets and target.model not in args.targets:
                continue
            found = sweep(
                target, clients=args.clients, server=args.server, serve_args=serve_args, seconds=args.seconds
            )
            reports.extend(found)
            best = max((r.sessions for r in found if r.meets()), default=0)
            verdict = "met" if best >= target.sessions else "MISSED"
            print(
                f"=> {target.model} {target.scenario} {target.rate:g} Hz: largest N on time {best} "
                f"(target >= {target.sessions}, aim {target.aim}): {verdict}\n",
                flush=True,
            )
    else:
        # A clear error for an unknown model before the trajectory's minutes; myo-sim's own spelling.
        args.model = model_source(args.model).name
        report = run(
            model=args.model,
            scenario=resolve_scenario(args.model, args.scenario),
            name_scenario=args.scenario != DEFAULT_SCENARIO,
            rate=args.rate,
            sessions=args.sessions,
            seconds=args.seconds or 20.0,
            clients=args.clients,
            server=args.server,
            serve_args=serve_args,
            estimator=args.estimator,
        )
        print(report.line())
        if args.floor:
            floor = transport_floor(min(args.sessions, 50), args.rate)
            least = args.sessions * args.rate * report.ukf_cycle_us / 1e6 + floor.cores(
                args.sessions, args.rate
            )
            print(
                f"  floor: bare grpc.aio, {min(args.sessions, 50)} streams: {floor.server_us:.0f} us server and "
                f"{floor.client_us:.0f} us client CPU per tick; with the UKF cycle, {args.sessions} sessions "
                f"need at least {least:.2f} of this machine's {os.cpu_count()} cores; a bare frame's transit "
                f"p50 / p99 {floor.transit_p50_ms:.2f} / {floor.transit_p99_ms:.2f} ms, "
                f"{100 * floor.over_grace:.1f} % of frames past the grace on transit alone"
            )
        for error in report.errors:
            print(f"  {error}")
        reports = [report]
    if args.json:
        args.json.write_text(json.dumps([asdict(r) for r in reports], indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
