"""Runs one research object through a real jitdyn session and records what the server answered
beside the truth::

    spec = RunSpec("pendulum_3", Scenario.PASSIVE, seconds=10, preset=Preset.THESIS)
    trace = run_lockstep(client, spec)             # every tick: truth, filter state, covariance, source
    trace.truth_state, trace.estimate, trace.covariance

LOCKSTEP runs are deterministic: the network is emulated in virtual time by client.netem, so the
server sees the same frames, skips and late frames in the same order every time.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from jitdyn.client import Client, FrameData, Rejection, SessionOptions, TickResult
from jitdyn.experiments.netem import PERFECT, NetworkProfile, Schedule, gap_schedule, lockstep_schedule
from jitdyn.experiments.objects import ResearchObject, TrueState, UnstableSimulation
from jitdyn.experiments.progress import progress_bar
from jitdyn.experiments.recorded import research_object
from jitdyn.registry.info import joint_types
from jitdyn.storage.records import dof_units
from jitdyn.vocabulary import Channel, Clock, EstimatorKind, Output, Preset, Scenario

__all__ = ["ModelCache", "RunSpec", "Trace", "estimate_of", "run_lockstep"]


@dataclass(frozen=True)
class RunSpec:
    """One session: an object in a scenario, an estimator, a network, a length."""

    object: str  # "pendulum_1".."pendulum_3", "biped", "myoelbow", "myohand"
    scenario: Scenario
    seconds: float
    estimator: EstimatorKind = EstimatorKind.UKF
    preset: Preset = Preset.JITDYN
    seed: int = 0
    network: NetworkProfile = PERFECT
    grace: float = 0.0  # s: a frame later than this after its tick is late (LOCKSTEP emulation)
    gaps: tuple[int, int] | None = None  # (gap ticks, period ticks): deterministic gaps instead of `network`
    gap_first: int | None = None  # the tick the first gap starts at (None: one period in)
    overrides: Mapping[str, Any] = field(default_factory=dict)  # estimator settings beyond the preset
    # The scenario the session is opened with: None, the object's; "" the server's choice (the
    # client names none); or a scenario (a wrong one, to test absorption).
    open_as: Scenario | Literal[""] | None = None
    noise: tuple[float, float] | None = None  # white sensor noise (q std, qd std), seeded by `seed`
    default_settings: bool = False  # send no estimator settings at all (every default of the server)

    @property
    def label(self) -> str:
        estimator: str = self.preset if self.estimator is EstimatorKind.UKF else self.estimator
        if self.default_settings:
            estimator = "defaults"
        extra = "".join(f",{k}={v}" for k, v in sorted(self.overrides.items()))
        opened = "" if self.open_as is None else f",opened {self.open_as or 'unset'}"
        noisy = "" if self.noise is None else ",noisy"
        return f"{self.object}/{self.scenario.value}/{estimator}{extra}{opened}{noisy}"


@dataclass(frozen=True)
class Trace:
    """What happened, tick by tick. T ticks, state dimension nx ([q, qd] or [q, qd, qdd])."""

    spec: RunSpec
    dt: float
    nq: int
    nv: int
    joint_names: tuple[str, ...]
    settings: Mapping[str, object]  # the estimator settings in force, as the server reported them
    measurement_dim: int  # components of the measurement (NIS degrees of freedom)
    t: np.ndarray  # (T,)
    truth_state: np.ndarray  # (T, nx) the true state in the filter's layout
    estimate: np.ndarray  # (T, nx) the filter state the server answered at the tick
    covariance: np.ndarray | None  # (T, nx, nx); None for the dead-reckoning estimators
    corrected: np.ndarray  # (T, nx) the filter state after late frames were applied
    ctrl: np.ndarray  # (T, nu) the control that acted over the interval ending at each tick
    source: tuple[str, ...]  # (T,) MEASURED | PREDICTED (answer at the tick)
    received: np.ndarray  # (T,) bool: the frame was there when the tick was answered
    nis: np.ndarray  # (T,) NaN where no measurement was used
    compute_us: np.ndarray  # (T,) server compute time of the tick's answer
    reinitialised: int  # ticks where the divergence guard re-initialised the filter
    rejected: int
    corrected_ticks: int
    wall_seconds: float
    adapted: int = 0  # ticks where the adaptive noise model said it changed R or Q
    absorbed: int = 0  # ticks where a NIS window far out made the filter widen its covariance
    opened_scenario: str = ""  # the scenario the server gave the session
    opened_reason: str = ""  # and why
    stopped: tuple[float, str] | None = (
        None  # (t, why) when the truth became unstable and the run ended early
    )
    dof_units: tuple[str, ...] = ()  # (nv,) "rad" or "m" (storage.records.dof_units); () unknown

    @property
    def nx(self) -> int:
        return int(self.estimate.shape[1])

    def component(self, which: str, *, corrected: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(truth, estimate) of one block: "q", "qd" or "qdd"; each (T, nv)."""
        blocks = {"q": 0, "qd": 1, "qdd": 2}
        if which not in blocks:
            raise ValueError(f"which must be one of {list(blocks)}, got {which!r}")
        start = blocks[which] * self.nv
        if start + self.nv > self.nx:
            raise ValueError(f"the state of this run has no {which!r} block (dimension {self.nx})")
        estimate = self.corrected if corrected else self.estimate
        return self.truth_state[:, start : start + self.nv], estimate[:, start : start + self.nv]


class ModelCache:
    """Registers MyoSuite models once per server; built-in models are opened by name."""

    def __init__(self, client: Client) -> None:
        self._client = client
        self._ids: dict[str, str] = {}

    def options(self, obj: ResearchObject) -> dict[str, Any]:
        source = obj.source
        if source.builtin:
            return {"model_name": source.name}
        if source.name not in self._ids:
            model, _ = self._client.register_model(
                name=source.name,
                mjcf=source.mjcf,
                assets=source.assets,
                description=f"MyoSuite {source.name}",
                tags=source.tags,
            )
            self._ids[source.name] = model.id
        return {"model_id": self._ids[source.name]}


def estimate_of(result: TickResult, nq: int, nv: int) -> tuple[np.ndarray, np.ndarray]:
    """The (qpos, qvel) a controller should use: the filter's state, else the answered state."""
    if result.filter_state.size >= nq + nv:
        return np.asarray(result.filter_state[:nq]), np.asarray(result.filter_state[nq : nq + nv])
    return np.asarray(result.qpos), np.asarray(result.qvel)


def _measured(scenario: Scenario) -> tuple[Channel, ...]:
    # The thesis' measurement vector is the whole state: [q, qd] or, controlled, [q, qd, qdd];
    # a controlled frame carries the control that acted too (not a measurement: an input).
    if scenario is Scenario.CONTROLLED:
        return (Channel.QPOS, Channel.QVEL, Channel.QACC, Channel.CTRL)
    return (Channel.QPOS, Channel.QVEL)


def _frame(
    seq: int, truth: TrueState, scenario: Scenario, noise: tuple[np.ndarray, np.ndarray] | None = None
) -> FrameData:
    controlled = scenario is Scenario.CONTROLLED
    qpos, qvel = truth.qpos, truth.qvel
    if noise is not None:
        qpos, qvel = qpos + noise[0], qvel + noise[1]
    return FrameData(
        seq=seq,
        t=truth.t,
        qpos=qpos,
        qvel=qvel,
        qacc=truth.qacc if controlled else None,
        ctrl=truth.ctrl if controlled else None,
    )


def _schedule(spec: RunSpec, ticks: int, dt: float) -> Schedule:
    if spec.gaps is not None:
        gap_ticks, period = spec.gaps
        return gap_schedule(ticks, dt=dt, gap_ticks=gap_ticks, period=period, first=spec.gap_first)
    return lockstep_schedule(ticks, dt=dt, profile=spec.network, seed=spec.seed, grace=spec.grace)


def run_lockstep(
    client: Client,
    spec: RunSpec,
    *,
    models: ModelCache | None = None,
    obj: ResearchObject | None = None,
    progress: bool = True,
) -> Trace:
    """Runs `spec` as one LOCKSTEP session and returns its trace.

    Tick k: the truth is at time k dt; the server gets frame k (or a skip, and later the late frame,
    as the schedule says); a CONTROLLED object then gets the control its law computes from the
    latest answer's filter state, held until tick k + 1, and frame k + 1 reports it.
    """
    obj = obj or research_object(spec.object, spec.scenario)
    models = models or ModelCache(client)
    dt = obj.dt
    ticks = max(2, round(spec.seconds / dt))
    schedule = _schedule(spec, ticks, dt)
    settings: dict[str, object] = (
        {}
        if spec.default_settings
        else {"estimator": spec.estimator, "preset": spec.preset, **spec.overrides}
    )
    opened_as = spec.scenario if spec.open_as is None else (spec.open_as or None)
    noise_rng = np.random.default_rng(spec.seed + 7919)
    options = SessionOptions(
        **models.options(obj),
        scenario=opened_as,
        dt=dt,
        clock=Clock.LOCKSTEP,
        estimator=settings,
        measured=_measured(
            opened_as if opened_as in (Scenario.PASSIVE, Scenario.CONTROLLED) else spec.scenario
        ),
        outputs=(Output.FILTER_STATE,),
        # Every late frame of the emulated network is applied: a history as long as the run. A run
        # of deterministic gaps has no late frames (they are lost), and a history as long as the
        # run would pass the server's memory limit on myoHand's 5000 ticks.
        history=min(10_000, ticks + 1) if spec.gaps is None else min(64, ticks + 1),
    )
    by_tick: dict[int, list[Any]] = {}
    for delivery in schedule.deliveries:
        by_tick.setdefault(delivery.tick, []).append(delivery)

    truths: list[TrueState] = [obj.reset(spec.seed)]
    # Sensor noise per tick, drawn once per tick whatever the schedule, so that every estimator
    # of a comparison sees the same noisy frames.
    noises: list[tuple[np.ndarray, np.ndarray]] = []
    if spec.noise is not None:
        for _ in range(ticks + 1):
            noises.append(
                (
                    spec.noise[0] * noise_rng.standard_normal(obj.nq),
                    spec.noise[1] * noise_rng.standard_normal(obj.nv),
                )
            )
    answers: dict[int, TickResult] = {}
    finals: dict[int, TickResult] = {}
    rejected = 0
    corrected = 0
    stopped: tuple[float, str] | None = None
    started = time.perf_counter()
    bar = progress_bar(total=ticks, desc=spec.label, unit="tick", enabled=progress)
    with client.open_session(options) as session:
        opened = session.opened
        nq, nv = obj.nq, obj.nv

        def deliver(kind: str, seq: int) -> TickResult | None:
            nonlocal rejected
            if kind == "skip":
                answer = session.skip(seq)
            else:
                answer = session.send_frame(
                    _frame(seq, truths[seq], spec.scenario, noises[seq] if noises else None)
                )
            if isinstance(answer, Rejection):
                rejected += 1
                return None
            return answer

        for j in range(ticks + 1):
            for d in by_tick.get(j, ()):
                if d.late_ticks > 0:
                    late = deliver("frame", d.seq)
                    if late is not None:
                        corrected += 1
                        finals[late.seq] = late
            if j == ticks:
                break
            kind = (
                "frame"
                if any(d.seq == j and d.late_ticks == 0 and d.kind == "frame" for d in by_tick[j])
                else "skip"
            )
            answer = deliver(kind, j)
            if answer is None:
                raise RuntimeError(
                    f"{spec.label}: the server rejected tick {j}'s {kind}; see the session log"
                )
            answers[j] = finals[j] = answer
            try:
                if spec.scenario is Scenario.CONTROLLED:
                    q, qd = estimate_of(answer, nq, nv)
                    truths.append(obj.step(obj.control(truths[j].t, q, qd)))
                else:
                    truths.append(obj.step())
            except UnstableSimulation as error:
                # A law fed a diverged estimate can throw the truth itself off the rails; the run
                # ends there, and the trace says when.
                stopped = (error.t, str(error))
                ticks = j + 1
                break
            bar.update(1)
    bar.close()
    wall = time.perf_counter() - started

    layout = 3 if opened.scenario == Scenario.CONTROLLED else 2
    # DRIVEN filters carry the unknown force after [q, qd]; the truth has no such state (the force
    # the filter holds over a tick is a modelling device), so the trace keeps the [q, qd] block of
    # the mean and the covariance, and NEES is that marginal's.
    size = nq + (layout - 1) * nv
    side = layout * nv
    truth_state = np.array([np.concatenate([s.qpos, s.qvel, s.qacc][:layout]) for s in truths[:ticks]])
    estimate = np.array([_state(answers[k], size) for k in range(ticks)])
    final = np.array([_state(finals[k], size) for k in range(ticks)])
    covariances = [answers[k].covariance for k in range(ticks)]
    covariance = (
        None if any(c is None for c in covariances) else np.array([c[:side, :side] for c in covariances])  # type: ignore[index]
    )
    measured_channels = [c for c in opened.measured if c in (Channel.QPOS, Channel.QVEL, Channel.QACC)]
    return Trace(
        spec=spec,
        dt=dt,
        nq=nq,
        nv=nv,
        joint_names=tuple(opened.model.joint_names),
        dof_units=dof_units(joint_types(obj.model)),
        settings=dict(opened.estimator),
        measurement_dim=len(measured_channels) * nv,
        t=np.arange(ticks) * dt,
        truth_state=truth_state,
        estimate=estimate,
        covariance=covariance,
        corrected=final,
        ctrl=np.array([s.ctrl for s in truths[:ticks]]),
        source=tuple(answers[k].source for k in range(ticks)),
        received=np.array([answers[k].frame_received for k in range(ticks)]),
        nis=np.array([np.nan if answers[k].nis is None else answers[k].nis for k in range(ticks)]),
        compute_us=np.array([answers[k].compute_us for k in range(ticks)], dtype=float),
        reinitialised=sum(1 for k in range(ticks) if answers[k].reinitialised),
        adapted=sum(1 for k in range(ticks) if answers[k].adapted),
        absorbed=sum(1 for k in range(ticks) if answers[k].absorbed),
        opened_scenario=opened.scenario,
        opened_reason=opened.scenario_reason,
        rejected=rejected,
        corrected_ticks=corrected,
        wall_seconds=wall,
        stopped=stopped,
    )


def _state(result: TickResult, size: int) -> np.ndarray:
    if result.filter_state.size >= size:
        return np.asarray(result.filter_state[:size], dtype=float)
    # Before the first frame there is no filter state; NaN keeps the tick out of the metrics.
    return np.full(size, math.nan)
