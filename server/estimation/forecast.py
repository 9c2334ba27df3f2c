"""The forecast over a gap as a combination of predictors the server scores on its own frames
(forecast combination, Bates and Granger 1969; the selection of an interacting-multiple-model
filter without its mixing)::

    forecasts = ForecastCombiner(process, dt=0.05, steps_per_tick=10, horizon=4)
    forecasts.advance()                         # every tick, before the frame is used
    forecasts.observe(z_qpos, z_qvel, mean_qpos=q, mean_qvel=qd, act=act, force=f, rate=None)
    answer = forecasts.forecast()               # over a gap: CombinedForecast(weights, qpos, ...) or None

The predictors, from the last frame and the filter's last posterior (each a named family of
estimation/predictors.py, where a new one is added):
- MODEL: the posterior mean rolled out by the process model under its estimated force (the force
  held, or ramped with its rate under the integrated random walk): the physics' forecast;
- STATIC, CONSTANT_VELOCITY, CONSTANT_ACCELERATION: IEEE 1278's extrapolators from the last frame
  (qdd from the last two frames' qd), exactly as estimation/deadreckoning.py computes them;
- LEARNED (a combiner built with `learner=True`): motion matching over the session's own frames
  (estimation/matching.py): what followed the past moments most like the last frame. A scoring
  probe matches when it starts, the last frame's probe when a gap first asks for it. Where the
  motion does not repeat, its scores are poor and its weight falls
  (docs/decisions/0026-learned-foresight.md).

Scoring: every `stride` ticks a probe starts from the frame and posterior of that tick and is
carried forward one tick per tick, for `horizon` ticks; whenever a frame arrives, every live probe
h ticks old gives each predictor's error at horizon h. The error covariance of the predictors at
each horizon, C_h (P x P, pooled over dofs), is a fading-memory average of those errors. Over a gap
of h ticks the answer is sum_p w_p q_p with the weights of least error variance, w = argmin w' C_h w
over w >= 0, sum w = 1 (exact: every subset of the P = 4 predictors is tried). Until a horizon has
MIN_SAMPLES samples the filter answers alone. A measurement's noise adds the same variance to every
predictor's error (its covariance is R 11'), which moves no weight.

Novelty guard: the scores describe the motion before the gap, and a predictor far out of its
scored regime (constant acceleration over the take-off of a jump, the model's rollout of it) is
not described by them. Over a gap, a predictor whose departure from a reference now, the RMS over
dofs of q_p - r @ q, exceeds NOVELTY times the RMS departure of its scored past at that horizon
(e_p - r @ e is q_p - r @ q, the frame cancels, so its mean square is C_pp - 2 (C r)_p + r'C r of
C_h) has its errors taken as larger by the ratio over NOVELTY, s_p: C_h's row and column p times
s_p (and D_h's, for the answer's variances), and the weights are solved again on that; by the
ratio's square for MODEL, the rollout of physics under a held force, whose small scored errors
over a jump's push-off otherwise kept its weight past its end
(docs/decisions/0219-a-novel-rollout-weighs-by-the-square.md). With the prior, on a motion the
session scores unlike the prior's, a horizon with fewer than SETTLED scores has a short past, often
a slow start, from which the start itself departs: there a predictor that is the reference's by
r_p takes 1 + (1 - r_p)(s_p - 1), judged by the share of it that is not the reference's, as STATIC
is never judged (docs/decisions/0222-a-short-past-does-not-judge-a-start-of-motion.md). The answer falls back on the
predictors still in their regime, STATIC at least. The reference r is STATIC moved towards
CONSTANT_ACCELERATION as far as the last two frames' velocities agree: a real start of motion
builds its speed over frames and is measured from what they extrapolate; a glitch of one frame's
velocity has none of it the frame before and is measured from STATIC. It costs a gap tick O(P nv),
and a solve of the weights on the ticks where it acts
(docs/decisions/0027-forecast-novelty-guard.md; its reference:
docs/decisions/0216-a-start-of-motion-is-not-a-glitch.md).

Regime change: a score at which every one of PREDICTORS erred by more than SURPRISE times the RMS
error of its scored past at that horizon is a change of the motion none of them foresaw (a
landing's impact); the scores before it describe a motion that has ended, and it replaces C_h and
D_h (fading weight 1) instead of weighing 1 - FORGETTING (docs/decisions/0028-forecast-regime-change.md).

The answer's own error variances: the variance of the combined error at horizon h, w' C_h w
per dof for q, and the same with D_h, the fading covariance of the predictors' qd errors (scored
against the frame's qvel, pooled over dofs as C_h is), for qd; less the noise of the frames they
were scored against (R of q and qd, which is in every score but not in the answer's error against
the truth). The filter reports, over [q, qd], the larger of these and its own predicted variances
(estimation/ukf.py says why). Why pooled over dofs: docs/decisions/0025-forecast-pooled-covariances.md.

Cost: the live probes are rows of one table and are stepped together, one `mujoco.batch.Batch`
call per tick (each probe's own state and force; the batch reports the qacc of the last step as
mj_step does, which the MODEL predictor answers with), and scored together, one stacked product
per frame; the weights of a horizon solve each size of subset as one stacked system. The numbers
are those of stepping and scoring each probe in turn, bit for bit (tests/server/test_forecast.py
keeps that loop as its reference). With the learned predictor a frame's scoring waits, up to
PENDING frames or until a forecast is asked for, and the waiting ones are reckoned together: its
continuations cost a few dozen array operations per call whatever their number, which had been
most of its cost on a 50 ms tick. The result is the same, bit for bit.

Pure numpy and MuJoCo, no gRPC; one combiner per filter, driven from one thread; its state is
plain arrays, so `snapshot()`/`restore()` serve the timewarp and a replay is exact.

This is the reference. A session on the NATIVE engine runs the same combination compiled
(native/forecast.cc, matching.cc and, with the prior, prior.cc, through native/combiner.py;
estimation/foresight.py chooses), held to these numbers to 1e-9: there a DRIVEN cycle's forecast
costs about its probes' physics, 3.3-4.1 times less than here (a 2-link arm at 50 Hz, myoElbow at
500 Hz, a 3-joint leg with the prior at 100 Hz; docs/decisions/0208-the-forecast-in-the-native-engine.md,
docs/decisions/0218-the-prior-in-the-native-engine.md).
"""

from __future__ import annotations

import functools
import itertools
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Final

import mujoco
import mujoco.batch
import numpy as np

from jitdyn.server.estimation import predictors
from jitdyn.server.estimation.interface import SHARED_WITH_EARLIER
from jitdyn.server.estimation.matching import K, MotionMatcher
from jitdyn.server.estimation.predictors import FAMILIES, PRIOR, Family, Probes
from jitdyn.server.estimation.prior import K as PRIOR_K
from jitdyn.server.estimation.prior import PriorMatcher

__all__ = [
    "LEARNED",
    "MIN_SAMPLES",
    "PREDICTORS",
    "CombinedForecast",
    "CombinerSnapshot",
    "ForecastCombiner",
]

# The predictors' order in weights (Result.forecast_weights), and the learned one after them: the
# families of estimation/predictors.py.
PREDICTORS: Final = predictors.names(FAMILIES)
LEARNED: Final = predictors.LEARNED.names[0]
# Samples a horizon needs before its weights answer; fading memory of the error covariances
# (weight of the past per sample 0.8: about 5 scored forecasts per horizon, so that the weights
# follow the regime of the motion just before a gap; measured in docs/experiments.md).
MIN_SAMPLES: Final = 3
# Scored forecasts of LEARNED from a real match a horizon needs before LEARNED takes weight there
# (until it has a match it answers as CONSTANT_VELOCITY, and scores earned so must not weigh a
# match made later): about the fading memory's length.
LEARNED_SAMPLES: Final = 5
FORGETTING: Final = 0.8
# Probes alive at once: the cost of scoring is this many single-point rollouts of one tick per tick.
PROBES: Final = 16
# With the learned predictor, the scores of this many frames wait and are reckoned together (see
# _Scores): its continuations are a few dozen array operations however many rows they hold.
PENDING: Final = 16
# The answer's variances: the most of them that the scored frames' noise may take out (an estimate
# of R larger than a score is that estimate's error, not a perfect forecast), and a floor (rad^2,
# m^2, (rad/s)^2, (m/s)^2) below which no answer claims to know a dof.
MAX_NOISE_SHARE: Final = 0.9
VARIANCE_FLOOR: Final = 1e-12
# The novelty guard over a gap: a predictor departing from its reference (STATIC moved towards
# CONSTANT_ACCELERATION as far as the last two frames' velocities agree) by more than NOVELTY times
# the RMS departure of its scored past at that horizon has its errors taken as larger by the ratio over
# NOVELTY, at most MAX_NOVELTY times (its variance 1e6 times: all but dropped; far larger factors
# would let the solver's ridge, 1e-9 of the mean variance, swamp the others' variances). NOVELTY
# measured on the recordings at 1.5, 2 and 3 (docs/decisions/0027-forecast-novelty-guard.md). The
# model's rollout (MODEL) takes the square of that ratio
# (docs/decisions/0219-a-novel-rollout-weighs-by-the-square.md).
NOVELTY: Final = 2.0
MAX_NOVELTY: Final = 1e3
# A regime change: a score at which every one of PREDICTORS erred by more than SURPRISE times the
# RMS error of its scored past at that horizon (its error variance over SURPRISE^2 C_pp) describes
# a motion the past scores do not (a landing's impact); it replaces the horizon's covariances
# (fading weight 1) instead of weighing 1 - FORGETTING. Measured at 1.5, 2, 2.5 and 3
# (docs/decisions/0028-forecast-regime-change.md).
SURPRISE: Final = 2.0
# Scores a horizon needs before the novelty guard judges the reference's own predictors on a motion
# the session scores unlike the prior's (_agreement below 1): before, a predictor that is part of
# the reference (STATIC, CONSTANT_ACCELERATION as far as the last two frames' velocities agree) is
# judged as the reference is, by the share of it that is not the reference's
# (docs/decisions/0222-a-short-past-does-not-judge-a-start-of-motion.md).
SETTLED: Final = 12

Predictions = tuple[np.ndarray, np.ndarray, np.ndarray]

# Columns of the probes' integer marks.
_ORIGIN: Final = 0  # tick of the frame the probe starts from
_AGE: Final = 1  # ticks carried forward
_KEEP: Final = 2  # 1: a scoring probe; 0: only the last frame's, kept for a gap
_RAMP: Final = 3  # 1: its force ramps with its rate (integrated random walk)
_MATCHED: Final = 4  # 1: its LEARNED match is made (its columns hold it, NaN ticks for none)


@dataclass(frozen=True)
class CombinedForecast:
    """The combination's answer h ticks after the last frame: weights (P,) in PREDICTORS' order,
    qpos (nq,), qvel (nv,), qacc (nv,); its error variances per dof, of q and qd (nv,) each
    (see the module docstring)."""

    weights: np.ndarray
    qpos: np.ndarray
    qvel: np.ndarray
    qacc: np.ndarray
    var_q: np.ndarray
    var_qd: np.ndarray
    predictors: tuple[str, ...] = PREDICTORS  # the weights' names, in their order


@dataclass(frozen=True)
class _Columns:
    """Where each of a probe's vectors sits in its row of the table: the MODEL predictor's state
    now (qpos, qvel, qacc, act), its force and rate, and the frame's anchor for the extrapolators
    (q0, v0, a0)."""

    qpos: slice
    qvel: slice
    qacc: slice
    act: slice
    force: slice
    rate: slice
    q0: slice
    v0: slice
    a0: slice
    match_ticks: slice
    match_weights: slice
    prior_rows: slice  # the prior's match, (legs, PRIOR_K) flattened
    prior_weights: slice
    width: int

    @staticmethod
    def of(nq: int, nv: int, na: int, k: int, prior: int = 0) -> _Columns:
        sizes = {"qpos": nq, "qvel": nv, "qacc": nv, "act": na, "force": nv, "rate": nv}
        sizes |= {"q0": nv, "v0": nv, "a0": nv, "match_ticks": k, "match_weights": k}
        sizes |= {"prior_rows": prior, "prior_weights": prior}
        start, spans = 0, {}
        for name, size in sizes.items():
            spans[name] = slice(start, start + size)
            start += size
        return _Columns(**spans, width=start)


@dataclass(frozen=True)
class _Scores:
    """A frame's scoring, waiting to be reckoned: the scoring probes' rows of the table (S, width)
    and ages (S,) when the frame came, and the frame's qpos and qvel (nv,). Reckoned later, it
    gives what it would have given then: a LEARNED continuation reads rows of the matcher's log no
    later than the probe's own frame, which a later frame never rewrites (matching.py)."""

    rows: np.ndarray
    ages: np.ndarray
    qpos: np.ndarray
    qvel: np.ndarray


@dataclass(frozen=True)
class CombinerSnapshot:
    """A ForecastCombiner's whole state: its probes, scores and last frame's anchor."""

    tick: int
    marks: np.ndarray  # (probes, 5)
    table: np.ndarray  # (probes, width)
    cov: np.ndarray
    cov_v: np.ndarray
    count: np.ndarray
    anchor: tuple[np.ndarray, np.ndarray, int] | None
    # The learned predictor's state beside its log of frames; the log is indexed by tick and a
    # replay rewrites it (estimation/matching.py), so a snapshot does not copy it.
    learner: np.ndarray | None
    learned_count: np.ndarray
    # The prior's ring of recent frames (estimation/prior.py), when the combiner has the prior.
    prior: tuple[np.ndarray, np.ndarray, np.ndarray] | None
    # The scorings still waiting; each is shared with the snapshots taken after it came, so a
    # snapshot's own memory is its newest one (SHARED_WITH_EARLIER, server/runtime/limits.py).
    pending: tuple[_Scores, ...] = field(default=(), metadata={SHARED_WITH_EARLIER: True})


class ForecastCombiner:
    """See the module docstring. process: the filter's process model (warm start off, actuation
    off for DRIVEN), whose qfrc_applied is the estimated force; horizon: ticks scored (the longest
    gap whose weights are learnt; a longer gap uses the last horizon's); learner: add the LEARNED
    predictor; families: the predictors (estimation/predictors.py), FAMILIES unless given."""

    # The live probes, rows [0, n) oldest first: their vectors (_Columns) and integer marks.
    _table: np.ndarray  # (capacity, width)
    _marks: np.ndarray  # (capacity, 5)

    def __init__(
        self,
        process: mujoco.MjModel,
        *,
        dt: float,
        steps_per_tick: int,
        horizon: int,
        learner: bool = False,
        prior: PriorMatcher | None = None,
        families: tuple[Family, ...] = FAMILIES,
    ) -> None:
        if int(process.nq) != int(process.nv):
            raise ValueError("the forecast combination needs nq == nv (no ball or free joints)")
        self._model = process
        self._dt = float(dt)
        self._nstep = int(steps_per_tick)
        self._h = float(process.opt.timestep)
        self._horizon = max(1, int(horizon))
        self._stride = max(1, -(-self._horizon // PROBES))
        self._nv = int(process.nv)
        self._na = int(process.na)
        self._matcher = MotionMatcher(nv=self._nv, dt=self._dt, horizon=self._horizon) if learner else None
        self._prior = prior
        self._families = families + ((predictors.LEARNED,) if learner else ()) + ((PRIOR,) if prior else ())
        self._predictors = predictors.names(self._families)
        # Which predictors learn from the session's frames (no weight before LEARNED_SAMPLES real
        # matches, no vote on a regime change); which vote on one (neither they nor the prior);
        # STATIC and CONSTANT_ACCELERATION, between which the novelty guard's reference lies.
        self._learned_mask = np.array([f.learned for f in self._families for _ in f.names], dtype=bool)
        self._fixed = np.flatnonzero(~self._learned_mask)
        self._voters = np.array(
            [i for i in self._fixed if self._predictors[i] != PRIOR.names[0]], dtype=np.intp
        )
        self._static = self._predictors.index("STATIC")
        self._accelerating = self._predictors.index("CONSTANT_ACCELERATION")
        self._rollout = self._predictors.index("MODEL")
        self._prior_cols = PRIOR_K * prior.legs if prior is not None else 0
        self._prior_block, self._prior_mask, self._prior_cov = self._prior_scores(prior)
        self._columns = _Columns.of(
            int(process.nq), self._nv, self._na, K if learner else 0, self._prior_cols
        )
        # Scoring probes alive at once, and the last frame's (twice, for a second frame of a tick).
        self._n = 0
        self._capacity = 0
        self._grow(-(-self._horizon // self._stride) + 3)
        self.reset()

    def _prior_scores(
        self, prior: PriorMatcher | None
    ) -> tuple[np.ndarray | None, np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
        """The predictors the prior's scores cover (STATIC, the other extrapolators, PRIOR), their
        block of (P, P), and its covariances of q and qd errors at every horizon (H + 1, P, P) each;
        None without the prior or its scores."""
        P = len(self._predictors)
        mask = np.zeros((P, P), dtype=bool)
        if prior is None or prior.scores_at(self._dt) is None:
            return None, mask, None
        names = ("STATIC", "CONSTANT_VELOCITY", "CONSTANT_ACCELERATION", PRIOR.names[0])
        block = np.array([self._predictors.index(name) for name in names])  # PriorScores' order
        mask[np.ix_(block, block)] = True
        C, D = np.zeros((2, self._horizon + 1, P, P))
        for h in range(1, self._horizon + 1):
            scored = prior.scores_at(h * self._dt)
            assert scored is not None
            C[h][np.ix_(block, block)], D[h][np.ix_(block, block)] = scored
        return block, mask, (C, D)

    @property
    def horizon(self) -> int:
        return self._horizon

    @property
    def nv(self) -> int:
        return self._nv

    @property
    def na(self) -> int:
        return self._na

    def fill_window(self, frames: Callable[[int], tuple[np.ndarray, np.ndarray]]) -> int:
        """Ticks pass with the learned predictor's whole window of frames (q, qd) = frames(tick)
        recorded and nothing scored: what a measure of a learnt session's cost starts from. Returns
        the tick reached (0 without the learned predictor)."""
        if self._matcher is None:
            return self._tick
        for _ in range(self._matcher.window):
            self._tick += 1
            self._matcher.record(self._tick, *frames(self._tick))
        return self._tick

    @property
    def predictors(self) -> tuple[str, ...]:
        """The predictors' names in the order of the weights."""
        return self._predictors

    def reset(self) -> None:
        """Forget every score and probe (the learned predictor keeps the frames it has seen: they
        are the motion's, not the filter's)."""
        P = len(self._predictors)
        self._tick = 0
        self._n = 0  # live probes: rows [0, n) of the table, oldest first
        self._cov = np.zeros((self._horizon + 1, P, P))
        self._cov_v = np.zeros((self._horizon + 1, P, P))  # D_h: the same of the qd errors
        # The weights of each horizon, as long as its covariance has not changed: the filter asks
        # for a forecast on every predict (a frame may not come), and solving every subset of the
        # predictors took 1.2 ms of myoElbow's 2 ms tick when done each time.
        self._weights: dict[int, np.ndarray] = {}
        self._variances: dict[int, tuple[float, float]] = {}  # w' C_h w and w' D_h w, as _weights
        self._count = np.zeros(self._horizon + 1)
        self._learned_count = np.zeros(self._horizon + 1)  # LEARNED's scores from a real match
        self._anchor: tuple[np.ndarray, np.ndarray, int] | None = None  # last frame's (q, v, tick)
        self._pending: tuple[_Scores, ...] = ()  # frames' scorings not yet reckoned, oldest first

    def advance(self) -> None:
        """One tick passes: every probe is carried one tick forward (a scoring probe that has
        reached the horizon waits for the next frame, which scores it and lets it go)."""
        self._tick += 1
        n = self._n
        if n == 0:
            return
        marks = self._marks[:n]
        moving = (marks[:, _KEEP] == 0) | (marks[:, _AGE] < self._horizon)
        if moving.all():
            self._step(slice(0, n), self._ids[:n])
            marks[:, _AGE] += 1
        elif moving.any():
            ids = self._ids[:n][moving]
            self._step(ids, ids)
            marks[ids, _AGE] += 1

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
        n = self._n
        marks = self._marks[:n]
        age, keep = marks[:, _AGE], marks[:, _KEEP] == 1
        # Only scoring probes score; the last frame's probe was kept for a gap alone.
        scoring = keep & (age >= 1) & (age <= self._horizon)
        if scoring.any():
            ids = np.flatnonzero(scoring)
            if self._matcher is None:
                self._score(self._table[ids], self._marks[ids, _AGE], qpos, qvel, None)
            else:
                scores = _Scores(self._table[ids], self._marks[ids, _AGE], np.array(qpos), np.array(qvel))
                self._pending += (scores,)
                if len(self._pending) >= PENDING:
                    self._reckon()
        survive = keep & (age < self._horizon)
        if survive[:-1].all():
            m = n - 1 if n and not survive[-1] else n  # at most the last frame's probe goes
        else:
            survivors = np.flatnonzero(survive)
            m = survivors.size
            self._marks[:m] = self._marks[survivors]
            self._table[:m] = self._table[survivors]
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
        keep = streak and self._tick % self._stride == 0
        for learner in (self._matcher, self._prior):
            if learner is not None:
                learner.record(self._tick, qpos, qvel)
        if m + 1 > self._capacity:
            self._grow(2 * self._capacity)
        c, row = self._columns, self._table[m]
        row[c.qpos], row[c.qvel], row[c.qacc] = mean_qpos, mean_qvel, 0.0
        row[c.act], row[c.force] = act, force
        row[c.rate] = 0.0 if rate is None else rate
        row[c.q0], row[c.v0], row[c.a0] = qpos, qvel, a0
        self._marks[m] = (self._tick, 0, keep, rate is not None, 0)
        self._n = m + 1
        if keep:
            self._match(m)

    def forecast(
        self,
        *,
        noise_q: np.ndarray | None = None,
        noise_qd: np.ndarray | None = None,
        ended: bool = False,
    ) -> CombinedForecast | None:
        """The combination's answer now, when the last frame is some ticks old and that horizon's
        weights are learnt; else None (the filter answers). noise_q, noise_qd (nv,): the variance of
        the scored frames' noise on q and qd (R's diagonal), taken out of the answer's variances
        (to at most MAX_NOISE_SHARE of them); None takes nothing out. ended: asked on the frame
        that ends a gap, for the answer the gap's last tick gave (one tick earlier)."""
        # The last frame's probe is the newest, the last row (a second frame of the same tick
        # starts a second one after it); it answers once it has been carried forward.
        i = self._n - 1
        if i < 0 or self._marks[i, _ORIGIN] != self._last_origin() or self._marks[i, _AGE] == 0:
            return None
        self._reckon()
        if self._tick - int(self._marks[i, _ORIGIN]) - int(ended) > self._horizon:
            # Past the scored horizon nothing says how good a predictor is, and the last frame's
            # probe has stopped there (it waits to be scored): its answer would stand still for the
            # rest of the gap. The filter answers, its prediction moving on.
            return None
        h = min(int(self._marks[i, _AGE]), self._horizon)
        if self._count[h] < MIN_SAMPLES and self._prior is None:
            return None
        if not self._marks[i, _MATCHED]:
            self._match(i)
        matched = self._prior is None or not np.isnan(self._table[i, self._columns.prior_rows]).all()
        weights = self._weights.get(h) if matched else self._solve_weights(h, matched=False)
        if weights is None:
            weights = self._weights[h] = self._solve_weights(h)
            weights.flags.writeable = False
        q, v, a = self._predictions(i)
        row = self._table[i]
        reference = self._reference(_confirmed(row[self._columns.v0], row[self._columns.a0], self._dt))
        scale = _novelty(
            q,
            self._weighing(h)[0],
            reference,
            (self._static, self._rollout),
            settled=bool(self._count[h] >= SETTLED or self._agreement(h) >= 1.0),
        )
        if scale is not None:
            weights = self._solve_weights(h, scale, matched=matched)
        var_q, var_qd = self._answer_covariance(h, weights, noise_q, noise_qd, scale)
        return CombinedForecast(
            weights=weights,
            qpos=weights @ q,
            qvel=weights @ v,
            qacc=weights @ a,
            var_q=var_q,
            var_qd=var_qd,
            predictors=self._predictors,
        )

    def _answer_covariance(
        self,
        h: int,
        w: np.ndarray,
        noise_q: np.ndarray | None,
        noise_qd: np.ndarray | None,
        scale: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(nv,) each: the combination's error variances of q and qd at horizon h (O(nv); the
        scored variances are kept with the weights until a score changes them); scale (P,): the
        novelty guard's factors on the predictors' errors, which the answer's variances take too."""
        if scale is not None:
            S = scale[:, None] * scale[None, :]
            C, D = self._weighing(h)
            guarded = (float(w @ (S * C) @ w), float(w @ (S * D) @ w))
            return _net_of_noise(guarded[0], noise_q, self._nv), _net_of_noise(guarded[1], noise_qd, self._nv)
        scored = self._variances.get(h)
        if scored is None:
            C, D = self._weighing(h)
            scored = self._variances[h] = (float(w @ C @ w), float(w @ D @ w))
        return _net_of_noise(scored[0], noise_q, self._nv), _net_of_noise(scored[1], noise_qd, self._nv)

    def snapshot(self) -> CombinerSnapshot:
        n = self._n
        return CombinerSnapshot(
            tick=self._tick,
            marks=self._marks[:n].copy(),
            table=self._table[:n].copy(),
            cov=self._cov.copy(),
            cov_v=self._cov_v.copy(),
            count=self._count.copy(),
            anchor=self._anchor,
            learner=None if self._matcher is None else self._matcher.state(),
            learned_count=self._learned_count.copy(),
            prior=None if self._prior is None else self._prior.state(),
            pending=self._pending,
        )

    def restore(self, snap: CombinerSnapshot) -> None:
        n = snap.marks.shape[0]
        if n > self._capacity:
            self._grow(n)
        self._tick = snap.tick
        self._marks[:n], self._table[:n] = snap.marks, snap.table
        self._n = n
        self._cov = snap.cov.copy()
        self._cov_v = snap.cov_v.copy()
        self._count = snap.count.copy()
        self._learned_count = snap.learned_count.copy()
        self._anchor = snap.anchor
        self._pending = snap.pending
        if self._matcher is not None and snap.learner is not None:
            self._matcher.restore(snap.learner)
        if self._prior is not None and snap.prior is not None:
            self._prior.restore(snap.prior)
        self._weights = {}
        self._variances = {}

    # -- internals --------------------------------------------------------------------------------

    def _grow(self, capacity: int) -> None:
        """Room for `capacity` probes: the table, the marks and the batch that steps them."""
        n = self._n
        table = np.zeros((capacity, self._columns.width))
        marks = np.zeros((capacity, 5), dtype=np.int64)
        if n:
            table[:n], marks[:n] = self._table[:n], self._marks[:n]
        self._table, self._marks = table, marks
        self._ids = np.arange(capacity, dtype=np.int32)
        # nthread=1: the batch steps on the calling thread, as the probes' single MjData did (a
        # tick's probes are a few dozen microseconds of physics, too little to hand to a worker).
        self._batch = mujoco.batch.Batch(self._model, nsim=capacity, nthread=1)
        b = self._batch
        self._qpos, self._qvel, self._act = b.bind("qpos"), b.bind("qvel"), b.bind("act")
        self._qfrc, self._qacc = b.bind("qfrc_applied"), b.bind("qacc")
        b.bind("ctrl")[:] = 0.0  # actuation is off in the process model; ctrl stays zero
        self._capacity = capacity

    def _reference(self, confirmed: float) -> np.ndarray:
        """(P,) the novelty guard's reference as weights on the predictors: STATIC moved towards
        CONSTANT_ACCELERATION by `confirmed`, how far the last two frames' velocities agree."""
        reference = np.zeros(len(self._predictors))
        reference[self._static] = 1.0 - confirmed
        reference[self._accelerating] += confirmed
        return reference

    def _last_origin(self) -> int:
        return -1 if self._anchor is None else self._anchor[2]

    def _solve_weights(self, h: int, scale: np.ndarray | None = None, *, matched: bool = True) -> np.ndarray:
        """The weights of horizon h; LEARNED's 0 until it has LEARNED_SAMPLES scores from real
        matches there, and with the prior, only its scored predictors weigh until h has MIN_SAMPLES
        scores of the session's own, and PRIOR 0 when the probe it answers has no match of it (its
        scores were earned by matches). scale (P,): the novelty guard's factors on the
        predictors' errors."""
        C = self._weighing(h)[0]
        if scale is not None:
            C = scale[:, None] * C * scale[None, :]
        if self._prior_block is not None and self._count[h] < MIN_SAMPLES:
            allowed = self._prior_block
        elif matched and (self._matcher is None or self._learned_count[h] >= LEARNED_SAMPLES):
            return _min_variance_weights(C)
        elif self._matcher is None or self._learned_count[h] >= LEARNED_SAMPLES:
            allowed = np.arange(len(self._predictors))
        else:
            allowed = self._fixed
        if not matched:
            allowed = allowed[allowed != len(self._predictors) - 1]  # PRIOR is the last
        weights = np.zeros(len(self._predictors))
        weights[allowed] = _min_variance_weights(C[allowed[:, None], allowed[None, :]])
        return weights

    def _weighing(self, h: int) -> tuple[np.ndarray, np.ndarray]:
        """The covariances (P, P) of q and qd errors the weights of horizon h come from: the scored
        ones; with the prior, its scores on other people's walking (PriorScores) over STATIC, the
        other extrapolators and PRIOR, blended with the session's as a fading memory holds a score
        made before the session's n: FORGETTING^n of the prior's, times how far the session's own
        scores agree with the prior's (_agreement), the rest the session's
        (docs/decisions/0186-prior-predictor.md, docs/decisions/0222-a-short-past-does-not-judge-a-start-of-motion.md). Once the session has a score at h, the prior's
        covariances are taken at the session's scale, the variance of the best of the prior's
        predictors the session's best: the prior says how the predictors compare, the session how
        well the best of them forecasts its motion
        (docs/decisions/0211-the-prior-at-its-best-predictors-scale.md)."""
        if self._prior_cov is None or self._prior_block is None:
            return self._cov[h], self._cov_v[h]
        share = _PRIOR_SHARE[min(int(self._count[h]), _PRIOR_SHARE.size - 1)] * self._agreement(h)
        block, prior = self._prior_mask, self._prior_cov
        C0, D0 = (
            _at_scale(prior[0][h], self._cov[h], self._prior_block),
            _at_scale(prior[1][h], self._cov_v[h], self._prior_block),
        )
        C = np.where(block, share * C0 + (1.0 - share) * self._cov[h], self._cov[h])
        D = np.where(block, share * D0 + (1.0 - share) * self._cov_v[h], self._cov_v[h])
        return C, D

    def _agreement(self, h: int) -> float:
        """How far the session's own scores at h agree with the prior's, in [0, 1]: the lowest scored
        variance of the prior's predictors over PRIOR's own (1 where PRIOR scores best, or before h
        has MIN_SAMPLES scores). The prior's scores are gait's, where PRIOR forecasts best; on a
        motion where the session scores PRIOR below the extrapolators, they describe another motion
        (docs/decisions/0222-a-short-past-does-not-judge-a-start-of-motion.md)."""
        if self._prior_block is None or self._count[h] < MIN_SAMPLES:
            return 1.0
        scored = np.diagonal(self._cov[h])
        prior = float(scored[self._prior_block[-1]])
        best = float(np.min(scored[self._prior_block]))
        return 1.0 if not prior > 0.0 else min(best / prior, 1.0)

    def _match(self, i: int) -> None:
        """Probe i's LEARNED match, from its frame (the log holds it: its origin is a frame's tick)."""
        self._marks[i, _MATCHED] = 1
        c, row = self._columns, self._table[i]
        if self._prior is not None:
            rows, weights = self._prior.match(int(self._marks[i, _ORIGIN]))
            row[c.prior_rows], row[c.prior_weights] = rows.ravel(), weights.ravel()
        if self._matcher is None:
            return
        found = self._matcher.match(int(self._marks[i, _ORIGIN]))
        if found is None:
            row[c.match_ticks], row[c.match_weights] = np.nan, 0.0
        else:
            row[c.match_ticks], row[c.match_weights] = found.ticks, found.weights

    def _probes(
        self,
        rows: np.ndarray,
        ages: np.ndarray,
        learned: Predictions | None,
        prior: Predictions | None = None,
    ) -> Probes:
        """Table rows (S, width) at ages (S,) as the predictors read them (prior: PRIOR's, when
        already followed)."""
        c = self._columns
        return Probes(
            qpos=rows[:, c.qpos],
            qvel=rows[:, c.qvel],
            qacc=rows[:, c.qacc],
            q0=rows[:, c.q0],
            v0=rows[:, c.v0],
            a0=rows[:, c.a0],
            t=(ages * self._dt)[:, None],
            learned=learned,
            prior=prior if prior is not None else self._followed(rows, ages, learned),
        )

    def _followed(
        self, rows: np.ndarray, ages: np.ndarray, learned: Predictions | None
    ) -> Predictions | None:
        """PRIOR's qpos, qvel, qacc (S, nv) for table rows (S, width) at ages (S,); the dofs of no
        leg LEARNED's (the session's own history), else constant velocity."""
        if self._prior is None:
            return None
        c = self._columns
        anchor = (rows[:, c.q0], rows[:, c.v0], rows[:, c.a0])
        t = (ages * self._dt)[:, None]
        fallback = learned or (anchor[0] + anchor[1] * t, anchor[1], np.zeros_like(anchor[1]))
        shape = (rows.shape[0], self._prior.legs, PRIOR_K)
        matched = (rows[:, c.prior_rows].reshape(shape), rows[:, c.prior_weights].reshape(shape))
        return self._prior.follow(*matched, ages, anchor, fallback)

    def _predict(self, probes: Probes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(S, P, nv) each: every predictor's qpos, qvel, qacc, family by family."""
        S = probes.t.shape[0]
        q, v, a = np.empty((3, S, len(self._predictors), self._nv))
        start = 0
        for family in self._families:
            end = start + len(family.names)
            q[:, start:end], v[:, start:end], a[:, start:end] = family.predict(probes)
            start = end
        return q, v, a

    def _learned(
        self, rows: np.ndarray, ages: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The LEARNED predictor's qpos, qvel, qacc (S, nv) for table rows (S, width) at ages (S,)."""
        if self._matcher is None:
            return None
        c = self._columns
        return self._matcher.follow(
            rows[:, c.match_ticks], rows[:, c.match_weights], ages, rows[:, c.q0], rows[:, c.v0]
        )

    def _step(self, rows: slice | np.ndarray, ids: np.ndarray) -> None:
        """Probes `ids` (sorted; `rows`, the same rows as a slice when they are contiguous) one
        tick forward: one batched call when the forces are held, one per physics step when they
        ramp."""
        c, table, nstep = self._columns, self._table, self._nstep
        self._qpos[rows] = table[rows, c.qpos]
        self._qvel[rows] = table[rows, c.qvel]
        if self._na:
            self._act[rows] = table[rows, c.act]
        ramp = self._marks[rows, _RAMP] == 1
        if not ramp.any():
            self._qfrc[rows] = table[rows, c.force]
            self._batch.step(ids, nstep)
        else:
            held, ramped = ids[~ramp], ids[ramp]
            if held.size:
                self._qfrc[held] = table[held, c.force]
                self._batch.step(held, nstep)
            force, rate = table[ramped, c.force], table[ramped, c.rate]
            for s in range(nstep):
                self._qfrc[ramped] = force + (s + 0.5) * self._h * rate
                self._batch.step(ramped, 1)
            table[ramped, c.force] = force + nstep * self._h * rate
        table[rows, c.qpos] = self._qpos[rows]
        table[rows, c.qvel] = self._qvel[rows]
        table[rows, c.qacc] = self._qacc[rows]
        if self._na:
            table[rows, c.act] = self._act[rows]

    def _predictions(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(P, nv) each: every predictor's qpos, qvel, qacc for probe i at its age."""
        rows, ages = self._table[i : i + 1], self._marks[i : i + 1, _AGE]
        q, v, a = self._predict(self._probes(rows, ages, self._learned(rows, ages)))
        return q[0], v[0], a[0]

    def _reckon(self) -> None:
        """Reckon the waiting scorings, in order, the LEARNED continuations of all of them in one
        call."""
        pending, self._pending = self._pending, ()
        if not pending or self._matcher is None:
            return
        c, rows = self._columns, np.concatenate([p.rows for p in pending])
        ages = np.concatenate([p.ages for p in pending])
        learned = self._matcher.follow(
            rows[:, c.match_ticks], rows[:, c.match_weights], ages, rows[:, c.q0], rows[:, c.v0]
        )
        prior = self._followed(rows, ages, learned)
        start = 0
        for p in pending:
            end = start + p.ages.size
            part = slice(start, end)
            self._score(
                p.rows,
                p.ages,
                p.qpos,
                p.qvel,
                (learned[0][part], learned[1][part], learned[2][part]),
                None if prior is None else (prior[0][part], prior[1][part], prior[2][part]),
            )
            start = end

    def _score(
        self,
        rows: np.ndarray,
        ages: np.ndarray,
        qpos: np.ndarray,
        qvel: np.ndarray,
        learned: Predictions | None,
        prior: Predictions | None = None,
    ) -> None:
        """Scoring probes, their rows (S, width) and ages (S,) (which all differ), against a frame's
        qpos (the weights) and qpos and qvel (the answer's covariance); learned: the LEARNED
        predictor's qpos, qvel and qacc (S, nv) each, with the learned predictor (prior: PRIOR's,
        when already followed)."""
        c = self._columns
        positions, velocities, _ = self._predict(self._probes(rows, ages, learned, prior))
        if learned is not None:
            matched = ages[~np.isnan(rows[:, c.match_ticks][:, 0])]
            np.add.at(self._learned_count, matched, 1.0)
        errors = positions - qpos[None, None, :]  # (S, P, nv)
        verrors = velocities - qvel[None, None, :]  # the qd of `_predictions`, against the frame's
        finite = np.isfinite(errors).all(axis=(1, 2)) & np.isfinite(verrors).all(axis=(1, 2))
        if not finite.all():
            errors, verrors, ages = errors[finite], verrors[finite], ages[finite]
        if ages.size == 0:
            return
        # A probe that diverged without going non-finite (a rollout under a wild force) squares
        # past the largest float: it is left out as a non-finite one is, and says nothing on stderr.
        with np.errstate(over="ignore", invalid="ignore"):
            cov = errors @ errors.transpose(0, 2, 1) / self._nv
            cov_v = verrors @ verrors.transpose(0, 2, 1) / self._nv
        bounded = np.isfinite(cov).all(axis=(1, 2)) & np.isfinite(cov_v).all(axis=(1, 2))
        if not bounded.all():
            cov, cov_v, ages = cov[bounded], cov_v[bounded], ages[bounded]
            if ages.size == 0:
                return
        # Rows are oldest first, so ages fall along them; only probes that waited at the horizon
        # through a gap share one, the horizon, at the front.
        if ages.size < 2 or ages[0] != ages[1]:
            d = _FADING[np.minimum(self._count[ages], _FADING.size - 1).astype(np.intp)]
            d = np.where(self._surprised(ages, cov), 1.0, d)[:, None, None]
            self._cov[ages] = (1.0 - d) * self._cov[ages] + d * cov
            self._cov_v[ages] = (1.0 - d) * self._cov_v[ages] + d * cov_v
            self._count[ages] += 1
        else:
            # One sample after the other at the shared age, oldest first.
            for h, c, cv in zip(ages.tolist(), cov, cov_v, strict=True):
                d1 = 1.0 if self._surprised(np.array([h]), c[None])[0] else _fading(float(self._count[h]))
                self._cov[h] = (1.0 - d1) * self._cov[h] + d1 * c
                self._cov_v[h] = (1.0 - d1) * self._cov_v[h] + d1 * cv
                self._count[h] += 1
        for h in ages.tolist():
            self._weights.pop(h, None)
            self._variances.pop(h, None)

    def _surprised(self, ages: np.ndarray, cov: np.ndarray) -> np.ndarray:
        """(S,) which scores, their pooled covariances (S, P, P) at ages (S,), mark a regime change:
        every one of PREDICTORS' error variances above SURPRISE^2 times its scored past's at that
        age, once the age has MIN_SAMPLES scores (a predictor scored exact, past 0, is surprised by
        any error)."""
        voters = self._voters
        now = np.diagonal(cov, axis1=1, axis2=2)[:, voters]
        past = np.diagonal(self._cov[ages], axis1=1, axis2=2)[:, voters]
        surprised: np.ndarray = (self._count[ages] >= MIN_SAMPLES) & np.all(
            now > SURPRISE * SURPRISE * past, axis=1
        )
        return surprised


def _fading(count: float) -> float:
    """Sage and Husa's bias-corrected fading weight of the next sample after `count` of them: the
    first sample does not count for ever."""
    return (1.0 - FORGETTING) / (1.0 - float(FORGETTING ** (count + 1)))


# _fading of every count until it no longer changes (FORGETTING ** (count + 1) below half an ulp of
# 1), computed by Python's scalar power: numpy's vectorised power differs from it in the last bit
# for some counts, and the weights must not depend on how many probes scored at once.
_FADING: Final = np.array(
    list(itertools.takewhile(lambda d: d != 1.0 - FORGETTING, map(_fading, itertools.count(0.0))))
    + [1.0 - FORGETTING]
)


# The prior's share of the covariances a horizon's weights come from after n scores of the session's
# own (FORGETTING^n, by Python's scalar power as _FADING; nil from where it no longer counts).
_PRIOR_SHARE: Final = np.array([FORGETTING**n for n in range(200)] + [0.0])


def _at_scale(prior: np.ndarray, session: np.ndarray, block: np.ndarray) -> np.ndarray:
    """The prior's covariance (P, P) times the session's lowest variance among the prior's
    predictors `block` over the prior's own lowest (as it is while the session has no score there,
    or either is nil): STATIC's variance is the motion's size, which says little of how well a
    smooth motion that is not gait is forecast."""
    ours, theirs = float(np.min(np.diagonal(session)[block])), float(np.min(np.diagonal(prior)[block]))
    return prior if ours <= 0.0 or theirs <= 0.0 else prior * (ours / theirs)


def _confirmed(v0: np.ndarray, a0: np.ndarray, dt: float) -> float:
    """How far the last two frames' velocities agree, in [0, 1]: v0 (nv,) and the velocity one tick
    before it, v0 - a0 dt, their product over the larger square (1: the same; 0: a still frame, or
    opposed). A real start of motion builds its velocity over several frames; a glitch of one
    frame's velocity has none of it the frame before (or after)."""
    before = v0 - a0 * dt
    larger = max(float(v0 @ v0), float(before @ before))
    if not larger > 0.0:
        return 0.0
    return min(max(float(v0 @ before) / larger, 0.0), 1.0)


def _novelty(
    q: np.ndarray, C: np.ndarray, reference: np.ndarray, rows: tuple[int, int], *, settled: bool = True
) -> np.ndarray | None:
    """(P,) the novelty guard's factors on the predictors' errors at a gap, or None where none is
    novel: a predictor whose departure now from the reference (reference (P,): weights on the
    predictors; the RMS over dofs of q_p - reference @ q) exceeds NOVELTY times the RMS departure
    of its scored past at this horizon (e_p - reference @ e, from the pooled covariance:
    C_pp - 2 (C r)_p + r'C r) has its errors taken as larger by the ratio of the two over NOVELTY,
    by its square for the model's rollout, at most MAX_NOVELTY (STATIC is never novel: the answer
    falls back on it at least); rows: STATIC's and the rollout's. Not settled (fewer than SETTLED
    scores): a factor s of a predictor that is the reference's by r_p is 1 + (1 - r_p)(s - 1)."""
    static, rollout = rows
    now = np.mean(np.square(q - reference @ q), axis=1)
    Cr = C @ reference
    limit = NOVELTY * NOVELTY * np.maximum(np.diagonal(C) - 2.0 * Cr + float(reference @ Cr), 0.0)
    novel = now > limit
    novel[static] = False
    if not novel.any():
        return None
    scale = np.ones(q.shape[0])
    with np.errstate(divide="ignore"):
        ratio = now[novel] / limit[novel]
        factor = np.where(np.flatnonzero(novel) == rollout, ratio, np.sqrt(ratio))
        scale[novel] = np.minimum(factor, MAX_NOVELTY)
    if not settled:
        scale = 1.0 + (1.0 - reference) * (scale - 1.0)
    return scale


def _net_of_noise(scored: float, noise: np.ndarray | None, nv: int) -> np.ndarray:
    """(nv,) a scored error variance less the scored frames' noise (nv,), to at most
    MAX_NOISE_SHARE of it, and at least VARIANCE_FLOOR."""
    if noise is None:
        return np.full(nv, max(scored, VARIANCE_FLOOR))
    return np.maximum(np.maximum(scored - noise, (1.0 - MAX_NOISE_SHARE) * scored), VARIANCE_FLOOR)


def _min_variance_weights(C: np.ndarray) -> np.ndarray:
    """argmin w' C w over w >= 0, sum w = 1, for a small C (P, P): the best of the unconstrained
    minimum-variance weights of every subset whose weights are all >= 0 (the optimum's support is
    one of them). The subsets of each size are solved as one stack (LAPACK's gesv on each, as one
    at a time would)."""
    P = C.shape[0]
    scale = float(np.trace(C)) / P
    if not np.isfinite(scale) or scale <= 0.0:
        w = np.zeros(P)
        w[0] = 1.0
        return w
    # A little ridge keeps near-collinear predictors (CV and CA over one tick) from extreme weights.
    C = C + 1e-9 * scale * np.eye(P)
    subsets = _subsets(P)
    best_w, best_v = None, np.inf
    for size in subsets:
        solved = _solve_each(C[size[:, :, None], size[:, None, :]])
        if solved is None:
            continue
        x, ok = solved
        totals = x.sum(axis=1)
        for j in np.flatnonzero(ok & (totals > 0.0) & np.all(x >= 0.0, axis=1)).tolist():
            w = np.zeros(P)
            w[size[j]] = x[j] / totals[j]
            v = float(w @ C @ w)
            if v < best_v:
                best_w, best_v = w, v
    if best_w is None:
        best_w = np.zeros(P)
        best_w[int(np.argmin(np.diag(C)))] = 1.0
    return best_w


@functools.cache
def _subsets(P: int) -> tuple[np.ndarray, ...]:
    """Every subset of range(P), by size: one (subsets, size) index array per size."""
    return tuple(np.array(list(itertools.combinations(range(P), k)), dtype=np.intp) for k in range(1, P + 1))


def _solve_each(systems: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """x (m, k) with A x = 1 for each A of `systems` (m, k, k), and which were solved (m,) (a
    singular one is not); None when none was."""
    m, k = systems.shape[:2]
    try:
        return np.linalg.solve(systems, np.ones((m, k, 1)))[..., 0], np.ones(m, dtype=bool)
    except np.linalg.LinAlgError:
        x, ok = np.zeros((m, k)), np.zeros(m, dtype=bool)
        for i, A in enumerate(systems):
            try:
                x[i], ok[i] = np.linalg.solve(A, np.ones(k)), True
            except np.linalg.LinAlgError:
                pass
        return (x, ok) if ok.any() else None
