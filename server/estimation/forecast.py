"""The forecast over a gap as a combination of predictors the server scores on its own frames
(forecast combination, Bates and Granger 1969; the selection of an interacting-multiple-model
filter without its mixing)::

    forecasts = ForecastCombiner(process, dt=0.05, steps_per_tick=10, nv=3)
    forecasts.advance()                         # every tick, before the frame is used
    forecasts.observe(z_qpos, z_qvel, posterior=(q, qd, act, f, fd))   # every frame
    answer = forecasts.forecast(ticks=3)        # over a gap: (weights, qpos, qvel, qacc) or None

The predictors, from the last frame and the filter's last posterior:
- MODEL: the posterior mean rolled out by the process model under its estimated force (the force
  held, or ramped with its rate under the integrated random walk): the physics' forecast;
- STATIC, CONSTANT_VELOCITY, CONSTANT_ACCELERATION: IEEE 1278's extrapolators from the last frame
  (qdd from the last two frames' qd), exactly as estimation/deadreckoning.py computes them.

Scoring: every `stride` ticks a probe starts from the frame and posterior of that tick and is
carried forward one tick per tick, for `horizon` ticks; whenever a frame arrives, every live probe
h ticks old gives each predictor's error at horizon h. The error covariance of the predictors at
each horizon, C_h (P x P, pooled over dofs), is a fading-memory average of those errors. Over a gap
of h ticks the answer is sum_p w_p q_p with the weights of least error variance, w = argmin w' C_h w
over w >= 0, sum w = 1 (exact: every subset of the P = 4 predictors is tried). Until a horizon has
MIN_SAMPLES samples the filter answers alone. A measurement's noise adds the same variance to every
predictor's error (its covariance is R 11'), which moves no weight.

Pure numpy and MuJoCo, no gRPC; one combiner per filter, driven from one thread; its state is
plain arrays, so `snapshot()`/`restore()` serve the timewarp and a replay is exact.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Final

import mujoco
import numpy as np

__all__ = ["MIN_SAMPLES", "PREDICTORS", "Forecast", "ForecastCombiner"]

# The predictors' order in weights (Result.forecast_weights).
PREDICTORS: Final = ("MODEL", "STATIC", "CONSTANT_VELOCITY", "CONSTANT_ACCELERATION")
# Samples a horizon needs before its weights answer; fading memory of the error covariances
# (weight of the past per sample 0.8: about 5 scored forecasts per horizon, so that the weights
# follow the regime of the motion just before a gap; measured in docs/experiments.md).
MIN_SAMPLES: Final = 3
FORGETTING: Final = 0.8
# Probes alive at once: the cost of scoring is this many single-point rollouts of one tick per tick.
PROBES: Final = 16


@dataclass(frozen=True)
class Forecast:
    """The combination's answer h ticks after the last frame: weights (P,) in PREDICTORS' order,
    qpos (nq,), qvel (nv,), qacc (nv,)."""

    weights: np.ndarray
    qpos: np.ndarray
    qvel: np.ndarray
    qacc: np.ndarray


@dataclass(frozen=True)
class _Probe:
    origin: int  # tick of the frame it starts from
    age: int  # ticks carried forward
    keep: bool  # a scoring probe (else only the last frame's, for a gap)
    qpos: np.ndarray  # the MODEL predictor's state now
    qvel: np.ndarray
    qacc: np.ndarray
    act: np.ndarray
    force: np.ndarray
    rate: np.ndarray | None
    q0: np.ndarray  # the frame's anchor for the extrapolators
    v0: np.ndarray
    a0: np.ndarray


@dataclass(frozen=True)
class _Snapshot:
    tick: int
    probes: tuple[_Probe, ...]
    cov: np.ndarray
    count: np.ndarray
    anchor: tuple[np.ndarray, np.ndarray, int] | None


class ForecastCombiner:
    """See the module docstring. process: the filter's process model (warm start off, actuation
    off for DRIVEN), whose qfrc_applied is the estimated force; horizon: ticks scored (the longest
    gap whose weights are learnt; a longer gap uses the last horizon's)."""

    def __init__(
        self,
        process: mujoco.MjModel,
        *,
        dt: float,
        steps_per_tick: int,
        horizon: int,
    ) -> None:
        if int(process.nq) != int(process.nv):
            raise ValueError("the forecast combination needs nq == nv (no ball or free joints)")
        self._model = process
        self._data = mujoco.MjData(process)
        self._dt = float(dt)
        self._nstep = int(steps_per_tick)
        self._h = float(process.opt.timestep)
        self._horizon = max(1, int(horizon))
        self._stride = max(1, -(-self._horizon // PROBES))
        self._nv = int(process.nv)
        self.reset()

    @property
    def horizon(self) -> int:
        return self._horizon

    def reset(self) -> None:
        """Forget every score and probe."""
        P = len(PREDICTORS)
        self._tick = 0
        self._probes: list[_Probe] = []
        self._cov = np.zeros((self._horizon + 1, P, P))
        # The weights of each horizon, as long as its covariance has not changed: the filter asks
        # for a forecast on every predict (a frame may not come), and solving every subset of the
        # predictors took 1.2 ms of myoElbow's 2 ms tick when done each time.
        self._weights: dict[int, np.ndarray] = {}
        self._count = np.zeros(self._horizon + 1)
        self._anchor: tuple[np.ndarray, np.ndarray, int] | None = None  # last frame's (q, v, tick)

    def advance(self) -> None:
        """One tick passes: every probe is carried one tick forward."""
        self._tick += 1
        self._probes = [self._step(p) for p in self._probes]

    def observe(
        self,
        qpos: np.ndarray,
        qvel: np.ndarray,
        *,
        mean_qpos: np.ndarray,
        mean_qvel: np.ndarray,
        act: np.ndarray,
        force: np.ndarray,
        rate: np.ndarray | None,
    ) -> None:
        """A frame (qpos, qvel measured) at this tick, and the filter's posterior after it: score
        the live probes against the frame, then start this tick's probe."""
        survivors: list[_Probe] = []
        for p in self._probes:
            if p.age >= 1 and p.age <= self._horizon:
                self._score(p, qpos)
            if p.keep and p.age < self._horizon:
                survivors.append(p)
        previous = self._anchor
        if previous is not None and previous[2] < self._tick:
            a0 = (qvel - previous[1]) / ((self._tick - previous[2]) * self._dt)
        else:
            a0 = np.zeros(self._nv)
        # Only a frame that follows a frame of the tick before starts a scoring probe: a gap starts
        # after such a frame, and an anchor whose qdd spans a gap (or whose posterior has just come
        # back from one) predicts worse than the anchors gaps start from.
        streak = previous is not None and previous[2] == self._tick - 1
        self._anchor = (np.array(qpos), np.array(qvel), self._tick)
        probe = _Probe(
            origin=self._tick,
            age=0,
            keep=streak and self._tick % self._stride == 0,
            qpos=np.array(mean_qpos),
            qvel=np.array(mean_qvel),
            qacc=np.zeros(self._nv),
            act=np.array(act),
            force=np.array(force),
            rate=None if rate is None else np.array(rate),
            q0=np.array(qpos),
            v0=np.array(qvel),
            a0=np.asarray(a0),
        )
        survivors.append(probe)
        self._probes = survivors

    def forecast(self) -> Forecast | None:
        """The combination's answer now, when the last frame is some ticks old and that horizon's
        weights are learnt; else None (the filter answers)."""
        latest = next(
            (p for p in reversed(self._probes) if p.age > 0 and p.origin == self._last_origin()), None
        )
        if latest is None:
            return None
        h = min(latest.age, self._horizon)
        if self._count[h] < MIN_SAMPLES:
            return None
        weights = self._weights.get(h)
        if weights is None:
            weights = self._weights[h] = _min_variance_weights(self._cov[h])
            weights.flags.writeable = False
        q, v, a = self._predictions(latest)
        return Forecast(
            weights=weights,
            qpos=weights @ q,
            qvel=weights @ v,
            qacc=weights @ a,
        )

    def snapshot(self) -> _Snapshot:
        return _Snapshot(
            tick=self._tick,
            probes=tuple(self._probes),
            cov=self._cov.copy(),
            count=self._count.copy(),
            anchor=self._anchor,
        )

    def restore(self, snap: _Snapshot) -> None:
        self._tick = snap.tick
        self._probes = list(snap.probes)
        self._cov = snap.cov.copy()
        self._count = snap.count.copy()
        self._anchor = snap.anchor
        self._weights = {}

    # -- internals --------------------------------------------------------------------------------

    def _last_origin(self) -> int:
        return -1 if self._anchor is None else self._anchor[2]

    def _predictions(self, p: _Probe) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(P, nv) each: every predictor's qpos, qvel, qacc for probe p at its age."""
        t = p.age * self._dt
        zero = np.zeros(self._nv)
        q = np.stack([p.qpos, p.q0, p.q0 + p.v0 * t, p.q0 + p.v0 * t + 0.5 * p.a0 * t * t])
        v = np.stack([p.qvel, p.v0, p.v0, p.v0 + p.a0 * t])
        a = np.stack([p.qacc, zero, zero, p.a0])
        return q, v, a

    def _positions(self, p: _Probe) -> np.ndarray:
        """(P, nv): every predictor's qpos for probe p at its age (the q of `_predictions`)."""
        t = p.age * self._dt
        q = np.empty((len(PREDICTORS), self._nv))
        q[0], q[1] = p.qpos, p.q0
        q[2] = p.q0 + p.v0 * t
        q[3] = p.q0 + p.v0 * t + 0.5 * p.a0 * t * t
        return q

    def _score(self, p: _Probe, qpos: np.ndarray) -> None:
        if not p.keep:
            return  # only the last frame's probe, kept for a gap: it scores nothing
        errors = self._positions(p) - qpos[None, :]  # (P, nv)
        if not np.all(np.isfinite(errors)):
            return
        h = p.age
        c = errors @ errors.T / self._nv
        # Sage and Husa's bias-corrected fading weight: the first sample does not count for ever.
        d = (1.0 - FORGETTING) / (1.0 - FORGETTING ** (self._count[h] + 1))
        self._cov[h] = (1.0 - d) * self._cov[h] + d * c
        self._count[h] += 1
        self._weights.pop(h, None)

    def _step(self, p: _Probe) -> _Probe:
        if p.age >= self._horizon and p.keep:
            return p
        m, d = self._model, self._data
        d.qpos[:], d.qvel[:] = p.qpos, p.qvel
        if m.na:
            d.act[:] = p.act
        d.ctrl[:] = 0.0
        force = p.force
        if p.rate is None:
            d.qfrc_applied[:] = force
            mujoco.mj_step(m, d, self._nstep)
        else:
            for s in range(self._nstep):
                d.qfrc_applied[:] = force + (s + 0.5) * self._h * p.rate
                mujoco.mj_step(m, d)
            force = force + self._nstep * self._h * p.rate
        return _Probe(
            origin=p.origin,
            age=p.age + 1,
            keep=p.keep,
            qpos=d.qpos.copy(),
            qvel=d.qvel.copy(),
            qacc=d.qacc.copy(),
            act=d.act.copy() if m.na else p.act,
            force=force,
            rate=p.rate,
            q0=p.q0,
            v0=p.v0,
            a0=p.a0,
        )


def _min_variance_weights(C: np.ndarray) -> np.ndarray:
    """argmin w' C w over w >= 0, sum w = 1, for a small C (P, P): the best of the unconstrained
    minimum-variance weights of every subset whose weights are all >= 0 (the optimum's support is
    one of them)."""
    P = C.shape[0]
    scale = float(np.trace(C)) / P
    if not np.isfinite(scale) or scale <= 0.0:
        w = np.zeros(P)
        w[0] = 1.0
        return w
    # A little ridge keeps near-collinear predictors (CV and CA over one tick) from extreme weights.
    C = C + 1e-9 * scale * np.eye(P)
    best_w, best_v = None, np.inf
    for k in range(1, P + 1):
        for subset in itertools.combinations(range(P), k):
            idx = list(subset)
            sub = C[np.ix_(idx, idx)]
            try:
                x = np.linalg.solve(sub, np.ones(k))
            except np.linalg.LinAlgError:
                continue
            total = float(x.sum())
            if total <= 0.0 or not np.all(x >= 0.0):
                continue
            w = np.zeros(P)
            w[idx] = x / total
            v = float(w @ C @ w)
            if v < best_v:
                best_w, best_v = w, v
    if best_w is None:
        best_w = np.zeros(P)
        best_w[int(np.argmin(np.diag(C)))] = 1.0
    return best_w
