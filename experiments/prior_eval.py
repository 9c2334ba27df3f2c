"""The prior of human motion evaluated leaving one subject out: every recording of a person is
answered by a prior without that person (its model's tag prior.without.<subject>), beside the same
recording on a model whose joints say no role (no prior: the session's own history alone) and
IEEE 1278's extrapolators, with 100 ms of frames lost every 250 ms, from the first frame::

    rows = evaluate(run, recordings=("xsens_gait",), sensors=("perfect",), seconds=None)
    jitdyn experiments prior [--quick]

Each row: the q error at 35 and 100 ms after the last frame over the first stride (the gaps of the
first FIRST_STRIDE seconds) and over the whole run, as a multiple of the best extrapolator there,
and which prior answered. Why this protocol: docs/decisions/0188-prior-leave-one-subject-out.md.

With phases (`evaluate(..., phases=PHASES)`, what `jitdyn experiments prior` runs) every recording
is run once more for each later start of the same schedule, and each cell pools the gaps of all
phases, with a 90 % bootstrap interval over its gaps of the ratio to the best extrapolator; phase 0
is the single-phase protocol, whose cells each row keeps (docs/decisions/0202-gap-phases.md).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Final

import numpy as np

from jitdyn.experiments.metrics import ticks_since_frame
from jitdyn.experiments.objects import ResearchObject, Scenario
from jitdyn.experiments.prior_sources import WALKS, recorded_walk
from jitdyn.experiments.recorded import RECORDINGS, SUBJECT, RecordedMotion, research_object
from jitdyn.experiments.runner import RunSpec, Trace
from jitdyn.server.estimation.prior import library
from jitdyn.vocabulary import EstimatorKind

__all__ = [
    "FIRST_STRIDE",
    "GAPS",
    "HORIZONS",
    "PHASES",
    "RECORDINGS_EVALUATED",
    "SINGLE_PHASE",
    "PriorRow",
    "evaluate",
    "prior_used",
    "short_limit",
]

# 100 ms of frames lost every 250 ms (ticks of 10 ms); the horizons read (s); the first stride (s).
GAPS: Final = (10, 25)
HORIZONS: Final = (0.035, 0.100)
FIRST_STRIDE: Final = 1.25
# The gaps' phases (s): the first gap starts one period in (250 ms) plus this. (0.0,) is the
# single-phase protocol of 0188-0201; five phases a fifth of a period apart put a first stride's
# cell at 20 gaps instead of 4 (docs/decisions/0202-gap-phases.md).
SINGLE_PHASE: Final = (0.0,)
PHASES: Final = (0.0, 0.05, 0.10, 0.15, 0.20)
# The bootstrap interval of a cell's ratio: its level, its draws and their seed.
LEVEL: Final = 0.9
DRAWS: Final = 2000
RECORDINGS_EVALUATED: Final = (*RECORDINGS, *(f"{w}_walk" for w in WALKS))
EXTRAPOLATORS: Final = (
    EstimatorKind.STATIC,
    EstimatorKind.CONSTANT_VELOCITY,
    EstimatorKind.CONSTANT_ACCELERATION,
)
# How each session is opened: the defaults with the prior, the defaults with no roles, and the
# extrapolators (the label, roles, the estimator or None for the server's defaults).
SESSIONS: Final = (
    ("defaults", True, None),
    ("no roles", False, None),
    *((str(e.value), True, e) for e in EXTRAPOLATORS),
)


def repetitive(recording: str) -> bool:
    return RECORDINGS.get(recording, True)


def prior_used(recording: str) -> str:
    """Which prior answers `recording`: its subjects, and who is left out."""
    subject = subject_of(recording)
    return library(() if subject is None else (subject,)).describe()


def target(recording: str, horizon: float, sensors: str) -> float | None:
    """The largest multiple of the best extrapolator asked (None: none): gait 0.8 x at 35 ms and
    0.5 x at 100 ms with perfect frames, 0.7 x at 100 ms with a wearable's; motion that does not
    repeat 1.05 x."""
    if not repetitive(recording):
        return 1.05
    if sensors != "perfect":
        return None if horizon < 0.05 else 0.7
    return 0.8 if horizon < 0.05 else 0.5


def short_limit(recording: str, horizon: float) -> float | None:
    """Issue 33's must-have 4 (None: it asks nothing): gait at or below the best extrapolator at
    35 ms; motion that does not repeat within 1.05 x at every horizon."""
    if not repetitive(recording):
        return 1.05
    return 1.0 if horizon < 0.05 else None


def _best(errors: dict[str, float]) -> tuple[str, float]:
    found = [(str(e.value), errors[str(e.value)]) for e in EXTRAPOLATORS]
    return min(found, key=lambda item: item[1] if math.isfinite(item[1]) else math.inf)


@dataclass(frozen=True, eq=False)
class PriorRow:
    """One recording, sensors, window and horizon: each session's q error (the RMS over the gaps of
    every phase), and the prior used."""

    recording: str
    prior: str
    sensors: str
    window: str
    horizon: float
    errors: dict[str, float]
    # Each gap's squared q error (the mean over joints) per session, phase after phase, gap i of
    # every session the same gap; and each phase's RMS errors.
    gaps: dict[str, np.ndarray] = field(default_factory=dict)
    by_phase: dict[float, dict[str, float]] = field(default_factory=dict)

    @property
    def best(self) -> tuple[str, float]:
        return _best(self.errors)

    def ratio(self, label: str) -> float:
        return self.errors[label] / self.best[1]

    def phase_ratio(self, phase: float, label: str = "defaults") -> float:
        """The ratio of one phase's gaps alone (phase 0.0: the single-phase protocol's cell)."""
        errors = self.by_phase[phase]
        return errors[label] / _best(errors)[1]

    @property
    def count(self) -> int:
        """The gaps the cell holds."""
        return len(self.gaps.get("defaults", ()))

    def interval(
        self, label: str = "defaults", *, level: float = LEVEL, draws: int = DRAWS
    ) -> tuple[float, float]:
        """The bootstrap interval of ratio(label): the gaps drawn with replacement, the same draw for
        every session, the best extrapolator chosen again in each draw."""
        n = self.count
        if n == 0:
            return math.nan, math.nan
        rng = np.random.default_rng(0)
        draw = rng.integers(0, n, size=(draws, n))
        own = self.gaps[label][draw].mean(axis=1)
        best = np.min(
            [np.nan_to_num(self.gaps[str(e.value)][draw].mean(axis=1), nan=np.inf) for e in EXTRAPOLATORS],
            axis=0,
        )
        ratios = np.sqrt(own / best)
        tail = (1.0 - level) / 2.0 * 100.0
        return float(np.percentile(ratios, tail)), float(np.percentile(ratios, 100.0 - tail))

    def standing(self, limit: float | None) -> str:
        """The defaults against `limit`: met or missed, and whether the limit lies outside the
        cell's interval (the verdict holds at that level) or inside it."""
        if limit is None:
            return ""
        ratio, (low, high) = self.ratio("defaults"), self.interval()
        verdict = "met" if ratio <= limit else "missed"
        if high <= limit or low > limit:
            return f"{verdict}, outside the {LEVEL:.0%} interval"
        return f"{verdict}, limit inside the {LEVEL:.0%} interval"

    @property
    def verdict(self) -> str:
        limit, ratio = target(self.recording, self.horizon, self.sensors), self.ratio("defaults")
        if limit is None:
            return ""
        return "met" if ratio <= limit else f"missed by {ratio - limit:.3g}"


def subject_of(recording: str) -> str | None:
    """Whose motion `recording` is, as the prior names its people (None: none of them)."""
    walk = recording.removesuffix("_walk")
    return walk if walk in WALKS and recording.endswith("_walk") else SUBJECT.get(recording)


def _recorded(name: str, *, roles: bool) -> RecordedMotion:
    subject = subject_of(name)
    if subject in WALKS:
        return recorded_walk(subject, roles=roles)
    obj = research_object(name, Scenario.EXTERNAL, roles=roles)
    if not isinstance(obj, RecordedMotion):
        raise TypeError(
            f"{name!r} is not a recorded motion; the recordings are {', '.join(RECORDINGS_EVALUATED)}"
        )
    return obj


def _gap_errors(trace: Trace, h: int, *, until: float | None) -> np.ndarray:
    """Each gap's squared q error (the mean over joints) h ticks after its last frame, over the
    run's ticks before `until` seconds, in time order."""
    ticks = trace.t.shape[0] if until is None else int(np.searchsorted(trace.t, until))
    nq = trace.nq
    since = ticks_since_frame(trace.received[:ticks])
    squared = ((trace.truth_state[:ticks, :nq] - trace.estimate[:ticks, :nq]) ** 2).mean(axis=1)
    return np.asarray(squared[since == h], dtype=float)


def _rms(squared: np.ndarray) -> float:
    return float(np.sqrt(squared.mean())) if squared.size else math.nan


_Cell = tuple[str, float]  # (window, horizon)


def _phase(
    run: Callable[[RunSpec, ResearchObject], Trace],
    recording: str,
    objects: dict[bool, RecordedMotion],
    length: float,
    noise: tuple[float, float] | None,
    phase: float,
) -> dict[_Cell, dict[str, np.ndarray]]:
    """Every session of one phase: {(window, horizon): {label: each gap's squared error}}, the
    labels' gaps cut to the same count (a run that stopped early has fewer)."""
    dt = objects[True].dt
    first = GAPS[1] + round(phase / dt)
    cells: dict[_Cell, dict[str, np.ndarray]] = {}
    for label, roles, estimator in SESSIONS:
        spec = RunSpec(
            recording,
            Scenario.EXTERNAL,
            length,
            estimator=estimator or EstimatorKind.UKF,
            gaps=GAPS,
            gap_first=first,
            noise=noise,
            open_as="" if estimator is None else None,
            default_settings=estimator is None,
        )
        trace = run(spec, objects[roles])
        for window, until in (("first stride", FIRST_STRIDE), ("whole run", None)):
            for horizon in HORIZONS:
                h = math.ceil(horizon / dt - 1e-9)
                cells.setdefault((window, horizon), {})[label] = _gap_errors(trace, h, until=until)
    for by_label in cells.values():
        n = min(len(g) for g in by_label.values())
        for label in by_label:
            by_label[label] = by_label[label][:n]
    return cells


def evaluate(
    run: Callable[[RunSpec, ResearchObject], Trace],
    *,
    recordings: Sequence[str] = RECORDINGS_EVALUATED,
    sensors: dict[str, tuple[float, float] | None],
    seconds: float | None = None,
    phases: Sequence[float] = SINGLE_PHASE,
) -> list[PriorRow]:
    """The rows of every recording named, each run by `run` (a session of the spec on the object;
    seconds: at most this much of each recording) once per phase (s after the single-phase
    protocol's first gap; every cell pools the gaps of all phases)."""
    rows = []
    for recording in recordings:
        objects = {roles: _recorded(recording, roles=roles) for roles in (True, False)}
        length = objects[True].seconds if seconds is None else min(seconds, objects[True].seconds)
        for name, noise in sensors.items():
            runs = {phase: _phase(run, recording, objects, length, noise, phase) for phase in phases}
            for window, horizon in runs[phases[0]]:
                pooled = {
                    label: np.concatenate([runs[p][window, horizon][label] for p in phases])
                    for label in runs[phases[0]][window, horizon]
                }
                by_phase = {
                    p: {label: _rms(g) for label, g in runs[p][window, horizon].items()} for p in phases
                }
                errors = {label: _rms(g) for label, g in pooled.items()}
                rows.append(
                    PriorRow(
                        recording, prior_used(recording), name, window, horizon, errors, pooled, by_phase
                    )
                )
    return rows
