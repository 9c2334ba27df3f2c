"""The cases of a session's stream: Frame's shape, finiteness and checksum, the sequence rules of
LOCKSTEP and REALTIME, late and lost frames (Source, RejectReason) and the clock exchange
(SyncPing, SyncPong), rules of dynamics.proto checked over the wire.
"""

from __future__ import annotations

import math
import time
from typing import Final

import grpc

from jitdyn.compliance.models import PENDULUM
from jitdyn.compliance.suite import (
    DT,
    Context,
    Skipped,
    case,
    check,
    finite,
    frame,
    measured,
    reason_name,
    rejected_as,
    result_of,
    source_name,
)
from jitdyn.compliance.wire import CaseFailed, Ended, Stream, frame_checksum
from jitdyn.v1 import common_pb2, dynamics_pb2

__all__: list[str] = []

Code = grpc.StatusCode

# Frame.checksum's test vector: seq 1, t 0.05, qpos [0.1], qvel [-0.2].
_VECTOR: Final = 0x698C163E
# The REALTIME sessions' frame period and grace (s): long enough for a loaded machine's scheduling.
_RT_DT: Final = 0.05
_RT_GRACE: Final = 0.025


def _lockstep(ctx: Context, stream: Stream, **fields: object) -> dynamics_pb2.SessionOpened:
    return ctx.open(stream, model_id=ctx.model(PENDULUM).id, dt=DT, **fields)


@case("frame.measured", "a frame on time is answered MEASURED: its own q, finite dynamics of every dof")
def _(ctx: Context) -> str:
    with ctx.wire.stream() as stream:
        _lockstep(ctx, stream)
        for seq in range(3):
            result = measured(stream, seq, q=0.1 * seq)
            check(
                list(result.qpos) == [0.1 * seq],
                f"tick {seq}: qpos {list(result.qpos)}, the frame's {[0.1 * seq]}",
            )
            check(abs(result.t - seq * DT) < 1e-9, f"tick {seq}: t {result.t}, expected {seq * DT}")
            check(result.frame_received, f"tick {seq}: frame_received is false")
            check(
                len(result.qfrc_inverse) == 1 and finite(result.qfrc_inverse),
                f"qfrc_inverse {list(result.qfrc_inverse)}",
            )
            check(finite([*result.qvel, *result.qacc]), f"tick {seq}: qvel or qacc not finite")
        summary = ctx.close(stream)
    check(
        (summary.ticks, summary.measured) == (3, 3),
        f"summary: {summary.ticks} ticks, {summary.measured} measured",
    )
    return "3 ticks MEASURED"


@case(
    "frame.shape", "a channel of the wrong length, or one the session measures missing, is rejected BAD_SHAPE"
)
def _(ctx: Context) -> str:
    with ctx.wire.stream() as stream:
        _lockstep(ctx, stream)
        stream.send(frame=frame(0, qpos=[0.1, 0.2]))
        rejected_as(stream, 0, "BAD_SHAPE")
        stream.send(frame=dynamics_pb2.Frame(seq=0, t=0.0, qpos=[0.1]))
        rejected_as(stream, 0, "BAD_SHAPE")
        measured(stream, 0)  # the session goes on
        ctx.close(stream)
    return "qpos of 2 on nq 1; qvel missing"


@case("frame.not_finite", "a NaN or an infinity in a frame is rejected NOT_FINITE")
def _(ctx: Context) -> str:
    with ctx.wire.stream() as stream:
        _lockstep(ctx, stream)
        stream.send(frame=frame(0, qpos=[math.nan]))
        rejected_as(stream, 0, "NOT_FINITE")
        stream.send(frame=frame(0, qvel=[math.inf]))
        rejected_as(stream, 0, "NOT_FINITE")
        measured(stream, 0)
        ctx.close(stream)
    return "NaN in qpos, inf in qvel"


@case("frame.checksum", "a frame with the contract's CRC32C is used; a wrong one is rejected BAD_CHECKSUM")
def _(ctx: Context) -> str:
    vector = frame_checksum(1, 0.05, {"qpos": [0.1], "qvel": [-0.2]})
    check(vector == _VECTOR, f"the suite's own checksum of the test vector is {vector:#x}, not {_VECTOR:#x}")
    with ctx.wire.stream() as stream:
        _lockstep(ctx, stream)
        good = frame(0, qpos=[0.3], qvel=[-0.1])
        good.checksum = frame_checksum(0, 0.0, {"qpos": [0.3], "qvel": [-0.1]})
        stream.send(frame=good)
        check(
            source_name(result_of(stream, 0).source) == "MEASURED",
            "a frame with a good checksum was not MEASURED",
        )
        bad = frame(1)
        bad.checksum = frame_checksum(1, DT, {"qpos": [0.1], "qvel": [0.0]}) ^ 1
        stream.send(frame=bad)
        rejected_as(stream, 1, "BAD_CHECKSUM")
        ctx.close(stream)
    return f"test vector {vector:#010x}"


# -- sequence rules --------------------------------------------------------------------------------


@case(
    "sequence.lockstep",
    "LOCKSTEP: a frame ahead is OUT_OF_ORDER, a tick's second frame DUPLICATE, skip predicts",
)
def _(ctx: Context) -> str:
    with ctx.wire.stream() as stream:
        _lockstep(ctx, stream)
        measured(stream, 0)
        stream.send(frame=frame(2))
        rejected_as(stream, 2, "OUT_OF_ORDER")
        stream.send(frame=frame(0))
        rejected_as(stream, 0, "DUPLICATE")
        stream.send(skip=dynamics_pb2.Skip(seq=1))
        predicted = result_of(stream, 1)
        check(
            source_name(predicted.source) == "PREDICTED",
            f"a skipped tick answered {source_name(predicted.source)}",
        )
        check(not predicted.frame_received, "a skipped tick says its frame was received")
        check(
            len(predicted.qpos) == 1 and finite(predicted.qpos),
            f"a prediction's qpos is {list(predicted.qpos)}",
        )
        stream.send(skip=dynamics_pb2.Skip(seq=5))
        rejected_as(stream, 5, "OUT_OF_ORDER")
        measured(stream, 2)
        summary = ctx.close(stream)
    check(summary.rejected == 3, f"summary.rejected is {summary.rejected}, 3 were rejected")
    return "ahead, duplicate, skip, skip ahead"


@case("late.lockstep", "LOCKSTEP: the frame of a skipped tick is answered CORRECTED (or rejected TOO_OLD)")
def _(ctx: Context) -> str:
    with ctx.wire.stream() as stream:
        _lockstep(ctx, stream)
        measured(stream, 0)
        stream.send(skip=dynamics_pb2.Skip(seq=1))
        check(source_name(result_of(stream, 1).source) == "PREDICTED", "a skipped tick was not PREDICTED")
        stream.send(frame=frame(1))
        answer = stream.receive()
        check(not isinstance(answer, Ended), f"the late frame of tick 1 ended the stream: {answer}")
        assert isinstance(answer, dynamics_pb2.StreamSessionResponse)  # for mypy: checked above
        kind = answer.WhichOneof("payload")
        if kind == "result":
            late = answer.result
            check(
                late.seq == 1 and source_name(late.source) == "CORRECTED",
                f"late frame of tick 1: {late.seq} {source_name(late.source)}",
            )
            check(late.late_ticks >= 1, f"a CORRECTED result has late_ticks {late.late_ticks}")
            got = "CORRECTED"
        else:
            check(kind == "rejected", f"the late frame of tick 1 was answered {kind}")
            check(
                reason_name(answer.rejected.reason) == "TOO_OLD",
                f"the late frame of tick 1 was rejected {reason_name(answer.rejected.reason)}",
            )
            got = "TOO_OLD"
        measured(stream, 2)
        ctx.close(stream)
    return got


@case("late.too_old", "a frame older than the session's history is rejected TOO_OLD")
def _(ctx: Context) -> str:
    with ctx.wire.stream() as stream:
        opened = _lockstep(ctx, stream, history=3)
        check(opened.history == 3, f"history 3 asked, {opened.history} in force")
        measured(stream, 0)
        for seq in range(1, 7):
            stream.send(skip=dynamics_pb2.Skip(seq=seq))
            result_of(stream, seq)
        stream.send(frame=frame(1))
        rejected_as(stream, 1, "TOO_OLD")
        ctx.close(stream)
    return "history 3, frame 6 ticks late"


# -- REALTIME ------------------------------------------------------------------------------------------


def _realtime(ctx: Context) -> tuple[Stream, float]:
    """A REALTIME session's stream, and the client clock's zero (time.monotonic() as `opened`
    arrived). A server may refuse a REALTIME session for its load (RESOURCE_EXHAUSTED): the open is
    tried again every second for ctx.admission_wait, then the case is skipped, saying so."""
    request = dynamics_pb2.OpenSession(
        model_id=ctx.model(PENDULUM).id, dt=_RT_DT, clock=common_pb2.CLOCK_REALTIME, grace=_RT_GRACE
    )
    until = time.monotonic() + ctx.admission_wait
    while True:
        stream = ctx.wire.stream()
        stream.send(open=request)
        answer = stream.receive(timeout=60.0)
        if isinstance(answer, dynamics_pb2.StreamSessionResponse) and answer.HasField("opened"):
            start = time.monotonic()
            grace = answer.opened.grace
            check(abs(grace - _RT_GRACE) < 1e-9, f"grace {_RT_GRACE} asked, {grace} in force")
            return stream, start
        stream.close()
        if not isinstance(answer, Ended) or answer.code != Code.RESOURCE_EXHAUSTED:
            raise CaseFailed(f"a REALTIME open was answered {answer}")
        ctx.provoked.add(answer.code.name)
        if time.monotonic() > until:
            raise Skipped(
                f"not admitted: the server refused a {1 / _RT_DT:g} Hz REALTIME session for "
                f"{ctx.admission_wait:g} s (RESOURCE_EXHAUSTED: {answer.details})"
            )
        time.sleep(1.0)


def _at(start: float, t: float) -> None:
    time.sleep(max(0.0, start + t - time.monotonic()))


def _answers(stream: Stream, until: float) -> dict[tuple[int, str], dynamics_pb2.Result]:
    """Results by (seq, source), read until the monotonic time `until`."""
    found: dict[tuple[int, str], dynamics_pb2.Result] = {}
    while (answer := stream.poll(max(0.0, until - time.monotonic()))) is not None:
        if isinstance(answer, Ended):
            break
        if answer.WhichOneof("payload") == "result":
            found[answer.result.seq, source_name(answer.result.source)] = answer.result
    return found


@case(
    "late.realtime",
    "REALTIME: a late frame's tick is PREDICTED then CORRECTED (or TOO_OLD); a lost one stays PREDICTED",
)
def _(ctx: Context) -> str:
    late, lost, ticks = 3, 5, 8
    stream, start = _realtime(ctx)
    with stream:
        for seq in range(ticks):
            if seq in (late, lost):
                continue
            _at(start, seq * _RT_DT)
            stream.send(frame=frame(seq, dt=_RT_DT))
            if seq == late + 1:  # two ticks after its own: its deadline has passed
                stream.send(frame=frame(late, dt=_RT_DT))
        answers = _answers(stream, start + ticks * _RT_DT + 0.5)
        summary = ctx.close(stream)
    check((late, "PREDICTED") in answers, f"tick {late}, its frame late, was not answered PREDICTED when due")
    check((lost, "PREDICTED") in answers, f"tick {lost}, its frame lost, was not answered PREDICTED")
    check((lost, "CORRECTED") not in answers, f"tick {lost}, whose frame never came, was CORRECTED")
    # A frame sent on time may still reach a busy server after its deadline: then CORRECTED.
    sent = [s for s in range(ticks) if s not in (late, lost)]
    unused = [s for s in sent if (s, "MEASURED") not in answers and (s, "CORRECTED") not in answers]
    check(not unused, f"ticks {unused}, their frames sent on time, were neither MEASURED nor CORRECTED")
    check(any((s, "MEASURED") in answers for s in sent), "no frame sent on time was answered MEASURED")
    if (late, "CORRECTED") in answers:
        got = f"CORRECTED after {answers[late, 'CORRECTED'].late_ticks} ticks"
    else:
        check(summary.rejected >= 1, f"tick {late}'s late frame was neither CORRECTED nor rejected")
        got = "TOO_OLD"
    check(summary.ticks >= ticks - 1, f"summary.ticks {summary.ticks} of the {ticks} ticks the session ran")
    return got


@case(
    "realtime.sequence",
    "REALTIME: `skip` is rejected WRONG_CLOCK, a frame far ahead of the clock OUT_OF_ORDER",
)
def _(ctx: Context) -> str:
    stream, _ = _realtime(ctx)
    with stream:
        stream.send(skip=dynamics_pb2.Skip(seq=0))
        rejected_as(stream, 0, "WRONG_CLOCK", passing=("result",))
        stream.send(frame=frame(100_000, dt=_RT_DT))
        rejected_as(stream, 100_000, "OUT_OF_ORDER", passing=("result",))
        ctx.close(stream)
    return "skip; seq 100000 at t 0"


@case(
    "clock.sync",
    "`sync` is answered with t1 echoed, t2 <= t3, a small offset and, once reported, the round trip",
)
def _(ctx: Context) -> str:
    stream, start = _realtime(ctx)
    with stream:
        pongs = []
        previous: tuple[int, float] | None = None
        for probe in range(1, 4):
            ping = dynamics_pb2.SyncPing(id=probe, client_send_time=time.monotonic() - start)
            if previous is not None:
                ping.previous_id, ping.previous_receive_time = previous
            stream.send(sync=ping)
            pong: dynamics_pb2.SyncPong = stream.expect("sync", passing=("result",))
            previous = (pong.id, time.monotonic() - start)
            check(pong.id == probe, f"probe {probe} answered with id {pong.id}")
            check(pong.client_send_time == ping.client_send_time, "the pong's t1 is not the ping's")
            t2, t3 = pong.server_receive_time, pong.server_send_time
            check(0.0 <= t2 <= t3, f"server times t2 {t2}, t3 {t3}: expected 0 <= t2 <= t3")
            check(
                math.isfinite(pong.offset) and abs(pong.offset) < 1.0,
                f"offset {pong.offset} s on one machine",
            )
            pongs.append(pong)
        ctx.close(stream)
    check(pongs[0].round_trip == 0.0, f"round_trip before any report is {pongs[0].round_trip}, not 0")
    check(pongs[-1].round_trip > 0.0, "round_trip is still 0 after two probes reported their answers")
    return f"offset {pongs[-1].offset * 1e3:.2f} ms, round trip {pongs[-1].round_trip * 1e3:.2f} ms"
