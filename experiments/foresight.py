"""Foresight on recorded human motion: the default session's gap answers against the best
extrapolator per recording and horizon, the targets they are held to, and what the learned
predictor (server/estimation/matching.py) costs a tick beside the tick's physics.

    rows = foresight_rows(errors)              # errors: {(recording, sensors, estimator): {gap: error}}
    added_us, physics_us = learned_cost("pendulum_3", dt=0.05)
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Mapping

import mujoco
import numpy as np

from jitdyn.experiments.objects import load_source
from jitdyn.experiments.prior_eval import prior_used
from jitdyn.experiments.recorded import RECORDINGS
from jitdyn.server.estimation.config import LARGE_STATE
from jitdyn.server.estimation.forecast import ForecastCombiner
from jitdyn.server.estimation.foresight import FORECAST_HORIZON
from jitdyn.server.estimation.propagate import process_model, step_seconds

__all__ = ["HORIZONS", "RECORDING_GAPS", "foresight_rows", "learned_cost", "target"]

# The horizons read off the recordings (s), and their gaps: 500 ms without frames every 1.25 s.
HORIZONS = (0.035, 0.100, 0.200, 0.500)
RECORDING_GAPS = (0.5, 1.25)
EXTRAPOLATORS = ("STATIC", "CONSTANT_VELOCITY", "CONSTANT_ACCELERATION")


def target(*, repetitive: bool, sensors: str, gap: float) -> float | None:
    """The largest multiple of the best extrapolator the defaults may answer with (None: no
    target): repetitive motion 0.8 x at 35 ms and 0.5 x at 100 and 200 ms (0.7 x at 100 ms with a
    wearable's noise); motion that does not repeat 1.05 x at every horizon (the learner must not
    hurt where there is nothing to learn)."""
    ms = round(gap * 1000)
    if not repetitive:
        return 1.05
    if sensors == "perfect":
        return {35: 0.8, 100: 0.5, 200: 0.5}.get(ms)
    return 0.7 if ms == 100 else None


def foresight_rows(
    errors: Mapping[tuple[str, str, str], Mapping[float, float]],
) -> list[tuple[object, ...]]:
    """Per recording, sensors and horizon: the prior of human motion that answered it (its people,
    the recording's own left out), the defaults' q error, the best extrapolator's, their ratio, the
    target and its verdict. errors: (recording, sensors, estimator label) -> {gap: error}."""
    rows: list[tuple[object, ...]] = []
    pairs = sorted(
        {(name, sensors) for name, sensors, _ in errors}, key=lambda p: (list(RECORDINGS).index(p[0]), p[1])
    )
    for name, sensors in pairs:
        ours = errors[name, sensors, "UKF, defaults"]
        for gap in HORIZONS:
            best_label, best = min(
                ((e, errors[name, sensors, e][gap]) for e in EXTRAPOLATORS),
                key=lambda v: v[1] if math.isfinite(v[1]) else math.inf,
            )
            ratio = ours[gap] / best
            limit = target(repetitive=RECORDINGS[name], sensors=sensors, gap=gap)
            verdict = "" if limit is None else ("met" if ratio <= limit else f"missed by {ratio - limit:.3g}")
            rows.append(
                (
                    name,
                    prior_used(name),
                    "repetitive" if RECORDINGS[name] else "not repetitive",
                    sensors,
                    round(gap * 1000),
                    ours[gap],
                    best,
                    best_label,
                    ratio,
                    "" if limit is None else f"<= {limit:g} x",
                    verdict,
                )
            )
    return rows


def _tick_us(combiner: ForecastCombiner, *, dt: float, start: int, count: int) -> float:
    """CPU time (us) of a tick of `combiner` with its frame (advance, observe: the scoring) on a
    periodic motion of its dofs (the cost does not depend on what the motion is), the best of three
    runs."""
    nv = combiner.nv
    phase, w = np.arange(nv), 2 * math.pi / 0.8
    act, force = np.zeros(combiner.na), np.zeros(nv)

    def tick(k: int) -> None:
        q, v = 0.3 * np.sin(w * k * dt + phase), 0.3 * w * np.cos(w * k * dt + phase)
        combiner.advance()
        combiner.observe(q, v, mean_qpos=q, mean_qvel=v, act=act, force=force, rate=None)

    for k in range(start, start + combiner.horizon + 4):  # every probe alive
        tick(k)
    best, k = math.inf, start + combiner.horizon + 4
    for _ in range(3):
        began = time.thread_time()
        for j in range(k, k + count):
            tick(j)
        best = min(best, time.thread_time() - began)
        k += count
    return best / count * 1e6


def learned_cost(name: str, *, dt: float, ticks: int = 300) -> tuple[float, float]:
    """(us, us): what the learned predictor adds to a tick with a frame of a DRIVEN session's
    forecast combination of model `name` (the CPU time of a tick with it less one without, each the
    best of three runs of `ticks` ticks, the learner's window full; a gap's ticks instead solve for
    5 weights instead of 4, once a horizon), and the tick's physics (the filter's
    sigma points times the physics steps of a tick, one mj_step priced by step_seconds)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # myo_sim: "Attaching a spec with an empty prefix"
        model = load_source(name).compile()
    process = process_model(model, scenario="DRIVEN")
    nv = int(model.nv)
    steps = max(1, round(dt / process.opt.timestep))
    horizon = math.ceil(FORECAST_HORIZON / dt - 1e-9)
    costs = []
    for learner in (False, True):
        combiner = ForecastCombiner(process, dt=dt, steps_per_tick=steps, horizon=horizon, learner=learner)
        warm = combiner.fill_window(lambda k: _frame(k, dt=dt, nv=nv)) if learner else 0
        costs.append(_tick_us(combiner, dt=dt, start=warm, count=ticks))
    n = 2 * nv  # [q, qd]: 2n + 1 points below LARGE_STATE (of [q, qd, f]), n + 1 simplex points from it on
    nsigma = 2 * (3 * nv) + 1 if 3 * nv < LARGE_STATE else n + 1
    physics = nsigma * steps * step_seconds(process, mujoco.MjData(process)) * 1e6
    return costs[1] - costs[0], physics


def _frame(k: int, *, dt: float, nv: int) -> tuple[np.ndarray, np.ndarray]:
    phase, w = np.arange(nv), 2 * math.pi / 0.8
    return 0.3 * np.sin(w * k * dt + phase), 0.3 * w * np.cos(w * k * dt + phase)
