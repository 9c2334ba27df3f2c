"""A prior of human motion: motion matching over a library of other people's walking, shipped with
jitdyn (human_prior.npz, built by experiments/prior_build.py), for the joints whose role says what
they are (hip flexion, knee flexion, ankle dorsiflexion; jitdyn.roles)::

    library = PriorLibrary.load()                     # or .load(without=("xsens",)): leave one out
    matcher = PriorMatcher(library, legs=legs, nv=3, dt=0.01)
    matcher.record(tick, qpos, qvel)                  # every frame, at its tick
    rows, weights = matcher.match(tick)               # (L, K) each, L legs; NaN rows: no match
    q, v, a = matcher.follow(rows, weights, ages, q0, v0, fallback)   # (S, nv) each

A leg is the session's hip, knee and (where it has one) ankle on one side, each with its sign. Its
feature now: the change of each joint's angle over the last 50, 100 and 150 ms and its velocity
(times FEATURE_TIME), each divided by its spread over the library; offsets differ between people
and measuring systems, so no absolute angle is compared. A match is the K library moments nearest
to it among the legs that have all of the session leg's joints, weighted by inverse distance; what
it predicts is the frame's q plus their weighted displacement over the age, and the frame's own
qd where it differs from theirs, fading with FADE (as estimation/matching.py does with the
session's own past). Dofs of no leg take `fallback` (the session's own history, or constant
velocity). Why a prior and how it was chosen: docs/decisions/0186-prior-predictor.md.

Cost: a match is a query of a k-d tree over the library's candidates (scipy's cKDTree, one per leg's
joints and set of lags present, built at its first use and shared by every session of the library):
some 40 us, where a pass over all of them (`nearest`, kept as the reference the tree is tested
against) took 200-1000 us (the library holds some 34,000 moments; a 3-joint leg's F is 12).
docs/decisions/0190-prior-lookup-by-tree.md. This is the reference of the native engine's
matcher (native/prior.cc), which a session on the NATIVE engine uses: a pass over the candidates
summed as the tree sums a distance (docs/decisions/0218-the-prior-in-the-native-engine.md).
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import numpy as np
from scipy.spatial import cKDTree

from jitdyn.roles import JointRole

__all__ = [
    "FEATURE_TIME",
    "LAGS",
    "PRIOR_FILE",
    "Index",
    "K",
    "Leg",
    "PriorLibrary",
    "PriorMatcher",
    "legs_of",
    "library",
    "nearest",
    "prior_without",
]

PRIOR_FILE: Final = Path(__file__).with_name("human_prior.npz")
# The feature: angle changes over these lags (s), and the velocity times FEATURE_TIME (s), so that
# both are angles; K moments blended; the fade (s) of the frame's own qd into the matches'.
LAGS: Final = (0.05, 0.10, 0.15)
FEATURE_TIME: Final = 0.1
K: Final = 10
FADE: Final = 0.1
# A moment whose nearest library moment is farther than this (squared, per feature component, in
# spreads) is not one the prior has seen (a jump's take-off and landing: up to 27; the farthest of
# every walk scored leaving its person out: 2.4): no match, and the prior answers as constant
# velocity (docs/decisions/0186-prior-predictor.md).
FARTHEST: Final = 4.0
JOINTS: Final = ("hip", "knee", "ankle")  # the library's columns, as jitdyn.roles names them
_WITHOUT: Final = "prior.without."


def prior_without(tags: tuple[str, ...]) -> tuple[str, ...]:
    """The subjects a model's tags "prior.without.<subject>" leave out of its prior (a model of a
    recorded person: that person's recordings never score it)."""
    return tuple(tag[len(_WITHOUT) :] for tag in tags if tag.startswith(_WITHOUT))


@functools.lru_cache(maxsize=8)
def library(without: tuple[str, ...] = ()) -> PriorLibrary:
    """The shipped library, `without` those subjects; read once per process and choice."""
    return PriorLibrary.load(without=without)


def legs_of(roles: tuple[JointRole, ...]) -> tuple[Leg, ...]:
    """The legs of a model's joint roles: one per side with a hip and a knee (an ankle if it has
    one); a lone hip, knee or ankle is no leg (its motion alone says little of the gait's phase)."""
    out = []
    for side in sorted({r.side for r in roles}):
        by_kind = {r.kind: r for r in roles if r.side == side}
        if "hip" not in by_kind or "knee" not in by_kind:
            continue
        picked = [by_kind.get(kind) for kind in JOINTS]
        dofs = tuple(-1 if r is None else r.dof for r in picked)
        signs = tuple(1.0 if r is None else r.sign for r in picked)
        out.append(Leg(dofs=(dofs[0], dofs[1], dofs[2]), signs=(signs[0], signs[1], signs[2])))
    return tuple(out)


@dataclass(frozen=True)
class Leg:
    """One of the session's legs: the dof of each of JOINTS (-1: it has none) and its sign (+1 when
    the dof's positive direction is flexion, dorsiflexion for the ankle)."""

    dofs: tuple[int, int, int]
    signs: tuple[float, float, float]

    @property
    def joints(self) -> np.ndarray:
        """Which of JOINTS the leg has, (3,) bool."""
        return np.array([d >= 0 for d in self.dofs])


@dataclass(frozen=True)
class PriorLibrary:
    """The moments a match searches: q and qd (N, 3) at `rate` Hz over JOINTS (NaN: not recorded),
    the first and last row of each row's clip (N,), each row's subject (N,) (an index of
    `subjects`); `candidate` (N,) rows with a lag's history in their clip and their subject not left
    out. The scores of the prior and the IEEE 1278 extrapolators on each subject's walking
    (`scores`, experiments/prior_build.py) give its weights before a session has scores of its own."""

    rate: float
    q: np.ndarray
    v: np.ndarray
    first: np.ndarray
    last: np.ndarray
    subject: np.ndarray
    subjects: tuple[str, ...]
    candidate: np.ndarray
    features: np.ndarray  # (N, 3, 4): per joint, the lags' changes and the velocity term
    spread: np.ndarray  # (3, 4)
    scores: PriorScores
    without: tuple[str, ...] = ()

    @classmethod
    def load(cls, path: Path = PRIOR_FILE, *, without: tuple[str, ...] = ()) -> PriorLibrary:
        """The library in `path`, its subjects in `without` left out (ValueError naming one it has
        not)."""
        with np.load(path) as data:
            arrays = {name: np.array(data[name]) for name in data.files}
        return cls.of(arrays, without=without)

    @classmethod
    def of(
        cls, arrays: dict[str, np.ndarray], *, without: tuple[str, ...] = (), scored: bool = True
    ) -> PriorLibrary:
        """The library of experiments/prior_build.py's arrays (human_prior.npz's), `without` left
        out; scored False: without its scores (while a build computes them)."""
        subjects = tuple(str(s) for s in arrays["subjects"])
        unknown = sorted(set(without) - set(subjects))
        if unknown:
            raise ValueError(f"the prior has no subject {unknown[0]!r}; it has {', '.join(subjects)}")
        rate = float(arrays["rate"])
        q, v = np.asarray(arrays["q"], dtype=float), np.asarray(arrays["v"], dtype=float)
        first, subject = np.asarray(arrays["first"]), np.asarray(arrays["subject"])
        features = library_features(q, v, rate=rate)
        rows = np.arange(q.shape[0])
        kept = ~np.isin(subject, [subjects.index(s) for s in without])
        candidate = kept & (rows - first >= round(max(LAGS) * rate))
        with np.errstate(invalid="ignore"):
            spread = np.sqrt(np.nanmean(np.square(features[candidate]), axis=0))
        return cls(
            rate=rate,
            q=q,
            v=v,
            first=first,
            last=np.asarray(arrays["last"]),
            subject=subject,
            subjects=subjects,
            candidate=candidate,
            features=features,
            spread=np.where(np.isfinite(spread) & (spread > 0.0), spread, 1.0),
            scores=PriorScores.of(arrays if scored else {}, subjects=subjects, without=without),
            without=tuple(without),
        )

    def columns(self, columns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """q and qd (N, J) over `columns` (J,) of JOINTS, copied once per choice of them: copied on
        every continuation, they had been most of its time."""
        key = tuple(int(c) for c in columns)
        found = self._columns.get(key)
        if found is None:
            found = self._columns[key] = (self.q[:, columns], self.v[:, columns])
        return found

    @functools.cached_property
    def _columns(self) -> dict[tuple[int, ...], tuple[np.ndarray, np.ndarray]]:
        return {}

    def index(self, columns: np.ndarray, present: tuple[bool, ...]) -> Index:
        """What a match over `columns` (J,) of JOINTS searches, with the feature's components
        `present` (len(LAGS) + 1,) per joint; built at the first call (PriorMatcher builds every
        one its legs need), then shared."""
        key = (tuple(int(c) for c in columns), present)
        found = self._indexes.get(key)
        if found is None:
            has = self.candidate & np.all(np.isfinite(self.q[:, columns]), axis=1)
            rows = np.flatnonzero(has)
            scaled = (self.features[rows][:, columns] / self.spread[columns]).reshape(rows.size, -1)
            kept = np.tile(np.array(present), len(key[0]))
            found = self._indexes[key] = Index(rows, (scaled, np.square(scaled)), cKDTree(scaled[:, kept]))
        return found

    @functools.cached_property
    def _indexes(self) -> dict[tuple[tuple[int, ...], tuple[bool, ...]], Index]:
        return {}

    def describe(self) -> str:
        """Which people the library holds, for a report: "5 subjects (fukuchi, ...), xsens left out"."""
        kept = [s for s in self.subjects if s not in self.without]
        out = f"{len(kept)} subjects ({', '.join(kept)})"
        return out + (f", {', '.join(self.without)} left out" if self.without else "")


@dataclass(frozen=True)
class Index:
    """The candidates of a match (N,) (rows of the library), their scaled features (N, F) and the
    squares of those, and a k-d tree of the features over the components a match compares."""

    rows: np.ndarray
    features: tuple[np.ndarray, np.ndarray]
    tree: cKDTree


@dataclass(frozen=True)
class PriorScores:
    """The pooled covariances of STATIC's, CONSTANT_VELOCITY's, CONSTANT_ACCELERATION's and the
    prior's errors (q: `cov`, qd: `cov_v`, (H, 4, 4)) at horizons `seconds` (H,), over the kept
    subjects' walking, each scored by a prior without that subject (and without those left out)."""

    seconds: np.ndarray
    cov: np.ndarray
    cov_v: np.ndarray

    @classmethod
    def of(
        cls, data: dict[str, np.ndarray], *, subjects: tuple[str, ...], without: tuple[str, ...]
    ) -> PriorScores:
        """From the arrays pair_cov and pair_cov_v (subjects, subjects, H, 4, 4), pair[i, j]: subject
        j scored by the library without subjects i and j (i == j: without j); none before a build
        has scored them (seconds empty)."""
        if "pair_cov" not in data:
            empty = np.zeros((0, 4, 4))
            return cls(seconds=np.zeros(0), cov=empty, cov_v=empty)
        pair, pair_v = data["pair_cov"], data["pair_cov_v"]
        left = [subjects.index(s) for s in without]
        scored = [j for j in range(len(subjects)) if j not in left]
        if len(left) > 1:
            raise ValueError(f"a prior leaves out at most one subject here, got {list(without)}")
        i = left[0] if left else None
        cov = np.mean([pair[j if i is None else i, j] for j in scored], axis=0)
        cov_v = np.mean([pair_v[j if i is None else i, j] for j in scored], axis=0)
        return cls(seconds=np.asarray(data["seconds"], dtype=float), cov=cov, cov_v=cov_v)

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The covariances (4, 4) each at t seconds, linear between the horizons scored."""
        s = self.seconds
        j = int(np.clip(np.searchsorted(s, t), 1, s.size - 1))
        f = float(np.clip((t - s[j - 1]) / (s[j] - s[j - 1]), 0.0, 1.0))
        return (1 - f) * self.cov[j - 1] + f * self.cov[j], (1 - f) * self.cov_v[j - 1] + f * self.cov_v[j]


def library_features(q: np.ndarray, v: np.ndarray, *, rate: float) -> np.ndarray:
    """(N, 3, 4) every row's feature (NaN where a lag leaves its clip is not checked here: a row is
    a candidate only with its lags in its clip)."""
    out = np.full((q.shape[0], q.shape[1], len(LAGS) + 1), np.nan)
    for i, lag in enumerate(LAGS):
        rows = round(lag * rate)
        out[rows:, :, i] = q[:-rows] - q[rows:]
    out[:, :, -1] = v * FEATURE_TIME
    return out


class PriorMatcher:
    """See the module docstring: one session's matches against the library, its legs given;
    exhaustive: every match a pass over all of the candidates (`nearest`) instead of the tree's query,
    the same moments (the reference, and the benchmark's other arm)."""

    def __init__(
        self, library: PriorLibrary, *, legs: tuple[Leg, ...], nv: int, dt: float, exhaustive: bool = False
    ) -> None:
        if not legs or not dt > 0.0:
            raise ValueError(f"a prior matcher needs a leg and dt > 0, got {len(legs)} legs, dt {dt}")
        self._library, self._legs, self._nv, self._dt = library, legs, int(nv), float(dt)
        self._lags = [max(1, round(lag / dt)) for lag in LAGS]
        self._ring = max(self._lags) + 1
        self._stamp = np.full(self._ring, -1, dtype=np.int64)
        self._q = np.zeros((self._ring, nv))
        self._v = np.zeros((self._ring, nv))
        self._dofs = [np.array([d for d in leg.dofs if d >= 0]) for leg in legs]
        self._signs = [
            np.array([s for d, s in zip(leg.dofs, leg.signs, strict=True) if d >= 0]) for leg in legs
        ]
        self._columns = [np.flatnonzero(leg.joints) for leg in legs]
        self._exhaustive = exhaustive
        for cols in self._columns:  # every set of lags present, so that no match builds a tree
            for lags in itertools.product((True, False), repeat=len(LAGS)):
                library.index(cols, (*lags, True))
        self.roled = np.zeros(nv, dtype=bool)
        for dofs in self._dofs:
            self.roled[dofs] = True

    @property
    def legs(self) -> int:
        return len(self._legs)

    @property
    def library(self) -> PriorLibrary:
        return self._library

    @property
    def dt(self) -> float:
        return self._dt

    def joints(self) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], ...]:
        """Per leg, the columns of JOINTS it has (J,), the session's dofs of them (J,) and their
        signs (J,): what the native engine's matcher is built from."""
        return tuple(zip(self._columns, self._dofs, self._signs, strict=True))

    def scores_at(self, t: float) -> tuple[np.ndarray, np.ndarray] | None:
        """The library's pooled covariances (4, 4) of q and qd errors at t seconds (PriorScores), or
        None when it has none."""
        scores = self._library.scores
        return None if scores.seconds.size == 0 else scores.at(t)

    def record(self, tick: int, qpos: np.ndarray, qvel: np.ndarray) -> None:
        """The frame of `tick` (nv,) each."""
        row = tick % self._ring
        self._stamp[row] = tick
        self._q[row], self._v[row] = qpos, qvel

    def match(self, tick: int) -> tuple[np.ndarray, np.ndarray]:
        """(L, K) library rows and weights of each leg's match for the frame of `tick` (recorded);
        rows NaN when that frame is not recorded or its motion is unlike any the library holds
        (FARTHEST). A lag whose frame is missing (a gap less than
        LAGS' longest ago) is left out of the distance: a session with short gaps still matches."""
        rows = np.full((len(self._legs), K), np.nan)
        weights = np.zeros((len(self._legs), K))
        ring = self._ring
        if self._stamp[tick % ring] != tick:
            return rows, weights
        present = np.array([self._stamp[(tick - lag) % ring] == tick - lag for lag in self._lags] + [True])
        now = self._q[tick % ring]
        for i, (dofs, signs) in enumerate(zip(self._dofs, self._signs, strict=True)):
            feature = np.zeros((dofs.size, len(LAGS) + 1))
            for j, lag in enumerate(self._lags):
                if present[j]:
                    feature[:, j] = (self._q[(tick - lag) % ring, dofs] - now[dofs]) * signs
            feature[:, -1] = self._v[tick % ring, dofs] * signs * FEATURE_TIME
            query = (feature / self._library.spread[self._columns[i]]).ravel()
            mask = np.tile(present, dofs.size)
            index = self._library.index(self._columns[i], tuple(present.tolist()))
            if self._exhaustive:
                found, w, d = nearest(index.features, query, mask.astype(float))
            else:
                found, w, d = nearest_in_tree(index.tree, query[mask])
            if d <= FARTHEST * mask.sum():
                rows[i], weights[i] = index.rows[found], w
        return rows, weights

    def state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The frames a match reads (its ring), for a snapshot: a replay after a rewind matches as
        the first pass did."""
        return self._stamp.copy(), self._q.copy(), self._v.copy()

    def restore(self, state: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
        self._stamp[:], self._q[:], self._v[:] = state

    def follow(
        self,
        rows: np.ndarray,
        weights: np.ndarray,
        ages: np.ndarray,
        anchor: tuple[np.ndarray, np.ndarray, np.ndarray],
        fallback: tuple[np.ndarray, np.ndarray, np.ndarray],
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """qpos, qvel, qacc (S, nv) `ages` (S,) ticks on from frames anchor = (q0, v0, a0) (S, nv)
        each, of S matches (rows, weights (S, L, K)): each leg's dofs from its match (constant
        velocity where it has none), the others `fallback`'s (S, nv) each."""
        q, v, a = (np.array(x, dtype=float) for x in fallback)
        q0, v0, a0 = anchor
        t = np.asarray(ages, dtype=float) * self._dt
        for i, (dofs, signs) in enumerate(zip(self._dofs, self._signs, strict=True)):
            lq, lv, la = follow_library(
                self._library,
                self._columns[i],
                rows[:, i],
                weights[:, i],
                t,
                (q0[:, dofs] * signs, v0[:, dofs] * signs, a0[:, dofs] * signs),
            )
            q[:, dofs], v[:, dofs], a[:, dofs] = lq * signs, lv * signs, la * signs
        return q, v, a


def nearest_in_tree(tree: cKDTree, query: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """`nearest` by a k-d tree of the candidates' features over the components present only: the
    K nearest rows (K,), their inverse-distance weights, and the nearest one's squared distance."""
    distance, found = tree.query(query, k=K)
    d = np.square(distance)
    w = 1.0 / (d + 1e-3 * float(d[0]) + 1e-12)
    return np.asarray(found), w / w.sum(), float(d[0])


def nearest(
    features: tuple[np.ndarray, np.ndarray], query: np.ndarray, mask: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float]:
    """The K rows of features (N, F) (and their squares) nearest to `query` (F,) over the
    components `mask` (F,) weighs 1, their inverse-distance weights (summing to 1), and the nearest
    one's squared distance. Two products with the library instead of a difference of it: a match's
    cost."""
    f, squares = features
    d = np.maximum(squares @ mask - 2.0 * (f @ (query * mask)) + float(np.square(query) @ mask), 0.0)
    found = d.argpartition(K - 1)[:K]
    nearest_d = float(d[found].min())
    w = 1.0 / (d[found] + 1e-3 * nearest_d + 1e-12)
    return found, w / w.sum(), nearest_d


def follow_library(
    library: PriorLibrary,
    columns: np.ndarray,
    rows: np.ndarray,
    weights: np.ndarray,
    t: np.ndarray,
    anchor: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(S, J) q, qd, qdd of S matches (rows, weights (S, K)) t (S,) seconds on from anchor = (q0,
    v0, a0) (S, J) each, in the library's signs, over its `columns` (J,): the candidates' displacement between
    the row and t later (linear between rows; a candidate whose clip ends before is dropped), and the
    frame's qd and qdd where they differ from theirs, fading with FADE. No match, or no
    continuation left: constant velocity."""
    q0, v0, a0 = anchor
    known = ~np.isnan(rows[:, 0])
    start = np.where(np.isnan(rows), 0, rows).astype(np.int64)
    later = start + (t * library.rate)[:, None]
    below = np.floor(later).astype(np.int64)
    inside = known[:, None] & (below + 1 <= library.last[start])
    below = np.where(inside, below, start)
    f = (later - below)[..., None]
    w = weights * inside
    total = w.sum(axis=1, keepdims=True)
    none = total[:, 0] == 0.0
    w = w / np.where(none[:, None], 1.0, total)
    Q, V = library.columns(columns)

    def at(x: np.ndarray) -> np.ndarray:
        return np.asarray((1.0 - f) * x[below] + f * x[np.minimum(below + 1, x.shape[0] - 1)])

    mine = np.where(known[:, None], weights, 0.0)
    v_start = np.einsum("sk,skj->sj", mine, V[start])
    a_start = np.einsum("sk,skj->sj", mine, (V[start] - V[start - 1]) * library.rate)
    # The frame's own qd and qdd beyond the matches', each fading with FADE: u = t / FADE.
    u = (t / FADE)[:, None]
    fade = np.exp(-u)
    dv0, da0 = v0 - v_start, a0 - a_start
    q = q0 + np.einsum("sk,skj->sj", w, at(Q) - Q[start])
    q = q + dv0 * (FADE * (1.0 - fade)) + da0 * (FADE * FADE * (u - 1.0 + fade))
    v = v0 + np.einsum("sk,skj->sj", w, at(V) - V[start]) - dv0 * (1.0 - fade) + da0 * (FADE * (1.0 - fade))
    a = np.einsum("sk,skj->sj", w, (V[np.minimum(below + 1, V.shape[0] - 1)] - V[below]) * library.rate)
    a = a - dv0 * (fade / FADE) + da0 * fade
    if none.any():
        q[none], v[none], a[none] = q0[none] + v0[none] * t[none, None], v0[none], 0.0
    return q, v, a
