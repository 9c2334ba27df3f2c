"""Builds the prior of human motion that jitdyn ships (server/estimation/human_prior.npz) from the
walking recordings of experiments/prior_sources.py, reproducibly (the same packages give the same
file, byte for byte)::

    python -m jitdyn.experiments.prior_build                 # writes the shipped file
    python -m jitdyn.experiments.prior_build --out FILE --cache DIR

What it holds: every leg of every subject at 100 Hz, and again played SPEEDS times faster or slower
(cubic spline), so that a cadence no subject walked at still finds its match; each row's clip and
subject; and the scores of the prior against IEEE 1278's extrapolators on each subject's own
recordings, every subject scored by the prior without it, and without it and each other subject in
turn (a session that leaves a subject out is given weights no score of that subject helped make).
Why: docs/decisions/0185-a-prior-of-human-motion.md.
"""

from __future__ import annotations

import argparse
import io
import time
import zipfile
from pathlib import Path
from typing import Final

import numpy as np
from scipy.interpolate import CubicSpline

from jitdyn.experiments.prior_sources import (
    RATE,
    SUBJECTS,
    digest,
    fetch_archives,
    walking_legs,
)
from jitdyn.server.estimation.extrapolators import moved
from jitdyn.server.estimation.prior import (
    FEATURE_TIME,
    LAGS,
    PRIOR_FILE,
    K,
    PriorLibrary,
    follow_library,
)

__all__ = ["HORIZONS", "SPEEDS", "build", "main", "score"]

# How much faster than recorded each leg is played (the recording itself at 1).
SPEEDS: Final = (0.8, 0.9, 1.0, 1.12, 1.25)
# The horizons scored (rows at RATE: 10 ms to 0.5 s), and every how many rows an anchor.
HORIZONS: Final = np.arange(1, 51)
ANCHOR_EVERY: Final = 2
_CHUNK: Final = 256


def clips(legs: dict[str, list[np.ndarray]]) -> dict[str, np.ndarray]:
    """The library's arrays but the scores: q, v (N, 3), first, last, subject (N,), subjects, rate."""
    q, v, first, last, subject = [], [], [], [], []
    start = 0
    for code, name in enumerate(SUBJECTS):
        for leg in legs[name]:
            t = np.arange(leg.shape[0]) / RATE
            known = np.isfinite(leg[0])
            for speed in SPEEDS:
                grid = np.arange(0.0, t[-1] * 1.0 / speed + 1e-9, 1.0 / RATE)
                played = np.full((grid.size, leg.shape[1]), np.nan)
                played[:, known] = CubicSpline(t, leg[:, known])(grid * speed)
                n = played.shape[0]
                q.append(played)
                v.append(np.gradient(played, 1.0 / RATE, axis=0))
                first.append(np.full(n, start))
                last.append(np.full(n, start + n - 1))
                subject.append(np.full(n, code))
                start += n
    return {
        "rate": np.array(RATE),
        "q": np.concatenate(q).astype(np.float32),
        "v": np.concatenate(v).astype(np.float32),
        "first": np.concatenate(first).astype(np.int32),
        "last": np.concatenate(last).astype(np.int32),
        "subject": np.concatenate(subject).astype(np.int8),
        "subjects": np.array(list(SUBJECTS)),
    }


def score(library: PriorLibrary, legs: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(H, 4, 4) each: the pooled covariances of STATIC's, CONSTANT_VELOCITY's,
    CONSTANT_ACCELERATION's and the prior's q errors and qd errors at HORIZONS, over anchors every
    ANCHOR_EVERY rows of `legs` (perfect frames; qdd from the last two frames' qd, as the forecast
    combination's anchors)."""
    total = np.zeros((HORIZONS.size, 4, 4))
    total_v = np.zeros_like(total)
    count = 0
    for leg in legs:
        columns = np.flatnonzero(np.isfinite(leg[0]))
        v = np.gradient(leg, 1.0 / RATE, axis=0)
        anchors = np.arange(round(max(LAGS) * RATE) + 1, leg.shape[0] - HORIZONS[-1], ANCHOR_EVERY)
        rows, weights = _matches(library, leg[:, columns], v[:, columns], anchors, columns)
        q0, v0 = leg[anchors][:, columns], v[anchors][:, columns]
        a0 = (v0 - v[anchors - 1][:, columns]) * RATE
        for i, h in enumerate(HORIZONS):
            t = np.full(anchors.size, h / RATE)
            eq, ev, _ = moved(q0, v0, a0, t[:, None])  # (S, 3, J)
            pq, pv, _ = follow_library(library, columns, rows, weights, t, (q0, v0, a0))
            errors = np.concatenate([eq, pq[:, None, :]], axis=1) - leg[anchors + h][:, None, columns]
            verrors = np.concatenate([ev, pv[:, None, :]], axis=1) - v[anchors + h][:, None, columns]
            total[i] += np.einsum("spj,sqj->pq", errors, errors)
            total_v[i] += np.einsum("spj,sqj->pq", verrors, verrors)
        count += anchors.size * columns.size
    return total / count, total_v / count


def _matches(
    library: PriorLibrary, q: np.ndarray, v: np.ndarray, anchors: np.ndarray, columns: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(S, K) rows and weights of each anchor's match, as PriorMatcher.match makes them, in chunks
    of queries against the candidates that have the leg's joints."""
    has = library.candidate & np.all(np.isfinite(library.q[:, columns]), axis=1)
    candidates = np.flatnonzero(has)
    spread = library.spread[columns]
    features = (library.features[candidates][:, columns] / spread).reshape(candidates.size, -1)
    lags = [round(lag * RATE) for lag in LAGS]
    query = np.stack([q[anchors - lag] - q[anchors] for lag in lags] + [v[anchors] * FEATURE_TIME], axis=-1)
    query = (query / spread).reshape(anchors.size, -1)
    rows, weights = np.empty((anchors.size, K)), np.empty((anchors.size, K))
    norms = np.square(features).sum(axis=1)
    for s in range(0, anchors.size, _CHUNK):
        chunk = query[s : s + _CHUNK]
        d = norms[None, :] - 2.0 * chunk @ features.T + np.square(chunk).sum(axis=1)[:, None]
        d = np.maximum(d, 0.0)
        found = d.argpartition(K - 1, axis=1)[:, :K]
        nearest = np.take_along_axis(d, found, axis=1)
        w = 1.0 / (nearest + 1e-3 * nearest.min(axis=1, keepdims=True) + 1e-12)
        rows[s : s + _CHUNK] = candidates[found]
        weights[s : s + _CHUNK] = w / w.sum(axis=1, keepdims=True)
    return rows, weights


def build(cache: Path, *, progress: bool = True) -> dict[str, np.ndarray]:
    """Every array of human_prior.npz, from the sources (pip downloads the archives into `cache`)."""
    archives = fetch_archives(cache)
    if progress:
        for name, path in archives.items():
            print(f"{name}  sha256 {digest(path)}", flush=True)
    legs = walking_legs(archives)
    arrays = clips(legs)
    names = list(SUBJECTS)
    n = len(names)
    pair = np.zeros((n, n, HORIZONS.size, 4, 4))
    pair_v = np.zeros_like(pair)
    started = time.monotonic()
    for j, scored in enumerate(names):
        for i, other in enumerate(names):
            without = (scored,) if i == j else (scored, other)
            library = PriorLibrary.of(arrays, without=without, scored=False)
            pair[i, j], pair_v[i, j] = score(library, legs[scored])
        if progress:
            print(f"scored {scored} ({j + 1}/{n}, {time.monotonic() - started:.0f} s)", flush=True)
    return arrays | {"seconds": HORIZONS / RATE, "pair_cov": pair, "pair_cov_v": pair_v}


def write(arrays: dict[str, np.ndarray], out: Path) -> None:
    """The .npz, compressed, with no timestamps in it (the same arrays give the same bytes)."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name, array in arrays.items():
            member = io.BytesIO()
            np.lib.format.write_array(member, np.asarray(array), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            archive.writestr(info, member.getvalue(), compress_type=zipfile.ZIP_DEFLATED)
    out.write_bytes(buffer.getvalue())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m jitdyn.experiments.prior_build",
        description="Build the prior of human motion jitdyn ships from the walking recordings that "
        "biomdp, scikit-kinematics, gaitkit and GaitAnalysisToolKit ship (the first two installed; "
        "the last two's sdists downloaded by pip into --cache).",
    )
    parser.add_argument(
        "--out", type=Path, default=PRIOR_FILE, help="the file to write (default: %(default)s)"
    )
    parser.add_argument(
        "--cache",
        type=Path,
        default=Path.home() / ".cache" / "jitdyn" / "prior-sources",
        help="where the downloaded sdists are kept (default: %(default)s)",
    )
    args = parser.parse_args(argv)
    arrays = build(args.cache)
    write(arrays, args.out)
    print(f"wrote {args.out} ({args.out.stat().st_size / 1e6:.2f} MB, {arrays['q'].shape[0]} rows)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
