"""A REALTIME session waits for late frames (server/runtime/session.py, docs/decisions/0007): a tick
without its frame is answered by a glance ahead, and the estimator runs each tick once, in tick
order, when its frame comes; it ends bit for bit where a run with every frame on time ends."""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
import pytest

from jitdyn.registry import builtin_model_path
from jitdyn.server.estimation.config import resolve_config
from jitdyn.server.estimation.dynamics import Dynamics
from jitdyn.server.estimation.factory import make_estimator
from jitdyn.server.estimation.interface import Estimate, Estimator, Measurement
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.runtime.frames import FrameIn
from jitdyn.server.runtime.session import SessionRuntime
from jitdyn.vocabulary import Scenario, Source


@dataclass(frozen=True)
class Case:
    model: str
    scenario: Scenario
    dt: float


CASES = [
    Case("pendulum_3", Scenario.PASSIVE, 0.05),
    Case("biped", Scenario.CONTROLLED, 0.01),
]


class Counting:
    """The real estimator, with the ticks of physics it runs counted (predict and advance)."""

    def __init__(self, inner: Estimator) -> None:
        self.inner = inner
        self.ticks = 0

    def __getattr__(self, name: str) -> object:
        return getattr(self.inner, name)

    def predict(self, *, ctrl: np.ndarray | None) -> Estimate:
        self.ticks += 1
        return self.inner.predict(ctrl=ctrl)

    def advance(self, *, ctrl: np.ndarray | None) -> None:
        self.ticks += 1
        self.inner.advance(ctrl=ctrl)

    def update(self, m: Measurement) -> Estimate:
        return self.inner.update(m)

    def step(self, *, ctrl: np.ndarray | None, m: Measurement) -> Estimate:
        self.ticks += 1
        return self.inner.step(ctrl=ctrl, m=m)


def _frames(model: mujoco.MjModel, case: Case, ticks: int) -> list[FrameIn]:
    data = mujoco.MjData(model)
    data.qpos[:] = model.qpos0
    data.qpos[-3:] += [0.5, -0.3, 0.2]
    steps = round(case.dt / model.opt.timestep)
    frames = []
    for k in range(ticks):
        ctrl = 0.5 * np.sin(0.3 * k + np.arange(model.nu)) if case.scenario == Scenario.CONTROLLED else None
        frames.append(
            FrameIn(
                seq=k,
                t=k * case.dt,
                qpos=data.qpos.copy(),
                qvel=data.qvel.copy(),
                qacc=None,
                ctrl=ctrl,
                sensordata=None,
                received=k * case.dt,
            )
        )
        if ctrl is not None:
            data.ctrl[:] = ctrl
        for _ in range(steps):
            mujoco.mj_step(model, data)
    return frames


def _runtime(
    model: mujoco.MjModel, case: Case, pool: WorkerPool, *, wait: bool
) -> tuple[SessionRuntime, Counting]:
    config = resolve_config(
        model=model,
        scenario=case.scenario,
        dt=case.dt,
        preset="JITDYN",
        measured={"qpos", "qvel"},
    )
    estimator = Counting(make_estimator(model, config, pool=pool))
    runtime = SessionRuntime(
        model=model,
        estimator=estimator,  # type: ignore[arg-type]  # the real estimator, its ticks counted
        dynamics=Dynamics(model, outputs=frozenset({"INVERSE_DYNAMICS"})),
        dt=case.dt,
        scenario=case.scenario,
        history=50,
        wait_for_late=wait,
    )
    return runtime, estimator


def _state(estimator: Counting) -> tuple[np.ndarray, np.ndarray]:
    now = estimator.inner.extrapolate(0.0)
    return np.array(now.state), np.array(now.covariance)


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.model)
def test_frames_late_by_three_ticks_cost_one_tick_each_and_end_where_on_time_frames_end(case: Case) -> None:
    model = mujoco.MjModel.from_xml_path(str(builtin_model_path(case.model)))
    late, ticks = 3, 40
    frames = _frames(model, case, ticks + late)
    with WorkerPool(1) as pool:
        on_time, on_time_estimator = _runtime(model, case, pool, wait=False)
        for k in range(ticks):
            on_time.advance(frames[k])

        runtime, estimator = _runtime(model, case, pool, wait=True)
        answers = []
        costs = []
        for k in range(ticks + late):
            if k >= late:
                costs.append(runtime.late_cost(k - late))
                corrected = runtime.apply_late(frames[k - late])
                assert (corrected.source, corrected.late_ticks) == (
                    Source.CORRECTED,
                    min(late, ticks + late - k),
                )
            if k < ticks:
                answers.append(runtime.advance(None))
        # The first late frame replays the ticks run before the session knew frames come late (its
        # own now, the rest over the next ticks, so the next late frame finds its tick waiting);
        # from then on each costs one tick of the filter: the ticks before it waited for it (a
        # timewarp would replay `late` ticks for each).
        assert costs[0] == late and set(costs[1:]) == {1}, costs
        assert estimator.ticks <= ticks + late  # the on-time run's, plus the first timewarp's
        state, covariance = _state(estimator)
        on_time_state, on_time_covariance = _state(on_time_estimator)
        np.testing.assert_array_equal(state, on_time_state)
        np.testing.assert_array_equal(covariance, on_time_covariance)
        # The answers given while the frames were on their way follow the body.
        errors = [np.max(np.abs(a.qpos - frames[a.seq].qpos)) for a in answers[late + 2 :]]
        assert all(a.source == Source.PREDICTED for a in answers)
        assert max(errors) < 0.05, errors


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.model)
def test_a_lost_frame_and_a_frame_later_than_the_wait_end_where_the_same_frames_on_time_end(
    case: Case,
) -> None:
    model = mujoco.MjModel.from_xml_path(str(builtin_model_path(case.model)))
    ticks, lost, very_late = 40, 20, 25
    frames = _frames(model, case, ticks)
    with WorkerPool(1) as pool:
        on_time, on_time_estimator = _runtime(model, case, pool, wait=False)
        for k in range(ticks):
            on_time.advance(None if k == lost else frames[k])

        runtime, estimator = _runtime(model, case, pool, wait=True)
        arrivals: dict[int, list[int]] = {}
        for k in range(ticks):
            if k not in (lost, very_late):
                arrivals.setdefault(k + 2, []).append(k)  # two ticks late
        arrivals.setdefault(very_late + 7, []).append(very_late)  # past the wait: a timewarp
        costs = {}
        for k in range(ticks + 8):
            for seq in arrivals.get(k, []):
                costs[seq] = runtime.late_cost(seq)
                assert runtime.apply_late(frames[seq]).source == Source.CORRECTED
            if k < ticks:
                runtime.advance(None)
        # The lost frame's tick ran without it when its wait ended, so the next frame cost one
        # tick; the frame later than the wait replayed the ticks run since its tick.
        assert costs[lost + 1] == 1 and costs[very_late] > 2, costs
        state, covariance = _state(estimator)
        on_time_state, on_time_covariance = _state(on_time_estimator)
        np.testing.assert_array_equal(state, on_time_state)
        np.testing.assert_array_equal(covariance, on_time_covariance)


def test_glance_changes_nothing_and_stays_near_the_unscented_extrapolation() -> None:
    case = CASES[0]
    model = mujoco.MjModel.from_xml_path(str(builtin_model_path(case.model)))
    frames = _frames(model, case, 6)
    with WorkerPool(1) as pool:
        runtime, estimator = _runtime(model, case, pool, wait=True)
        for frame in frames:
            runtime.advance(frame)
        before = _state(estimator)
        now = estimator.inner.glance(0.0)
        np.testing.assert_array_equal(now.state, before[0])
        for ticks in (1, 3):
            glance = estimator.inner.glance(ticks * case.dt)
            sigma = estimator.inner.extrapolate(ticks * case.dt)
            assert np.max(np.abs(glance.qpos - sigma.qpos)) < 1e-3
            assert np.all(np.diag(glance.covariance) >= np.diag(before[1]))
        after = _state(estimator)
        np.testing.assert_array_equal(after[0], before[0])
        np.testing.assert_array_equal(after[1], before[1])


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.model)
def test_a_replay_runs_only_the_late_tick_and_the_rest_is_caught_up_over_the_next_ticks(case: Case) -> None:
    """The rest of the frames on time, one in ten sent 4 ticks late, after the on-time frames of the
    ticks after it made the estimator run its tick without it: each is CORRECTED with the estimate
    an on-time run has at its tick, for one tick of the filter, and the ticks the replay would have
    run are caught up at most _CATCH_UP a tick beyond the clock's (docs/decisions/0167)."""
    model = mujoco.MjModel.from_xml_path(str(builtin_model_path(case.model)))
    ticks, late = 60, 4
    frames = _frames(model, case, ticks)
    delayed = set(range(10, ticks - late - 8, 10))
    with WorkerPool(1) as pool:
        on_time, on_time_estimator = _runtime(model, case, pool, wait=False)
        on_time_estimates = {}
        for k in range(ticks):
            on_time_estimates[k] = on_time.advance(frames[k]).estimate

        runtime, estimator = _runtime(model, case, pool, wait=True)
        runs_per_tick, caught_up = [], []
        for k in range(ticks):
            before = estimator.ticks
            runtime.advance(None if k in delayed else frames[k])
            runs_per_tick.append(estimator.ticks - before)
            caught_up.append(runtime.caught_up)
            if k - late in delayed:
                seq = k - late
                assert runtime.replay_cost(seq) == 1
                before = estimator.ticks
                corrected = runtime.apply_late(frames[seq])
                assert estimator.ticks - before == 1
                assert corrected.source == Source.CORRECTED and corrected.estimate is not None
                expected = on_time_estimates[seq]
                assert expected is not None
                np.testing.assert_array_equal(corrected.estimate.state, expected.state)
                np.testing.assert_array_equal(corrected.estimate.covariance, expected.covariance)
        assert max(runs_per_tick) <= 3, runs_per_tick  # its own tick and _CATCH_UP more
        # The time a tick spent on a replay's ticks is told apart (admission counts it as replay):
        # none before the first late frame, some on the tick after each.
        first = min(delayed) + late
        assert caught_up[:first] == [0.0] * first
        assert all(caught_up[seq + late + 1] > 0.0 for seq in delayed), caught_up
        state, covariance = _state(estimator)
        on_time_state, on_time_covariance = _state(on_time_estimator)
        np.testing.assert_array_equal(state, on_time_state)
        np.testing.assert_array_equal(covariance, on_time_covariance)
