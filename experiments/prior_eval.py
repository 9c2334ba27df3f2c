"""The prior of human motion evaluated leaving one subject out: every recording of a person is
answered by a prior without that person (its model's tag prior.without.<subject>), beside the same
recording on a model whose joints say no role (no prior: the session's own history alone) and
IEEE 1278's extrapolators, with 100 ms of frames lost every 250 ms, from the first frame::

    rows = evaluate(run, recordings=("xsens_gait",), sensors=("perfect",), seconds=None)
    jitdyn experiments prior [--quick]

Each row: the q error at 35 and 100 ms after the last frame over the first stride (the gaps of the
first FIRST_STRIDE seconds) and over the whole run, as a multiple of the best extrapolator there,
and which prior answered. Why this protocol: docs/decisions/0188-prior-leave-one-subject-out.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np

from jitdyn.experiments.metrics import gap_error_profile
from jitdyn.experiments.objects import ResearchObject, Scenario
from jitdyn.experiments.prior_sources import WALKS, recorded_walk
from jitdyn.experiments.recorded import RECORDINGS, SUBJECT, RecordedMotion, research_object
from jitdyn.experiments.runner import RunSpec, Trace
from jitdyn.server.estimation.prior import library
from jitdyn.vocabulary import EstimatorKind

__all__ = ["FIRST_STRIDE", "GAPS", "HORIZONS", "RECORDINGS_EVALUATED", "PriorRow", "evaluate", "prior_used"]

# 100 ms of frames lost every 250 ms (ticks of 10 ms); the horizons read (s); the first stride (s).
GAPS: Final = (10, 25)
HORIZONS: Final = (0.035, 0.100)
FIRST_STRIDE: Final = 1.25
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


@dataclass(frozen=True)
class PriorRow:
    """One recording, sensors, window and horizon: each session's q error, and the prior used."""

    recording: str
    prior: str
    sensors: str
    window: str
    horizon: float
    errors: dict[str, float]

    @property
    def best(self) -> tuple[str, float]:
        found = [(str(e.value), self.errors[str(e.value)]) for e in EXTRAPOLATORS]
        return min(found, key=lambda item: item[1] if math.isfinite(item[1]) else math.inf)

    def ratio(self, label: str) -> float:
        return self.errors[label] / self.best[1]

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


def _errors(trace: Trace, *, until: float | None) -> dict[int, float]:
    """{ticks since the last frame: RMS q error} over the run's ticks before `until` seconds."""
    ticks = trace.t.shape[0] if until is None else int(np.searchsorted(trace.t, until))
    nq = trace.nq
    return gap_error_profile(
        trace.truth_state[:ticks, :nq], trace.estimate[:ticks, :nq], trace.received[:ticks]
    )


def evaluate(
    run: Callable[[RunSpec, ResearchObject], Trace],
    *,
    recordings: Sequence[str] = RECORDINGS_EVALUATED,
    sensors: dict[str, tuple[float, float] | None],
    seconds: float | None = None,
) -> list[PriorRow]:
    """The rows of every recording named, each run by `run` (a session of the spec on the object;
    seconds: at most this much of each recording)."""
    rows = []
    for recording in recordings:
        objects = {roles: _recorded(recording, roles=roles) for roles in (True, False)}
        length = objects[True].seconds if seconds is None else min(seconds, objects[True].seconds)
        for name, noise in sensors.items():
            profiles: dict[str, dict[str, dict[int, float]]] = {"first stride": {}, "whole run": {}}
            for label, roles, estimator in SESSIONS:
                spec = RunSpec(
                    recording,
                    Scenario.EXTERNAL,
                    length,
                    estimator=estimator or EstimatorKind.UKF,
                    gaps=GAPS,
                    noise=noise,
                    open_as="" if estimator is None else None,
                    default_settings=estimator is None,
                )
                trace = run(spec, objects[roles])
                profiles["first stride"][label] = _errors(trace, until=FIRST_STRIDE)
                profiles["whole run"][label] = _errors(trace, until=None)
            for window, by_label in profiles.items():
                for horizon in HORIZONS:
                    h = math.ceil(horizon / objects[True].dt - 1e-9)
                    errors = {label: by_label[label].get(h, math.nan) for label in by_label}
                    rows.append(PriorRow(recording, prior_used(recording), name, window, horizon, errors))
    return rows
