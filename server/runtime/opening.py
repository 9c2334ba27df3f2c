"""Opening a session: the model and the estimator resolved, the reasons for the choices written, the
subject anonymised, the stored header begun, a REALTIME session priced and admitted.

    opener = SessionOpener(services, limits=StreamLimits())
    opened = opener.open_session(request)        # blocking: run it off the event loop
    ...
    opened.discard()                               # an open its client left before it was used

Errors are the project's (jitdyn.errors): InvalidArgument for a bad request, NotFound for a model
that does not exist, ResourceExhausted for a session the server cannot carry; for a resume
(`request.resume`), PermissionDenied for a token that is forged, altered, expired, another tenant's
or stale (server/runtime/resume.py), NotFound for a session that is not open, FailedPrecondition
where the server shares no index with other replicas.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any, Final

import mujoco

from jitdyn.errors import FailedPrecondition, InvalidArgument, ResourceExhausted
from jitdyn.estimator_settings import SETTINGS
from jitdyn.registry import ModelInfo
from jitdyn.roles import joint_roles
from jitdyn.server.estimation.config import EstimatorConfig, default_scenario, resolve_config
from jitdyn.server.estimation.dynamics import Dynamics
from jitdyn.server.estimation.factory import make_estimator, measure_cycle
from jitdyn.server.estimation.interface import Estimator
from jitdyn.server.estimation.prior import prior_without
from jitdyn.server.runtime.admission import Ticket
from jitdyn.server.runtime.choice import CostTable, ModelCosts
from jitdyn.server.runtime.costs import snapshot_bytes, tick_cost
from jitdyn.server.runtime.limits import DEFAULT_STREAM_LIMITS, StreamLimits
from jitdyn.server.runtime.plan import OpenRequest, SessionPlan, plan_session
from jitdyn.server.runtime.resume import ResumeTokens
from jitdyn.server.runtime.services import Services
from jitdyn.server.runtime.session import SessionRuntime
from jitdyn.storage.failures import STORAGE_ERRORS, storage_failure
from jitdyn.storage.parquet import header_from_json
from jitdyn.storage.recorder import SessionRecorder
from jitdyn.storage.records import SessionHeader
from jitdyn.storage.shared import TakenOver
from jitdyn.vocabulary import Clock, EstimatorChoice, JointType, Preset, Scenario

__all__ = ["OpenedSession", "Rehearsal", "SessionOpener", "TickPrice", "Unrehearsed"]


class Unrehearsed(Exception):
    """A REALTIME open whose fit hangs on what a tick costs this process around its filter, not yet
    measured for such a session: the servicer rehearses it (server/transport/rehearsal.py), tells
    the opener what it measured (`SessionOpener.rehearsed`) and opens again."""

    def __init__(self, key: tuple[object, ...], model: mujoco.MjModel, name: str) -> None:
        super().__init__("this open waits for a rehearsal of its ticks")
        self.key = key
        self.model = model  # what the rehearsal's frames are of
        self.name = name  # the model's name, for the log


@dataclass(frozen=True, slots=True)
class Rehearsal:
    """What a rehearsal of a REALTIME session measured: this process's CPU per tick of it, alone,
    at its rate, the filter included; and how long it ran."""

    cost: float  # s of process CPU per tick
    ticks: int
    seconds: float  # s of wall time
    measured: int  # ticks answered MEASURED by their deadlines (the filter run, not shed)

    @property
    def on_time(self) -> float:
        """The share of its ticks answered MEASURED by their deadlines."""
        return self.measured / self.ticks if self.ticks else 0.0


# The share of a rehearsal's ticks that must be answered MEASURED by their deadlines for such a
# session to be admitted: what an admitted session is promised (at least 99 %).
ON_TIME: Final = 0.99
# How long a rehearsal stands for the sessions of its kind: the machine's load and the process's
# code around the filter change; a minute of opens at most is priced from it.
_REHEARSAL_AGE: Final = 60.0  # s


@dataclass(frozen=True, slots=True)
class TickPrice:
    """What one REALTIME tick of a model and its settings costs in this process."""

    cost: float  # s: the physics and linear algebra, priced (the --max-tick-share check)
    cycle: float | None  # s: one predict + update, measured once the price alone admits it
    nsigma: int
    state_dimension: int


@dataclass(frozen=True, slots=True)
class _DoorPrice:
    """A REALTIME open's price, remembered for the door: the next identical open is refused from it,
    without its model, while the process has no room for it."""

    filter_seconds: float  # s: the measured predict + update
    what: str  # the session as admission names it ("pendulum_3 (passive) at 20 Hz")
    at: float  # monotonic s when it was priced
    rehearsed: Rehearsal | None = None  # what a rehearsal of such a session measured


# How long a remembered price stands for its request: a name's newest version may change (a new
# registration on any replica), so the door believes it one admission window, then the slow path
# looks the model up again (once per request and window: ~3 ms against ~2 ms per refusal saved).
_DOOR_PRICE_AGE: Final = 2.0  # s
_DOOR_PRICES: Final = 256  # requests remembered; the oldest are forgotten first


def _door_key(request: OpenRequest) -> tuple[object, ...] | None:
    """What prices an open (its model, settings, rate and channels, not its subject), or None for
    an inline model, whose registration is itself the open's work."""
    choice = request.model
    if choice.inline is not None:
        return None
    return (
        request.tenant,
        choice.model_id,
        choice.name,
        choice.version,
        request.scenario,
        request.dt,
        request.measured,
        request.outputs,
        request.horizon,
        request.history,
        tuple(sorted(request.estimator.items())),
    )


@dataclass(frozen=True, kw_only=True)
class OpenedSession:
    """A session ready to run: what the stream needs, and what `opened` tells the client."""

    plan: SessionPlan  # its scenario resolved
    scenario: Scenario
    info: ModelInfo
    runtime: SessionRuntime
    recorder: SessionRecorder
    ticket: Ticket | None  # REALTIME: this session's share of the process's tick budget
    sizes: dict[str, int]  # each frame field's length for this model (transport/frame_check.py)
    settings: dict[str, object]  # the estimator settings in force, preset included
    state_dimension: int
    pseudonym: str
    scenario_reason: str  # why this scenario
    noise_reason: str  # why this noise model
    estimator_choice: EstimatorChoice  # how the estimator and its sigma points were chosen
    estimator_reason: str  # and why, in words
    costs: CostTable | None = None  # the model's stored estimator costs (None: not measured)
    tokens: ResumeTokens | None = None  # a shared tier's: what issues this session's resume tokens
    resume_token: str = field(default="", repr=False)  # "" without a shared tier; never logged
    resume_from_seq: int | None = None  # a resumed session: the first tick this stream answers
    resume_reason: str = ""  # a resumed session: how its estimator continues
    elapsed: float = 0.0  # s since the session first opened (a resumed session's clock goes on)

    @property
    def session_id(self) -> str:
        return self.recorder.header.session_id

    def fresh_token(self) -> str:
        """A new resume token of this session under its current lease epoch, expiring the tokens'
        ttl from now ("" without a shared tier)."""
        return _resume_token(self.tokens, self.recorder)

    def discard(self) -> None:
        """Undo the open (its share of the budget, its log and index row). Blocking."""
        if self.ticket is not None:
            self.ticket.release()
        self.recorder.discard()


@dataclass(frozen=True, kw_only=True)
class _Resolved:
    """An open between its checks and its start: the model, the plan and the estimator."""

    tenant: str
    info: ModelInfo
    model: mujoco.MjModel
    plan: SessionPlan
    scenario: Scenario
    scenario_reason: str
    config: EstimatorConfig
    estimator: Estimator
    ticket: Ticket | None
    taken: TakenOver | None  # a resumed session, held under a new epoch
    choice: _Choice


@dataclass(frozen=True, kw_only=True)
class _Choice:
    """How an open's estimator was chosen: the settings the choice adds to the request's, and why."""

    how: EstimatorChoice
    reason: str
    settings: dict[str, object] = field(default_factory=dict)
    costs: CostTable | None = None


# The settings that name the estimator: set by the open or the model's defaults, they are the
# choice; otherwise a REALTIME session's is made by cost (server/runtime/choice.py).
_CHOSEN_SETTINGS: Final = ("estimator", "sigma_points")


class SessionOpener:
    """Opens the sessions of one server. `on_admission(refused)` is told of every REALTIME
    admission decision (the transport counts them for its metrics)."""

    def __init__(
        self,
        services: Services,
        *,
        limits: StreamLimits = DEFAULT_STREAM_LIMITS,
        on_admission: Callable[[bool], None] | None = None,
    ) -> None:
        self._services = services
        self._limits = limits
        self._on_admission = on_admission
        # What a tick of (model, settings) costs here, measured at its first REALTIME open and
        # reused: every open of a hundred sessions of one model would otherwise time its own
        # throwaway filter while the others' ticks wait.
        self._prices: dict[tuple[str, EstimatorConfig], TickPrice] = {}
        self._prices_lock = threading.Lock()
        # What rehearsals measured, by model, settings and what the session asks of each tick (None:
        # tried, and it did not run), and when.
        self._rehearsals: dict[tuple[object, ...], tuple[Rehearsal | None, float]] = {}
        # Whether the transport rehearses the opens that raise Unrehearsed (it sets this).
        self.rehearsals = False
        # The door's memory: what the last opens cost, by request (insertion-ordered, oldest first).
        self._door_prices: dict[tuple[object, ...], _DoorPrice] = {}
        self._door_lock = threading.Lock()  # never held for more than a lookup or an insert
        self._costs = ModelCosts(
            services.registry,
            engine=services.engine,
            share=limits.max_tick_share,
            max_nv=services.limits.max_state_dimension,
            measured=services.admission.start_window,
        )

    @property
    def limits(self) -> StreamLimits:
        return self._limits

    def check_door(self, request: OpenRequest) -> None:
        """ResourceExhausted, saying why, when `request` opens a new REALTIME session and the process
        admits none now whatever it costs (Admission.full), or none of the price an identical open
        had a moment ago (Admission.refusal). Cheap and non-blocking: asked on the event loop
        before the open queues for the slow steps' thread, so that the surplus of a burst of opens
        is refused without looking up, loading and pricing its model."""
        if request.clock != Clock.REALTIME or request.resume is not None:
            return
        if not (math.isfinite(request.dt) and request.dt > 0):
            return  # refused as invalid on the slow path, which says why
        choice = request.model
        named = choice.name or choice.model_id or (choice.inline.name if choice.inline else "") or "a model"
        admission = self._services.admission
        admission.observe_open()
        reason = admission.full(f"{named} at {1 / request.dt:g} Hz")
        known = None if reason is not None else self._door_price(request)
        if known is not None:
            rehearsed = known.rehearsed
            reason = admission.refusal(
                cost_per_tick=known.filter_seconds + admission.overhead
                if rehearsed is None
                else max(known.filter_seconds, rehearsed.cost),
                filter_seconds=known.filter_seconds,
                dt=request.dt,
                what=known.what,
                priced_by=None if rehearsed is None else _rehearsed_words(rehearsed),
            )
        if reason is not None:
            if self._on_admission is not None:
                self._on_admission(True)
            raise ResourceExhausted(reason)

    def _door_price(self, request: OpenRequest) -> _DoorPrice | None:
        key = _door_key(request)
        if key is None:
            return None
        with self._door_lock:
            known = self._door_prices.get(key)
        if known is None or time.monotonic() - known.at > _DOOR_PRICE_AGE:
            return None
        return known

    def _remember_price(
        self, request: OpenRequest, filter_seconds: float, what: str, rehearsed: Rehearsal | None
    ) -> None:
        key = _door_key(request)
        if key is None:
            return
        with self._door_lock:
            self._door_prices.pop(key, None)
            self._door_prices[key] = _DoorPrice(filter_seconds, what, time.monotonic(), rehearsed)
            while len(self._door_prices) > _DOOR_PRICES:
                del self._door_prices[next(iter(self._door_prices))]

    def open_session(self, request: OpenRequest, *, rehearsal: bool = False) -> OpenedSession:
        """Open `request`'s session, or continue the one it resumes. Blocking (the model, the
        estimator, the log's first write). Unrehearsed when its admission waits for a rehearsal;
        `rehearsal`: open it as that rehearsal, admitted by no one, to be discarded."""
        try:
            if rehearsal:
                return self._open(dataclasses.replace(request, resume=None), None, rehearsal=True)
            return self._open_or_resume(request)
        except STORAGE_ERRORS as error:
            # The registry or the index (the shared tier's database) did not answer.
            raise storage_failure("the session could not be opened", error) from None

    def _open_or_resume(self, request: OpenRequest) -> OpenedSession:
        if request.resume is None:
            return self._open(request, None)
        taken = self._take_over(request)
        try:
            return self._open(request, taken)
        except BaseException:
            shared = self._services.shared
            if shared is not None:
                # Left for another resume (or, nobody resuming it, for a live replica to store).
                shared.park(taken.lease, ended_as=taken.ended_as)
            raise

    def _take_over(self, request: OpenRequest) -> TakenOver:
        """The session `request` resumes, held by this server from now on. A resume always takes
        the session over, even from a live holder: a client presenting the token says its stream
        is gone, and the holder, fenced by the new epoch, can write nothing more to it."""
        resume, shared = request.resume, self._services.shared
        assert resume is not None
        if shared is None:
            raise FailedPrecondition(
                "open.resume: this server cannot resume sessions: it shares no index with other "
                "replicas (serve with --index postgresql+psycopg://...)"
            )
        epoch = self._services.resume_tokens.check(
            resume.token, session_id=resume.session_id, tenant=request.tenant
        )
        return shared.take_over(resume.session_id, tenant=request.tenant, token_epoch=epoch)

    def _open(
        self, request: OpenRequest, taken: TakenOver | None, *, rehearsal: bool = False
    ) -> OpenedSession:
        info, model = self._model(request)
        plan = plan_session(request, timestep=info.timestep)
        limit = self._services.limits.max_state_dimension
        if model.nv > limit:
            raise ResourceExhausted(
                f"model {info.name!r} has nv = {model.nv}; this server allows at most {limit} "
                "(--max-state-dimension)"
            )
        scenario, scenario_reason = _scenario(plan, model)
        plan = dataclasses.replace(plan, scenario=scenario)
        choice = self._choose(info, model, plan, scenario)
        config = resolve_config(
            model=model,
            scenario=scenario,
            dt=plan.dt,
            requested={**choice.settings, **plan.estimator_request},
            model_defaults=info.defaults.get(scenario, {}),
            preset=plan.preset,
            measured=plan.measured,
            engine=self._services.engine,
        )
        config = dataclasses.replace(
            config, roles=joint_roles(info.joints, info.tags), prior_without=prior_without(info.tags)
        )
        # REALTIME: admitted (or refused) before anything is built for the session, from a price
        # measured once per model and settings, so that a burst of opens past capacity costs the
        # sessions already running next to nothing.
        ticket = (
            self._admit(request, info, model, config, plan, resumed=taken is not None)
            if plan.clock == Clock.REALTIME and not rehearsal
            else None
        )
        try:
            estimator = make_estimator(model, config, pool=self._services.pool)
            self._limits.check_history(
                history=plan.history,
                snapshot_bytes=snapshot_bytes(estimator.snapshot()),
                state_dimension=estimator.state_dimension,
            )
            resolved = _Resolved(
                tenant=request.tenant,
                info=info,
                model=model,
                plan=plan,
                scenario=scenario,
                scenario_reason=scenario_reason,
                config=config,
                estimator=estimator,
                ticket=ticket,
                taken=taken,
                choice=choice,
            )
            return self._start(resolved)
        except BaseException:
            if ticket is not None:
                ticket.release()
            raise

    def _choose(
        self, info: ModelInfo, model: mujoco.MjModel, plan: SessionPlan, scenario: Scenario
    ) -> _Choice:
        """How the session's estimator is chosen: asked for, by the model's defaults, by the
        preset (LOCKSTEP, THESIS, --estimator-choice preset), or by the model's stored cost
        (ResourceExhausted when no candidate fits the tick). Only an open the cost chooses for
        measures a model that has no costs stored; the others show what is stored."""
        costs = self._costs.stored([info]).get(info.id)
        asked = [name for name in _CHOSEN_SETTINGS if name in plan.estimator_request]
        if asked:
            return _Choice(
                how=EstimatorChoice.ASKED,
                reason=f"asked for: open.estimator sets {' and '.join(asked)}",
                costs=costs,
            )
        defaults = info.defaults.get(scenario, {})
        named = [name for name in _CHOSEN_SETTINGS if name in defaults]
        if named:
            return _Choice(
                how=EstimatorChoice.MODEL_DEFAULTS,
                reason=f"the model's defaults for SCENARIO_{scenario.name} set {' and '.join(named)}",
                costs=costs,
            )
        why = _preset_reason(plan, by_cost=self._services.choose_by_cost)
        if why:
            return _Choice(how=EstimatorChoice.PRESET, reason=f"the preset's: {why}", costs=costs)
        costs = self._costs.table(info, model)
        if not costs.of(scenario):
            return _Choice(
                how=EstimatorChoice.PRESET,
                reason=f"the preset's: no cost was measured for SCENARIO_{scenario.name} on this model",
                costs=costs,
            )
        chosen = costs.choose(scenario, plan.dt)
        return _Choice(
            how=EstimatorChoice.BY_COST, reason=chosen.reason, settings=dict(chosen.settings), costs=costs
        )

    def _model(self, request: OpenRequest) -> tuple[ModelInfo, mujoco.MjModel]:
        """The model `request` names (registered first when sent inline) and its compiled copy."""
        registry, tenant, choice = self._services.registry, request.tenant, request.model
        if choice.inline is not None:
            inline = choice.inline
            info, _ = registry.register(
                name=inline.name,
                mjcf=inline.mjcf,
                assets=dict(inline.assets),
                metadata=inline.metadata,
                tenant=tenant,
            )
        elif choice.model_id:
            info = registry.get(tenant=tenant, model_id=choice.model_id)
        else:
            info = registry.get(tenant=tenant, name=choice.name, version=choice.version)
        return info, registry.load(info.id, tenant=tenant)

    def tick_price(
        self, info: ModelInfo, model: mujoco.MjModel, config: EstimatorConfig, *, cycle: bool
    ) -> TickPrice:
        """What a tick of `config` costs on this model, priced at its first REALTIME open in this
        process (on a throwaway estimator) and reused; `cycle`: also time one predict + update,
        once (a session that the price alone refuses never costs the others that)."""
        key = (info.id, config)
        pool = self._services.pool
        with self._prices_lock:
            known = self._prices.get(key)
            if known is None:
                probe = make_estimator(model, config, pool=pool)
                nsigma = int(getattr(probe, "nsigma", 1))
                known = self._prices[key] = TickPrice(
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
                measured = measure_cycle(model, config, pool=pool)
                known = self._prices[key] = dataclasses.replace(known, cycle=measured)
            return known

    def rehearsed(self, key: tuple[object, ...], rehearsal: Rehearsal | None) -> None:
        """What the rehearsal of an open that raised Unrehearsed(key) measured (None: it did not
        run; such opens are then priced without one, until the rehearsal's age)."""
        with self._prices_lock:
            self._rehearsals[key] = (rehearsal, time.monotonic())

    def was_rehearsed(self, key: tuple[object, ...]) -> bool:
        """Whether an open of `key` was rehearsed lately (whether or not its rehearsal ran)."""
        return self._rehearsal(key)[0]

    def _rehearsal(self, key: tuple[object, ...]) -> tuple[bool, Rehearsal | None]:
        """Whether an open of `key` was rehearsed lately, and what its rehearsal measured."""
        with self._prices_lock:
            known = self._rehearsals.get(key)
        if known is None or time.monotonic() - known[1] > _REHEARSAL_AGE:
            return False, None
        return True, known[0]

    def _admit(
        self,
        request: OpenRequest,
        info: ModelInfo,
        model: mujoco.MjModel,
        config: EstimatorConfig,
        plan: SessionPlan,
        *,
        resumed: bool,
    ) -> Ticket:
        """A REALTIME session's ticket: its price checked against dt, then its measured cycle
        against what the process and the machine have left (a resumed session is admitted
        whatever the load: Admission.admit)."""
        price = self.tick_price(info, model, config, cycle=False)
        self._limits.check_tick_cost(
            price.cost,
            dt=plan.dt,
            state_dimension=price.state_dimension,
            nsigma=price.nsigma,
            steps=plan.steps_per_tick,
        )
        admission = self._services.admission
        refused, decided = False, True
        try:
            cycle = self.tick_price(info, model, config, cycle=True).cycle
            if cycle is None:  # pragma: no cover - measured just above
                raise RuntimeError("the filter cycle was not measured")
            what = f"{info.name} ({str(plan.scenario).lower()}) at {1 / plan.dt:g} Hz"
            key = _rehearsal_key(info, config, plan)
            tried, rehearsed = self._rehearsal(key)
            if not resumed:
                self._remember_price(request, cycle, what, rehearsed)
            if (
                not (tried or resumed)
                and self.rehearsals
                and admission.wants_rehearsal(filter_seconds=cycle, dt=plan.dt)
            ):
                raise Unrehearsed(key, model, info.name)
            if rehearsed is not None and not resumed and rehearsed.on_time < ON_TIME:
                admission.count_refusal()
                raise ResourceExhausted(_late_rehearsal(what, rehearsed, budget=admission.budget, dt=plan.dt))
            return admission.admit(
                cost_per_tick=cycle + admission.overhead if rehearsed is None else max(cycle, rehearsed.cost),
                filter_seconds=cycle,
                grace=plan.grace,
                dt=plan.dt,
                what=what,
                resumed=resumed,
                priced_by=None if rehearsed is None else _rehearsed_words(rehearsed),
            )
        except ResourceExhausted:
            refused = True
            raise
        except Unrehearsed:
            decided = False  # decided once rehearsed, when it opens again
            raise
        finally:
            if self._on_admission is not None and decided:
                self._on_admission(refused)

    def _start(self, resolved: _Resolved) -> OpenedSession:
        """Begin the stored session (its header, its log) and build its runtime."""
        services, plan, model = self._services, resolved.plan, resolved.model
        tokens = services.resume_tokens if services.shared is not None else None
        settings: dict[str, object] = {
            k: v for k, v in dataclasses.asdict(resolved.config).items() if k in SETTINGS
        }
        settings["preset"] = plan.preset
        attributes = services.anonymiser.check_attributes(plan.subject_attributes)
        pseudonym = services.anonymiser.pseudonym(plan.subject_id, tenant=resolved.tenant)
        taken = resolved.taken
        if taken is None:
            header = _header(resolved, settings=settings, pseudonym=pseudonym, attributes=attributes)
            first_tick = 0
        else:
            header, first_tick = _resumed_header(resolved, taken)
        recorder = SessionRecorder(
            data_root=services.data_root,
            index=services.index,
            header=header,
            committer=services.committer,
            shared=services.shared,
            resumed=taken,
            root=services.root,
        )
        try:
            runtime = SessionRuntime(
                model=model,
                estimator=resolved.estimator,
                dynamics=Dynamics(model, outputs=plan.outputs),
                dt=plan.dt,
                scenario=resolved.scenario,
                history=plan.history,
                max_history_bytes=self._limits.max_history_bytes,
                first_tick=first_tick,
                wait_for_late=plan.clock == Clock.REALTIME,  # docs/decisions/0007
            )
            return OpenedSession(
                plan=plan,
                scenario=resolved.scenario,
                info=resolved.info,
                runtime=runtime,
                recorder=recorder,
                ticket=resolved.ticket,
                sizes=_sizes(model),
                settings=settings,
                state_dimension=resolved.estimator.state_dimension,
                pseudonym=pseudonym,
                scenario_reason=resolved.scenario_reason,
                noise_reason=_noise_reason(resolved),
                **_chosen(resolved.choice),
                tokens=tokens,
                resume_token=_resume_token(tokens, recorder),
                resume_from_seq=None if taken is None else first_tick,
                resume_reason="" if taken is None else _resume_reason(first_tick, plan.clock),
                elapsed=0.0 if taken is None else (datetime.now(UTC) - header.started_at).total_seconds(),
            )
        except BaseException:
            recorder.discard()
            raise


def _rehearsal_key(info: ModelInfo, config: EstimatorConfig, plan: SessionPlan) -> tuple[object, ...]:
    """What a rehearsal measures a tick of: the model, the estimator, the rate and what each tick
    answers."""
    return (info.id, config, plan.dt, plan.measured, plan.outputs, plan.horizon)


def _late_rehearsal(what: str, rehearsal: Rehearsal, *, budget: float, dt: float) -> str:
    """Why a session whose rehearsal was not answered on time is refused."""
    fits = min(budget / rehearsal.cost, 0.8 / dt) if rehearsal.cost > 0 else 0.8 / dt
    return (
        f"a session of {what} was rehearsed alone on this server process: {rehearsal.measured} of its "
        f"{rehearsal.ticks} ticks were answered MEASURED by their deadlines ({100 * ON_TIME:g} % are "
        f"promised), at {1e6 * rehearsal.cost:.0f} us of the process's CPU a tick: its answers could not "
        f"be on time. A rate of at most {fits:.0f} Hz may fit here. Try again later, on another server, "
        "or at a lower rate"
    )


def _rehearsed_words(rehearsal: Rehearsal) -> str:
    """Where a rehearsed price comes from, for a refusal."""
    return (
        f"rehearsed: this process ran {rehearsal.ticks} ticks of such a session alone over "
        f"{rehearsal.seconds:.2f} s and measured its CPU"
    )


def _preset_reason(plan: SessionPlan, *, by_cost: bool) -> str:
    """Why a session that names no estimator gets the preset's, or "" when its cost chooses."""
    if plan.preset != Preset.JITDYN:
        return f"PRESET_{plan.preset.name} runs its own filter"
    if plan.clock != Clock.REALTIME:
        return f"CLOCK_{plan.clock.name} has no tick to fit"
    if not by_cost:
        return "this server runs --estimator-choice preset"
    return ""


def _chosen(choice: _Choice) -> dict[str, Any]:
    """What `opened` says of the estimator's choice (OpenedSession's fields)."""
    return {"estimator_choice": choice.how, "estimator_reason": choice.reason, "costs": choice.costs}


def _resume_token(tokens: ResumeTokens | None, recorder: SessionRecorder) -> str:
    """A resume token of `recorder`'s session under the epoch it holds it by; "" without a shared tier."""
    epoch = recorder.epoch
    if tokens is None or epoch is None:
        return ""
    return tokens.issue(recorder.header.session_id, tenant=recorder.header.tenant, epoch=epoch)


def _resume_reason(first_tick: int, clock: Clock) -> str:
    """What a resumed session's client is told in `resume_reason`."""
    stored = f"ticks 0-{first_tick - 1} are stored" if first_tick > 0 else "no tick of it was stored yet"
    replay = (
        "; the ticks that passed while it moved are answered late from the frames re-sent for them"
        if clock == Clock.REALTIME
        else ""
    )
    return f"{stored}; the estimator restarts from the frame of tick {first_tick}{replay}"


def _resumed_header(resolved: _Resolved, taken: TakenOver) -> tuple[SessionHeader, int]:
    """The stored header of a session taken over for a resume, and its first tick to come."""
    header = header_from_json(taken.header_json)
    if header.model_id != resolved.info.id:
        raise InvalidArgument(
            f"open.resume: session {header.session_id} runs model {header.model_id}, the open "
            f"names {resolved.info.id}; resume with the open the session was opened with"
        )
    return header, 0 if taken.durable_seq is None else taken.durable_seq + 1


def _scenario(plan: SessionPlan, model: mujoco.MjModel) -> tuple[Scenario, str]:
    """The session's scenario and why: the client's, or the one the model calls for."""
    if plan.scenario is not None:
        return plan.scenario, f"open.scenario asked for SCENARIO_{plan.scenario.name}"
    chosen, reason = default_scenario(model)
    return Scenario(chosen), f"open.scenario unset: {reason}"


def _noise_reason(resolved: _Resolved) -> str:
    """Why the session's noise model is what it is: asked for, the model's default, or the preset's."""
    noise_model = str(resolved.config.noise_model)
    if "noise_model" in resolved.plan.estimator_request:
        return f"open.estimator.noise_model asked for NOISE_MODEL_{noise_model}"
    if "noise_model" in resolved.info.defaults.get(resolved.scenario, {}):
        return f"the model's defaults for SCENARIO_{resolved.scenario.name} set NOISE_MODEL_{noise_model}"
    return f"PRESET_{resolved.plan.preset.name}'s default for SCENARIO_{resolved.scenario.name}"


def _header(
    resolved: _Resolved, *, settings: dict[str, object], pseudonym: str, attributes: dict[str, str]
) -> SessionHeader:
    """The stored session's header: which model, which settings, whose (pseudonymous) motion."""
    info, model, plan = resolved.info, resolved.model, resolved.plan
    return SessionHeader(
        session_id=str(uuid.uuid4()),
        tenant=resolved.tenant,
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
        scenario=resolved.scenario,
        clock=plan.clock,
        estimator=settings,
        subject_pseudonym=pseudonym,
        subject_attributes=attributes,
        started_at=datetime.now(UTC),
        joint_types=tuple(j.type for j in info.joints),
        actuator_names=tuple(a.name for a in info.actuators),
    )


def _sizes(model: mujoco.MjModel) -> dict[str, int]:
    """Each frame field's length for `model`."""
    return {
        "qpos": model.nq,
        "qvel": model.nv,
        "qacc": model.nv,
        "ctrl": model.nu,
        "sensordata": model.nsensordata,
    }


_DOFS = {JointType.FREE: 6, JointType.BALL: 3}


def _dof_names(model: mujoco.MjModel, info: ModelInfo) -> tuple[str, ...]:
    """One name per degree of freedom: the joint's name, suffixed for multi-dof joints."""
    names: list[str] = []
    for joint in info.joints:
        ndof = _DOFS.get(JointType(joint.type), 1)
        names.extend([joint.name] if ndof == 1 else [f"{joint.name}_{i}" for i in range(ndof)])
    if len(names) != model.nv:
        names = [f"dof{i}" for i in range(model.nv)]
    return tuple(names)
