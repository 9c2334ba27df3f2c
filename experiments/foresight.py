"""Foresight on recorded human motion: the default session's gap answers against the best
extrapolator per recording and horizon, the targets they are held to, and what the learned
predictor (server/estimation/matching.py) costs a tick beside the tick's physics.

    rows = foresight_rows(errors)              # errors: {(recording, sensors, estimator): {gap: error}}
    matching_us, physics_us = learned_cost("pendulum_3", dt=0.05)
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Mapping

import mujoco
import numpy as np

from jitdyn.experiments.objects import load_source
from jitdyn.experiments.recorded import RECORDINGS
from jitdyn.server.estimation.config import LARGE_STATE
from jitdyn.server.estimation.forecast import PROBES
from jitdyn.server.estimation.matching import K, MotionMatcher
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
    """Per recording, sensors and horizon: the defaults' q error, the best extrapolator's, their
    ratio, the target and its verdict. errors: (recording, sensors, estimator label) -> {gap: error}."""
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


def _thread_us(run: Callable[[], None], count: int) -> float:
    began = time.thread_time()
    for _ in range(count):
        run()
    return (time.thread_time() - began) / count * 1e6


def learned_cost(name: str, *, dt: float, seconds: float = 2.0) -> tuple[float, float]:
    """(us, us): CPU time of the learned predictor's work in a tick of a DRIVEN session of model
    `name` (frame recorded, a probe matched every stride ticks, every live probe followed), with a
    full window; and of the tick's physics (the filter's sigma points times the physics steps of a
    tick, one mj_step priced by step_seconds). The best of three runs of `seconds` of ticks."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # myo_sim: "Attaching a spec with an empty prefix"
        model = load_source(name).compile()
    process = process_model(model, scenario="DRIVEN")
    nv = int(model.nv)
    horizon = math.ceil(0.5 / dt - 1e-9)
    stride = max(1, -(-horizon // PROBES))
    matcher = MotionMatcher(nv=nv, dt=dt, horizon=horizon)
    phase, w = np.arange(nv), 2 * math.pi / 0.8
    warm = round(25.0 / dt)
    for k in range(warm):  # a periodic motion: the cost does not depend on what the motion is
        matcher.record(k, 0.5 * np.sin(w * k * dt + phase), 0.5 * w * np.cos(w * k * dt + phase))
    live = np.full((PROBES, K), float(warm - horizon - 7))
    weights = np.full((PROBES, K), 1.0 / K)
    ages = np.arange(PROBES) % horizon + 1
    tick = [warm]

    def one() -> None:
        k = tick[0]
        tick[0] = k + 1
        q, v = 0.5 * np.sin(w * k * dt + phase), 0.5 * w * np.cos(w * k * dt + phase)
        matcher.record(k, q, v)
        if k % stride == 0:
            matcher.match(k)
        matcher.follow(live, weights, ages, np.tile(q, (PROBES, 1)), np.tile(v, (PROBES, 1)))

    count = max(100, round(seconds / dt))
    matching = min(_thread_us(one, count) for _ in range(3))
    n = 2 * nv  # [q, qd]: 2n + 1 points below LARGE_STATE (of [q, qd, f]), n + 1 simplex points from it on
    nsigma = 2 * (3 * nv) + 1 if 3 * nv < LARGE_STATE else n + 1
    steps = max(1, round(dt / process.opt.timestep))
    physics = nsigma * steps * step_seconds(process, mujoco.MjData(process)) * 1e6
    return matching, physics
