"""Two learned predictors of human motion side by side, in one run: motion matching over the
session's own past (server/estimation/matching.py) and an online autoregression fitted by recursive
least squares, against IEEE 1278's extrapolators, on the recorded motions; and what a tick of each
costs against the physics of a DRIVEN filter's tick.

Accuracy: every frame of a recording arrives (100 Hz, perfect or with the wearable's noise); at
every tick each predictor forecasts q 35, 100, 200 and 500 ms on from what it has seen; the RMS of
the q error over dofs and ticks (from 2 s on, when both learners have some past), and each
learner's as a multiple of the best extrapolator's at that horizon.

The autoregression: for each horizon h its own linear map (direct multi-step), from the same
feature a match compares (q at four lags over 150 ms, qd, and 1) to q(t + h) - q(t), all dofs at
once, fitted by RLS with forgetting 0.999 (half-life about 7 s at 100 Hz), P0 = 100 I.

Cost: CPU time per tick on pendulum_3 (dt 50 ms) and myoHand (dt 2 ms), a periodic motion of the
model's dofs (the cost does not depend on what the motion is): for matching, what it adds to a
tick with a frame of the forecast combination, window full (experiments/foresight.learned_cost);
for the autoregression, a frame learnt and a prediction at each of its four horizons; beside one
tick of the DRIVEN filter's physics (its sigma points times the steps of a tick, one mj_step of
the process model priced by estimation/propagate.step_seconds).

    python -m benchmarks.learned                 # needs jitdyn[experiments] (biomdp, myo_sim)
    python -m benchmarks.learned --noise         # with the wearable's noise
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable

import numpy as np

from benchmarks.ukf_cycle import load
from jitdyn.experiments.foresight import learned_cost
from jitdyn.experiments.recorded import RECORDINGS, research_object
from jitdyn.server.estimation.extrapolators import EXTRAPOLATORS, extrapolate
from jitdyn.server.estimation.matching import K, MotionMatcher
from jitdyn.vocabulary import Scenario

HORIZONS = (0.035, 0.100, 0.200, 0.500)
WEARABLE = (0.005, 0.05)
FORGET = 0.999


class RlsAutoregression:
    """Direct multi-step autoregression per horizon, fitted online by RLS (see the docstring)."""

    def __init__(self, *, nv: int, dt: float, horizons: tuple[int, ...]) -> None:
        self._nv, self._dt, self._horizons = nv, dt, horizons
        lag = max(3, round(0.15 / dt))
        self._lags = np.array([round(i * lag / 3) for i in range(4)])
        d = 5 * nv + 1
        self._theta = {h: np.zeros((d, nv)) for h in horizons}
        self._P = {h: 100.0 * np.eye(d) for h in horizons}
        self._q: list[np.ndarray] = []
        self._v: list[np.ndarray] = []

    def _feature(self, t: int) -> np.ndarray | None:
        if t - int(self._lags[-1]) < 0:
            return None
        q = np.concatenate([self._q[t - lag] - self._q[t] for lag in self._lags[1:]])
        return np.concatenate([q, self._q[t], self._v[t], [1.0]])

    def record(self, q: np.ndarray, v: np.ndarray) -> None:
        self._q.append(q)
        self._v.append(v)
        t = len(self._q) - 1
        for h in self._horizons:
            x = self._feature(t - h)
            if x is None:
                continue
            P, theta = self._P[h], self._theta[h]
            Px = P @ x
            gain = Px / (FORGET + x @ Px)
            theta += np.outer(gain, (q - self._q[t - h]) - x @ theta)
            self._P[h] = (P - np.outer(gain, Px)) / FORGET

    def predict(self, h: int) -> np.ndarray | None:
        t = len(self._q) - 1
        x = self._feature(t)
        return None if x is None else self._q[t] + x @ self._theta[h]


def _truth(name: str) -> tuple[np.ndarray, np.ndarray, float]:
    obj = research_object(name, Scenario.EXTERNAL)
    states = [obj.reset(0)]
    while True:
        try:
            states.append(obj.step())
        except IndexError:
            break
    return np.array([s.qpos for s in states]), np.array([s.qvel for s in states]), obj.dt


def accuracy(name: str, *, noise: bool) -> list[tuple[float, dict[str, float]]]:
    """Per horizon, each predictor's RMS q error (see the module docstring)."""
    q, v, dt = _truth(name)
    rng = np.random.default_rng(0)
    zq, zv = q.copy(), v.copy()
    if noise:
        zq += WEARABLE[0] * rng.standard_normal(q.shape)
        zv += WEARABLE[1] * rng.standard_normal(v.shape)
    steps = tuple(math.ceil(h / dt - 1e-9) for h in HORIZONS)
    T, nv = q.shape
    matcher = MotionMatcher(nv=nv, dt=dt, horizon=max(steps))
    ar = RlsAutoregression(nv=nv, dt=dt, horizons=steps)
    names = ("STATIC", "CONSTANT_VELOCITY", "CONSTANT_ACCELERATION", "MATCHING", "RLS_AR")
    sums = {(n, h): 0.0 for n in names for h in steps}
    counts = dict.fromkeys(steps, 0)
    first = round(2.0 / dt)
    for t in range(T):
        matcher.record(t, zq[t], zv[t])
        ar.record(zq[t], zv[t])
        if t < first:
            continue
        found = matcher.match(t)
        a0 = (zv[t] - zv[t - 1]) / dt
        for h in steps:
            if t + h >= T:
                continue
            s = h * dt
            guesses = {str(kind.value): extrapolate(kind, zq[t], zv[t], a0, s)[0] for kind in EXTRAPOLATORS}
            ticks = np.full((1, K), np.nan) if found is None else found.ticks[None, :].astype(float)
            weights = np.zeros((1, K)) if found is None else found.weights[None, :]
            guesses["MATCHING"] = matcher.follow(ticks, weights, np.array([h]), zq[t][None], zv[t][None])[0][
                0
            ]
            guess = ar.predict(h)
            guesses["RLS_AR"] = guesses["CONSTANT_VELOCITY"] if guess is None else guess
            for n in names:
                sums[n, h] += float(np.mean((guesses[n] - q[t + h]) ** 2))
            counts[h] += 1
    return [
        (hz, {n: math.sqrt(sums[n, h] / max(1, counts[h])) for n in names})
        for hz, h in zip(HORIZONS, steps, strict=True)
    ]


def _thread_us(run: Callable[[], None], count: int) -> float:
    began = time.thread_time()
    for _ in range(count):
        run()
    return (time.thread_time() - began) / count * 1e6


def autoregression_cost(name: str, dt: float) -> float:
    """us per tick of the autoregression: a frame learnt by each horizon's RLS, each predicting."""
    nv = int(load(name)[0].nv)
    ar = RlsAutoregression(nv=nv, dt=dt, horizons=tuple(math.ceil(h / dt - 1e-9) for h in HORIZONS))
    phase, w = np.arange(nv), 2 * math.pi / 0.8
    tick = [0]

    def one() -> None:
        k = tick[0]
        tick[0] = k + 1
        ar.record(0.3 * np.sin(w * k * dt + phase), 0.3 * w * np.cos(w * k * dt + phase))
        for h in ar._horizons:
            ar.predict(h)

    for _ in range(200):
        one()
    return min(_thread_us(one, 300) for _ in range(3))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--noise", action="store_true", help="the wearable's noise on every frame")
    args = parser.parse_args()
    print(
        f"accuracy, {'wearable' if args.noise else 'perfect'} frames (RMS q error, rad; x best extrapolator)"
    )
    print(f"{'recording':<11} {'ms':>4} {'STATIC':>9} {'CV':>9} {'CA':>9} {'MATCHING':>9} {'RLS_AR':>9} "
          f"{'match/best':>10} {'ar/best':>8}")  # fmt: skip
    for name in RECORDINGS:
        for horizon, errors in accuracy(name, noise=args.noise):
            best = min(errors[n] for n in ("STATIC", "CONSTANT_VELOCITY", "CONSTANT_ACCELERATION"))
            cells = " ".join(f"{errors[n]:9.4f}" for n in errors)
            print(f"{name:<11} {horizon * 1000:4.0f} {cells} {errors['MATCHING'] / best:10.3f} "
                  f"{errors['RLS_AR'] / best:8.3f}")  # fmt: skip
    print("\ncost per tick (us, CPU; matching: what it adds to a tick of the forecast combination)")
    print(f"{'model':<11} {'matching':>9} {'RLS_AR':>9} {'physics':>9} {'match/phys':>10} {'ar/phys':>8}")
    for name, dt in (("pendulum_3", 0.05), ("myohand", 0.002)):
        m, p = learned_cost(name, dt=dt)
        a = autoregression_cost(name, dt)
        print(f"{name:<11} {m:9.1f} {a:9.1f} {p:9.1f} {m / p:10.3f} {a / p:8.3f}")


if __name__ == "__main__":
    main()
