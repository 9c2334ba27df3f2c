"""`jitdyn replay FILE`: recorded joint angles (OpenSim .mot/.sto, C3D, CSV; cli/trials.py)
streamed into a session on a registered model. REALTIME sends each sample at its time on the
file's own clock over the demo's emulated network; LOCKSTEP sends each as soon as the last is
answered. The columns drive the model's joints by name or by a map file (cli/joint_map.py), and
the velocities are the angles' central differences. Progress, the summary and the stored session
are the demo's (experiments/feed.py), its predictions compared with the recording.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, TextIO

import numpy as np
from scipy.interpolate import CubicSpline

from jitdyn.cli.joint_map import JointMap, map_joints, model_joints, read_map_file
from jitdyn.cli.trials import Trial, rate_of, read_trial
from jitdyn.client import Client, FrameData, ModelRef, SessionOptions
from jitdyn.errors import InvalidArgument
from jitdyn.experiments.feed import (
    Answers,
    Context,
    describe_network,
    describe_session,
    expectation,
    feed_lockstep,
    feed_realtime,
    finish,
    open_session,
    report,
    stored_session,
)
from jitdyn.experiments.netem import PERFECT, NetworkProfile
from jitdyn.experiments.progress import progress_bar
from jitdyn.settings import parse_model_reference
from jitdyn.vocabulary import Channel, Clock, Output, Scenario

__all__ = ["ReplaySettings", "Samples", "load_trial", "mapped_model", "run_replay", "session_dt"]


@dataclass(frozen=True)
class ReplaySettings:
    file: Path
    # A registered model: NAME, NAME:VERSION or its id (sha256:...).
    model: str
    map_file: Path | None = None
    # None: the server's choice for the model (DRIVEN for one with actuators).
    scenario: Scenario | None = None
    # None: REALTIME, or LOCKSTEP (said so) when the server refuses the REALTIME session.
    clock: Clock | None = None
    network: NetworkProfile = PERFECT
    seed: int = 0
    # None: as the file says (a .mot's inDegrees; degrees in C3D; radians in CSV).
    angles: Literal["deg", "rad"] | None = None
    # The session's tick in seconds; None: the file's step, rounded up to a whole multiple of the
    # model's timestep (a session's dt is one).
    dt: float | None = None
    # The part of the file replayed, in seconds on its clock; None: from its first, to its last sample.
    start: float | None = None
    end: float | None = None


def mapped_model(
    client: Client,
    reference: str,
    *,
    columns: tuple[str, ...],
    find: Callable[[str], int | None],
    map_file: Path | None,
) -> tuple[ModelRef, JointMap]:
    """The registered model `reference` names, and the links of `columns` to its joints (`find`:
    the index of the column known by a name)."""
    model_id, name, version = parse_model_reference(reference)
    message = client.get_model_message(model_id=model_id, name=name, version=version)
    ref = ModelRef.from_message(message)
    entries = read_map_file(map_file) if map_file is not None else []
    mapping = map_joints(
        model_joints(message),
        columns,
        find=find,
        model=f"{ref.name} v{ref.version}",
        entries=entries,
        where=f"--map {map_file}",
    )
    return ref, mapping


def session_dt(step: float, timestep: float) -> float:
    """A sampling `step` rounded up to a whole multiple of the model's `timestep`, which a
    session's dt must be (docs/decisions/0170)."""
    return timestep * max(1, math.ceil(step / timestep - 1e-6))


def load_trial(settings: ReplaySettings) -> Trial:
    """The part of the file `settings` replay, read before a server is asked anything."""
    return read_trial(settings.file).between(settings.start, settings.end)


def run_replay(
    address: str,
    settings: ReplaySettings,
    trial: Trial,
    *,
    out: TextIO,
    progress: bool = True,
    local_data: Path | None = None,
) -> dict[str, object]:
    """Replay `trial` (load_trial) into a session at `address` as `settings` say; print and return
    its summary. The map is read before a session is opened."""
    degrees = trial.degrees if settings.angles is None else settings.angles == "deg"
    answers = Answers()
    with Client(address) as client:
        client.wait_ready()
        ref, mapping = mapped_model(
            client, settings.model, columns=trial.columns, find=trial.find, map_file=settings.map_file
        )
        samples = Samples.of(trial, mapping, timestep=ref.timestep, dt=settings.dt)
        told = trial.units if settings.angles is None else f"--angles {settings.angles}"
        ignored = f"; left out: {trial.ignored}" if trial.ignored else ""
        print(
            f"replaying {trial.path}: {trial.values.shape[0]} samples at {samples.rate:g} Hz, rotations in "
            f"{'degrees' if degrees else 'radians'} ({told}){ignored}",
            file=out,
        )
        print(mapping.line(), file=out)
        if samples.note:
            print(samples.note, file=out)
        options = SessionOptions(
            model_id=ref.id,
            scenario=settings.scenario,
            dt=samples.dt,
            clock=settings.clock or Clock.REALTIME,
            measured=(Channel.QPOS, Channel.QVEL),
            outputs=(Output.INVERSE_DYNAMICS,),
        )
        session, clock = open_session(client, options, asked=settings.clock, out=out)
        lockstep = clock is Clock.LOCKSTEP
        model = f"{ref.name} v{ref.version} ({ref.nv} dof)"
        ticks, chosen = len(samples.times), settings.scenario is None
        print(
            describe_session(
                session, model=model, dt=samples.dt, ticks=ticks, lockstep=lockstep, chosen=chosen
            ),
            file=out,
        )
        frames = samples.frames(mapping, nq=ref.nq, nv=ref.nv, degrees=degrees)
        bar = progress_bar(total=ticks, desc="samples answered", unit="sample", enabled=progress)
        network, seed = settings.network, settings.seed
        if lockstep:
            print(describe_network(network, seed=seed, lockstep=True), file=out)
            feed_lockstep(session, frames, answers, loss=network.loss, seed=seed, bar=bar)
        else:
            opened = session.opened
            late = expectation(network, grace=opened.grace, history=opened.history, dt=samples.dt)
            print(
                "\n".join(filter(None, (late, describe_network(network, seed=seed, lockstep=False)))),
                file=out,
            )
            feed_realtime(session, frames, answers, dt=samples.dt, network=network, seed=seed, bar=bar)
        summary = finish(session, answers, bar)
    context = Context(
        dt=samples.dt, lockstep=lockstep, address=address, local_data=local_data, reference="the recording"
    )
    numbers = report(answers, summary, context, out=out)
    print(stored_session(session.opened.session_id), file=out)
    return numbers


@dataclass(frozen=True)
class Samples:
    """The recording at the session's ticks: `times` (ticks,) from its first sample, k * dt;
    `angles` and `velocities` (ticks, columns) there. `note` says when they were resampled."""

    rate: float
    dt: float
    times: np.ndarray
    angles: np.ndarray
    velocities: np.ndarray
    note: str

    @classmethod
    def of(cls, trial: Trial, mapping: JointMap, *, timestep: float, dt: float | None) -> Samples:
        """The samples at `dt`, default the file's step rounded up to a whole multiple of the
        model's `timestep` (a session's dt is one). A cubic spline through the file's samples
        gives the angles and their velocities between them; at the file's own samples it is the
        file's values (docs/decisions/0170). InvalidArgument for a driving column with gaps
        (values not numbers)."""
        step = 1.0 / rate_of(trial)
        used = sorted({link.column for link in mapping.links})
        for column in used:
            gaps = np.flatnonzero(~np.isfinite(trial.values[:, column]))
            if gaps.size:
                raise InvalidArgument(
                    f"{trial.path}: column {trial.columns[column]} has {gaps.size} samples that are not numbers "
                    f"(gaps), the first at t = {trial.times[gaps[0]]:g} s; fill them before replaying"
                )
        tick = dt or session_dt(step, timestep)
        start, span = trial.times[0], trial.times[-1] - trial.times[0]
        times = start + np.arange(math.floor(span / tick + 1e-6) + 1) * tick
        spline = CubicSpline(trial.times, np.nan_to_num(trial.values), axis=0)
        note = ""
        if abs(tick - step) > 1e-6 * step:
            note = (
                f"resampled to {1 / tick:g} Hz (dt {tick * 1e3:g} ms, {len(times)} ticks): a session's dt is a "
                f"whole multiple of the model's timestep, {timestep * 1e3:g} ms"
                + (" (--dt)" if dt else "; --dt sets another")
            )
        return cls(
            rate=1.0 / step,
            dt=tick,
            times=times - start,
            angles=spline(times),
            velocities=spline(times, 1),
            note=note,
        )

    def frames(self, mapping: JointMap, *, nq: int, nv: int, degrees: bool) -> Iterator[FrameData]:
        """The frame of every tick: seq k at k * dt."""
        frame = mapping.framer(nq=nq, nv=nv, degrees=degrees)
        for k, t in enumerate(self.times):
            yield frame(self.angles[k], self.velocities[k], float(t), k)
