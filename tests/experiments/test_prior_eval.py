"""The prior of human motion left one subject out, over gRPC (experiments/prior_eval.py): on a
walk of a person the prior does not hold (Fukuchi et al.'s healthy adult, gaitkit's example; the
model's tag prior.without.fukuchi), with 100 ms of frames lost every 250 ms from the first frame,
the defaults' q error 100 ms after the last frame over the first stride is well below the same
session's on a model whose joints say no role (no prior), and the rows say which prior answered."""

from __future__ import annotations

from typing import Any

import pytest

from jitdyn.experiments import prior_eval
from jitdyn.experiments.runner import run_lockstep
from jitdyn.server.estimation import forecast, foresight

pytest.importorskip("scipy")


@pytest.mark.timeout(300)
def test_the_prior_lowers_the_first_strides_error_of_a_person_it_was_not_trained_on(client: Any) -> None:
    """Measured: 0.33 x the best extrapolator at 100 ms over the first stride (perfect frames),
    against 0.78 x without roles; 0.62 x against 0.88 x at 35 ms."""
    rows = prior_eval.evaluate(
        lambda spec, obj: run_lockstep(client, spec, obj=obj, progress=False),
        recordings=("fukuchi_walk",),
        sensors={"perfect": None},
    )
    by = {(r.window, round(r.horizon * 1000)): r for r in rows}
    first = by["first stride", 100]
    assert first.prior == "5 subjects (isen, xsens, parkinson, stroke, moore), fukuchi left out"
    assert first.ratio("defaults") < 0.6 * first.ratio("no roles"), first.errors
    assert first.ratio("defaults") <= 0.5, first.errors
    short = by["first stride", 35]
    assert short.ratio("defaults") < short.ratio("no roles") and short.ratio("defaults") <= 0.8, short.errors


@pytest.mark.timeout(300)
def test_the_novelty_guard_and_the_regime_rule_do_not_cost_gaits_short_horizon(
    client: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The stroke survivor's walk (left out of the prior), perfect frames: 35 ms after the last frame
    the defaults stand below the best extrapolator, over the first stride and the whole run, and
    below the same defaults with the novelty guard and the regime rule switched off (their factors
    too large to act). Measured: 0.467 and 0.373 x with them, 0.608 and 0.441 x without
    (docs/decisions/0191-short-horizons-on-gait.md; the guard's reference:
    docs/decisions/0216-a-start-of-motion-is-not-a-glitch.md; on gait the guard acts from the first
    scores: docs/decisions/0222-a-short-past-does-not-judge-a-start-of-motion.md). The rules' factors are set in
    forecast.py, the Python reference, so the run without them combines in Python; the run with
    them combines as the server does, natively (the same numbers to 1e-9,
    tests/server/test_native_forecast.py)."""

    def at_35_ms() -> dict[str, float]:
        rows = prior_eval.evaluate(
            lambda spec, obj: run_lockstep(client, spec, obj=obj, progress=False),
            recordings=("stroke_walk",),
            sensors={"perfect": None},
        )
        return {r.window: r.ratio("defaults") for r in rows if round(r.horizon * 1000) == 35}

    with_rules = at_35_ms()
    monkeypatch.setattr(forecast, "NOVELTY", 1e12)
    monkeypatch.setattr(forecast, "SURPRISE", 1e12)
    monkeypatch.setattr(foresight, "native_combination", lambda config: False)
    without = at_35_ms()
    for window in ("first stride", "whole run"):
        assert with_rules[window] <= 1.0, with_rules
        assert with_rules[window] < without[window], (with_rules, without)


@pytest.mark.timeout(300)
def test_motion_that_is_not_gait_is_not_answered_at_gaits_scale(client: Any) -> None:
    """The iSen person's movements that do not repeat (isen_tasks, the person left out of the
    prior), perfect frames: over the first stride the defaults stay within 1.05 x the best
    extrapolator at 100 ms, the prior's covariances taken at the session's scale. Measured 1.035 x
    (0.848 x at 35 ms) with the prior counted as far as the session's scores agree with it
    (docs/decisions/0222-a-short-past-does-not-judge-a-start-of-motion.md; pooled over five phases
    the cell goes from 1.225 to 0.974 x, the next test); 1.009 x (0.837 x) before it, with the
    novelty guard measured from what the last two frames' velocities
    agree on (docs/decisions/0216-a-start-of-motion-is-not-a-glitch.md), as with its factor
    squared on the model's rollout (docs/decisions/0219-a-novel-rollout-weighs-by-the-square.md);
    1.021 x (0.850 x) from
    STATIC, at the scale of the best of the prior's predictors
    (docs/decisions/0211-the-prior-at-its-best-predictors-scale.md); 1.008 x (0.809 x) at STATIC's;
    1.092 x with the prior's covariances at gait's scale (the model's rollout then took 0.99 of the
    weight on three scores of the session's own: docs/decisions/0192-the-prior-at-the-sessions-scale.md)."""
    rows = prior_eval.evaluate(
        lambda spec, obj: run_lockstep(client, spec, obj=obj, progress=False),
        recordings=("isen_tasks",),
        sensors={"perfect": None},
        seconds=1.5,
    )
    first = {round(r.horizon * 1000): r for r in rows if r.window == "first stride"}
    assert first[100].ratio("defaults") <= 1.05, first[100].errors
    assert first[35].ratio("defaults") <= 1.05, first[35].errors


@pytest.mark.timeout(300)
def test_a_start_of_motion_after_a_slow_start_is_answered_within_the_extrapolators(
    client: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The iSen person's movements that do not repeat (isen_tasks, left out of the prior), perfect
    frames, the first stride's gaps at all five phases pooled: a fast movement after a slow start,
    where constant acceleration forecasts best. The defaults stay within 1.05 x the best
    extrapolator at 100 ms: the prior's scores (gait's) count only as far as the session's own
    agree with them, and on such a motion, before SETTLED scores, the novelty guard judges
    constant acceleration by the share of it that is not the guard's reference. Without both (the Python combiner, as the server
    combines natively to 1e-9) the cell is missed. Measured 0.974 x; 1.225 x without
    (docs/decisions/0222-a-short-past-does-not-judge-a-start-of-motion.md)."""

    def first_stride() -> prior_eval.PriorRow:
        rows = prior_eval.evaluate(
            lambda spec, obj: run_lockstep(client, spec, obj=obj, progress=False),
            recordings=("isen_tasks",),
            sensors={"perfect": None},
            seconds=1.5,
            phases=prior_eval.PHASES,
        )
        return next(r for r in rows if r.window == "first stride" and round(r.horizon * 1000) == 100)

    with_rules = first_stride()
    monkeypatch.setattr(forecast, "SETTLED", 0)
    monkeypatch.setattr(forecast.ForecastCombiner, "_agreement", lambda self, h: 1.0)
    monkeypatch.setattr(foresight, "native_combination", lambda config: False)
    without = first_stride()
    assert with_rules.count == without.count == 19
    assert with_rules.ratio("defaults") <= 1.05, with_rules.errors
    assert without.ratio("defaults") > 1.05, without.errors


@pytest.mark.timeout(300)
def test_the_end_of_a_jumps_push_off_is_not_answered_with_the_models_rollout(client: Any) -> None:
    """The jump (cmj, perfect frames) with the first gap from 450 ms, whose gap at the end of the
    push-off (the joints stop at full extension) holds most of its error at 100 ms: the last two
    frames' velocities agree, and the model's rollout, its scored errors small over the push-off,
    carries the push-off past its end. The novelty guard weighs it by the square of its
    departure's ratio, and the defaults stay within 1.05 x the best extrapolator at 100 ms over
    the whole run. Measured 0.860 x; 1.602 x with the ratio itself
    (docs/decisions/0219-a-novel-rollout-weighs-by-the-square.md)."""
    rows = prior_eval.evaluate(
        lambda spec, obj: run_lockstep(client, spec, obj=obj, progress=False),
        recordings=("cmj",),
        sensors={"perfect": None},
        phases=(prior_eval.PHASES[-1],),
    )
    whole = {round(r.horizon * 1000): r for r in rows if r.window == "whole run"}
    assert whole[100].ratio("defaults") <= 1.05, whole[100].errors


@pytest.mark.timeout(300)
def test_phases_pool_the_gaps_of_later_starts_and_keep_the_single_phase_cells(client: Any) -> None:
    """The gaps at two phases (the first gap from 250 and from 350 ms) on Fukuchi's walk, perfect
    frames, 1.3 s: phase 0's cells are the single-phase protocol's, to the digit (the same
    sessions); the first stride's cells hold 4 gaps a phase, 8 pooled; the later phase's gaps are
    other gaps (other errors); each pooled ratio lies in its 90 % bootstrap interval, which has a
    width (docs/decisions/0202-gap-phases.md)."""

    def rows(phases: tuple[float, ...]) -> dict[tuple[str, int], prior_eval.PriorRow]:
        found = prior_eval.evaluate(
            lambda spec, obj: run_lockstep(client, spec, obj=obj, progress=False),
            recordings=("fukuchi_walk",),
            sensors={"perfect": None},
            seconds=1.3,
            phases=phases,
        )
        return {(r.window, round(r.horizon * 1000)): r for r in found}

    single, phased = rows(prior_eval.SINGLE_PHASE), rows((0.0, 0.1))
    assert (
        single.keys() == phased.keys() == {(w, h) for w in ("first stride", "whole run") for h in (35, 100)}
    )
    for cell, row in phased.items():
        one = single[cell]
        assert row.by_phase[0.0] == pytest.approx(one.errors, rel=1e-9), cell
        assert row.phase_ratio(0.0) == pytest.approx(one.ratio("defaults"), rel=1e-9), cell
        assert row.by_phase[0.1]["defaults"] != pytest.approx(one.errors["defaults"], rel=1e-3), cell
        assert row.count > one.count, cell
        low, high = row.interval()
        assert low <= row.ratio("defaults") <= high and low < high, (cell, low, high)
    assert [single["first stride", h].count for h in (35, 100)] == [4, 4]
    assert [phased["first stride", h].count for h in (35, 100)] == [8, 8]
