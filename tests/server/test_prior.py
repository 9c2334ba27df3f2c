"""The prior of human motion (server/estimation/prior.py) in the forecast combination: it answers
from the first gap, before the session has scores of its own; a replay after a rewind answers as
the first pass did; the shipped file holds the people it says, under 5 MB."""

from __future__ import annotations

import numpy as np
import pytest

from jitdyn.experiments.prior_sources import SUBJECTS
from jitdyn.experiments.recorded import chain_mjcf
from jitdyn.registry.info import describe_model
from jitdyn.roles import joint_roles
from jitdyn.server.estimation.forecast import MIN_SAMPLES, ForecastCombiner
from jitdyn.server.estimation.prior import PRIOR_FILE, PriorLibrary, PriorMatcher, legs_of, library
from jitdyn.server.estimation.propagate import process_model

mujoco = pytest.importorskip("mujoco")

DT = 0.01


def _walk(subject: str) -> np.ndarray:
    """(T, 3) a leg of `subject` as the library holds it at its recorded speed (its third clip of
    five: SPEEDS' 1)."""
    full = library()
    rows = np.flatnonzero(full.subject == full.subjects.index(subject))
    firsts = np.unique(full.first[rows])
    clip = np.arange(firsts[2], full.last[firsts[2]] + 1)
    return np.asarray(full.q[clip])


def _combiner(*, prior: bool, without: str = "moore") -> ForecastCombiner:
    model = mujoco.MjModel.from_xml_string(chain_mjcf())
    legs = legs_of(joint_roles(describe_model(model).joints, ()))
    matcher = PriorMatcher(library((without,)), legs=legs, nv=3, dt=DT) if prior else None
    process = process_model(model, scenario="DRIVEN")
    return ForecastCombiner(process, dt=DT, steps_per_tick=5, horizon=50, learner=True, prior=matcher)


def _feed(combiner: ForecastCombiner, q: np.ndarray, frames: range) -> None:
    v = np.gradient(q, DT, axis=0)
    zeros = np.zeros(3)
    for k in frames:
        combiner.advance()
        combiner.observe(q[k], v[k], mean_qpos=q[k], mean_qvel=v[k], act=np.zeros(0), force=zeros, rate=None)


def test_the_prior_answers_the_first_gap_before_the_session_has_scores_of_its_own() -> None:
    """20 frames of a walk the prior has not seen (moore, left out), then a gap: 300 ms into it
    the session has no score at that horizon. Without the prior the filter answers (None); with it
    the combination answers from the prior's scores on the other people (STATIC 0.58, PRIOR 0.38
    measured), closer to the walk than constant velocity and than STATIC."""
    q = _walk("moore")
    answers = {}
    for prior in (False, True):
        combiner = _combiner(prior=prior)
        _feed(combiner, q, range(20))
        for _ in range(30):
            combiner.advance()
        assert combiner._count[30] < MIN_SAMPLES
        answers[prior] = combiner.forecast()
    assert answers[False] is None
    answer = answers[True]
    assert answer is not None
    weights = dict(zip(answer.predictors, answer.weights, strict=True))
    assert weights["PRIOR"] > 0.3, weights
    assert weights["MODEL"] == 0.0 and weights["LEARNED"] == 0.0
    v = np.gradient(q, DT, axis=0)
    truth, error = q[49], np.linalg.norm(answer.qpos - q[49])
    assert error < np.linalg.norm(q[19] + v[19] * 0.3 - truth), error
    assert error < np.linalg.norm(q[19] - truth), error


def test_a_restored_combiner_with_the_prior_answers_as_the_first_pass() -> None:
    """Snapshot, frames and a gap, restore, the same again: the same answers, bit for bit (the
    prior's ring of recent frames is in the snapshot)."""
    q = _walk("parkinson")
    combiner = _combiner(prior=True, without="parkinson")
    _feed(combiner, q, range(60))
    snap = combiner.snapshot()

    def onward() -> list[np.ndarray]:
        _feed(combiner, q, range(60, 75))
        out = []
        for _ in range(12):
            combiner.advance()
            answer = combiner.forecast()
            assert answer is not None
            out.append(np.concatenate([answer.weights, answer.qpos, answer.var_q]))
        return out

    first = onward()
    combiner.restore(snap)
    again = onward()
    assert all(np.array_equal(a, b) for a, b in zip(first, again, strict=True))


def test_the_priors_covariances_take_the_scale_of_the_sessions_best_predictor(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A slow smooth swing that is not gait (0.3 sin t on every joint), scored for a second: at
    35 ms the session's CONSTANT_ACCELERATION errs far less than its STATIC, relative to each
    other, than gait's do. The prior's covariances the weights are blended from are the prior's
    times the session's lowest variance among the prior's predictors over the prior's own lowest
    (docs/decisions/0211-the-prior-at-its-best-predictors-scale.md), so constant acceleration does
    not look worse than the session scores it; at STATIC's scale it looked several times worse. (The
    prior's share counted whole here: how far the session agrees with it is the next test's.)"""
    monkeypatch.setattr(ForecastCombiner, "_agreement", lambda self, h: 1.0)
    t = np.arange(100) * DT
    q = np.stack([0.3 * np.sin(t + phase) for phase in (0.0, 1.0, 2.0)], axis=1)
    combiner = _combiner(prior=True)
    _feed(combiner, q, range(100))
    h = 4
    assert combiner._count[h] >= MIN_SAMPLES
    names = combiner.predictors
    block = np.array(
        [names.index(n) for n in ("STATIC", "CONSTANT_VELOCITY", "CONSTANT_ACCELERATION", "PRIOR")]
    )
    assert combiner._prior_cov is not None
    prior, session = combiner._prior_cov[0][h], combiner._cov[h]
    share = 0.8 ** int(combiner._count[h])
    blended = combiner._weighing(h)[0]
    scaled = (blended - (1.0 - share) * session)[np.ix_(block, block)] / share
    theirs, ours = np.diagonal(prior)[block], np.diagonal(session)[block]
    np.testing.assert_allclose(scaled, prior[np.ix_(block, block)] * ours.min() / theirs.min(), rtol=1e-6)
    ca, static = names.index("CONSTANT_ACCELERATION"), names.index("STATIC")
    at_static = prior[ca, ca] * session[static, static] / prior[static, static]
    assert at_static > 3.0 * scaled[2, 2], (at_static, scaled[2, 2], session[ca, ca])


def test_the_prior_counts_as_far_as_the_sessions_scores_agree_with_it() -> None:
    """The slow swing above, which is not gait: the session scores PRIOR far below the best of the
    extrapolators, and the prior's share of the covariances is FORGETTING^n times the best one's
    scored variance over PRIOR's (docs/decisions/0222-a-short-past-does-not-judge-a-start-of-motion.md)."""
    t = np.arange(100) * DT
    q = np.stack([0.3 * np.sin(t + phase) for phase in (0.0, 1.0, 2.0)], axis=1)
    combiner = _combiner(prior=True)
    _feed(combiner, q, range(100))
    h = 4
    names = combiner.predictors
    block = np.array(
        [names.index(n) for n in ("STATIC", "CONSTANT_VELOCITY", "CONSTANT_ACCELERATION", "PRIOR")]
    )
    session = combiner._cov[h]
    agreement = float(np.min(np.diagonal(session)[block]) / session[block[-1], block[-1]])
    assert agreement < 0.01
    assert combiner._agreement(h) == agreement
    assert combiner._prior_cov is not None
    prior = combiner._prior_cov[0][h]
    theirs, ours = np.diagonal(prior)[block], np.diagonal(session)[block]
    share = 0.8 ** int(combiner._count[h]) * agreement
    expected = share * prior * ours.min() / theirs.min() + (1.0 - share) * session
    blended = combiner._weighing(h)[0]
    np.testing.assert_allclose(blended[np.ix_(block, block)], expected[np.ix_(block, block)], rtol=1e-12)


def test_the_shipped_prior_holds_its_six_people_under_5_mb() -> None:
    assert PRIOR_FILE.stat().st_size < 5e6
    full = PriorLibrary.load()
    assert full.subjects == tuple(SUBJECTS)
    assert set(np.unique(full.subject)) == set(range(len(SUBJECTS)))
    assert full.describe() == f"6 subjects ({', '.join(SUBJECTS)})"
    assert library(("xsens",)).describe().endswith(", xsens left out")
    with pytest.raises(ValueError, match="the prior has no subject 'nobody'; it has isen, xsens"):
        PriorLibrary.load(without=("nobody",))


def test_the_trees_lookup_finds_the_moments_a_pass_over_every_candidate_finds() -> None:
    """A walk the library does not hold (stroke, left out), frames with a gap now and then (so that
    every set of lags present is searched): the k-d tree's matches are the exhaustive pass's, the
    same library moments with the same weights, but where two moments tie for the tenth place."""
    q = _walk("stroke")
    v = np.gradient(q, DT, axis=0)
    model = mujoco.MjModel.from_xml_string(chain_mjcf())
    legs = legs_of(joint_roles(describe_model(model).joints, ()))
    tree, scan = (
        PriorMatcher(library(("stroke",)), legs=legs, nv=3, dt=DT, exhaustive=e) for e in (False, True)
    )
    same = matched = 0
    for k in range(q.shape[0]):
        if k % 25 >= 20:  # 50 ms lost every 250 ms: the lags 50-150 ms back come and go
            continue
        for m in (tree, scan):
            m.record(k, q[k], v[k])
        (rows, weights), (rows_ref, weights_ref) = tree.match(k), scan.match(k)
        assert np.isnan(rows).all() == np.isnan(rows_ref).all()
        if np.isnan(rows).all():
            continue
        matched += 1
        order, order_ref = np.argsort(rows[0]), np.argsort(rows_ref[0])
        if np.array_equal(rows[0][order], rows_ref[0][order_ref]):
            same += 1
            np.testing.assert_allclose(weights[0][order], weights_ref[0][order_ref], rtol=1e-6)
    assert matched > 150 and same >= 0.97 * matched, (same, matched)
