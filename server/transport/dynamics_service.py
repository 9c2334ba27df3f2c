"""DynamicsService.StreamSession: one bidirectional stream is one session.

The servicer reads the stream, hands frames to the session runtime (server/runtime/session.py) off the event
loop, writes one response per request in order (LOCKSTEP) or one result per tick at its deadline
(REALTIME), and records every answer through the session recorder before it is sent.

With a shared tier, a stream that ends without a close parks its session for a resume instead of
ending it, and `drain` (SIGTERM) tells every open session to move to another replica (`moving`).
"""

from __future__ import annotations

import asyncio
import contextvars
import functools
import logging
import math
import secrets
import time
import traceback
from collections.abc import AsyncIterator, Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Final, TypeVar

import grpc

from jitdyn.errors import FailedPrecondition, InvalidArgument, JitdynError, ResourceExhausted, Unavailable
from jitdyn.mujoco_log import counting
from jitdyn.server.runtime.alarm import Alarm
from jitdyn.server.runtime.clients import LocalClients
from jitdyn.server.runtime.clock import ClockSync, MonotonicClock
from jitdyn.server.runtime.frames import FrameIn, Rejection
from jitdyn.server.runtime.limits import DEFAULT_STREAM_LIMITS, IdleTimeout, StreamLimits
from jitdyn.server.runtime.opening import OpenedSession, SessionOpener, Unrehearsed
from jitdyn.server.runtime.plan import OpenRequest
from jitdyn.server.runtime.services import Services
from jitdyn.server.runtime.session import Place, TickOutcome
from jitdyn.server.transport.auth import tenant_of
from jitdyn.server.transport.frame_check import check_frame
from jitdyn.server.transport.messages import (
    covariance_diagonal,
    record_tick,
    rejected_message,
    rejection_record,
    result_message,
    summary_info,
)
from jitdyn.server.transport.metrics import metrics
from jitdyn.server.transport.opening import open_request, opened_message
from jitdyn.server.transport.rehearsal import REHEARSAL_KEY, Marks, Rehearser, rehearse, warm_up
from jitdyn.server.transport.session_service import summary_to_pb
from jitdyn.server.transport.start_gate import StartGate
from jitdyn.server.transport.status import abort
from jitdyn.server.transport.tally import FLUSH_EVERY, CounterTally, HistogramTally
from jitdyn.storage.failures import STORAGE_ERRORS, storage_failure
from jitdyn.storage.records import SessionSummaryInfo
from jitdyn.v1 import dynamics_pb2, dynamics_pb2_grpc
from jitdyn.vocabulary import Clock, Horizon, RejectReason, SessionStatus, Source

__all__ = ["DynamicsServicer"]

_log = logging.getLogger(__name__)
# While a session's slow step runs beside the loop, the GIL changes hands as for a REALTIME session
# of this grace: every 0.5 ms (a fifth, docs/decisions/0003), not CPython's 5 ms.
_SLOW_STEP_GRACE: Final = 2.5e-3  # s

Response = dynamics_pb2.StreamSessionResponse
# What a held CORRECTED result goes out with (`_Stream.write`).
_FLUSHING: Final = frozenset({"result", "closed", "moving"})


def _batched(responses: tuple[Response, ...]) -> list[Response]:
    """`responses` with each run of results as one message (StreamSessionResponse.results)."""
    out: list[Response] = []
    run: list[Response] = []
    for response in (*responses, None):
        if response is not None and response.WhichOneof("payload") == "result":
            run.append(response)
            continue
        if len(run) == 1:
            out.append(run[0])
        elif run:
            out.append(Response(results=dynamics_pb2.ResultBatch(results=[r.result for r in run])))
        run = []
        if response is not None:
            out.append(response)
    return out


_Context = grpc.aio.ServicerContext[dynamics_pb2.StreamSessionRequest, Response]

# REALTIME: how far ahead of the clock a frame may arrive and wait for its tick.
_MAX_TICKS_AHEAD = 1000
# REALTIME: a tick whose deadline passed this long ago before the event loop got to it (the
# process is overloaded, or a timewarp held the loop) is answered at once from what the session
# has, flagged `late_compute`, instead of late after running the estimator (seconds).
SHED_AFTER = 0.003
# REALTIME: a frame is answered as it arrives once its tick's time has come, give or take this
# much error of the clock offset (seconds).
_EARLY_TOLERANCE = 0.002
# REALTIME resume: how long the ticks that passed while the session moved wait for the frames the
# client re-sends (the SDK sends them right after `opened`; a loaded replica may take a while to
# read them) before they are skipped (seconds).
RESUME_REPLAY_WAIT = 1.0
# REALTIME: how often a session asks admission whether it may go late, and how often it repeats
# the in-band `overloaded` warning while that holds (s).
OVERLOAD_CHECK = 1.0
OVERLOAD_REPEAT = 10.0


_R = TypeVar("_R")


def _counting_warnings(method: Callable[..., _R]) -> Callable[..., _R]:
    """Run a `_Stream` method with MuJoCo's warnings counted for its session."""

    @functools.wraps(method)
    def wrapped(self: _Stream, *args: Any, **kwargs: Any) -> _R:
        with counting(self.runtime.warnings):
            return method(self, *args, **kwargs)

    return wrapped


class _Stream:
    """One open session on one stream: the runtime, the recorder, the clock."""

    def __init__(
        self,
        opened: OpenedSession,
        limits: StreamLimits = DEFAULT_STREAM_LIMITS,
        *,
        marks: Marks | None = None,
    ) -> None:
        self.ticket = opened.ticket  # REALTIME: this session's share of the process's tick budget
        # A rehearsal's (server/transport/rehearsal.py): its ticks marked, the session discarded.
        self.marks = marks
        self.rehearsal = marks is not None
        self.limits = limits
        # The tick's metrics, counted here and added to the process's once a window (flush_metrics).
        m, process, model = metrics(), metrics().process, opened.info.name
        self._m_ticks = {s: CounterTally(m.ticks.labels(process, model, s)) for s in Source}
        self._m_shed = CounterTally(m.shed.labels(process, model))
        self._m_restarts = CounterTally(m.restarts.labels(process, model))
        self._m_compute = HistogramTally(m.compute.labels(process, model))
        self._m_lateness = HistogramTally(m.lateness.labels(process, model))
        self._m_lag = HistogramTally(m.durable_lag.labels(process))
        self._m_flush_at = time.monotonic() + FLUSH_EVERY
        self.opened = opened
        self.plan = opened.plan
        self.runtime = opened.runtime
        self.recorder = opened.recorder
        self.sizes = opened.sizes
        self.clock = MonotonicClock()
        self.sync = ClockSync()
        self.lock = asyncio.Lock()
        self.pending: dict[int, FrameIn] = {}
        self.closed = False
        # REALTIME resume: the ticks before `replay_below`, which passed while the session moved,
        # are answered from the re-sent frames as they come (not skipped, not shed) until
        # `replay_until` on the server clock.
        self.replay_below = 0
        self.replay_until = -math.inf
        # Responses come from the request loop, the REALTIME clock and a drain's `moving`.
        self._write_lock = asyncio.Lock()
        # REALTIME: late frames' CORRECTED results wait for the next write of a due tick and go in
        # it, one message when the client takes batches (OpenSession.accept_result_batches).
        self.batches = False
        self._held: list[Response] = []
        self._overload_checked = self._overload_told = -math.inf
        # monotonic s since every check found it unaffordable with its process's answers short
        self._late_since: float | None = None
        self._token_issued = time.monotonic()  # when the client's newest resume token was made

    async def write(self, context: _Context, *responses: Response, due: bool = False) -> None:
        """Send `responses` in order, as one batch: the request loop and the REALTIME clock each
        compute their answers in tick order, and a batch split across two holds of the lock would
        let the other writer's newer tick overtake the rest of it (the first answer to tick 58
        after tick 59's). The lock is FIFO, and batches queue in the order they were computed.
        Held CORRECTED results go first in the next batch that answers a tick, closes or moves the
        session, or that the clock writes at a deadline (`due`)."""
        if self._held and (due or any(r.WhichOneof("payload") in _FLUSHING for r in responses)):
            responses, self._held = (*self._held, *responses), []
        notice = self.overload_notice()
        self.renew_token(responses)
        async with self._write_lock:
            for response in _batched(responses) if self.batches else responses:
                await context.write(response)
            if notice is not None:
                await context.write(notice)

    def hold(self, responses: list[Response]) -> list[Response]:
        """REALTIME: keep a late frame's CORRECTED result for the next due tick's write (a tick is
        one write); what else there is goes now."""
        kept = [r for r in responses if r.WhichOneof("payload") == "result"]
        self._held.extend(kept)
        return [r for r in responses if r.WhichOneof("payload") != "result"]

    def renew_token(self, responses: tuple[Response, ...]) -> None:
        """Hand the client a fresh resume token on the first result among `responses` once its
        newest is half the tokens' ttl old: while a stream answers, its client's token stays good
        for at least half the ttl, whenever the stream breaks (docs/decisions/0164)."""
        tokens = self.opened.tokens
        if tokens is None or time.monotonic() - self._token_issued < tokens.ttl / 2:
            return
        for response in responses:
            if response.HasField("result"):
                response.result.resume_token = self.opened.fresh_token()
                self._token_issued = time.monotonic()
                return

    def flush_metrics(self) -> None:
        """Add what this session's ticks counted to the process's metrics: once a window, and when
        it ends. A rehearsal's ticks are not the process's sessions': dropped."""
        self._m_flush_at = time.monotonic() + FLUSH_EVERY
        if self.rehearsal:
            return
        for tally in (*self._m_ticks.values(), self._m_shed, self._m_restarts):
            tally.flush()
        for histogram in (self._m_compute, self._m_lateness, self._m_lag):
            histogram.flush()

    def overload_notice(self) -> Response | None:
        """REALTIME: the in-band warning that this session's answers may go late
        (Admission.unaffordable), asked at most every OVERLOAD_CHECK s and repeated every
        OVERLOAD_REPEAT s while it holds. Raises LateTimeout once it has held at every check for
        the late timeout with the process's answers short (late, or its CPU past its budget; a
        loop's lag alone only tells: Admission.answers_short): the session is ended (and stored),
        so that those admitted before it are on time again, instead of every session of the
        process going late together. The session admitted first is never ended: ending it would
        keep no one on time."""
        if self.ticket is None:
            return None
        now = self.clock.now()
        if now - self._overload_checked < OVERLOAD_CHECK:
            return None
        self._overload_checked = now
        admission = self.ticket.admission
        reason = admission.unaffordable(self.ticket)
        if reason is None:
            self._late_since = None
            return None
        mono, start = time.monotonic(), admission.late_evidence_from()
        if not admission.answers_short():
            # Told, not ended: the loop lags but the answers are on time.
            self._late_since = None
        elif self._late_since is None or self._late_since < start:
            self._late_since = max(mono, start)
        elif mono - self._late_since >= self.limits.late_timeout and admission.admitted_before(self.ticket):
            _log.warning(
                "session %s: ended, %.1f s after it was told it may go late: %s",
                self.recorder.header.session_id,
                mono - self._late_since,
                reason,
            )
            admission.ended_late()
            raise self.limits.late(mono - self._late_since)
        if now - self._overload_told < OVERLOAD_REPEAT:
            return None
        self._overload_told = now
        _log.warning("session %s: told it may go late: %s", self.recorder.header.session_id, reason)
        return Response(overloaded=dynamics_pb2.Overloaded(reason=reason, late_share=admission.late_share))

    # Everything below runs in a worker thread, under `lock`.

    def frame_delay(self, frame: FrameIn | None) -> float | None:
        if frame is None:
            return None
        if self.plan.clock != Clock.REALTIME:
            return 0.0
        return frame.received - self.sync.to_server(frame.seq * self.plan.dt)

    def record_result(self, outcome: TickOutcome, *, arrived: float) -> dynamics_pb2.Result:
        now = self.clock.now()
        receive_to_send = max(0, int((now - arrived) * 1e6))
        delay = self.frame_delay(outcome.frame)
        diagonal = covariance_diagonal(outcome)
        record_tick(
            self.recorder,
            outcome,
            server_time=now,
            frame_delay=delay,
            receive_to_send_us=receive_to_send,
            diagonal=diagonal,
        )
        durable = self.recorder.durable_seq
        self._m_ticks[outcome.source].inc()
        if outcome.estimate is not None and outcome.estimate.reinitialised:
            self._m_restarts.inc()
        if outcome.late_compute:
            self._m_shed.inc()
        else:
            self._m_compute.observe(outcome.compute_us / 1e6)
        self._m_lag.observe(outcome.seq - durable if durable is not None else outcome.seq + 1)
        if time.monotonic() >= self._m_flush_at:
            self.flush_metrics()
        return result_message(
            outcome,
            outputs=self.plan.outputs,
            frame_delay=delay or 0.0,
            receive_to_send_us=receive_to_send,
            durable_seq=durable,
            diagonal=diagonal,
        )

    def record_rejection(self, rejection: Rejection) -> Response:
        """Count, record and answer a frame or skip that is not used."""
        self.runtime.reject(rejection)
        metrics().rejections.labels(metrics().process, rejection.reason).inc()
        self.recorder.append(
            rejection_record(rejection, server_time=self.clock.now(), t=rejection.seq * self.plan.dt)
        )
        return Response(rejected=rejected_message(rejection))

    def reject(
        self, seq: int, reason: RejectReason, message: str, *, frame: FrameIn | None = None
    ) -> list[Response]:
        return [self.record_rejection(Rejection(seq, reason, message, frame))]

    def horizon(self) -> float:
        if self.plan.horizon == Horizon.HALF_ROUND_TRIP:
            return self.sync.round_trip / 2.0
        return 0.0

    @_counting_warnings
    def on_frame(self, message: dynamics_pb2.Frame, arrived: float) -> list[Response]:
        checked = check_frame(message, sizes=self.sizes, measured=self.plan.measured, received=arrived)
        if isinstance(checked, Rejection):
            return [self.record_rejection(checked)]
        seq = checked.seq
        place = self.runtime.classify(seq)
        lockstep = self.plan.clock == Clock.LOCKSTEP
        if place == Place.NEXT and lockstep:
            outcome = self.runtime.advance(checked)
            return [Response(result=self.record_result(outcome, arrived=arrived))]
        if place in (Place.NEXT, Place.FUTURE) and not lockstep:
            return self._wait_for_tick(checked)
        if place == Place.FUTURE:
            return self.reject(
                seq,
                RejectReason.OUT_OF_ORDER,
                f"frame {seq}: LOCKSTEP expects the next tick {self.runtime.next_tick} or a skipped tick "
                f"within the history, got {seq}",
            )
        if place == Place.DUPLICATE:
            return self.reject(seq, RejectReason.DUPLICATE, f"frame {seq}: tick {seq} already has a frame")
        if place == Place.TOO_OLD:
            return self.reject(seq, RejectReason.TOO_OLD, self._too_old(seq), frame=checked)
        return self._late(checked, arrived)

    def _late(self, frame: FrameIn, arrived: float) -> list[Response]:
        """A frame for a tick answered (or skipped) before it came: applied when it fits."""
        unaffordable = self._unaffordable_replay(frame.seq)
        if unaffordable is not None:
            self.runtime.note_late(frame.seq)  # refused, it still says how late frames come
            return self.reject(frame.seq, RejectReason.TOO_OLD, unaffordable, frame=frame)
        runs = self.runtime.replay_cost(frame.seq)
        started, cpu_started = time.perf_counter(), time.thread_time()
        outcome = self.runtime.apply_late(frame)
        if self.ticket is not None:
            self.ticket.observe_replay(
                time.perf_counter() - started, cpu=time.thread_time() - cpu_started, ticks=runs
            )
        corrected = [Response(result=self.record_result(outcome, arrived=arrived))]
        return self.hold(corrected) if self.plan.clock == Clock.REALTIME else corrected

    def _wait_for_tick(self, frame: FrameIn) -> list[Response]:
        """REALTIME: keep a frame for the next or a later tick until its time, then answer what is due."""
        seq = frame.seq
        if seq in self.pending:
            return self.reject(
                seq,
                RejectReason.DUPLICATE,
                f"frame {seq}: tick {seq} already has a frame waiting for its deadline",
            )
        if seq - self.runtime.next_tick >= _MAX_TICKS_AHEAD:
            return self.reject(
                seq,
                RejectReason.OUT_OF_ORDER,
                f"frame {seq}: seq must be less than {self.runtime.next_tick + _MAX_TICKS_AHEAD} "
                f"(the clock is at tick {self.runtime.next_tick}), got {seq}",
            )
        self.pending[seq] = frame
        skipped = self.catch_up()
        return skipped + self.answer_ready()

    def _unaffordable_replay(self, seq: int) -> str | None:
        """REALTIME: why a late frame's timewarp is not applied, or None when it fits.

        The timewarp replays every tick the estimator ran since the late one, on the event loop; it
        is applied only when it fits before this session's next deadline with the session's own
        next tick, and in the loop's idle share of the shortest grace of the process's sessions (the
        longest any of their next answers can wait: Admission.replay_room), and not while replays
        keep the process late (Admission.replays_behind), because replays on a server that is
        already behind make it fall further behind (docs/decisions/0001-timewarp-budget.md). A
        replayed tick is priced at what the session's own replays measured, and at its compute per
        tick before its first (Ticket.replay_price). A frame whose tick waited for it adds no work (docs/decisions/0007-wait-for-late-frames.md):
        it is always applied.
        """
        runs = self.runtime.replay_cost(seq)
        if self.ticket is None or runs == 0:
            return None
        behind = self.ticket.admission.replays_behind()
        if behind is not None:
            return (
                f"frame {seq}: {self.runtime.next_tick - seq} ticks late; applying it means running "
                f"{runs} ticks of the filter again, and this server process {behind}: late frames "
                "are not applied until it catches up"
            )
        cost = runs * self.ticket.replay_price
        own = self.deadline(self.runtime.next_tick) - self.clock.now() - self.ticket.cost_per_tick
        shared = self.ticket.admission.replay_room()
        if cost <= min(own, shared):
            return None
        room = (
            f"only {1e3 * max(0.0, own):.1f} ms are left before this session's next deadline after its own "
            f"tick ({1e3 * self.ticket.cost_per_tick:.1f} ms)"
            if own <= shared
            else f"the sessions of this server process (this one among them) can wait only "
            f"{1e3 * max(0.0, shared):.1f} ms for the loop"
        )
        return (
            f"frame {seq}: {self.runtime.next_tick - seq} ticks late; applying it means running "
            f"{runs} ticks of the filter again, about {1e3 * cost:.1f} ms, and {room}, so it is not applied"
        )

    def _too_old(self, seq: int) -> str:
        """Why a frame for `seq` can no longer be applied: past the history, or before ticks an
        overloaded server skipped (their history went with them)."""
        runtime = self.runtime
        oldest = runtime.oldest_late_tick
        if oldest > max(0, runtime.next_tick - runtime.history):
            return (
                f"frame {seq}: late frames are applied back to tick {oldest} only: the server was "
                f"behind and skipped ticks before it ({runtime.counts.skipped} so far in this session), "
                f"and no late frame replays across skipped ticks"
            )
        shrunk = (
            f" of the {self.plan.history} asked for: their snapshots have grown past --max-history-bytes"
            if runtime.history < self.plan.history
            else ""
        )
        return f"frame {seq}: late frames are applied back to tick {oldest} (history {runtime.history} ticks{shrunk}), got {seq}"

    @_counting_warnings
    def on_skip(self, seq: int, arrived: float) -> Response:
        if self.plan.clock != Clock.LOCKSTEP:
            return self.record_rejection(
                Rejection(
                    seq,
                    RejectReason.WRONG_CLOCK,
                    f"skip {seq}: skip is for CLOCK_LOCKSTEP sessions; this session is CLOCK_REALTIME",
                )
            )
        expected = self.runtime.next_tick
        if seq != expected:
            reason = RejectReason.DUPLICATE if seq < expected else RejectReason.OUT_OF_ORDER
            return self.record_rejection(
                Rejection(seq, reason, f"skip {seq}: skip must name the next tick {expected}, got {seq}")
            )
        outcome = self.runtime.advance(None)
        return Response(result=self.record_result(outcome, arrived=arrived))

    def start_replay(self) -> None:
        """REALTIME resume, as the session's clock restarts: the ticks from the first this stream
        answers up to the present passed while the session moved; the client re-sends their frames
        at once, and they are answered in order as they come, with the estimator, so the record and
        the filter stay continuous. At most `history` of them; older ones are skipped."""
        first = self.runtime.next_tick
        present = max(first, math.ceil((self.clock.now() - self.plan.grace) / self.plan.dt))
        oldest = max(first, present - self.runtime.history)
        if oldest > first:
            self.runtime.skip(oldest - first)
        self.replay_below = present
        self.replay_until = self.clock.now() + RESUME_REPLAY_WAIT

    def replaying(self) -> bool:
        """REALTIME resume: ticks that passed while the session moved still wait for their frames."""
        return self.runtime.next_tick < self.replay_below and self.clock.now() < self.replay_until

    def deadline(self, seq: int) -> float:
        """REALTIME: tick `seq`'s deadline on the server clock: its time plus the grace."""
        return self.sync.to_server(seq * self.plan.dt) + self.plan.grace

    def answer(self, frame: FrameIn | None, *, due: float, now: float) -> Response:
        """REALTIME: answer the next tick; without the estimator (shed) when the loop reached it
        more than SHED_AFTER after its deadline."""
        shed = now - self.deadline(self.runtime.next_tick) > SHED_AFTER and not self.replaying()
        if shed:
            outcome = self.runtime.shed(frame)
        else:
            cpu = time.thread_time()
            outcome = self.runtime.advance(frame, horizon=self.horizon())
            if self.ticket is not None:
                self._observe_tick(outcome.compute_us / 1e6, cpu=time.thread_time() - cpu)
        response = Response(result=self.record_result(outcome, arrived=due))
        if self.marks is not None:
            self.marks.tick(outcome.seq)
        lateness = max(0.0, self.clock.now() - self.deadline(outcome.seq))
        self._m_lateness.observe(lateness)
        if self.ticket is not None:
            self.ticket.answered(lateness)
        return response

    def _observe_tick(self, seconds: float, *, cpu: float) -> None:
        """The tick's cost for admission: what it spent catching up a late frame's replay
        (docs/decisions/0167) is the replay's, not the session's own tick."""
        assert self.ticket is not None
        caught_up = min(self.runtime.caught_up, seconds)
        if caught_up > 0.0:
            self.ticket.admission.observe_replay(caught_up)
        own = 1.0 - caught_up / seconds if seconds > 0.0 else 1.0
        self.ticket.observe(seconds - caught_up, cpu=cpu * own)

    def catch_up(self) -> list[Response]:
        """REALTIME: when the loop reaches a session more than a tick late, skip (answer not at all)
        every tick whose deadline is already SHED_AFTER behind but the newest, so that the next
        answer is about the present and an overloaded process sheds work instead of queueing it.
        A frame that was waiting for a skipped tick is applied as a late frame when the session
        keeps that tick waiting (a short stall of a session that waits for late frames), else it
        is rejected TOO_OLD, its values stored."""
        if self.replaying():
            return []
        seq = self.runtime.next_tick
        behind = self.clock.now() - self.sync.offset - self.plan.grace - SHED_AFTER
        # The newest tick whose deadline is more than SHED_AFTER gone: it is answered (shed); the
        # ones before it, a tick or more behind it, are not.
        newest = math.ceil(behind / self.plan.dt) - 1
        if newest - seq < 1:
            return []
        waiting = [frame for k in range(seq, newest) if (frame := self.pending.pop(k, None)) is not None]
        # A rehearsal's lateness is what it measures, and its session id is discarded: not logged.
        (_log.debug if self.rehearsal else _log.warning)(
            "session %s: the loop reached tick %d %.0f ms after its deadline; ticks %d-%d skipped",
            self.recorder.header.session_id,
            seq,
            1e3 * (self.clock.now() - self.deadline(seq)),
            seq,
            newest - 1,
        )
        self.runtime.skip(newest - seq)
        responses: list[Response] = []
        for frame in waiting:
            if self.runtime.classify(frame.seq) == Place.LATE:
                responses += self._late(frame, frame.received)
                continue
            responses += self.reject(
                frame.seq,
                RejectReason.TOO_OLD,
                f"frame {frame.seq}: the server was behind and skipped ticks {seq}-{newest - 1}; "
                "the frame is stored, not used",
                frame=frame,
            )
        return responses

    @_counting_warnings
    def answer_ready(self) -> list[Response]:
        """REALTIME: answer, at once, every next tick whose frame is here and whose time has come
        (on an on-time client, as its frame arrives: well before the deadline, which only a tick
        without a frame waits for)."""
        responses = []
        now = self.clock.now()
        while (seq := self.runtime.next_tick) in self.pending and now >= self.sync.to_server(
            seq * self.plan.dt
        ) - _EARLY_TOLERANCE:
            frame = self.pending.pop(seq)
            responses.append(self.answer(frame, due=frame.received, now=now))
        return responses

    @_counting_warnings
    def on_deadline(self, deadline: float) -> list[Response]:
        """REALTIME: the next tick's deadline: predicted when its frame did not come, then every
        following tick whose frame is already here."""
        frame = self.pending.pop(self.runtime.next_tick, None)
        responses = [self.answer(frame, due=deadline, now=self.clock.now())]
        responses.extend(self.answer_ready())
        return responses

    @_counting_warnings
    def drain(self) -> list[Response]:
        """REALTIME close: answer every tick up to the last frame that is waiting, at once."""
        responses = []
        while self.pending:
            frame = self.pending.pop(self.runtime.next_tick, None)
            now = self.clock.now()
            outcome = self.runtime.advance(frame, horizon=self.horizon())
            responses.append(Response(result=self.record_result(outcome, arrived=now)))
        return responses


class _RealtimeClock:
    """REALTIME: the task that answers a session's ticks at their time, and the one writer of its
    stream. It sleeps on one wake-up, moved as frames answer ticks: it wakes only for a deadline
    that finds its frame missing (or a frame that came early), not once a tick."""

    def __init__(self, stream: _Stream, context: _Context) -> None:
        self._stream = stream
        self._context = context
        self._wakeup = Alarm.of(asyncio.get_running_loop()).wakeup()

    async def write(self, *responses: Response, due: bool = False) -> None:
        await self._stream.write(self._context, *responses, due=due)

    def due(self) -> float:
        """When to wake: a tick whose frame is here waits only for its own time; one without, for
        its deadline (monotonic seconds)."""
        stream = self._stream
        seq = stream.runtime.next_tick
        if seq in stream.pending:
            at = stream.sync.to_server(seq * stream.plan.dt)
        elif stream.replaying():
            at = stream.replay_until  # a resume's passed tick waits for its re-sent frame
        else:
            at = stream.deadline(seq)
        return stream.clock.to_monotonic(at)

    def moved(self) -> None:
        """A request may have answered the next tick or moved its deadline."""
        self._wakeup.move(self.due())

    async def run(self) -> None:
        stream = self._stream
        while True:
            await self._wakeup.until(self.due())
            if stream.closed:
                return
            skipped = stream.catch_up()
            seq = stream.runtime.next_tick
            if seq in stream.pending:
                responses = stream.answer_ready()
            elif stream.replaying():
                responses = []
            elif stream.clock.now() >= stream.deadline(seq):
                responses = stream.on_deadline(stream.deadline(seq))
            else:
                responses = []  # a clock probe moved the deadline later
            await self.write(*skipped, *responses, due=True)


class DynamicsServicer(dynamics_pb2_grpc.DynamicsServiceServicer):
    """Serves StreamSession: converts its messages and statuses; the runtime opens and runs the
    session (server/runtime/opening.py, server/runtime/session.py)."""

    def __init__(self, services: Services, *, limits: StreamLimits = DEFAULT_STREAM_LIMITS) -> None:
        self._services = services
        self._limits = limits
        self._opener = SessionOpener(services, limits=limits, on_admission=self._count_admission)
        self._slow_steps = ThreadPoolExecutor(max_workers=1, thread_name_prefix="jitdyn-slow-steps")
        self._streams: dict[_Stream, _Context] = {}
        self._start_gate = StartGate()
        self._draining = False
        self._all_moved = asyncio.Event()
        admission = services.admission
        self._clients = LocalClients(admission.observe_client, needed=admission.machine_short)
        self._rehearser: Rehearser | None = None
        # One rehearsal at a time: each measures the process's CPU, which another would share. Its
        # stream marks its ticks here.
        self._rehearsing = asyncio.Lock()
        self._marks: Marks | None = None

    def rehearse_at(self, address: str) -> None:
        """Rehearse the opens that ask for it (server/runtime/opening.py Unrehearsed) from a client
        of this process's own on `address`, a loopback port only this process listens on."""
        self._rehearser = Rehearser(address, secrets.token_hex(16))
        self._opener.rehearsals = True

    def _is_rehearsal(self, context: _Context) -> bool:
        rehearser = self._rehearser
        if rehearser is None or self._marks is None:
            return False
        sent = dict(context.invocation_metadata() or ()).get(REHEARSAL_KEY)
        return isinstance(sent, str) and secrets.compare_digest(sent, rehearser.secret)

    def _count_admission(self, refused: bool) -> None:
        if refused:
            metrics().refusals.labels(metrics().process).inc()
        metrics().load.labels(metrics().process).set(self._services.admission.load())

    # grpc.aio also takes a stream handler that writes through `context.write` and returns None,
    # which the generated servicer's signature (iterators of responses) does not describe.
    async def StreamSession(  # type: ignore[override]
        self,
        request_iterator: AsyncIterator[dynamics_pb2.StreamSessionRequest],
        context: _Context,
    ) -> None:
        try:
            first = await anext(aiter(request_iterator), None)
        except StopAsyncIteration:  # pragma: no cover
            first = None
        if first is None:
            return
        stream, opened = await self._accept(first, context)
        stream.batches = first.open.accept_result_batches
        # A stream that ends without `close` was left by its client (cancelled, vanished, or just
        # stopped sending) or cut by a stopping server: stored as ABANDONED. Everything from here on
        # is inside the try, so that a cancel arriving while `opened` is written still stores the
        # session and releases its slot.
        metrics().open_sessions.labels(metrics().process).inc()
        if first.open.HasField("resume"):
            metrics().resumed.labels(metrics().process).inc()
        status = SessionStatus.ABANDONED
        try:
            await self._hold_start(stream)
            # The session clock starts as `opened` leaves, as the client's starts as it arrives:
            # opening (the log's fsync, the index row) took milliseconds, tens under load, which the
            # client's clock knows nothing of; counted in, every frame looked late until a clock
            # probe completed.
            stream.clock.restart(elapsed=stream.opened.elapsed)
            if stream.plan.clock == Clock.REALTIME and stream.opened.resume_from_seq is not None:
                stream.start_replay()
            self._streams[stream] = context
            await context.write(Response(opened=opened))
            if stream.plan.clock == Clock.REALTIME:
                await self._realtime(stream, request_iterator, context)
            else:
                await self._lockstep(stream, request_iterator, context)
        except JitdynError as error:
            ended = SessionStatus.ABANDONED if isinstance(error, IdleTimeout) else SessionStatus.FAILED
            await self._finish_quietly(stream, ended)
            # The status is set and the handler returns, rather than raising through
            # context.abort: a raised abort keeps this frame (and the session's estimator and
            # models) alive in its traceback's reference cycle until the garbage collector runs.
            context.set_code(error.code)
            context.set_details(str(error))
        finally:
            try:
                if not stream.closed:
                    # The client went away or the server is stopping: what arrived is stored (with
                    # a shared tier, kept for a resume).
                    await asyncio.shield(self._finish_quietly(stream, status))
            finally:
                # Also when a second cancel interrupts the wait above (the storing goes on).
                self._streams.pop(stream, None)
                if not self._streams:
                    self._all_moved.set()

    async def _hold_start(self, stream: _Stream) -> None:
        """A new REALTIME session's first ticks after the process's opens and refusals under way,
        not among them (server/transport/start_gate.py); a resumed one's clock goes on."""
        if (
            stream.plan.clock != Clock.REALTIME
            or stream.opened.resume_from_seq is not None
            or stream.rehearsal
        ):
            return
        held = await self._start_gate.wait()
        if held > 0.0:
            _log.debug(
                "session %s: started %.3f s after it was opened", stream.recorder.header.session_id, held
            )

    async def _accept(
        self, first: dynamics_pb2.StreamSessionRequest, context: _Context
    ) -> tuple[_Stream, dynamics_pb2.SessionOpened]:
        """Open the session the stream's first message asks for, or end the stream with the status
        that says why not."""
        kind = first.WhichOneof("payload")
        if kind != "open":
            await abort(
                context, FailedPrecondition(f"the first message of a session must be `open`, got `{kind}`")
            )
        if self._draining:
            await abort(
                context,
                Unavailable("this replica is draining (it is being stopped); open the session on another"),
            )
        try:
            request = open_request(first.open, tenant=tenant_of(context))
            if self._is_rehearsal(context):
                return await self._open(request, first.open, rehearsal=True)
            if request.clock == Clock.REALTIME:
                # A client on this machine: its start-up is not load (server/runtime/clients.py).
                await self._clients.look(context.peer())
            return await self._open(request, first.open)
        except JitdynError as error:
            # Logged too: a balancer may not pass the status on (HAProxy 2.6 resets the stream
            # instead, docs/decisions/0121-refusals-through-a-balancer.md), and the operator should know.
            if isinstance(error, ResourceExhausted):
                self._start_gate.refused()  # a burst's surplus; a malformed open holds no one
            resume = " (a resume)" if first.open.HasField("resume") else ""
            _log.info("an open%s was refused: %s: %s", resume, error.code.name, error)
            await abort(context, error)
        except Exception:  # noqa: BLE001 (a bug: logged with its traceback, as translate_errors does)
            # The client learns nothing of the server's insides.
            _log.exception("internal error while opening a session")
            await context.abort(grpc.StatusCode.INTERNAL, "internal server error; see the server log")
        raise AssertionError("unreachable: abort raises")  # pragma: no cover

    async def drain(self, *, grace: float) -> int:
        """Refuse new sessions, tell every open one to move (`moving`, with what is durable), and
        wait up to `grace` seconds for their clients to leave; the sessions still open then."""
        self._draining = True
        streams = list(self._streams.items())
        for stream, context in streams:
            await self._tell_to_move(stream, context)
        if self._streams:
            self._all_moved.clear()
            try:
                async with asyncio.timeout(grace):
                    while self._streams:
                        await self._all_moved.wait()
                        self._all_moved.clear()
            except TimeoutError:
                pass
        return len(self._streams)

    async def step_down(self) -> int:
        """This replica's leases ran past their renew deadline (the index does not answer it): tell
        every session of the shared tier to move, without waiting for a flush that cannot come.
        Each goes on here until its client has opened it elsewhere, so a session no other replica
        can take (the index is down for all) keeps being answered. The sessions told."""
        told = 0
        for stream, context in list(self._streams.items()):
            if stream.recorder.resumable:
                reason = "this replica cannot renew its lease (the index does not answer it)"
                await self._tell_to_move(stream, context, reason=reason, flush=False)
                told += 1
        return told

    async def _tell_to_move(
        self,
        stream: _Stream,
        context: _Context,
        *,
        reason: str = "the replica is draining (it is being stopped)",
        flush: bool = True,
    ) -> None:
        recorder = stream.recorder
        try:
            if flush:
                await asyncio.to_thread(recorder.flush, 5.0)
        except JitdynError as error:
            _log.warning("session %s: not flushed before moving: %s", recorder.header.session_id, error)
        durable = recorder.durable_seq
        moving = dynamics_pb2.Moving(reason=reason)
        if durable is not None:
            moving.durable_seq = durable
        try:
            await stream.write(context, Response(moving=moving))
        except Exception:  # noqa: BLE001 (a stream that has just ended: nothing to tell)
            _log.debug("session %s: `moving` not sent", recorder.header.session_id, exc_info=True)

    async def _open(
        self, request: OpenRequest, message: dynamics_pb2.OpenSession, *, rehearsal: bool = False
    ) -> tuple[_Stream, dynamics_pb2.SessionOpened]:
        services, tenant = self._services, request.tenant
        services.admit(tenant)
        try:
            if not rehearsal:
                self._opener.check_door(request)
        except JitdynError:
            services.release(tenant)
            raise
        marks = self._marks if rehearsal else None
        opening = asyncio.ensure_future(self._slow(self._open_sync, request, marks))
        try:
            with self._start_gate.opening():
                try:
                    return await asyncio.shield(opening)
                except Unrehearsed as need:
                    await self._rehearse(message, need)
                    opening = asyncio.ensure_future(self._slow(self._open_sync, request, marks))
                    return await asyncio.shield(opening)
        except JitdynError as error:
            # The refused open's frames (the model, an estimator of hundreds of MB for a large
            # model) would otherwise live in the error's traceback, kept in a reference cycle by
            # the handler until the garbage collector runs.
            traceback.clear_frames(error.__traceback__)
            services.release(tenant)
            raise
        except asyncio.CancelledError:
            # The client left while the session was being opened. The thread cannot be stopped, so
            # the handler waits for it and undoes what it built (log, index row, commit
            # registration) before the slot is given back.
            await asyncio.shield(self._abandon_open(opening, tenant))
            raise
        except BaseException:
            services.release(tenant)
            raise

    async def _rehearse(self, message: dynamics_pb2.OpenSession, need: Unrehearsed) -> None:
        """Rehearse the session `message` opens, alone on this process, and tell the opener and
        admission what its ticks cost (server/transport/rehearsal.py)."""
        rehearser = self._rehearser
        assert rehearser is not None  # the opener asks only once told it may (rehearse_at)
        async with self._rehearsing:
            if self._opener.was_rehearsed(need.key):
                return  # opens of one kind arriving together: the first one's rehearsal prices all
            self._marks = marks = Marks(warm=warm_up(message.dt))
            try:
                rehearsal = await asyncio.to_thread(rehearse, rehearser, message, need.model, marks=marks)
            finally:
                self._marks = None
            self._opener.rehearsed(need.key, rehearsal)
            self._services.admission.rehearsed()
        if rehearsal is None:
            _log.warning("a rehearsal at %g Hz did not run; the session is priced without it", 1 / message.dt)
            return
        _log.info(
            "rehearsed a session of %s at %g Hz: %d ticks in %.2f s, %d answered MEASURED by their "
            "deadlines, %.0f us of this process's CPU a tick",
            need.name,
            1 / message.dt,
            rehearsal.ticks,
            rehearsal.seconds,
            rehearsal.measured,
            1e6 * rehearsal.cost,
        )

    async def _abandon_open(
        self, opening: asyncio.Future[tuple[_Stream, dynamics_pb2.SessionOpened]], tenant: str
    ) -> None:
        try:
            stream, _ = await opening
            await self._slow(stream.opened.discard)
        except Exception:  # noqa: BLE001 (the open failed anyway, or the discard did: both only logged)
            _log.debug("an abandoned open ended with an error", exc_info=True)
        finally:
            self._services.release(tenant)

    def close(self) -> None:
        """Wait for the slow steps under way and queued (stores of sessions that ended), then stop
        their thread. Once the server has stopped; blocks."""
        self._slow_steps.shutdown(wait=True)

    async def _slow(self, call: Callable[..., _R], *args: Any, **kwargs: Any) -> _R:
        """`call(*args, **kwargs)` on the thread of the sessions' slow steps (opening one, storing
        one), one step at a time, the GIL changing hands meanwhile as for a session of
        _SLOW_STEP_GRACE. Such a step runs Python for tens of milliseconds (the registry's query, the
        estimator and its cost probe; a log's columns into Parquet): four of them at once in the
        loop's default executor held the GIL in turns with the loop, and each of the loop's waits
        for it in a tick (after a frame's read, a rollout, a write) cost up to the switch interval
        (stall reports: 79 ms with four opens beside the loop, 115 ms with four stores;
        docs/decisions/0009-the-loop-watched.md)."""
        admission = self._services.admission
        switch = admission.switch

        def step() -> _R:
            if switch is not None:
                switch.add(_SLOW_STEP_GRACE)
            cpu = time.thread_time()
            try:
                return call(*args, **kwargs)
            finally:
                admission.observe_aside(time.thread_time() - cpu)
                if switch is not None:
                    switch.remove(_SLOW_STEP_GRACE)

        context = contextvars.copy_context()
        return await asyncio.get_running_loop().run_in_executor(self._slow_steps, context.run, step)

    def _open_sync(
        self, request: OpenRequest, marks: Marks | None
    ) -> tuple[_Stream, dynamics_pb2.SessionOpened]:
        opened = self._opener.open_session(request, rehearsal=marks is not None)
        try:
            return _Stream(opened, self._limits, marks=marks), opened_message(opened)
        except BaseException:
            opened.discard()
            raise

    async def _lockstep(
        self,
        stream: _Stream,
        requests: AsyncIterator[dynamics_pb2.StreamSessionRequest],
        context: _Context,
    ) -> None:
        async for request in self._until_idle(requests):
            arrived = stream.clock.now()
            kind = request.WhichOneof("payload")
            if kind == "frame":
                await stream.write(context, *await asyncio.to_thread(stream.on_frame, request.frame, arrived))
            elif kind == "skip":
                await stream.write(
                    context, await asyncio.to_thread(stream.on_skip, request.skip.seq, arrived)
                )
            elif kind == "sync":
                await stream.write(context, self._pong(stream, request.sync, arrived))
            elif kind == "close":
                await stream.write(context, await self._close(stream))
                return
            else:
                raise InvalidArgument(_unexpected(kind))

    async def _realtime(
        self,
        stream: _Stream,
        requests: AsyncIterator[dynamics_pb2.StreamSessionRequest],
        context: _Context,
    ) -> None:
        # REALTIME runs on the event loop itself: a tick's work costs less than the two thread
        # hand-offs per tick a worker thread would add, and one loop per process (`jitdyn serve
        # --processes`) keeps every deadline in one queue, earliest first. Deadlines wake the loop
        # through a timerfd (server/runtime/alarm.py); see docs/decisions/0002-realtime-on-the-loop.md.
        clock = _RealtimeClock(stream, context)
        tick_task = asyncio.create_task(clock.run())
        try:
            async for request in self._until_idle(requests):
                if tick_task.done():
                    tick_task.result()  # surfaces a failure of the clock
                arrived = stream.clock.now()
                kind = request.WhichOneof("payload")
                if kind == "frame":
                    await clock.write(*stream.on_frame(request.frame, arrived))
                elif kind == "skip":
                    await clock.write(stream.on_skip(request.skip.seq, arrived))
                elif kind == "sync":
                    await clock.write(self._pong(stream, request.sync, arrived))  # may move the deadline
                elif kind == "close":
                    tick_task.cancel()
                    await clock.write(*stream.drain())
                    await clock.write(await self._close(stream))
                    return
                else:
                    raise InvalidArgument(_unexpected(kind))
                clock.moved()
        finally:
            tick_task.cancel()
            # The clock's own end (cancelled, or failed while the stream ends) is not news here.
            await asyncio.gather(tick_task, return_exceptions=True)

    async def _until_idle(
        self, requests: AsyncIterator[dynamics_pb2.StreamSessionRequest]
    ) -> AsyncIterator[dynamics_pb2.StreamSessionRequest]:
        """The requests, until the client sends nothing for the idle timeout (IdleTimeout).

        One timer a stream, which re-arms itself when it finds a read younger than the timeout:
        not a timeout a read (asyncio.timeout's schedule and cancel on every frame of every session
        were a sixth of the loop's Python outside the tick, in a cProfile under load)."""
        loop = asyncio.get_running_loop()
        task = asyncio.current_task()
        idle = self._limits.idle_timeout
        reading_since: float | None = loop.time()  # None while the caller handles a request
        expired = False
        timer: asyncio.TimerHandle

        def check() -> None:
            nonlocal timer, expired
            now = loop.time()
            if reading_since is None or now < reading_since + idle:
                timer = loop.call_at(now + idle if reading_since is None else reading_since + idle, check)
                return
            expired = True
            if task is not None:
                task.cancel()

        timer = loop.call_at(loop.time() + idle, check)
        iterator = aiter(requests)
        try:
            while True:
                reading_since = loop.time()
                try:
                    request = await anext(iterator)
                except StopAsyncIteration:
                    return
                except asyncio.CancelledError:
                    if expired and task is not None and task.uncancel() == 0:
                        raise self._limits.idle() from None
                    raise
                reading_since = None
                yield request
        finally:
            timer.cancel()

    def _pong(self, stream: _Stream, ping: dynamics_pb2.SyncPing, arrived: float) -> Response:
        if not math.isfinite(ping.client_send_time):
            raise InvalidArgument(f"sync.client_send_time must be finite, got {ping.client_send_time}")
        sent = stream.clock.now()
        stream.sync.on_probe(
            probe_id=ping.id,
            client_send_time=ping.client_send_time,
            server_receive_time=arrived,
            server_send_time=sent,
            previous_id=ping.previous_id if ping.HasField("previous_receive_time") else None,
            previous_receive_time=ping.previous_receive_time
            if ping.HasField("previous_receive_time")
            else None,
        )
        if stream.plan.clock == Clock.REALTIME:
            # A client clock that leaps would make the session tick as fast as the CPU allows
            # (ahead) or never (behind); either way it is refused.
            self._limits.check_clock_offset(stream.sync.offset)
        return Response(
            sync=dynamics_pb2.SyncPong(
                id=ping.id,
                client_send_time=ping.client_send_time,
                server_receive_time=arrived,
                server_send_time=sent,
                offset=stream.sync.offset,
                round_trip=stream.sync.round_trip,
            )
        )

    async def _close(self, stream: _Stream) -> Response:
        summary, location = await self._finish(stream, SessionStatus.COMPLETE)
        return Response(closed=dynamics_pb2.SessionClosed(summary=summary_to_pb(summary, location=location)))

    async def _finish_quietly(self, stream: _Stream, status: SessionStatus) -> None:
        """End a session that is ending anyway; a store that fails now keeps its log, which the
        next start recovers, so the failure is logged rather than raised over the first error."""
        try:
            await self._finish(stream, status)
        except Exception:  # noqa: BLE001 (any failure: logged with its traceback, as the docstring says)
            _log.exception(
                "session %s could not be closed; its log is recovered at the next start",
                stream.recorder.header.session_id,
            )

    async def _finish(self, stream: _Stream, status: SessionStatus) -> tuple[SessionSummaryInfo, str]:
        async with stream.lock:
            if stream.closed:
                raise FailedPrecondition("the session is already closed")
            stream.closed = True
        stream.runtime.counts.mujoco_warnings = stream.runtime.warnings.count
        if stream.runtime.counts.mujoco_warnings:
            _log.warning(
                "session %s: MuJoCo warned %d times (the jitdyn.mujoco log says what about)",
                stream.recorder.header.session_id,
                stream.runtime.counts.mujoco_warnings,
            )
        summary = summary_info(stream.runtime.counts, duration=stream.clock.now())
        stream.runtime.release()
        stream.pending.clear()
        try:
            if stream.rehearsal:
                await self._slow(stream.opened.discard)
                location = ""
            elif status == SessionStatus.ABANDONED and stream.recorder.resumable:
                await self._slow(stream.recorder.park)
                location = ""
            else:
                location = await self._slow(stream.recorder.close, summary, status=status)
                summary = stream.recorder.stored_summary or summary
        except STORAGE_ERRORS as error:
            raise storage_failure(
                f"session {stream.recorder.header.session_id} could not be stored", error
            ) from None
        finally:
            self._services.release(stream.recorder.header.tenant)
            stream.flush_metrics()
            metrics().open_sessions.labels(metrics().process).dec()
            if stream.ticket is not None:
                stream.ticket.release()
                metrics().load.labels(metrics().process).set(self._services.admission.load())
        return summary, location


def _unexpected(kind: str | None) -> str:
    if kind == "open":
        return "open must be sent once, as the first message; got a second `open`"
    return f"a request must carry one of open, frame, skip, sync, close; got {kind or 'nothing'}"
