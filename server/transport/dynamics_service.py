"""DynamicsService.StreamSession: one bidirectional stream is one session.

The servicer reads the stream, hands frames to the session runtime (server/runtime/session.py) off the event
loop, writes one response per request in order (LOCKSTEP) or one result per tick at its deadline
(REALTIME), and records every answer through the session recorder before it is sent.
"""

from __future__ import annotations

import asyncio
import dataclasses
import functools
import logging
import math
import threading
import traceback
import uuid
from collections.abc import AsyncIterator, Callable
from datetime import UTC, datetime
from typing import Any, TypeVar

import grpc
import mujoco

from jitdyn.errors import FailedPrecondition, InvalidArgument, JitdynError, ResourceExhausted
from jitdyn.mujoco_log import counting
from jitdyn.registry import ModelInfo
from jitdyn.server.estimation.dynamics import Dynamics
from jitdyn.server.estimation.estimator import (
    SETTING_FIELDS,
    Estimator,
    EstimatorConfig,
    default_scenario,
    resolve_config,
)
from jitdyn.server.estimation.factory import make_estimator, measure_cycle
from jitdyn.server.runtime.admission import Ticket
from jitdyn.server.runtime.alarm import Alarm
from jitdyn.server.runtime.clock import ClockSync, MonotonicClock
from jitdyn.server.runtime.frames import FrameIn, Rejection
from jitdyn.server.runtime.limits import (
    DEFAULT_STREAM_LIMITS,
    IdleTimeout,
    StreamLimits,
    snapshot_bytes,
    tick_cost,
)
from jitdyn.server.runtime.services import Services
from jitdyn.server.runtime.session import SessionRuntime, TickOutcome
from jitdyn.server.transport.auth import tenant_of
from jitdyn.server.transport.frame_check import check_frame
from jitdyn.server.transport.messages import (
    rejected_message,
    rejection_record,
    result_message,
    summary_info,
    tick_record,
)
from jitdyn.server.transport.metrics import metrics
from jitdyn.server.transport.model_messages import metadata_from_message, model_message, settings_message
from jitdyn.server.transport.opening import SessionPlan, plan_session
from jitdyn.server.transport.session_service import summary_to_pb
from jitdyn.server.transport.status import abort
from jitdyn.storage.failures import STORAGE_ERRORS, storage_failure
from jitdyn.storage.recorder import SessionRecorder
from jitdyn.storage.records import SessionHeader, SessionSummaryInfo
from jitdyn.v1 import common_pb2, dynamics_pb2, dynamics_pb2_grpc

__all__ = ["DynamicsServicer"]

_log = logging.getLogger(__name__)

Response = dynamics_pb2.StreamSessionResponse
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
        *,
        services: Services,
        plan: SessionPlan,
        runtime: SessionRuntime,
        recorder: SessionRecorder,
        sizes: dict[str, int],
        clock: MonotonicClock,
        ticket: Ticket | None = None,
    ) -> None:
        self.services = services
        self.ticket = ticket  # REALTIME: this session's share of the process's tick budget
        m, process, model = metrics(), metrics().process, recorder.header.model_name
        self._m_ticks = {s: m.ticks.labels(process, model, s) for s in ("MEASURED", "PREDICTED", "CORRECTED")}
        self._m_shed = m.shed.labels(process, model)
        self._m_compute = m.compute.labels(process, model)
        self._m_lateness = m.lateness.labels(process, model)
        self._m_lag = m.durable_lag.labels(process)
        self.plan = plan
        self.runtime = runtime
        self.recorder = recorder
        self.sizes = sizes
        self.clock = clock
        self.sync = ClockSync()
        self.lock = asyncio.Lock()
        self.pending: dict[int, FrameIn] = {}
        self.closed = False

    # Everything below runs in a worker thread, under `lock`.

    def frame_delay(self, frame: FrameIn | None) -> float | None:
        if frame is None:
            return None
        if self.plan.clock != "REALTIME":
            return 0.0
        return frame.received - self.sync.to_server(frame.seq * self.plan.dt)

    def record_result(self, outcome: TickOutcome, *, arrived: float) -> dynamics_pb2.Result:
        now = self.clock.now()
        receive_to_send = max(0, int((now - arrived) * 1e6))
        delay = self.frame_delay(outcome.frame)
        self.recorder.append(
            tick_record(outcome, server_time=now, frame_delay=delay, receive_to_send_us=receive_to_send)
        )
        durable = self.recorder.durable_seq
        self._m_ticks[outcome.source].inc()
        if outcome.late_compute:
            self._m_shed.inc()
        else:
            self._m_compute.observe(outcome.compute_us / 1e6)
        self._m_lag.observe(outcome.seq - durable if durable is not None else outcome.seq + 1)
        return result_message(
            outcome,
            outputs=self.plan.outputs,
            frame_delay=delay or 0.0,
            receive_to_send_us=receive_to_send,
            durable_seq=durable,
        )

    def record_rejection(self, rejection: Rejection) -> dynamics_pb2.Rejected:
        self.runtime.reject(rejection)
        metrics().rejections.labels(metrics().process, rejection.reason).inc()
        self.recorder.append(
            rejection_record(rejection, server_time=self.clock.now(), t=rejection.seq * self.plan.dt)
        )
        return rejected_message(rejection)

    def horizon(self) -> float:
        if self.plan.horizon == "HALF_ROUND_TRIP":
            return self.sync.round_trip / 2.0
        return 0.0

    @_counting_warnings
    def on_frame(self, message: dynamics_pb2.Frame, arrived: float) -> list[Response]:
        checked = check_frame(message, sizes=self.sizes, measured=self.plan.measured, received=arrived)
        if isinstance(checked, Rejection):
            return [Response(rejected=self.record_rejection(checked))]
        seq = checked.seq
        place = self.runtime.classify(seq)
        lockstep = self.plan.clock == "LOCKSTEP"
        if place == "next" and lockstep:
            outcome = self.runtime.advance(checked)
            return [Response(result=self.record_result(outcome, arrived=arrived))]
        if place in ("next", "future") and not lockstep:
            if seq in self.pending:
                return [
                    Response(
                        rejected=self.record_rejection(
                            Rejection(
                                seq,
                                "DUPLICATE",
                                f"frame {seq}: tick {seq} already has a frame waiting for its deadline",
                            )
                        )
                    )
                ]
            if seq - self.runtime.next_tick >= _MAX_TICKS_AHEAD:
                return [
                    Response(
                        rejected=self.record_rejection(
                            Rejection(
                                seq,
                                "OUT_OF_ORDER",
                                f"frame {seq}: seq must be less than {self.runtime.next_tick + _MAX_TICKS_AHEAD} "
                                f"(the clock is at tick {self.runtime.next_tick}), got {seq}",
                            )
                        )
                    )
                ]
            self.pending[seq] = checked
            self.catch_up()
            return self.answer_ready()
        if place == "future":
            return [
                Response(
                    rejected=self.record_rejection(
                        Rejection(
                            seq,
                            "OUT_OF_ORDER",
                            f"frame {seq}: LOCKSTEP expects the next tick {self.runtime.next_tick} or a skipped tick "
                            f"within the history, got {seq}",
                        )
                    )
                )
            ]
        if place == "duplicate":
            return [
                Response(
                    rejected=self.record_rejection(
                        Rejection(seq, "DUPLICATE", f"frame {seq}: tick {seq} already has a frame")
                    )
                )
            ]
        if place == "too_old":
            return [Response(rejected=self.record_rejection(Rejection(seq, "TOO_OLD", self._too_old(seq))))]
        if self.ticket is not None:
            # REALTIME: a timewarp replays every tick since the late one, on the event loop. It is
            # applied only when it fits, with the session's own next tick, in half a tick:
            # replays on a server that is already behind made it fall further behind (late frames
            # begot late frames: a 200 Hz biped session that replayed a 1-tick-late frame whenever
            # it fitted in half of what its ticks leave free had 10 % of its frames late, and they
            # reached the loop 5 ms late at p99 instead of 1.1 ms).
            replay = self.runtime.next_tick - seq
            cost = replay * self.ticket.compute_per_tick
            free = max(0.0, self.plan.dt / 2 - self.ticket.cost_per_tick)
            if cost > free:
                return [
                    Response(
                        rejected=self.record_rejection(
                            Rejection(
                                seq,
                                "TOO_OLD",
                                f"frame {seq}: {replay} ticks late; replaying them would take about "
                                f"{1e3 * cost:.1f} ms, and with this session's own ticks at {1e3 * self.ticket.cost_per_tick:.1f} ms "
                                f"only {1e3 * free:.1f} ms of half its {1e3 * self.plan.dt:g} ms tick is free, so it is not applied",
                            )
                        )
                    )
                ]
        outcome = self.runtime.apply_late(checked)
        return [Response(result=self.record_result(outcome, arrived=arrived))]

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
        if self.plan.clock != "LOCKSTEP":
            return Response(
                rejected=self.record_rejection(
                    Rejection(
                        seq,
                        "WRONG_CLOCK",
                        f"skip {seq}: skip is for CLOCK_LOCKSTEP sessions; this session is CLOCK_REALTIME",
                    )
                )
            )
        expected = self.runtime.next_tick
        if seq != expected:
            reason = "DUPLICATE" if seq < expected else "OUT_OF_ORDER"
            return Response(
                rejected=self.record_rejection(
                    Rejection(seq, reason, f"skip {seq}: skip must name the next tick {expected}, got {seq}")
                )
            )
        outcome = self.runtime.advance(None)
        return Response(result=self.record_result(outcome, arrived=arrived))

    def deadline(self, seq: int) -> float:
        """REALTIME: tick `seq`'s deadline on the server clock: its time plus the grace."""
        return self.sync.to_server(seq * self.plan.dt) + self.plan.grace

    def answer(self, frame: FrameIn | None, *, due: float, now: float) -> Response:
        """REALTIME: answer the next tick; without the estimator (shed) when the loop reached it
        more than SHED_AFTER after its deadline."""
        shed = now - self.deadline(self.runtime.next_tick) > SHED_AFTER
        if shed:
            outcome = self.runtime.shed(frame)
        else:
            outcome = self.runtime.advance(frame, horizon=self.horizon())
            if self.ticket is not None:
                self.ticket.observe(outcome.compute_us / 1e6)
        response = Response(result=self.record_result(outcome, arrived=due))
        self._m_lateness.observe(max(0.0, self.clock.now() - self.deadline(outcome.seq)))
        return response

    def catch_up(self) -> None:
        """REALTIME: when the loop reaches a session more than a tick late, skip (answer not at all)
        every tick whose deadline is already SHED_AFTER behind but the newest, so that the next
        answer is about the present and an overloaded process sheds work instead of queueing it."""
        seq = self.runtime.next_tick
        behind = self.clock.now() - self.sync.offset - self.plan.grace - SHED_AFTER
        # The newest tick whose deadline is more than SHED_AFTER gone: it is answered (shed); the
        # ones before it, a tick or more behind it, are not.
        newest = math.ceil(behind / self.plan.dt) - 1
        if newest - seq >= 1:
            for k in range(seq, newest):
                self.pending.pop(k, None)
            self.runtime.skip(newest - seq)

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


@dataclasses.dataclass(frozen=True, slots=True)
class _TickPrice:
    """What one REALTIME tick of a model and its settings costs in this process."""

    cost: float  # s: the physics and linear algebra, priced (the --max-tick-share check)
    cycle: float | None  # s: one predict + update, measured once the price alone admits it
    nsigma: int
    state_dimension: int


class DynamicsServicer(dynamics_pb2_grpc.DynamicsServiceServicer):
    """Serves StreamSession."""

    def __init__(self, services: Services, *, limits: StreamLimits = DEFAULT_STREAM_LIMITS) -> None:
        self._services = services
        self._limits = limits
        # What a tick of (model, settings) costs here, measured at its first REALTIME open and
        # reused: every open of a hundred sessions of one model would otherwise time its own
        # throwaway filter while the others' ticks wait.
        self._costs: dict[tuple[str, EstimatorConfig], _TickPrice] = {}
        self._costs_lock = threading.Lock()

    def _tick_price(
        self, info: ModelInfo, model: mujoco.MjModel, config: EstimatorConfig, *, cycle: bool
    ) -> _TickPrice:
        """What a tick of `config` costs on this model, priced at its first REALTIME open in this
        process (on a throwaway estimator) and reused; `cycle`: also time one predict + update,
        once (a session that the price alone refuses never costs the others that)."""
        key = (info.id, config)
        with self._costs_lock:
            known = self._costs.get(key)
            if known is None:
                probe = make_estimator(model, config, pool=self._services.pool)
                nsigma = int(getattr(probe, "nsigma", 1))
                known = self._costs[key] = _TickPrice(
                    cost=tick_cost(
                        model,
                        nsigma=nsigma,
                        steps_per_tick=config.steps_per_tick,
                        state_dimension=probe.state_dimension,
                    ),
                    cycle=None,
                    nsigma=nsigma,
                    state_dimension=probe.state_dimension,
                )
            if cycle and known.cycle is None:
                measured = measure_cycle(model, config, pool=self._services.pool)
                known = self._costs[key] = dataclasses.replace(known, cycle=measured)
            return known

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
        kind = first.WhichOneof("payload")
        if kind != "open":
            await abort(
                context, FailedPrecondition(f"the first message of a session must be `open`, got `{kind}`")
            )
        tenant = tenant_of(context)
        try:
            stream, opened = await self._open(first.open, tenant)
        except JitdynError as error:
            await abort(context, error)
        except Exception:  # noqa: BLE001 (a bug: logged with its traceback, as translate_errors does)
            # The client learns nothing of the server's insides.
            _log.exception("internal error while opening a session")
            await context.abort(grpc.StatusCode.INTERNAL, "internal server error; see the server log")
        # A stream that ends without `close` was left by its client (cancelled, vanished, or just
        # stopped sending) or cut by a stopping server: stored as ABANDONED. Everything from here on
        # is inside the try, so that a cancel arriving while `opened` is written still stores the
        # session and releases its slot.
        metrics().open_sessions.labels(metrics().process).inc()
        status = "ABANDONED"
        try:
            # The session clock starts as `opened` leaves, as the client's starts as it arrives:
            # opening (the log's fsync, the index row) took milliseconds, tens under load, which the
            # client's clock knows nothing of; counted in, every frame looked late until a clock
            # probe completed.
            stream.clock.restart()
            await context.write(Response(opened=opened))
            if stream.plan.clock == "REALTIME":
                await self._realtime(stream, request_iterator, context)
            else:
                await self._lockstep(stream, request_iterator, context)
        except JitdynError as error:
            await self._finish_quietly(stream, "ABANDONED" if isinstance(error, IdleTimeout) else "FAILED")
            # The status is set and the handler returns, rather than raising through
            # context.abort: a raised abort keeps this frame (and the session's estimator and
            # models) alive in its traceback's reference cycle until the garbage collector runs.
            context.set_code(error.code)
            context.set_details(str(error))
        finally:
            if not stream.closed:
                # The client went away or the server is stopping: what arrived is stored.
                await asyncio.shield(self._finish_quietly(stream, status))

    async def _open(
        self, request: dynamics_pb2.OpenSession, tenant: str
    ) -> tuple[_Stream, dynamics_pb2.SessionOpened]:
        services = self._services
        services.admit(tenant)
        opening = asyncio.ensure_future(asyncio.to_thread(self._open_sync, request, tenant))
        try:
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

    async def _abandon_open(
        self, opening: asyncio.Future[tuple[_Stream, dynamics_pb2.SessionOpened]], tenant: str
    ) -> None:
        try:
            stream, _ = await opening
            if stream.ticket is not None:
                stream.ticket.release()  # its share of the tick budget, too
            await asyncio.to_thread(stream.recorder.discard)
        except Exception:  # noqa: BLE001 (the open failed anyway, or the discard did: both only logged)
            _log.debug("an abandoned open ended with an error", exc_info=True)
        finally:
            self._services.release(tenant)

    def _open_sync(
        self, request: dynamics_pb2.OpenSession, tenant: str
    ) -> tuple[_Stream, dynamics_pb2.SessionOpened]:
        services = self._services
        registry = services.registry
        which = request.WhichOneof("model")
        if which is None:
            raise InvalidArgument("open.model must be set: model_id, model_name or inline_model")
        if which != "model_name" and request.model_version:
            raise InvalidArgument(
                f"open.model_version must be 0 with open.{which}, got {request.model_version}"
            )
        if which == "model_id":
            info = registry.get(tenant=tenant, model_id=request.model_id)
        elif which == "model_name":
            info = registry.get(tenant=tenant, name=request.model_name, version=request.model_version)
        else:
            inline = request.inline_model
            info, _ = registry.register(
                name=inline.name,
                mjcf=inline.mjcf,
                assets=dict(inline.assets),
                metadata=metadata_from_message(inline.metadata),
                tenant=tenant,
            )
        model = registry.load(info.id, tenant=tenant)
        plan = plan_session(request, timestep=info.timestep)
        if model.nv > services.limits.max_state_dimension:
            raise ResourceExhausted(
                f"model {info.name!r} has nv = {model.nv}; this server allows at most "
                f"{services.limits.max_state_dimension} (--max-state-dimension)"
            )
        if plan.scenario is None:
            chosen, scenario_reason = default_scenario(model)
            plan = dataclasses.replace(plan, scenario=chosen.value)
            scenario_reason = f"open.scenario unset: {scenario_reason}"
        else:
            scenario_reason = f"open.scenario asked for SCENARIO_{plan.scenario}"
        scenario = str(plan.scenario)
        model_defaults = info.defaults.get(scenario, {})
        config = resolve_config(
            model=model,
            scenario=scenario,
            dt=plan.dt,
            requested=plan.estimator_request,
            model_defaults=model_defaults,
            preset=plan.preset,
            measured=plan.measured,
        )
        # REALTIME: admitted (or refused) before anything is built for the session, from a price
        # measured once per model and settings, so that a burst of opens past capacity costs the
        # sessions already running next to nothing.
        ticket: Ticket | None = None
        if plan.clock == "REALTIME":
            price = self._tick_price(info, model, config, cycle=False)
            self._limits.check_tick_cost(
                price.cost,
                dt=plan.dt,
                state_dimension=price.state_dimension,
                nsigma=price.nsigma,
                steps=plan.steps_per_tick,
            )
            try:
                cycle = self._tick_price(info, model, config, cycle=True).cycle
                if cycle is None:  # pragma: no cover - measured just above
                    raise RuntimeError("the filter cycle was not measured")
                ticket = services.admission.admit(
                    cost_per_tick=cycle + services.admission.overhead,
                    filter_seconds=cycle,
                    grace=plan.grace,
                    dt=plan.dt,
                    what=f"{info.name} ({scenario.lower()}) at {1 / plan.dt:g} Hz",
                )
            except ResourceExhausted:
                metrics().refusals.labels(metrics().process).inc()
                raise
            finally:
                metrics().load.labels(metrics().process).set(services.admission.load())
        try:
            estimator = make_estimator(model, config, pool=services.pool)
            self._limits.check_history(
                history=plan.history,
                snapshot_bytes=snapshot_bytes(estimator.snapshot()),
                state_dimension=estimator.state_dimension,
            )
        except BaseException:
            if ticket is not None:
                ticket.release()
            raise
        try:
            return self._build_stream(
                request, tenant, info, model, plan, config, estimator, ticket, scenario_reason
            )
        except BaseException:
            if ticket is not None:
                ticket.release()
            raise

    def _build_stream(
        self,
        request: dynamics_pb2.OpenSession,
        tenant: str,
        info: ModelInfo,
        model: mujoco.MjModel,
        plan: SessionPlan,
        config: EstimatorConfig,
        estimator: Estimator,
        ticket: Ticket | None,
        scenario_reason: str,
    ) -> tuple[_Stream, dynamics_pb2.SessionOpened]:
        services = self._services
        scenario = str(plan.scenario)
        model_defaults = info.defaults.get(scenario, {})
        settings = {k: v for k, v in dataclasses.asdict(config).items() if k in SETTING_FIELDS}
        settings["preset"] = plan.preset
        if "noise_model" in plan.estimator_request:
            noise_reason = f"open.estimator.noise_model asked for NOISE_MODEL_{config.noise_model}"
        elif "noise_model" in model_defaults:
            noise_reason = (
                f"the model's defaults for SCENARIO_{scenario} set NOISE_MODEL_{config.noise_model}"
            )
        else:
            noise_reason = f"PRESET_{plan.preset}'s default for SCENARIO_{scenario}"
        kept = services.anonymiser.check_attributes(plan.subject_attributes)
        pseudonym = services.anonymiser.pseudonym(plan.subject_id, tenant=tenant)
        session_id = str(uuid.uuid4())
        header = SessionHeader(
            session_id=session_id,
            tenant=tenant,
            model_id=info.id,
            model_name=info.name,
            model_version=info.version,
            joint_names=tuple(j.name for j in info.joints),
            dof_names=_dof_names(model, info),
            nq=model.nq,
            nv=model.nv,
            nu=model.nu,
            nsensordata=model.nsensordata,
            timestep=info.timestep,
            dt=plan.dt,
            scenario=scenario,
            clock=plan.clock,
            estimator=settings,
            subject_pseudonym=pseudonym,
            subject_attributes=kept,
            started_at=datetime.now(UTC),
            joint_types=tuple(j.type for j in info.joints),
            actuator_names=tuple(a.name for a in info.actuators),
        )
        recorder = SessionRecorder(
            data_root=services.data_root, index=services.index, header=header, committer=services.committer
        )
        try:
            return self._start(
                plan,
                model,
                info,
                estimator,
                recorder,
                settings,
                pseudonym,
                ticket=ticket,
                scenario_reason=scenario_reason,
                noise_reason=noise_reason,
            )
        except BaseException:
            recorder.discard()
            raise

    def _start(
        self,
        plan: SessionPlan,
        model: mujoco.MjModel,
        info: ModelInfo,
        estimator: Estimator,
        recorder: SessionRecorder,
        settings: dict[str, object],
        pseudonym: str,
        *,
        ticket: Ticket | None,
        scenario_reason: str,
        noise_reason: str,
    ) -> tuple[_Stream, dynamics_pb2.SessionOpened]:
        services = self._services
        session_id = recorder.header.session_id
        scenario = str(plan.scenario)
        runtime = SessionRuntime(
            model=model,
            estimator=estimator,
            dynamics=Dynamics(model, outputs=plan.outputs),
            dt=plan.dt,
            scenario=scenario,
            history=plan.history,
            max_history_bytes=self._limits.max_history_bytes,
        )
        sizes = {
            "qpos": model.nq,
            "qvel": model.nv,
            "qacc": model.nv,
            "ctrl": model.nu,
            "sensordata": model.nsensordata,
        }
        stream = _Stream(
            services=services,
            plan=plan,
            runtime=runtime,
            recorder=recorder,
            sizes=sizes,
            clock=MonotonicClock(),
            ticket=ticket,
        )
        opened = dynamics_pb2.SessionOpened(
            session_id=session_id,
            model=model_message(info),
            estimator=settings_message(settings),
            state_dimension=estimator.state_dimension,
            measured=[common_pb2.Channel.Value("CHANNEL_" + c.upper()) for c in sorted(plan.measured)],
            outputs=[common_pb2.Output.Value("OUTPUT_" + o) for o in sorted(plan.outputs)],
            grace=plan.grace,
            history=plan.history,
            subject_pseudonym=pseudonym,
            dt=plan.dt,
            steps_per_tick=plan.steps_per_tick,
            scenario=common_pb2.Scenario.Value("SCENARIO_" + scenario),
            scenario_reason=scenario_reason,
            noise_reason=noise_reason,
        )
        return stream, opened

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
                for response in await asyncio.to_thread(stream.on_frame, request.frame, arrived):
                    await context.write(response)
            elif kind == "skip":
                await context.write(await asyncio.to_thread(stream.on_skip, request.skip.seq, arrived))
            elif kind == "sync":
                await context.write(self._pong(stream, request.sync, arrived))
            elif kind == "close":
                await context.write(await self._close(stream))
                return
            else:
                raise InvalidArgument(_unexpected(kind))

    async def _realtime(
        self,
        stream: _Stream,
        requests: AsyncIterator[dynamics_pb2.StreamSessionRequest],
        context: _Context,
    ) -> None:
        write_lock = asyncio.Lock()

        async def write(response: Response) -> None:
            async with write_lock:
                await context.write(response)

        # REALTIME runs on the event loop itself: a tick's work (a few hundred microseconds for most
        # models) costs less than the two thread hand-offs per tick it replaced (profiled: the
        # executor's wake-ups and GIL hand-overs were a third of a tick's CPU), and one loop per
        # process (`jitdyn serve --processes`) keeps every deadline in one queue, earliest first.
        # Deadlines wake the loop through a timerfd: asyncio's own timers are whole milliseconds
        # late, a 500 Hz session's whole grace (server/runtime/alarm.py).
        # One wake-up per session, moved as frames answer its ticks: the clock task wakes only for a
        # deadline that finds its frame missing (or a frame that came early), not once a tick to
        # find the tick answered already (a loop wake-up, 52 us of CPU, on every tick).
        wakeup = Alarm.of(asyncio.get_running_loop()).wakeup()
        dt = stream.plan.dt

        def due() -> float:
            # A tick whose frame is here waits only for its own time; one without, for its deadline.
            seq = stream.runtime.next_tick
            at = stream.sync.to_server(seq * dt) if seq in stream.pending else stream.deadline(seq)
            return stream.clock.to_monotonic(at)

        async def ticker() -> None:
            while True:
                await wakeup.until(due())
                if stream.closed:
                    return
                stream.catch_up()
                seq = stream.runtime.next_tick
                if seq in stream.pending:
                    responses = stream.answer_ready()
                elif stream.clock.now() >= stream.deadline(seq):
                    responses = stream.on_deadline(stream.deadline(seq))
                else:
                    continue  # a clock probe moved the deadline later
                for response in responses:
                    await write(response)

        tick_task = asyncio.create_task(ticker())
        try:
            async for request in self._until_idle(requests):
                if tick_task.done():
                    tick_task.result()  # surfaces a failure of the clock
                arrived = stream.clock.now()
                kind = request.WhichOneof("payload")
                if kind == "frame":
                    for response in stream.on_frame(request.frame, arrived):
                        await write(response)
                elif kind == "skip":
                    await write(stream.on_skip(request.skip.seq, arrived))
                elif kind == "sync":
                    await write(self._pong(stream, request.sync, arrived))  # may move the deadline
                elif kind == "close":
                    tick_task.cancel()
                    for response in stream.drain():
                        await write(response)
                    await write(await self._close(stream))
                    return
                else:
                    raise InvalidArgument(_unexpected(kind))
                wakeup.move(due())
        finally:
            tick_task.cancel()
            # The clock's own end (cancelled, or failed while the stream ends) is not news here.
            await asyncio.gather(tick_task, return_exceptions=True)

    async def _until_idle(
        self, requests: AsyncIterator[dynamics_pb2.StreamSessionRequest]
    ) -> AsyncIterator[dynamics_pb2.StreamSessionRequest]:
        """The requests, until the client sends nothing for the idle timeout (IdleTimeout)."""
        iterator = aiter(requests)
        while True:
            try:
                # asyncio.timeout, not wait_for: in Python 3.11 wait_for wraps every read in a new
                # task, and this runs once per frame of every session.
                async with asyncio.timeout(self._limits.idle_timeout):
                    request = await anext(iterator)
            except StopAsyncIteration:
                return
            except TimeoutError:
                raise self._limits.idle() from None
            yield request

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
        if stream.plan.clock == "REALTIME":
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
        summary, location = await self._finish(stream, "COMPLETE")
        return Response(closed=dynamics_pb2.SessionClosed(summary=summary_to_pb(summary, location=location)))

    async def _finish_quietly(self, stream: _Stream, status: str) -> None:
        """End a session that is ending anyway; a store that fails now keeps its log, which the
        next start recovers, so the failure is logged rather than raised over the first error."""
        try:
            await self._finish(stream, status)
        except Exception:  # noqa: BLE001 (any failure: logged with its traceback, as the docstring says)
            _log.exception(
                "session %s could not be closed; its log is recovered at the next start",
                stream.recorder.header.session_id,
            )

    async def _finish(self, stream: _Stream, status: str) -> tuple[SessionSummaryInfo, str]:
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
            location = await asyncio.to_thread(stream.recorder.close, summary, status=status)
        except STORAGE_ERRORS as error:
            raise storage_failure(
                f"session {stream.recorder.header.session_id} could not be stored", error
            ) from None
        finally:
            self._services.release(stream.recorder.header.tenant)
            metrics().open_sessions.labels(metrics().process).dec()
            if stream.ticket is not None:
                stream.ticket.release()
                metrics().load.labels(metrics().process).set(self._services.admission.load())
        return summary, location


def _unexpected(kind: str | None) -> str:
    if kind == "open":
        return "open must be sent once, as the first message; got a second `open`"
    return f"a request must carry one of open, frame, skip, sync, close; got {kind or 'nothing'}"


def _dof_names(model: mujoco.MjModel, info: ModelInfo) -> tuple[str, ...]:
    """One name per degree of freedom: the joint's name, suffixed for multi-dof joints."""
    names: list[str] = []
    for joint in info.joints:
        ndof = {"free": 6, "ball": 3}.get(joint.type, 1)
        names.extend([joint.name] if ndof == 1 else [f"{joint.name}_{i}" for i in range(ndof)])
    if len(names) != model.nv:
        names = [f"dof{i}" for i in range(model.nv)]
    return tuple(names)
