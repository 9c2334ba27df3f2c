"""A predictor that learns the motion from the session's own past: motion matching, as character
animation does it (find the past moments most like now, and follow what came after them)::

    matcher = MotionMatcher(nv=3, dt=0.01, horizon=50)
    matcher.record(tick, qpos, qvel)            # every frame, at its tick
    found = matcher.match(tick)                  # at a frame's tick: Match(ticks, weights) or None
    q, v, a = matcher.follow(found_ticks, found_weights, ages, q0, v0)   # (S, nv) each

The log: the frames of the last WINDOW seconds, one row per tick (a tick without a frame is a
hole), in a ring indexed by the tick, each row stamped with its tick. A replay after a late frame
rewrites the same rows with the same frames, so a restored combiner matches as it did the first
time (the ring keeps REWIND_MARGIN seconds beyond the window, so that the rows a replay reads are
never those of its own future). Every CANDIDATE_EVERY seconds a frame also stores its feature: its
q at four lags over the last LAG seconds and its qd, the description of "now" that a match
compares. A match is the K nearest candidates by the distance of their features to the frame's,
each feature scaled by its spread (a fading variance over about the window), weighted by inverse
distance;
a candidate must have HORIZON ticks of past after it (its continuation is known).

What a match predicts h ticks on: the frame's q plus the weighted displacement of the candidates
over h ticks (the same for qd), over the candidates whose row h ticks on holds a frame; none of
them does, and it answers as CONSTANT_VELOCITY would. Why motion matching and not an online
autoregression: docs/decisions/0026-learned-foresight.md.

Cost: a match is O(window / CANDIDATE_EVERY x 5 nv) in one vectorised pass; memory is
O(window / dt x nv). Pure numpy; one matcher per filter, driven from one thread.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

import numpy as np

from jitdyn.server.estimation.extrapolators import extrapolate
from jitdyn.vocabulary import EstimatorKind

__all__ = ["CANDIDATE_EVERY", "LAG", "WINDOW", "K", "Match", "MotionMatcher"]

# The past a match searches (s), how far apart its candidates are (s), the span of a feature (s),
# and the candidates blended.
WINDOW: Final = 20.0
CANDIDATE_EVERY: Final = 0.01
LAG: Final = 0.15
K: Final = 10
# The time constant (s) over which the frame's own qd, where it differs from the candidates', fades
# into theirs.
FADE: Final = 0.1
# Seconds of rows kept beyond the window and the horizon: the deepest rewind whose replay matches
# exactly as the first pass did.
REWIND_MARGIN: Final = 2.0
# The rate of the features' fading moments per candidate (a memory of about the window).
SPREAD_RATE: Final = CANDIDATE_EVERY / WINDOW
_LAGS: Final = 4  # q at 0, LAG/3, 2 LAG/3, LAG


@dataclass(frozen=True)
class Match:
    """The K candidate ticks (K,) and their weights (K,) summing to 1."""

    ticks: np.ndarray
    weights: np.ndarray


class MotionMatcher:
    """See the module docstring. nv: dofs (q and qd alike: no ball or free joints); dt: the tick
    (s); horizon: the longest continuation asked for (ticks)."""

    def __init__(self, *, nv: int, dt: float, horizon: int) -> None:
        if nv < 1 or not dt > 0.0 or horizon < 1:
            raise ValueError(f"nv, dt and horizon must be positive, got {nv}, {dt}, {horizon}")
        self._nv, self._dt, self._horizon = int(nv), float(dt), int(horizon)
        self._window = max(2 * horizon, round(WINDOW / dt))
        self._capacity = self._window + horizon + round(REWIND_MARGIN / dt) + 1
        self._every = max(1, round(CANDIDATE_EVERY / dt))
        lag = max(_LAGS - 1, round(LAG / dt))
        self._lags = [round(i * lag / (_LAGS - 1)) for i in range(_LAGS)]
        self._slots = -(-self._capacity // self._every)
        self._stamp = np.full(self._capacity, -1, dtype=np.int64)
        self._q = np.zeros((self._capacity, self._nv))
        self._v = np.zeros((self._capacity, self._nv))
        self._a = np.zeros((self._capacity, self._nv))
        # Candidates: one slot every `every` ticks, stamped with its tick; (LAGS + 1) nv features.
        self._cstamp = np.full(self._slots, -1, dtype=np.int64)
        self._features = np.zeros((self._slots, (_LAGS + 1) * self._nv))
        self._scratch = np.empty_like(self._features)  # a match's differences, written in place
        self._last: tuple[int, np.ndarray | None] = (-1, None)  # the last candidate tick's feature
        self._moments = np.zeros((2, (_LAGS + 1) * self._nv))  # fading mean and variance

    @property
    def horizon(self) -> int:
        return self._horizon

    @property
    def window(self) -> int:
        """Ticks of past a match searches."""
        return self._window

    def record(self, tick: int, qpos: np.ndarray, qvel: np.ndarray) -> None:
        """The frame of `tick` (nv,) each; a tick recorded twice keeps the later frame."""
        row = tick % self._capacity
        previous = (tick - 1) % self._capacity
        self._stamp[row] = tick
        self._q[row], self._v[row] = qpos, qvel
        # qdd by the backward difference of qd (0 after a hole).
        if self._stamp[previous] == tick - 1:
            self._a[row] = (qvel - self._v[previous]) / self._dt
        else:
            self._a[row] = 0.0
        if tick % self._every == 0:
            slot = (tick // self._every) % self._slots
            feature = self._feature(tick)
            self._cstamp[slot] = -1 if feature is None else tick
            self._last = (tick, feature)
            if feature is not None:
                self._features[slot] = feature
                # The spread of each feature, a fading average over about the window.
                moments = self._moments
                moments[0] += SPREAD_RATE * (feature - moments[0])
                moments[1] += SPREAD_RATE * (np.square(feature - moments[0]) - moments[1])

    def state(self) -> np.ndarray:
        """The matcher's state beside its log (the features' fading moments), for a snapshot."""
        return self._moments.copy()

    def restore(self, state: np.ndarray) -> None:
        self._moments[:] = state

    def match(self, tick: int) -> Match | None:
        """The K candidates most like the frame of `tick` (recorded), or None (no feature for it:
        a hole within LAG before it, or too few candidates yet)."""
        query = self._last[1] if self._last[0] == tick else self._feature(tick)
        if query is None:
            return None
        stamps = self._cstamp
        out = (stamps <= tick - self._window) | (stamps > tick - self._horizon)
        if stamps.size - np.count_nonzero(out) < K:
            return None
        # Each feature by its spread.
        inverse = 1.0 / np.maximum(self._moments[1], 1e-18)
        squares = np.subtract(self._features, query, out=self._scratch)
        distance = np.square(squares, out=squares) @ inverse
        distance[out] = np.inf
        nearest = distance.argpartition(K - 1)[:K]
        d = distance[nearest]
        weights = 1.0 / (d + 1e-3 * float(d.min()) + 1e-12)
        return Match(ticks=stamps[nearest], weights=weights / weights.sum())

    def follow(
        self,
        ticks: np.ndarray,
        weights: np.ndarray,
        ages: np.ndarray,
        q0: np.ndarray,
        v0: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """qpos, qvel, qacc (S, nv) of S matches (ticks, weights (S, K)) `ages` (S,) ticks on from
        frames q0, v0 (S, nv): the weighted displacement of the candidates, and the difference of
        the frame's qd from theirs fading with time constant FADE (see the module docstring). A row
        of NaN ticks is no match: CONSTANT_VELOCITY's answer."""
        ages = np.asarray(ages, dtype=np.int64)
        t = (ages * self._dt)[:, None]
        known = ticks[:, 0] == ticks[:, 0]  # not NaN
        if not known.all():
            q, v, a = extrapolate(EstimatorKind.CONSTANT_VELOCITY, q0, v0, np.zeros_like(v0), t)
            if known.any():
                rows = np.flatnonzero(known)
                q[rows], v[rows], a[rows] = self.follow(
                    ticks[rows], weights[rows], ages[rows], q0[rows], v0[rows]
                )
            return q, v, a
        start = ticks.astype(np.int64)
        later = start + ages[:, None]
        capacity, stamp = self._capacity, self._stamp
        r0, r1 = start % capacity, later % capacity
        w = weights * (stamp[r1] == later)
        total = w.sum(axis=1, keepdims=True)
        none = total[:, 0] == 0.0
        w = (w / np.where(none[:, None], 1.0, total))[:, None, :]
        Q, V = self._q, self._v
        v_start = V[r0]
        fade = np.exp(-t / FADE)
        dv0 = v0 - (weights[:, None, :] @ v_start)[:, 0]
        q = q0 + (w @ (Q[r1] - Q[r0]))[:, 0] + dv0 * (FADE * (1.0 - fade))
        v = v0 + (w @ (V[r1] - v_start))[:, 0] - dv0 * (1.0 - fade)
        a = (w @ self._a[r1])[:, 0] - dv0 * (fade / FADE)
        if none.any():
            q[none], v[none], a[none] = q0[none] + v0[none] * t[none], v0[none], 0.0
        return q, v, a

    def _feature(self, tick: int) -> np.ndarray | None:
        """The feature of the frame of `tick`: its q at the lags and its qd, or None when a row is
        a hole."""
        stamp, capacity, rows = self._stamp, self._capacity, []
        for lag in self._lags:  # a few scalars: cheaper than arrays of them
            row = (tick - lag) % capacity
            if stamp[row] != tick - lag:
                return None
            rows.append(row)
        return np.concatenate([self._q[rows].ravel(), self._v[rows[0]]])
