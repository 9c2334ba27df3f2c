"""`jitdyn demo`: one REALTIME session of a simulated research object over an emulated network.

A session the server refuses REALTIME (a big MyoSuite model's tick does not fit its dt, or the
machine has no core free) runs LOCKSTEP instead unless a clock was asked for: each frame is
answered as it is sent, and a frame the network loses is a skipped tick, answered PREDICTED
(docs/decisions/0166).

The truth is simulated by MuJoCo on the client side; frames reach the server through a seeded
delaying sender (latency, jitter, loss), so some arrive after their tick's deadline: the server
answers those ticks PREDICTED by its estimator and CORRECTED when the frame comes. The summary
gives the server's counts as `jitdyn sessions list` shows them (storage.summary.format_counts),
compares the predictions with the truth and says where the session is stored. The progress bar
goes to stderr, and only when it is a terminal.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import mujoco
import numpy as np

from jitdyn.client import (
    Client,
    FrameData,
    Rejection,
    Session,
    SessionOptions,
    Summary,
    SyncSample,
    TickResult,
)
from jitdyn.errors import ResourceExhausted
from jitdyn.experiments.netem import DelayedSender, NetworkProfile
from jitdyn.experiments.objects import qpos_limits
from jitdyn.experiments.progress import ProgressBar, progress_bar
from jitdyn.experiments.truth import TruthSources, truth_model
from jitdyn.registry.info import joint_types
from jitdyn.storage.records import FORCE_UNITS, dof_units
from jitdyn.storage.summary import format_counts
from jitdyn.vocabulary import Channel, Clock, EstimatorKind, Output, Scenario, Source

__all__ = ["DemoSettings", "run_demo"]


@dataclass(frozen=True)
class DemoSettings:
    # A registered model: NAME, NAME:VERSION or its id (sha256:...).
    model: str = "pendulum_3"
    # None: PASSIVE for a built-in model, else the server's choice for the model.
    scenario: Scenario | None = None
    seconds: float = 10.0
    dt: float | None = None  # None: 50 ms for pendulums, else 10 model timesteps
    latency: float = 0.035  # s, one way
    jitter: float = 0.010  # s
    loss: float = 0.05
    seed: int = 0
    estimator: EstimatorKind = EstimatorKind.UKF
    # None: REALTIME, or LOCKSTEP (said so) when the server refuses the REALTIME session for its
    # cost or its machine's load, as it does a big MyoSuite model's.
    clock: Clock | None = None


def _start_pose(model: mujoco.MjModel, rng: np.random.Generator) -> np.ndarray:
    """(nq,) a deterministic start away from rest, so that gravity moves the body: each dof moved
    0.3 to 0.8 (rad or m) from qpos0, on the manifold of ball and free joints, inside the ranges of
    limited joints."""
    qpos = model.qpos0.copy()
    delta = rng.uniform(0.3, 0.8, model.nv) * np.sign(rng.standard_normal(model.nv))
    mujoco.mj_integratePos(model, qpos, delta, 1.0)
    lo, hi = qpos_limits(model)
    bounded = np.isfinite(lo)
    margin = 0.1 * (hi[bounded] - lo[bounded])
    qpos[bounded] = np.clip(qpos[bounded], lo[bounded] + margin, hi[bounded] - margin)
    return np.asarray(qpos, dtype=np.float64)


def run_demo(
    address: str,
    settings: DemoSettings,
    *,
    out: TextIO,
    progress: bool = True,
    local_data: Path | None = None,
    sources: TruthSources | None = None,
) -> dict[str, object]:
    """Run the demo session against the server at `address`; print and return its summary.

    `local_data`: the data folder of a server this process runs, so that the stored file is named
    by its path here; None for a remote server, whose data folder is its own. `sources`: where
    the model's MJCF is looked for (default: `local_data`'s store)."""
    answers = _Answers()
    with Client(address) as client:
        client.wait_ready()
        ref, model = truth_model(
            client, settings.model, sources or TruthSources(data=local_data), address=address
        )
        data = mujoco.MjData(model)
        data.qpos[:] = _start_pose(model, np.random.default_rng(settings.seed))
        mujoco.mj_forward(model, data)
        pendulum = ref.builtin and ref.name.startswith("pendulum")
        dt = settings.dt or (0.05 if pendulum else 10 * model.opt.timestep)
        ticks = max(1, round(settings.seconds / dt))
        scenario = settings.scenario or (Scenario.PASSIVE if ref.builtin else None)
        options = SessionOptions(
            model_id=ref.id,
            scenario=scenario,
            dt=dt,
            clock=settings.clock or Clock.REALTIME,
            estimator={"estimator": settings.estimator},
            measured=(Channel.QPOS, Channel.QVEL, Channel.CTRL)
            if scenario is Scenario.CONTROLLED
            else (Channel.QPOS, Channel.QVEL),
            outputs=(Output.INVERSE_DYNAMICS,),
        )
        session, clock = _open(client, options, settings, out)
        chosen = "" if scenario else f" ({session.opened.scenario_reason})"
        lockstep = clock is Clock.LOCKSTEP
        print(
            f"session {session.opened.session_id}: {ref.name} v{ref.version} ({model.nv} dof), "
            f"{session.opened.scenario.lower()}{chosen}, dt {dt * 1e3:g} ms, {ticks} ticks"
            f"{', LOCKSTEP' if lockstep else ''}, estimator {settings.estimator}, grace "
            f"{session.opened.grace * 1e3:g} ms",
            file=out,
        )
        simulation = _Truth(model, data, dt=dt, controlled=scenario is Scenario.CONTROLLED)
        bar = progress_bar(total=ticks, desc="ticks answered", unit="tick", enabled=progress)
        if lockstep:
            print(
                f"network: loss {settings.loss:.0%} as skipped ticks (seeded {settings.seed}); LOCKSTEP "
                "answers each frame as it is sent, so latency and jitter are not emulated",
                file=out,
            )
            _run_lockstep(session, simulation, answers, ticks=ticks, settings=settings, bar=bar)
        else:
            expectation = _expectation(
                settings, grace=session.opened.grace, history=session.opened.history, dt=dt
            )
            if expectation:
                print(expectation, file=out)
            print(
                f"network: latency {settings.latency * 1e3:g} ms, jitter {settings.jitter * 1e3:g} ms, "
                f"loss {settings.loss:.0%} (seeded {settings.seed})",
                file=out,
            )
            _run_realtime(session, simulation, answers, ticks=ticks, settings=settings, bar=bar)
        summary = session.close()
        bar.update(min(len(answers.results), ticks) - bar.n)
        bar.close()
        # Ticks the server's clock answered between the last frame and `close`.
        for seq in [seq for seq in answers.results if seq >= ticks]:
            del answers.results[seq]
    return _report(
        settings=settings,
        model=model,
        dt=dt,
        ticks=ticks,
        lost=answers.lost,
        truth=simulation.truth,
        results=answers.results,
        corrected=answers.corrected,
        rejections=answers.rejections,
        syncs=answers.syncs,
        summary=summary,
        out=out,
        address=address,
        local_data=local_data,
        lockstep=lockstep,
    )


def _open(
    client: Client, options: SessionOptions, settings: DemoSettings, out: TextIO
) -> tuple[Session, Clock]:
    """Open the session, and say on which clock; with no --clock, a REALTIME session the server
    refuses (its tick does not fit dt, or the machine has no core free for it) is opened LOCKSTEP
    instead, saying why."""
    try:
        return client.open_session(options), Clock(options.clock)
    except ResourceExhausted as error:
        if settings.clock is not None:
            raise
        print(
            f"the server refused a REALTIME session ({error}); running it LOCKSTEP instead, every frame "
            "answered as it is sent (give --clock realtime to be refused instead)",
            file=out,
        )
    return client.open_session(dataclasses.replace(options, clock=Clock.LOCKSTEP)), Clock.LOCKSTEP


@dataclass
class _Answers:
    """What the server answered, sorted by kind; `lost`: frames the emulated network dropped."""

    results: dict[int, TickResult] = field(default_factory=dict)
    corrected: list[TickResult] = field(default_factory=list)
    rejections: list[Rejection] = field(default_factory=list)
    syncs: list[SyncSample] = field(default_factory=list)
    lost: int = 0

    def collect(self, answers: list[TickResult | Rejection | SyncSample]) -> None:
        for answer in answers:
            if isinstance(answer, TickResult):
                if answer.source == Source.CORRECTED:
                    self.corrected.append(answer)
                else:
                    self.results[answer.seq] = answer
            elif isinstance(answer, Rejection):
                self.rejections.append(answer)
            else:
                self.syncs.append(answer)


class _Truth:
    """The simulated body: frame k is its state at k * dt, then it steps on to tick k + 1."""

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, *, dt: float, controlled: bool) -> None:
        self.model, self.data, self.dt, self.controlled = model, data, dt, controlled
        self.steps = max(1, round(dt / model.opt.timestep))
        self.truth: list[np.ndarray] = []

    def frame(self, k: int) -> FrameData:
        """Frame k, the state now; records it as the truth of tick k."""
        ctrl = np.zeros(self.model.nu)
        self.truth.append(np.concatenate([self.data.qpos, self.data.qvel]).copy())
        return FrameData(
            seq=k,
            t=k * self.dt,
            qpos=self.data.qpos.copy(),
            qvel=self.data.qvel.copy(),
            ctrl=ctrl if self.controlled else None,
        )

    def step(self) -> None:
        """On to the next tick, with zero controls."""
        self.data.ctrl[:] = 0.0
        for _ in range(self.steps):
            mujoco.mj_step(self.model, self.data)


def _run_realtime(
    session: Session,
    simulation: _Truth,
    answers: _Answers,
    *,
    ticks: int,
    settings: DemoSettings,
    bar: ProgressBar,
) -> None:
    """Send frame k at k * dt through the emulated network; then wait for the last answers."""
    dt = simulation.dt
    profile = NetworkProfile(latency=settings.latency, jitter=settings.jitter, loss=settings.loss)
    with DelayedSender(session.send, profile, seed=settings.seed) as network:
        for k in range(ticks):
            if k % 20 == 0:
                session.sync()
            # Frame k is measured at k * dt on the session clock.
            wait = k * dt - session.now()
            if wait > 0:
                time.sleep(wait)
            if not math.isfinite(network.submit(simulation.frame(k))):
                answers.lost += 1
            simulation.step()
            answers.collect(session.poll())
            bar.update(min(len(answers.results), ticks) - bar.n)
    # Every tick is answered by its deadline, and every frame that arrived by a result or a
    # rejection; wait for the last ones, then close (answers that come during `close` are not read).
    deadline = time.monotonic() + 2.0 + 4 * dt

    def waiting() -> bool:
        from_frames = len(answers.corrected) + len(answers.rejections)
        from_frames += sum(1 for r in answers.results.values() if r.source == Source.MEASURED)
        return from_frames < ticks - answers.lost or any(k not in answers.results for k in range(ticks))

    while waiting() and time.monotonic() < deadline:
        answers.collect(session.poll())
        time.sleep(dt / 4)


def _run_lockstep(
    session: Session,
    simulation: _Truth,
    answers: _Answers,
    *,
    ticks: int,
    settings: DemoSettings,
    bar: ProgressBar,
) -> None:
    """Send each frame and wait for its answer; a frame the network loses (seeded) is a skipped
    tick, which the server answers PREDICTED."""
    rng = np.random.default_rng(settings.seed)
    for k in range(ticks):
        frame = simulation.frame(k)
        if rng.random() < settings.loss:
            answers.lost += 1
            answer = session.skip(k)
        else:
            answer = session.send_frame(frame)
        answers.collect([answer])
        simulation.step()
        bar.update(min(len(answers.results), ticks) - bar.n)


def _report(
    *,
    settings: DemoSettings,
    model: mujoco.MjModel,
    dt: float,
    ticks: int,
    lost: int,
    truth: list[np.ndarray],
    results: dict[int, TickResult],
    corrected: list[TickResult],
    rejections: list[Rejection],
    syncs: list[SyncSample],
    summary: Summary,
    out: TextIO,
    address: str,
    local_data: Path | None,
    lockstep: bool,
) -> dict[str, object]:
    nq = model.nq
    by_source: dict[str, int] = {}
    for r in results.values():
        by_source[r.source] = by_source.get(r.source, 0) + 1
    # Ticks due before any frame had arrived are answered from the model's rest pose: the
    # estimator has nothing to start from yet, so they say nothing about it.
    arrived = [r.seq for r in [*results.values(), *corrected] if r.source != Source.PREDICTED]
    first_frame = min(arrived) if arrived else ticks
    predicted_errors = [
        float(np.max(np.abs(r.qpos - truth[r.seq][:nq])))
        for r in results.values()
        if r.source == Source.PREDICTED and first_frame < r.seq < len(truth)
    ]
    delays = np.array([r.receive_to_send_us for r in results.values()]) / 1e3
    extra = summary.ticks - ticks
    lines = [
        "",
        (
            f"frames sent {ticks}, lost on the emulated network {lost}, rejected {len(rejections)}; "
            f"answers received for {len(results)} of the {ticks} ticks"
        ),
        *_rejection_reasons(rejections),
        f"server's summary, as `jitdyn sessions list` shows it: {format_counts(summary)}",
    ]
    if extra > 0:
        lines.append(
            f"  {summary.ticks} ticks: the {ticks} of the frames sent, and {extra} more that the server's clock "
            "answered (PREDICTED) between the last frame and `close`"
        )
    lines.append(
        "  a tick answered PREDICTED and then CORRECTED, when its late frame arrived, counts once in "
        "ticks and once in each of predicted and corrected"
    )
    if predicted_errors:
        unit = " or ".join(sorted(set(dof_units(joint_types(model))), reverse=True)) or "rad"
        lines.append(
            f"predicted ticks after the first frame: |q error| vs truth median {np.median(predicted_errors):.2e} "
            f"{unit}, max {np.max(predicted_errors):.2e} {unit}"
        )
    forces = _force_ranges(model, [*results.values(), *(c for c in corrected if c.seq < ticks)], ticks)
    if forces:
        lines.append(forces)
    if delays.size:
        # A LOCKSTEP tick has no deadline: it is answered once its frame is in.
        what = "frame-to-answer (LOCKSTEP)" if lockstep else "deadline-to-send"
        lines.append(f"server {what}: median {np.median(delays):.2f} ms, max {np.max(delays):.2f} ms")
    if syncs:
        best = min(syncs, key=lambda s: s.round_trip)
        lines.append(
            f"clock sync: round trip {best.round_trip * 1e3:.2f} ms, offset {best.offset * 1e3:+.2f} ms "
            "(the server's session clock minus this client's: each starts its clock at `opened`, the "
            "server as it sends it, the client as it arrives, so on one host the offset is that "
            "message's transit and handling, not a clock error; the server places frames by it)"
        )
    location = summary.location
    if "://" in location:  # on the server's data root
        lines.append(f"stored: {location}")
    elif local_data is not None and location:
        lines.append(f"stored: {local_data / location}")
    else:
        lines.append(f"stored: {location} (in the data folder of the server at {address})")
    print("\n".join(lines), file=out)
    return {
        "ticks": ticks,
        "stored_ticks": summary.ticks,
        "results": len(results),
        "by_source": by_source,
        "corrected": len(corrected),
        "lost": lost,
        "rejected": len(rejections),
        "location": location,
        "predicted_errors": predicted_errors,
    }


def _force_ranges(model: mujoco.MjModel, answers: list[TickResult], ticks: int) -> str:
    """The range of qfrc_inverse of each dof over every answer of the session's ticks: the first
    answer of each tick and its correction, as the stored frames hold both. A correction comes
    from the late frame itself, whose motion can ask far larger forces than the prediction did
    (docs/decisions/0182)."""
    torques = np.array([r.qfrc_inverse for r in answers if r.qfrc_inverse.size])
    if not torques.size:
        return ""
    units = [FORCE_UNITS[unit] for unit in dof_units(joint_types(model))]
    ranges = ", ".join(
        f"[{a:+.2f}, {b:+.2f}] {unit}"
        for a, b, unit in zip(torques.min(axis=0), torques.max(axis=0), units, strict=True)
    )
    corrections = sum(1 for r in answers if r.source == Source.CORRECTED)
    return (
        f"qfrc_inverse range per dof over the {len(torques)} answers of the {ticks} ticks "
        f"({corrections} of them corrections, as stored): {ranges}"
    )


def _expectation(settings: DemoSettings, *, grace: float, history: int, dt: float) -> str:
    """What the network's latency will make of the session, as the server's rules say."""
    if settings.latency <= grace:
        return ""
    late = f"frames take {settings.latency * 1e3:g} ms to arrive and the server answers each tick {grace * 1e3:g} ms after it is due"
    if settings.latency - settings.jitter > grace + history * dt:
        return (
            f"{late}, past the {history} ticks ({history * dt * 1e3:g} ms) the server keeps to correct: expect "
            "every tick PREDICTED by the estimator and the frames rejected TOO_OLD"
        )
    return (
        f"{late}: expect most ticks PREDICTED by the estimator, then CORRECTED when their frame arrives (a frame "
        "whose replay the server has no time for is rejected TOO_OLD instead)"
    )


def _rejection_reasons(rejections: list[Rejection]) -> list[str]:
    """'  rejected 3: 2 TOO_OLD, 1 DUPLICATE', then the server's words for the first of each reason."""
    by_reason: dict[str, list[Rejection]] = {}
    for rejection in rejections:
        by_reason.setdefault(rejection.reason, []).append(rejection)
    if not by_reason:
        return []
    ranked = sorted(by_reason.items(), key=lambda item: -len(item[1]))
    lines = [
        f"  rejected {len(rejections)}: {', '.join(f'{len(found)} {reason}' for reason, found in ranked)}"
    ]
    lines += [f"  {reason}, as the server said of the first: {found[0].message}" for reason, found in ranked]
    return lines


def default_data_root() -> Path:
    return Path("jitdyn-data")
