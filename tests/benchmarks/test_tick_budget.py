"""benchmarks/tick_budget.py's attribution: hand-written py-spy stacks into the tick's stages, and
the threads' CPU spread over them. The benchmark itself runs for minutes and is not run here."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parents[2]
SERVICE = f"{ROOT}/server/transport/dynamics_service.py"
SITE = "/venv/lib/python3.11/site-packages"


@pytest.fixture
def budget(benchmark_module: Callable[[str], ModuleType]) -> ModuleType:
    return benchmark_module("tick_budget")


def stack(budget: ModuleType, *frames: tuple[str, str]) -> list[object]:
    """Frames innermost first, each (function, file)."""
    return [budget.Frame(function, file, 1) for function, file in frames]


CASES = {
    "the write": [
        ("_Stream.write", SERVICE),
        ("_RealtimeClock.write", SERVICE),
        ("_RealtimeClock.run", SERVICE),
    ],
    "the forecast (combination, matching, dead reckoning)": [
        ("Rollout.rollout", f"{SITE}/mujoco/rollout.py"),
        ("Propagator.__call__", f"{ROOT}/server/estimation/propagate.py"),
        ("ForecastCombiner._step", f"{ROOT}/server/estimation/forecast.py"),
        ("UnscentedFilter._predict", f"{ROOT}/server/estimation/ukf.py"),
        ("SessionRuntime.advance", f"{ROOT}/server/runtime/session.py"),
    ],
    "the glance ahead (ticks past the filter)": [
        ("Rollout.rollout", f"{SITE}/mujoco/rollout.py"),
        ("Propagator.__call__", f"{ROOT}/server/estimation/propagate.py"),
        ("Lookahead.glance", f"{ROOT}/server/estimation/lookahead.py"),
        ("UnscentedFilter.glance", f"{ROOT}/server/estimation/ukf.py"),
    ],
    "estimator cycle: the sigma points' physics": [
        ("Rollout.rollout", f"{SITE}/mujoco/rollout.py"),
        ("Propagator.__call__", f"{ROOT}/server/estimation/propagate.py"),
        ("SigmaProcess.propagate", f"{ROOT}/server/estimation/process.py"),
        ("SessionRuntime.advance", f"{ROOT}/server/runtime/session.py"),
    ],
    "estimator cycle: the filter's algebra": [
        ("cholesky", f"{SITE}/scipy/linalg/_decomp_cholesky.py"),
        ("UnscentedKalmanFilter.update", f"{SITE}/filterpy/kalman/UKF.py"),
        ("UnscentedFilter.update", f"{ROOT}/server/estimation/ukf.py"),
    ],
    "the record (storage: the row, the commit thread)": [
        ("SessionRecorder.append", f"{ROOT}/storage/recorder.py"),
        ("_Stream.record_result", SERVICE),
    ],
    "the result message": [("_Stream.record_result", SERVICE), ("_Stream.answer", SERVICE)],
    # A session's tallies of its metrics (server/transport/tally.py) are the metrics' cost.
    "metrics": [
        ("HistogramTally.observe", f"{ROOT}/server/transport/tally.py"),
        ("_Stream.record_result", SERVICE),
    ],
    "the clock": [
        ("MonotonicClock.now", f"{ROOT}/server/runtime/clock.py"),
        ("_Stream.record_result", SERVICE),
    ],
    "the event loop: asyncio, grpc.aio's Python, its poller": [
        ("Handle._run", "/usr/lib/python3.11/asyncio/events.py"),
        ("BaseEventLoop._run_once", "/usr/lib/python3.11/asyncio/base_events.py"),
        ("_serve", f"{ROOT}/cli/main.py"),
    ],
    # Installed as a wheel: the same files under site-packages/jitdyn/.
    "frame read and check": [
        ("frame_checksum", f"{SITE}/jitdyn/checksum.py"),
        ("check_frame", f"{SITE}/jitdyn/server/transport/frame_check.py"),
    ],
}


@pytest.mark.parametrize("stage", sorted(CASES))
def test_a_stack_is_in_the_stage_that_contains_it(budget: ModuleType, stage: str) -> None:
    assert budget.classify(stack(budget, *CASES[stage])) == stage


def test_a_gaps_answer_is_the_forecasts(budget: ModuleType) -> None:
    # The inverse dynamics of the combination's forecast (estimation/gap.py), and what the frame
    # that ends the gap teaches the adaptive noise, are the forecast's, not the filter's algebra.
    answering = stack(
        budget,
        ("Answers.inverse", f"{ROOT}/server/estimation/answer.py"),
        ("combined", f"{ROOT}/server/estimation/gap.py"),
        ("UnscentedFilter.predict", f"{ROOT}/server/estimation/ukf.py"),
    )
    learning = stack(
        budget,
        ("observe_gap", f"{ROOT}/server/estimation/adaptive_steps.py"),
        ("UnscentedFilter.update", f"{ROOT}/server/estimation/ukf.py"),
    )
    forecast = "the forecast (combination, matching, dead reckoning)"
    assert (budget.classify(answering), budget.classify(learning)) == (forecast, forecast)


def test_stage_names_are_unique(budget: ModuleType) -> None:
    names = [s.name for s in budget.STAGES] + [budget.NATIVE, budget.UNSAMPLED]
    assert len(names) == len(set(names))


def test_a_busy_sample_read_in_a_wait_is_not_spent(budget: ModuleType) -> None:
    selecting = stack(
        budget,
        ("EpollSelector.select", "/usr/lib/python3.11/selectors.py"),
        ("BaseEventLoop._run_once", "/usr/lib/python3.11/asyncio/base_events.py"),
        ("_serve", f"{ROOT}/cli/main.py"),
    )
    assert budget.classify(selecting) == budget.WAITING


def test_raw_samples_and_thread_cpu_make_the_stages_cpu(budget: ModuleType) -> None:
    raw = (
        f"thread (7): MainThread;_RealtimeClock.run ({SERVICE}:1);_Stream.write ({SERVICE}:140) 3\n"
        f"thread (7): MainThread;_Stream.answer ({SERVICE}:1);_Stream.record_result ({SERVICE}:2) 1\n"
        f"thread (9): jitdyn-commit;GroupCommitter._run ({ROOT}/storage/commit.py:300) 2\n"
        "thread (7): MainThread;BaseEventLoop._run_once (/usr/lib/python3.11/asyncio/base_events.py:1);"
        "EpollSelector.select (/usr/lib/python3.11/selectors.py:468) 5\n"
    )
    samples = budget.parse_raw(raw)
    assert samples == Counter(
        {
            (7, "the write"): 3,
            (7, "the result message"): 1,
            (9, "the record (storage: the row, the commit thread)"): 2,
            (7, budget.WAITING): 5,
        }
    )
    profile = budget.Profile(
        samples=samples,
        cpu={7: ("python", 0.8), 9: ("python", 0.1), 11: ("event_engine", 0.05), 12: ("python", 0.02)},
        python={7, 9, 12},
    )
    assert profile.stage_cpu() == pytest.approx(
        {
            "the write": 0.6,
            "the result message": 0.2,
            "the record (storage: the row, the commit thread)": 0.1,
            budget.NATIVE: 0.05,
            budget.UNSAMPLED: 0.02,
        }
    )
