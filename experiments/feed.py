"""Frames of joint angles into an open session, its answers out, and the summary: the core that
`jitdyn demo` (simulated frames), `jitdyn replay` (a recorded file) and `jitdyn lsl` (a live
stream) share::

    session, clock = open_session(client, options, asked=None, out=sys.stdout)
    answers = Answers()
    feed_realtime(session, frames, answers, dt=0.05, network=NetworkProfile(latency=0.035), seed=0, bar=bar)
    summary = finish(session, answers, bar)
    report(answers, summary, Context(dt=0.05, lockstep=False, address=address), out=sys.stdout)

REALTIME sends each frame at its time `t` on the session clock (at once when that time has passed,
as for a live stream), through a seeded emulated network when one is given; LOCKSTEP sends each
and waits for its answer, a frame the network loses being a skipped tick. The frames fed are kept
by seq: the summary compares the predictions with them (the truth of a simulation, the recording
of a replay).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

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
from jitdyn.experiments.progress import ProgressBar
from jitdyn.storage.records import FORCE_UNITS
from jitdyn.storage.summary import format_counts
from jitdyn.vocabulary import Clock, Source

__all__ = [
    "Answers",
    "Context",
    "describe_network",
    "describe_session",
    "expectation",
    "feed_lockstep",
    "feed_realtime",
    "finish",
    "open_session",
    "report",
    "stored_session",
]

Answer = TickResult | Rejection | SyncSample


def open_session(
    client: Client, options: SessionOptions, *, asked: Clock | None, out: TextIO
) -> tuple[Session, Clock]:
    """Open the session, and say on which clock. With no clock `asked`, a REALTIME session the
    server refuses (its tick does not fit dt, or the machine has no core free for it) is opened
    LOCKSTEP instead, saying why (docs/decisions/0166)."""
    try:
        return client.open_session(options), Clock(options.clock)
    except ResourceExhausted as error:
        if asked is not None:
            raise
        print(
            f"the server refused a REALTIME session ({error}); running it LOCKSTEP instead, every frame "
            "answered as it is sent (give --clock realtime to be refused instead)",
            file=out,
        )
    return client.open_session(dataclasses.replace(options, clock=Clock.LOCKSTEP)), Clock.LOCKSTEP


@dataclass
class Answers:
    """What the server answered, sorted by kind; `frames`: every frame fed, by seq (those the
    emulated network lost too, counted in `lost`). `listener` sees each result and rejection as
    it is collected (`jitdyn lsl` publishes them)."""

    results: dict[int, TickResult] = field(default_factory=dict)
    corrected: list[TickResult] = field(default_factory=list)
    rejections: list[Rejection] = field(default_factory=list)
    syncs: list[SyncSample] = field(default_factory=list)
    frames: dict[int, FrameData] = field(default_factory=dict)
    lost: int = 0
    gaps: int = 0  # LOCKSTEP ticks skipped because no frame came for them (a live stream's)
    listener: Callable[[TickResult | Rejection], None] | None = None

    def collect(self, answers: Iterable[Answer]) -> None:
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
                continue
            if self.listener is not None:
                self.listener(answer)

    def answered(self) -> int:
        """Ticks answered, at most one a frame fed (a progress bar's count)."""
        return min(len(self.results), len(self.frames))

    def outstanding(self) -> bool:
        """Whether a frame that arrived has no answer yet (a result or a rejection), or a tick fed
        has no result."""
        from_frames = len(self.corrected) + len(self.rejections)
        from_frames += sum(1 for r in self.results.values() if r.source == Source.MEASURED)
        return from_frames < len(self.frames) - self.lost or any(k not in self.results for k in self.frames)


def feed_realtime(
    session: Session,
    frames: Iterable[FrameData],
    answers: Answers,
    *,
    dt: float,
    network: NetworkProfile,
    seed: int,
    bar: ProgressBar,
) -> None:
    """Send each frame at its time `t` on the session clock through the emulated `network`; then
    wait for the last answers (up to 2 s and 4 ticks of `dt`)."""
    with DelayedSender(session.send, network, seed=seed) as sender:
        for i, frame in enumerate(frames):
            if i % 20 == 0:
                session.sync()
            wait = frame.t - session.now()
            if wait > 0:
                time.sleep(wait)
            answers.frames[frame.seq] = frame
            if not math.isfinite(sender.submit(frame)):
                answers.lost += 1
            answers.collect(session.poll())
            bar.update(answers.answered() - bar.n)
    # Every tick is answered by its deadline, and every frame that arrived by a result or a
    # rejection; wait for the last ones, then close (answers that come during `close` are not read).
    deadline = time.monotonic() + 2.0 + 4 * dt
    while answers.outstanding() and time.monotonic() < deadline:
        answers.collect(session.poll())
        time.sleep(dt / 4)


def feed_lockstep(
    session: Session,
    frames: Iterable[FrameData],
    answers: Answers,
    *,
    loss: float,
    seed: int,
    bar: ProgressBar,
) -> None:
    """Send each frame and wait for its answer; a frame the network loses (seeded), or a tick no
    frame comes for (a live stream's gap), is a skipped tick, which the server answers PREDICTED."""
    rng = np.random.default_rng(seed)
    following = 0
    for frame in frames:
        for seq in range(following, frame.seq):
            answers.gaps += 1
            answers.collect([session.skip(seq)])
        following = frame.seq + 1
        answers.frames[frame.seq] = frame
        if rng.random() < loss:
            answers.lost += 1
            answer = session.skip(frame.seq)
        else:
            answer = session.send_frame(frame)
        answers.collect([answer])
        bar.update(answers.answered() - bar.n)


def finish(session: Session, answers: Answers, bar: ProgressBar) -> Summary:
    """Close the session; drop the ticks its clock answered after the last frame fed."""
    summary = session.close()
    bar.update(answers.answered() - bar.n)
    bar.close()
    last = max(answers.frames, default=-1)
    for seq in [seq for seq in answers.results if seq > last]:
        del answers.results[seq]
    return summary


def describe_session(
    session: Session,
    *,
    model: str,
    dt: float,
    ticks: int | None,
    lockstep: bool,
    chosen: bool,
    extra: str = "",
) -> str:
    """'session ID: MODEL, SCENARIO, dt, ticks, clock...': `chosen`, the scenario was the server's
    choice (its reason is said); `ticks` None: as many as a live stream sends; `extra` goes before
    the grace."""
    opened = session.opened
    reason = f" ({opened.scenario_reason})" if chosen else ""
    count = "ticks while the stream sends" if ticks is None else f"{ticks} ticks"
    return (
        f"session {opened.session_id}: {model}, {opened.scenario.lower()}{reason}, dt {dt * 1e3:g} ms, "
        f"{count}{', LOCKSTEP' if lockstep else ''}{extra}, grace {opened.grace * 1e3:g} ms"
    )


def describe_network(network: NetworkProfile, *, seed: int, lockstep: bool) -> str:
    """The one line that says what the emulated network does to the frames."""
    if lockstep:
        return (
            f"network: loss {network.loss:.0%} as skipped ticks (seeded {seed}); LOCKSTEP "
            "answers each frame as it is sent, so latency and jitter are not emulated"
        )
    return (
        f"network: latency {network.latency * 1e3:g} ms, jitter {network.jitter * 1e3:g} ms, "
        f"loss {network.loss:.0%} (seeded {seed})"
    )


def expectation(network: NetworkProfile, *, grace: float, history: int, dt: float) -> str:
    """What the network's latency will make of the session, as the server's rules say."""
    if network.latency <= grace:
        return ""
    late = f"frames take {network.latency * 1e3:g} ms to arrive and the server answers each tick {grace * 1e3:g} ms after it is due"
    if network.latency - network.jitter > grace + history * dt:
        return (
            f"{late}, past the {history} ticks ({history * dt * 1e3:g} ms) the server keeps to correct: expect "
            "every tick PREDICTED by the estimator and the frames rejected TOO_OLD"
        )
    return (
        f"{late}: expect most ticks PREDICTED by the estimator, then CORRECTED when their frame arrives (a frame "
        "whose replay the server has no time for is rejected TOO_OLD instead)"
    )


@dataclass(frozen=True)
class Context:
    """What the summary needs beside the answers: the session's dt and clock, the server's
    address and, for a server this process runs, its data folder (so that the stored file is
    named by its path here); `reference` names what the frames are."""

    dt: float
    lockstep: bool
    address: str
    local_data: Path | None = None
    reference: str = "truth"
    # Each dof's unit, "rad" or "m" (storage.records.dof_units); empty: every dof in rad.
    dof_units: tuple[str, ...] = ()


def report(answers: Answers, summary: Summary, context: Context, *, out: TextIO) -> dict[str, object]:
    """Print the summary of a fed session; return its numbers."""
    results, ticks = answers.results, len(answers.frames) + answers.gaps
    by_source: dict[str, int] = {}
    for r in results.values():
        by_source[r.source] = by_source.get(r.source, 0) + 1
    predicted_errors = _predicted_errors(answers)
    lines = [
        "",
        (
            f"frames sent {len(answers.frames)}, lost on the emulated network {answers.lost}, "
            f"{f'ticks with no frame {answers.gaps}, ' if answers.gaps else ''}rejected "
            f"{len(answers.rejections)}; answers received for {len(results)} of the {ticks} ticks"
        ),
        *_rejection_reasons(answers.rejections),
        f"server's summary, as `jitdyn sessions list` shows it: {format_counts(summary)}",
    ]
    extra = summary.ticks - ticks
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
        unit = " or ".join(sorted(set(context.dof_units), reverse=True)) or "rad"
        lines.append(
            f"predicted ticks after the first frame: |q error| vs {context.reference} median "
            f"{np.median(predicted_errors):.2e} {unit}, max {np.max(predicted_errors):.2e} {unit}"
        )
    lines += _answer_lines(answers, context)
    lines.append(_stored(summary.location, context))
    print("\n".join(lines), file=out)
    return {
        "ticks": ticks,
        "stored_ticks": summary.ticks,
        "results": len(results),
        "by_source": by_source,
        "corrected": len(answers.corrected),
        "lost": answers.lost,
        "rejected": len(answers.rejections),
        "location": summary.location,
        "predicted_errors": predicted_errors,
    }


def stored_session(session_id: str) -> str:
    """The line that names the stored session and the commands that read it."""
    return f"stored session: {session_id} (jitdyn sessions show|plot|export {session_id[:8]})"


def _predicted_errors(answers: Answers) -> list[float]:
    """|q error| of each PREDICTED tick against its frame, after the first frame arrived: ticks
    due before that are answered from the model's rest pose, and say nothing of the estimator."""
    results = answers.results.values()
    arrived = [r.seq for r in [*results, *answers.corrected] if r.source != Source.PREDICTED]
    first_frame = min(arrived, default=math.inf)
    errors = []
    for r in results:
        frame = answers.frames.get(r.seq)
        if r.source == Source.PREDICTED and first_frame < r.seq and frame is not None:
            errors.append(float(np.max(np.abs(r.qpos - np.asarray(frame.qpos)))))
    return errors


def _force_ranges(answers: list[TickResult], ticks: int, context: Context) -> str:
    """The range of qfrc_inverse of each dof over every answer of the session's ticks: the first
    answer of each tick and its correction, as the stored frames hold both. A correction comes
    from the late frame itself, whose motion can ask far larger forces than the prediction did
    (docs/decisions/0182)."""
    torques = np.array([r.qfrc_inverse for r in answers if r.qfrc_inverse.size])
    if not torques.size:
        return ""
    units = [FORCE_UNITS[unit] for unit in context.dof_units] or ["N m"] * torques.shape[1]
    ranges = ", ".join(
        f"[{a:+.2f}, {b:+.2f}] {unit}"
        for a, b, unit in zip(torques.min(axis=0), torques.max(axis=0), units, strict=True)
    )
    corrections = sum(1 for r in answers if r.source == Source.CORRECTED)
    return (
        f"qfrc_inverse range per dof over the {len(torques)} answers of the {ticks} ticks "
        f"({corrections} of them corrections, as stored): {ranges}"
    )


def _answer_lines(answers: Answers, context: Context) -> list[str]:
    """The forces' ranges, the server's time to answer and the clock's sync."""
    results = answers.results.values()
    ticks = len(answers.frames) + answers.gaps
    lines = []
    forces = _force_ranges([*results, *(c for c in answers.corrected if c.seq < ticks)], ticks, context)
    if forces:
        lines.append(forces)
    delays = np.array([r.receive_to_send_us for r in results]) / 1e3
    if delays.size:
        # A LOCKSTEP tick has no deadline: it is answered once its frame is in.
        what = "frame-to-answer (LOCKSTEP)" if context.lockstep else "deadline-to-send"
        lines.append(f"server {what}: median {np.median(delays):.2f} ms, max {np.max(delays):.2f} ms")
    if answers.syncs:
        best = min(answers.syncs, key=lambda s: s.round_trip)
        lines.append(
            f"clock sync: round trip {best.round_trip * 1e3:.2f} ms, offset {best.offset * 1e3:+.2f} ms "
            "(the server's session clock minus this client's: each starts its clock at `opened`, the "
            "server as it sends it, the client as it arrives, so on one host the offset is that "
            "message's transit and handling, not a clock error; the server places frames by it)"
        )
    return lines


def _stored(location: str, context: Context) -> str:
    if "://" in location:  # on the server's data root
        return f"stored: {location}"
    if context.local_data is not None and location:
        return f"stored: {context.local_data / location}"
    return f"stored: {location} (in the data folder of the server at {context.address})"


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
