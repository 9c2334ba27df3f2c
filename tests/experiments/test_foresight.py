"""Foresight on recorded human motion that does not repeat (issue 21, must-have 5): over gRPC,
the jump (one countermovement jump, biomdp's Vicon recording), 500 ms of frames lost every 1.25 s as
in the gaps experiment, perfect frames: the default session's q error at 35 ms and at 500 ms stays
within 1.05 x the best IEEE 1278 extrapolator's."""

from __future__ import annotations

import math
from typing import Any

import pytest

from jitdyn.experiments.analysis import gap_profile
from jitdyn.experiments.foresight import EXTRAPOLATORS, RECORDING_GAPS
from jitdyn.experiments.runner import RunSpec, run_lockstep
from jitdyn.vocabulary import EstimatorKind, Scenario

pytest.importorskip("biomdp")

SECONDS = 7.9  # the whole recording: its take-off comes at 3.9 s, in the fourth gap


@pytest.mark.timeout(240)
def test_over_the_jump_the_defaults_stay_within_5_percent_of_the_best_extrapolator_at_35_and_500_ms(
    client: Any,
) -> None:
    """Measured at 500 ms: the defaults 0.39 rad against STATIC's 0.43 (0.89 x); without the novelty
    guard of the forecast combination (server/estimation/forecast.py) 1.35 rad, 3.1 x: over the gap
    of the take-off its weights, learnt while the person stood and crouched, followed the model's
    rollout and constant acceleration, metres off within half a second. At 35 ms: 0.0131 rad
    against CONSTANT_ACCELERATION's 0.0127 (1.03 x); without the regime change (a score that
    surprises every predictor replaces the horizon's covariance) 0.0134, 1.057 x: over the gap of
    the landing the weights were the flight's, the model's rollout 0.76."""
    dt = 0.01
    gap, every = RECORDING_GAPS
    ticks = math.ceil(gap / dt - 1e-9)
    short = math.ceil(0.035 / dt - 1e-9)
    gaps = (ticks, round(every / dt))
    defaults = RunSpec("cmj", Scenario.EXTERNAL, SECONDS, gaps=gaps, open_as="", default_settings=True)
    profiles = {"defaults": gap_profile(run_lockstep(client, defaults, progress=False))}
    for name in EXTRAPOLATORS:
        spec = RunSpec("cmj", Scenario.EXTERNAL, SECONDS, gaps=gaps, estimator=EstimatorKind(name))
        profiles[name] = gap_profile(run_lockstep(client, spec, progress=False))
    for h in (short, ticks):
        errors = {name: profile[h] for name, profile in profiles.items()}
        best = min(errors[name] for name in EXTRAPOLATORS)
        assert math.isfinite(errors["defaults"]) and errors["defaults"] <= 1.05 * best, (h, errors)
