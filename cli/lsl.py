"""`jitdyn lsl`: a Lab Streaming Layer stream of joint angles into a session, and the session's
answers out again as two LSL streams, which LabRecorder stores beside the lab's other streams:

- NAME (type `jitdyn.answers`): per answered tick, the estimated qpos and qvel, qfrc_inverse, the
  source (1 MEASURED, 2 PREDICTED, 3 CORRECTED, as `sessions export --format sto` codes it) and
  the tick's seq;
- NAME-lateness (type `jitdyn.lateness`): per answered tick, how late its frame reached the server
  (s after the tick's time; NaN for a tick without one) and the server's time to answer (s).

Both are stamped with the tick's time on this machine's LSL clock. A sample's time is mapped onto
that clock through the inlet's time_correction() (the offset of the sending machine's clock), then
onto the session's: the sample is the frame of the tick nearest to it, the first such sample when
the stream is faster than the ticks. The columns drive the joints as `jitdyn replay`'s do, and the
frames go through the same core (experiments/feed.py).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, TextIO

import numpy as np

from jitdyn.cli.extras import require_extra
from jitdyn.cli.joint_map import JointMap
from jitdyn.cli.replay import mapped_model, session_dt
from jitdyn.client import Client, FrameData, ModelRef, Rejection, SessionOptions, TickResult
from jitdyn.errors import FailedPrecondition, InvalidArgument
from jitdyn.experiments.feed import (
    Answers,
    Context,
    describe_session,
    feed_lockstep,
    feed_realtime,
    finish,
    open_session,
    report,
    stored_session,
)
from jitdyn.experiments.netem import PERFECT
from jitdyn.experiments.progress import progress_bar
from jitdyn.vocabulary import Channel, Clock, Output, Scenario, Source, to_proto

__all__ = ["LslSettings", "run_lsl"]

_DEGREES = ("deg", "degree", "degrees")


@dataclass(frozen=True)
class LslSettings:
    # The stream to take: its name, or its type (the first found of that type).
    stream: str
    model: str
    by: Literal["name", "type"] = "name"
    map_file: Path | None = None
    scenario: Scenario | None = None
    clock: Clock | None = None
    # None: as the channels' units say (degrees for deg, degree, degrees; else radians).
    angles: Literal["deg", "rad"] | None = None
    # The session's tick; None: the stream's nominal step, rounded up to a whole multiple of the
    # model's timestep.
    dt: float | None = None
    seconds: float | None = None  # None: until the stream stops
    wait: float = 10.0  # s to find the stream
    idle: float = 2.0  # s without a sample that end the session (before the first: `wait`)
    name: str = "jitdyn"  # of the published streams


def run_lsl(
    address: str,
    settings: LslSettings,
    *,
    out: TextIO,
    progress: bool = True,
    local_data: Path | None = None,
    stop: threading.Event | None = None,
) -> dict[str, object]:
    """Bridge the LSL stream of `settings` and a session at `address` until `settings.seconds`
    pass, the stream is silent for `settings.idle` or `stop` is set; print and return the summary."""
    require_extra("pylsl", what="pylsl (Lab Streaming Layer)", extra="lab")
    import pylsl

    inlet = _inlet(pylsl, settings)
    info = inlet.info(timeout=settings.wait)
    labels = tuple(info.get_channel_labels() or [f"channel_{i}" for i in range(info.channel_count())])
    answers = Answers()
    with Client(address) as client:
        client.wait_ready()
        ref, mapping = mapped_model(
            client, settings.model, columns=labels, find=_finder(labels), map_file=settings.map_file
        )
        degrees = _degrees(settings, info, mapping)
        rate = info.nominal_srate()
        if rate <= 0 and settings.dt is None:
            raise InvalidArgument(
                f"LSL stream {info.name()!r} has an irregular rate: give the session's --dt"
            )
        dt = settings.dt or session_dt(1.0 / rate, ref.timestep)
        print(
            f"LSL stream {info.name()!r} ({info.type()}, {info.channel_count()} channels at {rate:g} Hz from "
            f"{info.hostname()}), rotations in {'degrees' if degrees else 'radians'}",
            file=out,
        )
        print(mapping.line(), file=out)
        options = SessionOptions(
            model_id=ref.id,
            scenario=settings.scenario,
            dt=dt,
            clock=settings.clock or Clock.REALTIME,
            measured=(Channel.QPOS, Channel.QVEL),
            outputs=(Output.INVERSE_DYNAMICS,),
        )
        session, clock = open_session(client, options, asked=settings.clock, out=out)
        # The LSL time of the session clock's zero: a tick's time on the lab's clock.
        zero = pylsl.local_clock() - session.now()
        lockstep = clock is Clock.LOCKSTEP
        ticks = round(settings.seconds / dt) if settings.seconds else None
        model = f"{ref.name} v{ref.version} ({ref.nv} dof)"
        chosen = settings.scenario is None
        print(
            describe_session(session, model=model, dt=dt, ticks=ticks, lockstep=lockstep, chosen=chosen),
            file=out,
        )
        # LOCKSTEP has no clock of its own to keep: its tick 0 is the first sample's.
        start = None if lockstep else zero
        samples = _Samples(inlet, zero=start, dt=dt, settings=settings, stop=stop or threading.Event())
        samples.step = 1.0 / rate if rate > 0 else 0.0
        publish = _Publisher(pylsl, settings.name, ref, samples, session_id=session.opened.session_id)
        answers.listener = publish
        print(publish.line(), file=out)
        frames = samples.frames(mapping.framer(nq=ref.nq, nv=ref.nv, degrees=degrees))
        bar = progress_bar(total=ticks or 0, desc="ticks answered", unit="tick", enabled=progress)
        if lockstep:
            feed_lockstep(session, frames, answers, loss=0.0, seed=0, bar=bar)
        else:
            feed_realtime(session, frames, answers, dt=dt, network=PERFECT, seed=0, bar=bar)
        summary = finish(session, answers, bar)
        inlet.close_stream()
    print(f"the stream {samples.ended}", file=out)
    context = Context(
        dt=dt, lockstep=lockstep, address=address, local_data=local_data, reference="the stream"
    )
    numbers = report(answers, summary, context, out=out)
    print(stored_session(session.opened.session_id), file=out)
    return numbers


def _inlet(pylsl: Any, settings: LslSettings) -> Any:
    """The inlet of the first stream of the name or type asked for; FailedPrecondition when none
    answers within `settings.wait`."""
    found = pylsl.resolve_byprop(settings.by, settings.stream, minimum=1, timeout=settings.wait)
    if not found:
        raise FailedPrecondition(
            f"no LSL stream of {settings.by} {settings.stream!r} answered within {settings.wait:g} s (LSL looks "
            "as far as lsl_api.cfg's ResolveScope lets it: this machine, its link or its site)"
        )
    # liblsl smooths the stamps of a stream of nominal rate (dejitter): a sender's scheduling jitter is
    # not when the samples were taken. The clocks' offset is applied here, by time_correction().
    flags = pylsl.proc_dejitter | pylsl.proc_monotonize
    return pylsl.StreamInlet(found[0], max_buflen=60, recover=False, processing_flags=flags)


def _finder(labels: tuple[str, ...]) -> Callable[[str], int | None]:
    def find(name: str) -> int | None:
        return labels.index(name) if name in labels else None

    return find


def _degrees(settings: LslSettings, info: Any, mapping: JointMap) -> bool:
    """Whether the driving channels are in degrees: --angles, else their units, which must agree."""
    if settings.angles is not None:
        return settings.angles == "deg"
    units = list(info.get_channel_units() or [])
    used = {
        str(units[link.column]).strip().lower() if link.column < len(units) else "" for link in mapping.links
    }
    if len({unit in _DEGREES for unit in used}) > 1:
        raise InvalidArgument(
            f"the channels that drive joints are in {', '.join(sorted(u or 'no unit' for u in used))}: "
            "give --angles deg or rad"
        )
    return used.pop() in _DEGREES


class _Samples:
    """The inlet's samples as frames: each stamped on the sender's clock, corrected onto this
    machine's LSL clock (time_correction(), asked again every 5 s), then onto the session's, and
    put on the tick nearest it (docs/decisions/0171)."""

    def __init__(
        self, inlet: Any, *, zero: float | None, dt: float, settings: LslSettings, stop: threading.Event
    ) -> None:
        self.inlet, self.dt, self.settings, self.stop = inlet, dt, settings, stop
        # The LSL time of the session's zero; None: the first sample's.
        self.zero = zero
        self.ended = "was not read"
        self.step = 0.0  # the stream's nominal step (0: irregular, differenced at its stamps)
        from pylsl.util import LostError

        self.lost = LostError

    def frames(self, frame: Callable[[np.ndarray, np.ndarray, float, int], FrameData]) -> Iterator[FrameData]:
        last_seq, previous = -1, None
        correction, corrected_at = self.inlet.time_correction(timeout=self.settings.wait), time.monotonic()
        heard = time.monotonic()
        end = math.inf if self.settings.seconds is None else self.settings.seconds
        while True:
            if self.stop.is_set():
                self.ended = "was left (interrupted)"
                return
            # Before its first sample a stream gets as long as it took to find it.
            silence = self.settings.idle if last_seq >= 0 else self.settings.wait
            if time.monotonic() - heard > silence:
                self.ended = f"sent nothing for {silence:g} s: the session ends"
                return
            if time.monotonic() - corrected_at > 5.0:
                correction, corrected_at = self.inlet.time_correction(timeout=1.0), time.monotonic()
            try:
                chunk, stamps = self.inlet.pull_chunk(timeout=min(0.05, self.dt))
            except self.lost:
                self.ended = "was closed by its sender: the session ends"
                return
            if stamps:
                heard = time.monotonic()
            for values, stamp in zip(chunk, stamps, strict=True):
                if self.zero is None:
                    self.zero = stamp + correction
                t = stamp + correction - self.zero  # on the session's clock
                angles = np.asarray(values, dtype=np.float64)
                # A stream of a nominal rate is differenced at it: the stamps' jitter is not motion.
                step = self.step or (t - previous[1] if previous is not None else 0.0)
                velocities = (
                    (angles - previous[0]) / step
                    if previous is not None and step > 0
                    else np.zeros_like(angles)
                )
                previous = (angles, t)
                seq = round(t / self.dt)
                if t > end:
                    self.ended = f"was read for the {end:g} s asked"
                    return
                if seq > last_seq and seq >= 0:
                    last_seq = seq
                    yield frame(angles, velocities, seq * self.dt, seq)


class _Publisher:
    """The two outlets, and the sample each answer puts on them."""

    def __init__(self, pylsl: Any, name: str, ref: ModelRef, samples: _Samples, *, session_id: str) -> None:
        joints = list(ref.joint_names) if len(ref.joint_names) == ref.nq == ref.nv else None
        qpos = [f"qpos_{j}" for j in joints] if joints else [f"qpos_{i}" for i in range(ref.nq)]
        dofs = joints or [str(i) for i in range(ref.nv)]
        labels = [*qpos, *(f"qvel_{d}" for d in dofs), *(f"qfrc_inverse_{d}" for d in dofs), "source", "seq"]
        self.name, self.samples, self.channels = name, samples, len(labels)
        rate = 1.0 / samples.dt
        self.answers = _outlet(
            pylsl, name, "jitdyn.answers", labels, rate=rate, source=f"{session_id}-answers"
        )
        self.lateness = _outlet(
            pylsl,
            f"{name}-lateness",
            "jitdyn.lateness",
            ["frame_delay", "answer_time"],
            rate=rate,
            source=f"{session_id}-lateness",
        )

    def line(self) -> str:
        return (
            f"publishing LSL streams {self.name!r} (jitdyn.answers: qpos, qvel, qfrc_inverse, source and tick, "
            f"{self.channels} channels) and {self.name + '-lateness'!r} (jitdyn.lateness: frame_delay and "
            "answer_time, s), stamped with each tick's time"
        )

    def __call__(self, answer: TickResult | Rejection) -> None:
        if not isinstance(answer, TickResult):
            return
        stamp = (self.samples.zero or 0.0) + answer.seq * self.samples.dt
        source = float(to_proto(Source(answer.source)))
        self.answers.push_sample(
            [*answer.qpos, *answer.qvel, *answer.qfrc_inverse, source, answer.seq], stamp
        )
        delay = answer.frame_delay if answer.frame_received else math.nan
        self.lateness.push_sample([delay, answer.receive_to_send_us / 1e6], stamp)


def _outlet(pylsl: Any, name: str, kind: str, labels: list[str], *, rate: float, source: str) -> Any:
    info = pylsl.StreamInfo(name, kind, len(labels), rate, pylsl.cf_double64, source)
    info.set_channel_labels(labels)
    return pylsl.StreamOutlet(info)
