"""The experiments: every table and figure of the thesis' chapter 4, and what it leaves open.

Each experiment is a function of a `Context` (a connected client, the output folder, quick or full)
that runs sessions through the server and returns a report `Section`.
"""

from __future__ import annotations

import contextlib
import functools
import math
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from jitdyn.client import Client, FrameData, SessionOptions, SyncSample, TickResult
from jitdyn.experiments import prior_eval, thesis
from jitdyn.experiments.analysis import RunMetrics, gap_profile, summarise
from jitdyn.experiments.foresight import HORIZONS, RECORDING_GAPS, foresight_rows, learned_cost
from jitdyn.experiments.metrics import gap_errors
from jitdyn.experiments.netem import DelayedSender, Distribution, NetworkProfile, sample_delays
from jitdyn.experiments.objects import make_object
from jitdyn.experiments.progress import track
from jitdyn.experiments.recorded import RECORDINGS, research_object
from jitdyn.experiments.report import (
    Column,
    Figure,
    Section,
    Table,
    plot_bars,
    plot_error_over_time,
    plot_estimates,
    plot_gap_errors,
)
from jitdyn.experiments.runner import ModelCache, RunSpec, Trace, run_lockstep
from jitdyn.vocabulary import Clock, EstimatorKind, Output, Preset, Scenario, Source

__all__ = ["EXPERIMENTS", "GAPS", "Context", "Experiment"]

GAPS = (0.035, 0.100, 0.200)  # s: the gap lengths the error is read at
PRESETS = (Preset.THESIS, Preset.JITDYN)
BASELINES = (EstimatorKind.STATIC, EstimatorKind.CONSTANT_VELOCITY, EstimatorKind.CONSTANT_ACCELERATION)

# Run lengths (seconds): full, quick. The thesis does not give its run lengths; these cover ten
# switches of the controlled pendulum, five rocking cycles of the biped, two raise-lower cycles
# of the elbow and two finger waves of the hand.
_SECONDS = {
    "pendulum": (10.0, 0.5),
    "biped": (10.0, 0.1),
    "myoelbow": (8.0, 0.06),
    "myohand": (4.0, 0.02),
    "cmj": (7.9, 0.3),  # the recording lasts 7.985 s
    "isen_gait": (10.25, 4.0),  # 10.29 s
    "isen_tasks": (17.95, 4.0),  # 17.99 s
    "xsens_gait": (24.2, 4.0),  # 24.24 s
}


@dataclass
class Context:
    """What an experiment runs with."""

    client: Client
    out: Path
    quick: bool = False
    progress: bool = True
    seed: int = 0
    # Opens a server with the given number of workers and yields its address; None when the
    # harness runs against a given server (--server), whose workers it cannot change.
    servers: Callable[[int], contextlib.AbstractContextManager[str]] | None = None
    models: ModelCache = field(init=False)
    notes: list[str] = field(default_factory=list)  # what went wrong in the current experiment's runs

    def __post_init__(self) -> None:
        self.models = ModelCache(self.client)

    def seconds(self, obj: str) -> float:
        key = "pendulum" if obj.startswith("pendulum") else obj
        full, quick = _SECONDS[key]
        return quick if self.quick else full

    def run(self, spec: RunSpec, *, client: Client | None = None, models: ModelCache | None = None) -> Trace:
        trace = run_lockstep(
            client or self.client, spec, models=models or self.models, progress=self.progress
        )
        if trace.stopped is not None:
            t, why = trace.stopped
            self.notes.append(
                f"{spec.label}: the run ended at t = {t:.3g} s of {spec.seconds:.3g} s ({why}); its numbers "
                "cover the ticks before."
            )
        return trace

    def presets(self, obj: str, scenario: Scenario) -> dict[Preset, Trace]:
        """A run of `obj` in `scenario` with each preset, as long as `seconds(obj)`."""
        return {
            preset: self.run(RunSpec(obj, scenario, self.seconds(obj), preset=preset, seed=self.seed))
            for preset in PRESETS
        }


@dataclass(frozen=True)
class Experiment:
    name: str
    title: str
    help: str
    run: Callable[[Context], Section]


# --- the columns of the thesis' tables -----------------------------------------------------------


@dataclass(frozen=True)
class _Scored:
    """One preset's run of a thesis table: a row of its table."""

    preset: Preset
    metrics: RunMetrics


@dataclass(frozen=True)
class _PendulumScored(_Scored):
    row: thesis.PendulumRow  # the thesis' numbers for this pendulum


def _ci(interval: object) -> tuple[float, float]:
    return (float(interval.low), float(interval.high))  # type: ignore[attr-defined]


def _nees_cells(m: RunMetrics) -> tuple[object, ...]:
    """average NEES, verdict, single-sample CI, averaged CI, share of samples in the single CI."""
    if m.nees is None:
        return (None, "-", None, None, None)
    c = m.nees
    return (c.mean, c.verdict, _ci(c.single), _ci(c.averaged), c.fraction_inside)


def _nees_column(index: int, header: str) -> Column[_Scored]:
    return Column(header, lambda s: _nees_cells(s.metrics)[index])


def _block_column(header: str, block: str, *, settled: bool = False) -> Column[_Scored]:
    if settled:
        return Column(header, lambda s: s.metrics.settled[block])
    return Column(header, lambda s: s.metrics.armse[block])


_NEES = tuple(
    _nees_column(i, header)
    for i, header in enumerate(("avg NEES", "verdict", "NEES CI (1 sample)", "avg-NEES CI", "in CI"))
)
# What every table of the thesis says of a run's consistency, after its errors.
_CONSISTENCY: tuple[Column[_Scored], ...] = (
    *_NEES,
    Column("avg NIS", lambda s: None if s.metrics.nis is None else s.metrics.nis.mean),
    Column("reinit", lambda s: s.metrics.reinitialised),
)
_PRESET: Column[_Scored] = Column("preset", lambda s: s.preset)


def _blocks(scenario: Scenario) -> tuple[str, ...]:
    """The state's blocks: [q, qd, qdd] when the frames carry the control, else [q, qd]."""
    return ("q", "qd", "qdd") if scenario is Scenario.CONTROLLED else ("q", "qd")


def _thesis_block(block: str) -> Column[_PendulumScored]:
    """The thesis' aRMSE of `block` ("q", "qd", "qdd": the PendulumRow field of that name)."""
    return Column(f"thesis {block} aRMSE", lambda s: getattr(s.row, block))


# --- the pendulum tables (4.2, 4.4, 4.6) --------------------------------------------------------


@dataclass(frozen=True)
class _PendulumTable:
    name: str
    scenario: Scenario
    rows: Sequence[thesis.PendulumRow]
    title: str
    figures: str
    text: str


def _pendulum_table(ctx: Context, table: _PendulumTable) -> Section:
    blocks = _blocks(table.scenario)
    columns: list[Column[_PendulumScored]] = [
        Column("dof", lambda s: s.row.dof),
        _PRESET,
        *(_block_column(f"{b} aRMSE", b) for b in blocks),
        _block_column("q aRMSE from 1 s", "q", settled=True),
        *_CONSISTENCY,
        *(_thesis_block(b) for b in blocks),
        Column("thesis avg NEES", lambda s: s.row.nees),
        Column("thesis CI", lambda s: s.row.ci),
    ]
    scored: list[_PendulumScored] = []
    figs: list[Figure] = []
    scenario = table.scenario.value.lower()
    for row in table.rows:
        traces = ctx.presets(f"pendulum_{row.dof}", table.scenario)
        scored += [_PendulumScored(preset, summarise(trace), row) for preset, trace in traces.items()]
        file = f"{table.name}_{row.dof}dof.png"
        plot_estimates(traces, ctx.out / file, title=f"{row.dof}-dof pendulum, {scenario}")
        figs.append(
            Figure(
                file, f"{row.dof}-dof {scenario} pendulum: estimate against truth (thesis {table.figures})"
            )
        )
    result = Table.of(table.name, table.title, columns, scored)
    return Section(table.name, table.title, table.text, (result,), tuple(figs))


_TABLE_4_2 = _PendulumTable(
    name="table_4_2",
    scenario=Scenario.PASSIVE,
    rows=thesis.TABLE_4_2,
    title="Table 4.2: constant-velocity (passive) pendulums",
    figures="figures 4.2-4.4",
    text=(
        "Pendulums of 1-3 links released at rest with the first hinge at 45 degrees (plus a seeded "
        "0.01 rad perturbation of every hinge), gravity only, dt = 50 ms, every frame on time. "
        "The estimate is the filter's posterior at every tick."
    ),
)
_TABLE_4_4 = _PendulumTable(
    name="table_4_4",
    scenario=Scenario.CONTROLLED,
    rows=thesis.TABLE_4_4,
    title="Table 4.4: controlled pendulums",
    figures="figures 4.5-4.7",
    text=(
        "A computed-torque law, fed with the filter's state from the latest answer, moves the first "
        "hinge to +45 degrees and -45 degrees in turn every second (the chain held straight); frames "
        "carry q, qd, qdd and the control that acted; the state is [q, qd, qdd]."
    ),
)
_TABLE_4_6 = _PendulumTable(
    name="table_4_6",
    scenario=Scenario.EXTERNAL,
    rows=thesis.TABLE_4_6,
    title="Table 4.6: externally controlled pendulums",
    figures="figures 4.8-4.10",
    text=(
        "The same motion as table 4.4, driven by the same law on the true state; the server never "
        "sees the control and restores the force that acted by inverse dynamics; the state is [q, qd]."
    ),
)


# --- the biped tables (4.8, 4.9) ----------------------------------------------------------------


@dataclass(frozen=True)
class _BipedTable:
    name: str
    scenario: Scenario
    rows: Sequence[thesis.JointRow]
    nees: tuple[float, tuple[float, float]]
    title: str
    figure: str


def _biped_table(ctx: Context, table: _BipedTable) -> Section:
    name, scenario, title = table.name, table.scenario, table.title
    blocks = _blocks(scenario)
    traces = ctx.presets("biped", scenario)
    metrics = {preset: summarise(trace) for preset, trace in traces.items()}

    def joint_rmse(preset: Preset, block: str) -> Column[tuple[int, thesis.JointRow]]:
        return Column(f"{preset} {block} RMSE", lambda jr: metrics[preset].per_joint[block][jr[0]])

    def thesis_rmse(i: int, block: str) -> Column[tuple[int, thesis.JointRow]]:
        return Column(f"thesis {block} RMSE", lambda jr: (jr[1].x, jr[1].xd, jr[1].xdd)[i])

    joint_columns: list[Column[tuple[int, thesis.JointRow]]] = [
        Column("#", lambda jr: jr[0] + 1),
        Column("joint", lambda jr: jr[1].joint),
        *(joint_rmse(p, b) for p in PRESETS for b in blocks),
        *(thesis_rmse(i, b) for i, b in enumerate(blocks)),
    ]
    consistency_columns: list[Column[_Scored]] = [
        _PRESET,
        *(_block_column(f"{b} aRMSE", b) for b in blocks),
        *_CONSISTENCY,
        Column("thesis avg NEES", lambda s: table.nees[0]),
        Column("thesis CI", lambda s: table.nees[1]),
    ]
    obj = make_object("biped", scenario)
    file = f"{name}.png"
    plot_estimates(traces, ctx.out / file, title=f"biped, {scenario.value.lower()}")
    text = (
        f"The biped rocks in an A-frame stance: {obj.description}; dt = 5 ms, every frame on time. "
        "RMSE per joint (m for the slides, rad for the hinges)."
    )
    scored = [_Scored(p, m) for p, m in metrics.items()]
    return Section(
        name,
        title,
        text,
        (
            Table.of(name, title + ": RMSE per joint", joint_columns, enumerate(table.rows)),
            Table.of(f"{name}_nees", title + ": consistency", consistency_columns, scored),
        ),
        (Figure(file, f"biped {scenario.value.lower()}: estimate against truth (thesis {table.figure})"),),
    )


_TABLE_4_8 = _BipedTable(
    name="table_4_8",
    scenario=Scenario.CONTROLLED,
    rows=thesis.TABLE_4_8,
    nees=thesis.TABLE_4_8_NEES,
    title="Table 4.8: controlled biped",
    figure="figure 4.12",
)
_TABLE_4_9 = _BipedTable(
    name="table_4_9",
    scenario=Scenario.EXTERNAL,
    rows=thesis.TABLE_4_9,
    nees=thesis.TABLE_4_9_NEES,
    title="Table 4.9: externally controlled biped",
    figure="figure 4.13",
)


# --- the MyoSuite models (4.10, myoHand) ---------------------------------------------------------


def table_4_10(ctx: Context) -> Section:
    name = "table_4_10"
    title = "Table 4.10: externally controlled myoElbow"
    traces = ctx.presets("myoelbow", Scenario.EXTERNAL)
    reference = thesis.TABLE_4_10
    columns: list[Column[_Scored]] = [
        _PRESET,
        _block_column("q RMSE", "q"),
        _block_column("qd RMSE", "qd"),
        _block_column("q RMSE from 1 s", "q", settled=True),
        *_CONSISTENCY,
        Column("thesis q RMSE", lambda s: reference.x),
        Column("thesis qd RMSE", lambda s: reference.xd),
        Column("thesis avg NEES", lambda s: thesis.TABLE_4_10_NEES[0]),
        Column("thesis CI", lambda s: thesis.TABLE_4_10_NEES[1]),
    ]
    scored = [_Scored(preset, summarise(trace)) for preset, trace in traces.items()]
    file = f"{name}.png"
    plot_estimates(traces, ctx.out / file, title="myoElbow, externally controlled")
    obj = make_object("myoelbow", Scenario.EXTERNAL)
    text = (
        f"myoElbow (1 joint, 6 muscles): {obj.description}; dt = 2 ms; the server sees q and qd only "
        "(muscle activations are hidden state it never gets)."
    )
    return Section(
        name,
        title,
        text,
        (Table.of(name, title, columns, scored),),
        (Figure(file, "myoElbow: estimate against truth (thesis figure 4.14)"),),
    )


@dataclass(frozen=True)
class _HandRun(_Scored):
    trace: Trace

    @property
    def worst(self) -> int:
        """The joint of the largest q RMSE (0 when none is finite)."""
        q = self.metrics.per_joint["q"]
        return int(np.nanargmax(q)) if np.isfinite(q).any() else 0


_HAND_COLUMNS: tuple[Column[_HandRun], ...] = (
    _PRESET,
    Column("sigma points", lambda r: str(r.trace.settings.get("sigma_points", ""))),
    _block_column("q aRMSE", "q"),
    _block_column("qd aRMSE", "qd"),
    Column("joint 23 q RMSE", lambda r: float(r.metrics.per_joint["q"][22])),
    Column("worst joint", lambda r: r.trace.joint_names[r.worst]),
    Column("its q RMSE", lambda r: float(r.metrics.per_joint["q"][r.worst])),
    *_NEES[:2],
    Column("reinit", lambda r: r.metrics.reinitialised),
    Column("q error > 1 rad at (s)", lambda r: r.metrics.diverged_at),
    Column("compute (ms/tick)", lambda r: r.metrics.mean_compute_us / 1000.0),
)


def myohand(ctx: Context) -> Section:
    name = "myohand"
    title = "MyoHand, externally controlled (thesis figure 4.15)"
    traces = ctx.presets("myohand", Scenario.EXTERNAL)
    runs = [_HandRun(preset, summarise(trace), trace) for preset, trace in traces.items()]
    err_file, est_file = f"{name}_joint23.png", f"{name}.png"
    plot_error_over_time(traces, ctx.out / err_file, title="myoHand: error of the 23rd joint", joint=22)
    first = next(iter(traces.values()))
    picks = [
        first.joint_names.index(j)
        for j in ("mcp2_flexion_r", "pm3_flexion_r", "md5_flexion_r")
        if j in first.joint_names
    ]
    plot_estimates(traces, ctx.out / est_file, title="myoHand, externally controlled", joints=picks or [22])
    obj = make_object("myohand", Scenario.EXTERNAL)
    text = (
        f"myoHand (23 joints, 39 muscles): {obj.description}; dt = 2 ms. The thesis' filter accumulated "
        "error and diverged quickly; the JITDYN preset keeps the sigma-point weights O(1) "
        "(and uses simplex points at this size)."
    )
    return Section(
        name,
        title,
        text,
        (Table.of(name, title, _HAND_COLUMNS, runs),),
        (
            Figure(err_file, "myoHand: |q error| of the 23rd joint (md5_flexion) over time"),
            Figure(est_file, "myoHand: estimate against truth, three finger joints"),
        ),
    )


# --- dead reckoning over gaps ---------------------------------------------------------------------

# A wearable's sensors: white noise of 0.005 rad on q and 0.05 rad/s on qd (m, m/s on slides),
# seeded.
WEARABLE = (0.005, 0.05)
SENSORS: dict[str, tuple[float, float] | None] = {"perfect": None, "wearable": WEARABLE}


@dataclass(frozen=True)
class _GapObject:
    name: str
    scenario: Scenario
    driven: bool  # forces the server does not see move it: the targets of a driven object apply


def _gap_objects(ctx: Context) -> list[_GapObject]:
    if ctx.quick:
        return [
            _GapObject("pendulum_1", Scenario.PASSIVE, False),
            _GapObject("pendulum_1", Scenario.EXTERNAL, True),
            _GapObject("isen_gait", Scenario.EXTERNAL, True),
            _GapObject("isen_tasks", Scenario.EXTERNAL, True),
            _GapObject("xsens_gait", Scenario.EXTERNAL, True),
        ]
    return [
        _GapObject("pendulum_3", Scenario.PASSIVE, False),
        _GapObject("pendulum_3", Scenario.CONTROLLED, False),
        _GapObject("pendulum_3", Scenario.EXTERNAL, True),
        _GapObject("biped", Scenario.EXTERNAL, True),
        _GapObject("myoelbow", Scenario.EXTERNAL, True),
        _GapObject("myohand", Scenario.EXTERNAL, True),
        _GapObject("cmj", Scenario.EXTERNAL, True),
        _GapObject("isen_gait", Scenario.EXTERNAL, True),
        _GapObject("isen_tasks", Scenario.EXTERNAL, True),
        _GapObject("xsens_gait", Scenario.EXTERNAL, True),
    ]


@dataclass(frozen=True)
class _Estimator:
    label: str
    spec: dict[str, object]  # RunSpec fields


def _estimators(obj: _GapObject) -> list[_Estimator]:
    """Every estimator compared on `obj`, each at its defaults."""
    rows = [
        # What a client gets that names nothing: no scenario, no settings.
        _Estimator("UKF, defaults", {"open_as": "", "default_settings": True}),
        # The object's own scenario, named, with the JITDYN preset.
        _Estimator(f"UKF, {obj.scenario.value} named", {}),
    ]
    if obj.driven:
        # A driven motion opened with the wrong scenario, as a client that knows no better would.
        rows.append(_Estimator("UKF, PASSIVE named (wrong)", {"open_as": Scenario.PASSIVE}))
    rows += [_Estimator(b, {"estimator": b}) for b in BASELINES]
    return rows


@dataclass(frozen=True)
class _GapRun:
    obj: _GapObject
    sensors: str
    label: str
    by_gap: dict[float, float]
    metrics: RunMetrics
    trace: Trace


def _best_extrapolator(runs: Sequence[_GapRun], gap: float) -> tuple[str, float]:
    values = [(r.label, r.by_gap[gap]) for r in runs if r.label in BASELINES]
    return min(values, key=lambda v: v[1] if math.isfinite(v[1]) else math.inf)


def _fmt(x: float) -> str:
    return f"{x:.3g}"


def _targets(runs: Sequence[_GapRun]) -> list[tuple[object, ...]]:
    """Each target of dead reckoning over gaps beside the number it must beat, from the gaps runs
    (docs/decisions/0061-gaps-targets.md)."""
    rows: list[tuple[object, ...]] = []
    groups: dict[tuple[str, str], list[_GapRun]] = {}
    for r in runs:
        groups.setdefault((f"{r.obj.name}/{r.obj.scenario.value}", r.sensors), []).append(r)
    for (obj_label, sensors), group in groups.items():
        obj = group[0].obj
        by_label = {r.label: r for r in group}
        default = by_label["UKF, defaults"]
        for gap in GAPS:
            best_label, best = _best_extrapolator(group, gap)
            ms = round(gap * 1000)
            if obj.driven:
                factor = 1.0 if sensors == "perfect" else 0.5
                ours = default.by_gap[gap]
                rows.append(
                    (
                        f"driven, defaults <= {'' if factor == 1 else '0.5 x '}best extrapolator @{ms} ms",
                        obj_label,
                        sensors,
                        ours,
                        factor * best,
                        best_label,
                        "met" if ours <= factor * best else f"missed ({ours / best:.3g} x best)",
                    )
                )
                wrong = by_label["UKF, PASSIVE named (wrong)"].by_gap[gap]
                rows.append(
                    (
                        f"wrong scenario (PASSIVE) <= 2 x best extrapolator @{ms} ms",
                        obj_label,
                        sensors,
                        wrong,
                        2.0 * best,
                        best_label,
                        "met" if wrong <= 2.0 * best else f"missed ({wrong / best:.3g} x best)",
                    )
                )
            elif obj.scenario is Scenario.PASSIVE:
                ours = by_label["UKF, PASSIVE named"].by_gap[gap]
                rows.append(
                    (
                        f"PASSIVE, true model: <= best extrapolator / 10 @{ms} ms",
                        obj_label,
                        sensors,
                        ours,
                        best / 10.0,
                        best_label,
                        "met" if ours <= best / 10.0 else f"missed ({ours / best:.3g} x best)",
                    )
                )
    for r in runs:
        m = r.metrics
        if r.label != "UKF, defaults" or m.nees is None:
            continue
        per_dim = m.nees.mean / r.trace.nx
        inside = m.nees.fraction_inside
        ok = 0.5 <= per_dim <= 2.0 and inside >= 0.8
        rows.append(
            (
                "consistency, defaults: avg NEES / dim in [0.5, 2], >= 80 % of ticks in the 1-sample CI",
                f"{r.obj.name}/{r.obj.scenario.value}",
                r.sensors,
                f"{per_dim:.3g}, {inside:.0%}",
                "[0.5, 2], 80 %",
                "",
                "met" if ok else "missed",
            )
        )
    return rows


def gaps(ctx: Context) -> Section:
    name = "gaps"
    title = "Dead reckoning over gaps: the UKF against IEEE 1278's extrapolators"
    rows: list[tuple[object, ...]] = []
    figs: list[Figure] = []
    runs: list[_GapRun] = []
    for obj_spec in _gap_objects(ctx):
        obj = research_object(obj_spec.name, obj_spec.scenario)
        recorded = obj_spec.name in RECORDINGS
        # A gap every 0.5 s: the filter has frames again for 0.3 s before the next one; the
        # recordings: 500 ms every 1.25 s, for the horizons of foresight.
        gap, every = RECORDING_GAPS if recorded else (max(GAPS), 0.5)
        gap_ticks = math.ceil(gap / obj.dt - 1e-9)
        period = max(gap_ticks + 2, round(every / obj.dt))
        if recorded:
            seconds = ctx.seconds(obj_spec.name)
        elif obj_spec.name == "myohand" and not ctx.quick:
            seconds = 10.0  # the myoHand targets are over 10 s
        else:
            seconds = ctx.seconds(obj_spec.name)
        if ctx.quick:
            seconds = max(seconds, 3 * period * obj.dt)
        for sensors, noise in SENSORS.items():
            profiles: dict[str, dict[int, float]] = {}
            for est in _estimators(obj_spec):
                fields: dict[str, object] = {"preset": Preset.JITDYN, **est.spec}
                spec = RunSpec(
                    obj_spec.name,
                    obj_spec.scenario,
                    seconds,
                    seed=ctx.seed,
                    gaps=(gap_ticks, period),
                    noise=noise,
                    **fields,  # type: ignore[arg-type]
                )
                trace = ctx.run(spec)
                profile = gap_profile(trace)
                profiles[est.label] = profile
                g = gap_errors(est.label, profile, dt=obj.dt, gaps=HORIZONS)
                m = summarise(trace)
                runs.append(_GapRun(obj_spec, sensors, est.label, dict(g.by_gap), m, trace))
                nees = m.nees
                rows.append(
                    (
                        f"{obj_spec.name}/{obj_spec.scenario.value}",
                        sensors,
                        est.label,
                        trace.opened_scenario,
                        *(g.by_gap[x] if math.isfinite(g.by_gap[x]) else None for x in HORIZONS),
                        m.armse["q"],
                        None if nees is None else nees.mean / trace.nx,
                        None if nees is None else nees.fraction_inside,
                        trace.adapted,
                        trace.absorbed,
                        trace.reinitialised,
                        m.mean_compute_us / 1000.0,
                    )
                )
            file = f"gaps_{obj_spec.name}_{obj_spec.scenario.value.lower()}_{sensors}.png"
            plot_gap_errors(
                profiles,
                ctx.out / file,
                dt=obj.dt,
                marks=HORIZONS if recorded else GAPS,
                title=f"{obj_spec.name} {obj_spec.scenario.value.lower()}, {sensors} sensors: q error without frames",
            )
            figs.append(
                Figure(
                    file,
                    f"{obj_spec.name} {obj_spec.scenario.value.lower()}, {sensors} sensors: RMS q error against "
                    "the time since the last frame",
                )
            )
    columns = (
        "object",
        "sensors",
        "estimator",
        "scenario in force",
        *(f"q error @{round(g * 1000)} ms" for g in HORIZONS),
        "q aRMSE (whole run)",
        "avg NEES / dim",
        "in 1-sample CI",
        "adapted",
        "absorbed",
        "reinit",
        "compute (ms/tick)",
    )
    target_rows = _targets([r for r in runs if r.obj.name not in RECORDINGS])
    target_columns = ("target", "object", "sensors", "ours", "to beat", "best extrapolator", "verdict")
    myohand = [r for r in runs if r.obj.name == "myohand" and r.label == "UKF, defaults"]
    for r in myohand:
        q = r.metrics.armse["q"]
        rows_hand = [
            (
                "myoHand 10 s: q RMSE < 0.02 rad",
                "myohand/EXTERNAL",
                r.sensors,
                q,
                0.02,
                "",
                "met" if q < 0.02 else "missed",
            ),
            (
                "myoHand 10 s: no re-initialisation",
                "myohand/EXTERNAL",
                r.sensors,
                r.metrics.reinitialised,
                0,
                "",
                "met" if r.metrics.reinitialised == 0 else "missed",
            ),
            (
                "myoHand: cycle fits its 2 ms tick (mean server compute)",
                "myohand/EXTERNAL",
                r.sensors,
                r.metrics.mean_compute_us / 1000.0,
                2.0,
                "",
                "met" if r.metrics.mean_compute_us < 2000.0 else "missed",
            ),
        ]
        target_rows.extend(rows_hand)
    text = (
        "Every 0.5 s the frames stop for 200 ms (lost, never sent late); the server dead-reckons with "
        "the estimator named. The q error at a gap length is the RMS over joints and gaps of the "
        "answer that many ticks after the last frame (rounded up to whole ticks: at dt = 50 ms, "
        "35 ms is one tick). STATIC holds the last state, CONSTANT_VELOCITY moves q with the last "
        "qd, CONSTANT_ACCELERATION with the last qd and qdd (IEEE 1278.1 dead-reckoning; qdd from "
        "the difference of the last two frames' qd). 'Perfect' frames carry the true q and qd; "
        f"'wearable' frames add white noise of {WEARABLE[0]} rad (m) on q and {WEARABLE[1]} rad/s (m/s) "
        "on qd, seeded, the same noise for every estimator. 'UKF, defaults' sends no scenario and no "
        "settings: the server picks DRIVEN for every model here (they all have actuators). "
        "NEES is over [q, qd] (a DRIVEN filter's force has no truth to compare with). The recorded "
        "motions (cmj, isen_gait, isen_tasks, xsens_gait) lose 500 ms of frames every 1.25 s instead, for the "
        "horizons of foresight; the others have no 500 ms column."
    )
    return Section(
        name,
        title,
        text,
        (
            Table(f"{name}_targets", "Issue 10's targets", target_columns, tuple(target_rows)),
            _foresight_table(runs),
            _learned_cost_table(ctx),
            Table(name, title, columns, tuple(rows)),
        ),
        tuple(figs),
    )


def _foresight_table(runs: Sequence[_GapRun]) -> Table:
    """The defaults against the best extrapolator on the recorded motions, with the targets of
    foresight (docs/decisions/0026-learned-foresight.md)."""
    errors = {(r.obj.name, r.sensors, r.label): r.by_gap for r in runs if r.obj.name in RECORDINGS}
    columns = (
        "recording",
        "prior (subjects)",
        "motion",
        "sensors",
        "horizon (ms)",
        "defaults",
        "best extrapolator",
        "which",
        "defaults / best",
        "target",
        "verdict",
    )
    return Table("gaps_foresight", "Foresight on recorded motion", columns, tuple(foresight_rows(errors)))


def _learned_cost_table(ctx: Context) -> Table:
    """The learned predictor's CPU time per tick beside the tick's physics (experiments/foresight.py)."""
    rows = []
    for name, dt, limit in (("pendulum_3", 0.05, "< 100 us"), ("myohand", 0.002, "< 10 % of physics")):
        matching, physics = learned_cost(name, dt=dt, ticks=100 if ctx.quick else 300)
        ok = matching < 100.0 if name == "pendulum_3" else matching < 0.1 * physics
        rows.append(
            (name, dt * 1000, matching, physics, matching / physics, limit, "met" if ok else "missed")
        )
    columns = (
        "model",
        "dt (ms)",
        "learned (us/tick)",
        "physics (us/tick)",
        "learned / physics",
        "target",
        "verdict",
    )
    return Table("gaps_learned_cost", "The learned predictor's cost per tick", columns, tuple(rows))


# The thesis' R = 0.01 I says "measurements are noisy" for noise-free sensors; with P of order 1e-4
# the gain on q is then about 1 %, and the filter takes seconds to come back after a gap. The same
# preset with R = 1e-6 I shows what the measurement noise setting alone is worth.
TRUSTING = {"r": 1e-6}


def _network_estimators() -> list[tuple[str, EstimatorKind, Preset, dict[str, float]]]:
    """(label, estimator, preset, overrides) of every estimator compared in `network`."""
    ukf = EstimatorKind.UKF
    return (
        [("UKF " + p, ukf, p, {}) for p in PRESETS]
        + [("UKF JITDYN, R = 1e-6 I", ukf, Preset.JITDYN, TRUSTING)]
        + [(b, b, Preset.JITDYN, {}) for b in BASELINES]
    )


def network(ctx: Context) -> Section:
    name = "network"
    title = "Late and lost frames (LOCKSTEP network emulation)"
    profile = NetworkProfile(latency=0.035, jitter=0.010, distribution=Distribution.NORMAL, loss=0.05)
    objects = (
        [("pendulum_1", Scenario.PASSIVE)]
        if ctx.quick
        else [
            ("pendulum_3", Scenario.EXTERNAL),
            ("biped", Scenario.EXTERNAL),
            ("myoelbow", Scenario.EXTERNAL),
        ]
    )
    rows: list[tuple[object, ...]] = []
    for obj_name, scenario in objects:
        for label, estimator, preset, overrides in _network_estimators():
            spec = RunSpec(
                obj_name,
                scenario,
                ctx.seconds(obj_name),
                estimator=estimator,
                preset=preset,
                seed=ctx.seed,
                network=profile,
                grace=0.0,
                overrides=overrides,
            )
            trace = ctx.run(spec)
            on_time = summarise(trace)
            after = summarise(trace, corrected=True)
            predicted = sum(1 for s in trace.source if s == Source.PREDICTED) / len(trace.source)
            rows.append(
                (
                    f"{obj_name}/{scenario.value}",
                    label,
                    predicted,
                    trace.corrected_ticks,
                    on_time.armse["q"],
                    on_time.armse["qd"],
                    after.armse["q"],
                    on_time.reinitialised,
                )
            )
    columns = (
        "object",
        "estimator",
        "share predicted",
        "corrected",
        "q aRMSE at the tick",
        "qd aRMSE at the tick",
        "q aRMSE after corrections",
        "reinit",
    )
    text = (
        "One-way latency N(35 ms, 10 ms), 5 % loss, no grace: the server answers every tick before "
        "its frame can arrive (PREDICTED), then redoes the tick when the frame comes (CORRECTED, "
        "timewarp). 'At the tick' is what a client had on time; 'after corrections' what the "
        "stored session holds."
    )
    return Section(name, title, text, (Table(name, title, columns, tuple(rows)),))


# --- timing (figures 4.16, 4.17) -----------------------------------------------------------------


def _timing_models(ctx: Context) -> list[tuple[str, Scenario, Preset]]:
    pendulums = [
        (f"pendulum_{n}", s, Preset.THESIS)
        for n in (1, 2, 3)
        for s in (Scenario.PASSIVE, Scenario.CONTROLLED)
    ]
    if ctx.quick:
        return pendulums[:2]
    others = [
        (o, s, p)
        for o, s in (
            ("biped", Scenario.CONTROLLED),
            ("myoelbow", Scenario.EXTERNAL),
            ("myohand", Scenario.EXTERNAL),
        )
        for p in PRESETS
    ]
    return pendulums + others


def fig_4_16(ctx: Context) -> Section:
    name = "fig_4_16"
    title = "Figure 4.16: UKF overhead per step against the number of workers"
    seconds_for = {"pendulum": 2.0, "biped": 1.0, "myoelbow": 1.0, "myohand": 0.5}
    models = _timing_models(ctx)
    results: dict[str, dict[str, float]] = {}
    dts: dict[str, float] = {}

    @contextlib.contextmanager
    def given() -> Iterator[str]:
        yield ""

    setups: list[tuple[str, Callable[[], contextlib.AbstractContextManager[str]]]]
    if ctx.servers is not None:
        servers = ctx.servers
        setups = [(f"{w} worker{'s' if w > 1 else ''}", lambda w=w: servers(w)) for w in (1, 2)]  # type: ignore[misc]
    else:
        setups = [("the given server", given)]
    for series, open_server in setups:
        with open_server() as address:
            client = Client(address) if address else ctx.client
            cache = ModelCache(client) if address else ctx.models
            try:
                for obj_name, scenario, preset in models:
                    key = "pendulum" if obj_name.startswith("pendulum") else obj_name
                    seconds = 0.1 if ctx.quick else seconds_for[key]
                    spec = RunSpec(obj_name, scenario, seconds, preset=preset, seed=ctx.seed)
                    trace = ctx.run(spec, client=client, models=cache)
                    label = f"{obj_name}/{scenario.value}/{preset}"
                    # Tick 0 only initialises the filter; the overhead is that of the later ticks.
                    results.setdefault(label, {})[series] = float(np.mean(trace.compute_us[1:])) / 1000.0
                    dts[label] = trace.dt
            finally:
                if address:
                    client.close()
    labels = list(results)
    series_names = [s for s, _ in setups]
    rows = tuple(
        (
            label,
            dts[label] * 1000.0,
            *(results[label].get(s, math.nan) for s in series_names),
            max(results[label].values()) / (dts[label] * 1000.0),
        )
        for label in labels
    )
    columns = (
        "model/scenario/preset",
        "dt (ms)",
        *(f"compute (ms), {s}" for s in series_names),
        "worst / dt",
    )
    file = f"{name}.png"
    plot_bars(
        labels,
        {s: [results[lbl].get(s, math.nan) for lbl in labels] for s in series_names},
        ctx.out / file,
        title="server compute per tick (UKF predict + update + dynamics)",
        ylabel="ms per tick",
        log=True,
    )
    text = (
        "Mean server compute time per tick (the `compute_us` of every answer after the first), "
        "LOCKSTEP, every frame on time, on in-process servers with 1 and 2 workers sharing this "
        "machine. The thesis reports 10 ms per 50 ms step at worst (3-dof controlled pendulum) and "
        "could not run the biped (5 ms) or the MyoSuite models (2 ms) in real time."
    )
    return Section(
        name,
        title,
        text,
        (Table(name, title, columns, rows),),
        (Figure(file, "UKF overhead per tick against workers (thesis figure 4.16)"),),
    )


@dataclass(frozen=True)
class _RealtimeRun:
    on_time_delay: np.ndarray  # (T,) s: tick time to the arrival of its first answer at the client
    frame_delay: np.ndarray  # (T,) s: tick time to the arrival of the answer that used its frame
    measured_share: float
    missing: int


def _run_realtime(
    ctx: Context, obj_name: str, *, seconds: float, up: NetworkProfile, down: NetworkProfile
) -> _RealtimeRun:
    obj = make_object(obj_name, Scenario.PASSIVE)
    ticks = max(2, round(seconds / obj.dt))
    # Ticks run from the session's start; frames begin a few ticks later, after the clock sync.
    spare = 40
    truths = [obj.reset(ctx.seed)] + [obj.step() for _ in range(ticks + spare)]
    downlink = sample_delays(down, 4 * (ticks + spare), seed=ctx.seed + 1)
    first: dict[int, float] = {}
    with_frame: dict[int, float] = {}
    answers = 0
    synced = 0
    options = SessionOptions(
        **ctx.models.options(obj),
        scenario=Scenario.PASSIVE,
        dt=obj.dt,
        clock=Clock.REALTIME,
        estimator={"preset": Preset.THESIS},
        outputs=(Output.FILTER_STATE,),
    )
    with ctx.client.open_session(options) as session:
        base = time.monotonic() - session.now()  # the session clock's zero on time.monotonic

        def take(results: Sequence[object]) -> None:
            nonlocal answers, synced
            for r in results:
                if isinstance(r, SyncSample):
                    synced += 1
                if not isinstance(r, TickResult):
                    continue
                # The answer comes back over the emulated downlink too.
                arrival = r.received_at - base + float(downlink[answers % downlink.size])
                answers += 1
                sent = r.seq * obj.dt
                first.setdefault(r.seq, arrival - sent)
                if r.source in (Source.MEASURED, Source.CORRECTED) and r.seq not in with_frame:
                    with_frame[r.seq] = arrival - sent

        # Clock sync first, over the plain loopback: each probe completes the exchange before it,
        # so after four the server places client time on its clock from three round trips.
        for _ in range(4):
            before = synced
            session.sync()
            waited = time.monotonic() + 2.0
            while synced == before and time.monotonic() < waited:
                take(session.poll())
                time.sleep(0.001)
        k0 = math.ceil(session.now() / obj.dt) + 1
        if k0 > spare:
            raise RuntimeError(
                f"{obj_name}: the clock sync took {k0} ticks, more than the {spare} planned for"
            )
        seqs = range(k0, k0 + ticks)
        with DelayedSender(session.send, up, seed=ctx.seed) as uplink:
            for k in track(seqs, total=len(seqs), desc=f"{obj_name}/REALTIME", enabled=ctx.progress):
                wait = k * obj.dt - session.now()
                if wait > 0:
                    time.sleep(wait)
                s = truths[k]
                uplink.submit(FrameData(seq=k, t=s.t, qpos=s.qpos, qvel=s.qvel))
                take(session.poll())
        deadline = time.monotonic() + 2.0
        while not all(k in first for k in seqs) and time.monotonic() < deadline:
            take(session.poll())
            time.sleep(0.005)
        take(session.poll())
    return _RealtimeRun(
        on_time_delay=np.array([first.get(k, math.nan) for k in seqs]),
        frame_delay=np.array([with_frame.get(k, math.nan) for k in seqs]),
        measured_share=sum(1 for k in seqs if k in with_frame and with_frame[k] == first.get(k)) / ticks,
        missing=sum(1 for k in seqs if k not in first),
    )


def fig_4_17(ctx: Context) -> Section:
    name = "fig_4_17"
    title = "Figure 4.17: total delay per step of the passive pendulums in REALTIME"
    # 30-35 ms of network, as the thesis measured, split evenly between uplink and downlink.
    leg = NetworkProfile(latency=0.01625, jitter=0.00125, distribution=Distribution.UNIFORM)
    seconds = 0.5 if ctx.quick else 5.0
    rows: list[tuple[object, ...]] = []
    means: dict[str, list[float]] = {"first answer": [], "answer with the frame": []}
    groups = []
    for n in (1, 2, 3):
        run = _run_realtime(ctx, f"pendulum_{n}", seconds=seconds, up=leg, down=leg)
        first_ms = float(np.nanmean(run.on_time_delay)) * 1000.0
        frame_ms = float(np.nanmean(run.frame_delay)) * 1000.0
        rows.append(
            (
                n,
                first_ms,
                float(np.nanpercentile(run.on_time_delay, 95)) * 1000.0,
                frame_ms,
                float(np.nanpercentile(run.frame_delay, 95)) * 1000.0,
                run.measured_share,
                run.missing,
                "< 50",
            )
        )
        means["first answer"].append(first_ms)
        means["answer with the frame"].append(frame_ms)
        groups.append(f"{n}-dof")
    columns = (
        "dof",
        "first answer (ms, mean)",
        "p95",
        "answer with the frame (ms, mean)",
        "p95",
        "share MEASURED",
        "ticks without answer",
        "thesis (ms)",
    )
    file = f"{name}.png"
    plot_bars(
        groups,
        means,
        ctx.out / file,
        title="total delay per 50 ms step, 30-35 ms network",
        ylabel="ms from the tick to the answer",
        hline=50.0,
        hline_label="step (50 ms)",
    )
    text = (
        "REALTIME sessions, dt = 50 ms, default grace (dt / 2), THESIS preset. Frames leave the "
        "client at their tick's time over an emulated uplink of U(15, 17.5) ms; answers come back "
        "over a downlink of the same law (30-35 ms in all, the thesis' network). 'First answer': "
        "from the tick's time to the client receiving the tick's first answer (MEASURED, or "
        "PREDICTED when the frame missed the grace). 'Answer with the frame': to the answer that "
        "used the frame (MEASURED or CORRECTED), the thesis' total delay."
    )
    return Section(
        name,
        title,
        text,
        (Table(name, title, columns, tuple(rows)),),
        (Figure(file, "average total delay per step (thesis figure 4.17)"),),
    )


def _limit(limit: float | None) -> str:
    return "" if limit is None else f"<= {limit:g} x"


def _interval(row: prior_eval.PriorRow) -> str:
    low, high = row.interval()
    return f"{low:.3f}-{high:.3f}"


def _phase_range(row: prior_eval.PriorRow) -> str:
    ratios = [row.phase_ratio(p) for p in row.by_phase]
    return f"{min(ratios):.3f}-{max(ratios):.3f}"


def prior(ctx: Context) -> Section:
    """The prior of human motion left one subject out (experiments/prior_eval.py), with the gaps at
    five phases (one in --quick: the single-phase protocol; docs/decisions/0202-gap-phases.md)."""
    name = "prior"
    title = "Foresight from the first step: the prior of human motion, leaving one subject out"
    phases = prior_eval.SINGLE_PHASE if ctx.quick else prior_eval.PHASES
    rows = prior_eval.evaluate(
        lambda spec, obj: run_lockstep(ctx.client, spec, models=ctx.models, obj=obj, progress=ctx.progress),
        recordings=prior_eval.RECORDINGS_EVALUATED,
        sensors=SENSORS,
        seconds=3.0 if ctx.quick else None,
        phases=phases,
    )
    columns: tuple[Column[prior_eval.PriorRow], ...] = (
        Column("recording", lambda r: r.recording),
        Column("prior (subjects)", lambda r: r.prior),
        Column("sensors", lambda r: r.sensors),
        Column("window", lambda r: r.window),
        Column("horizon (ms)", lambda r: round(r.horizon * 1000)),
        Column("gaps", lambda r: r.count),
        Column("defaults", lambda r: r.errors["defaults"]),
        Column("no roles (no prior)", lambda r: r.errors["no roles"]),
        Column("best extrapolator", lambda r: r.best[1]),
        Column("which", lambda r: r.best[0]),
        Column("defaults / best", lambda r: r.ratio("defaults")),
        Column(f"{prior_eval.LEVEL:.0%} interval", _interval),
        Column("phase 0 alone", lambda r: r.phase_ratio(0.0)),
        Column("phases' range", _phase_range),
        Column("each phase", lambda r: " / ".join(f"{r.phase_ratio(p):.3f}" for p in r.by_phase)),
        Column("no roles / best", lambda r: r.ratio("no roles")),
        Column("target", lambda r: _limit(prior_eval.target(r.recording, r.horizon, r.sensors))),
        Column("verdict", lambda r: r.verdict),
        Column("short horizons (MH4)", lambda r: _limit(prior_eval.short_limit(r.recording, r.horizon))),
        Column("MH4 standing", lambda r: r.standing(prior_eval.short_limit(r.recording, r.horizon))),
    )
    starts = ", ".join(f"{250 + p * 1000:g}" for p in phases)
    text = (
        "Every recording of a person is answered by a prior of human motion without that person "
        "(leave one subject out; the prior column names who it holds), beside the same recording on "
        "a model whose joints say no role (the forecast combination without the prior) and the "
        "extrapolators. 100 ms of frames are lost every 250 ms, the first gap from "
        f"{starts} ms (one session each: {len(phases)} phase(s)); the q error 35 and 100 ms after "
        f"the last frame, over the gaps of the first {prior_eval.FIRST_STRIDE:g} s (the first "
        "stride) and over the whole run, pooled over the phases' gaps, as a multiple of the best "
        f"extrapolator, with its {prior_eval.LEVEL:.0%} bootstrap interval over the gaps. 'phase 0 "
        "alone': the single-phase protocol's cell (first gap from 250 ms); 'phases' range': each "
        "phase's own ratio, lowest to highest ('each phase': in the order of their starts). MH4: issue 33's must-have 4 (gait at 35 ms at or "
        "below the best extrapolator, motion that does not repeat within 1.05 x)."
    )
    return Section(name, title, text, (Table.of(name, title, columns, rows),))


def accuracy(ctx: Context) -> Section:
    """The estimator the server chooses by cost against the full UKF, offline on every model
    (experiments/accuracy.py); no session of the server runs."""
    # Imported here: the estimators run in this process, and --server runs need no server code.
    from jitdyn.experiments import accuracy as acc

    name = "accuracy"
    title = (
        "What the chosen estimator costs in accuracy: every model, the server's choice against the full UKF"
    )
    rows = acc.accuracy_rows(quick=ctx.quick, progress=ctx.progress)
    columns: tuple[Column[acc.AccuracyRow], ...] = (
        Column("model", lambda r: r.model),
        Column("nv", lambda r: r.nv),
        Column("scenario, rate", lambda r: f"{r.scenario.name} {r.rate:g} Hz"),
        Column("motion", lambda r: r.motion),
        Column("sensors", lambda r: r.sensors),
        Column("full UKF", lambda r: acc.label(r.choice.full)),
        Column("its tick (ms CPU)", lambda r: r.choice.full_cost * 1e3),
        Column("budget (ms)", lambda r: r.choice.budget * 1e3),
        Column("chosen", lambda r: acc.label(r.choice.settings)),
        Column("gaps", lambda r: r.full.gaps),
        Column("full UKF's error (rad)", lambda r: r.full_error),
        Column("chosen's error (rad)", lambda r: r.chosen_error),
        Column("chosen / full", lambda r: r.ratio),
        Column(f"<= {acc.BAR:g} x", lambda r: r.verdict),
    )
    text = (
        "For every built-in model (at 20 Hz, the biped at 200 Hz) and every myo-sim model that compiles "
        "here (at 100 Hz), in the scenario a session that names none gets: the estimator the server "
        "gives a REALTIME session that names none (server/runtime/choice.py: every candidate timed "
        "as registration times it, on this machine, then the most accurate whose tick fits "
        f"--max-tick-share {acc.SHARE:g} of dt) against the full UKF (the preset's, with its own "
        "sigma points, run offline however long its ticks take). The error is the mean |q error| "
        f"(rad; m on slides) of the answers in {acc.GAP * 1e3:g} ms gaps without frames every "
        f"{acc.EVERY * 1e3:g} ms, the first after {acc.EVERY * 1e3:g} ms, on (a) 'excited': the "
        "model's own motion under slow out-of-phase excitations of its actuators (benchmarks/cost_nv.py's), "
        "and (b) recorded gait at 100 Hz replayed on the hips, knees and ankles of every model whose "
        "joints have those roles (jitdyn.roles), each leg of the model given the recording's leg of "
        "its side, within the joints' ranges, every other joint at rest but those a joint equality "
        "couples to a replayed one: 'fukuchi' (gaitkit's healthy adult, both legs' hips, knees and "
        "ankles), 'isen' (biomdp's iSen stepping, hips and knees; the ankles at rest). 'wearable' "
        "frames carry seeded noise of 0.005 rad on q and 0.05 rad/s on qd, the same for both "
        "estimators. Where the chosen estimator is the full UKF, one run gives both columns."
    )
    return Section(name, title, text, (Table.of(name, title, columns, rows),))


EXPERIMENTS: dict[str, Experiment] = {
    e.name: e
    for e in (
        Experiment(
            "table_4_2",
            "passive pendulums",
            "Table 4.2: 1-3 link pendulums swinging under gravity "
            "(state [q, qd]); aRMSE, NEES and NIS per preset, estimate plots (figures 4.2-4.4).",
            functools.partial(_pendulum_table, table=_TABLE_4_2),
        ),
        Experiment(
            "table_4_4",
            "controlled pendulums",
            "Table 4.4: pendulums moved to the symmetrical "
            "position every second by a law fed with the filter's state (state [q, qd, qdd], control "
            "in the frames); figures 4.5-4.7.",
            functools.partial(_pendulum_table, table=_TABLE_4_4),
        ),
        Experiment(
            "table_4_6",
            "externally controlled pendulums",
            "Table 4.6: the same motion, control "
            "hidden from the server (inverse dynamics restores it); figures 4.8-4.10.",
            functools.partial(_pendulum_table, table=_TABLE_4_6),
        ),
        Experiment(
            "table_4_8",
            "controlled biped",
            "Table 4.8: the biped rocking under a law fed with the "
            "filter's state, dt 5 ms; RMSE per joint; figure 4.12.",
            functools.partial(_biped_table, table=_TABLE_4_8),
        ),
        Experiment(
            "table_4_9",
            "externally controlled biped",
            "Table 4.9: the same, control hidden; figure 4.13.",
            functools.partial(_biped_table, table=_TABLE_4_9),
        ),
        Experiment(
            "table_4_10",
            "myoElbow",
            "Table 4.10: MyoSuite elbow raising and lowering the forearm "
            "by muscle excitations the server never sees, dt 2 ms; figure 4.14.",
            table_4_10,
        ),
        Experiment(
            "myohand",
            "myoHand",
            "Figure 4.15: MyoSuite hand bending the fingers in turn, dt 2 ms: "
            "where the thesis' filter diverged.",
            myohand,
        ),
        Experiment(
            "fig_4_16",
            "UKF overhead",
            "Figure 4.16: server compute per tick with 1 and 2 workers, "
            "pendulums (THESIS) and the biped and MyoSuite models (both presets).",
            fig_4_16,
        ),
        Experiment(
            "fig_4_17",
            "REALTIME delay",
            "Figure 4.17: total delay per 50 ms step of the passive "
            "pendulums in REALTIME over an emulated 30-35 ms network.",
            fig_4_17,
        ),
        Experiment(
            "gaps",
            "gaps",
            "Beyond the thesis: the q error after 35, 100 and 200 ms without frames "
            "for the UKF (both presets) and the static, constant-velocity and constant-acceleration "
            "dead reckoning of IEEE 1278; on recorded human motion (a jump, steady stepping, "
            "movements that do not repeat, walking) also after 500 ms, the defaults as a multiple of the best "
            "extrapolator, and the learned predictor's cost per tick.",
            gaps,
        ),
        Experiment(
            "prior",
            "prior",
            "Beyond the thesis: the prior of human motion leaving one subject out: the defaults on every "
            "walk of the prior's people and the jump, with 100 ms of frames lost every 250 ms, against "
            "the same sessions without joint roles and the extrapolators, over the first stride and the run.",
            prior,
        ),
        Experiment(
            "network",
            "network",
            "Beyond the thesis: late (35 +/- 10 ms) and lost (5 %) frames in "
            "LOCKSTEP: the error of the on-time answers and after the timewarp corrections.",
            network,
        ),
        Experiment(
            "accuracy",
            "accuracy",
            "Beyond the thesis: on every built-in and myo-sim model, the estimator the server chooses "
            "by its measured cost against the full UKF, run offline: the mean q error over 100 ms gaps "
            "every 250 ms of the model's own excited motion and of recorded gait replayed on its hips, "
            "knees and ankles; the ratio against the bar of 1.1 x. Runs in this process, not through the "
            "server; the full run takes minutes (the full UKF of the big models: tens of ms a tick).",
            accuracy,
        ),
    )
}
