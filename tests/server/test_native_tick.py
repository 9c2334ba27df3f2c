"""A tick in one native call (server/estimation/native/tick.py, tick.cc) against the native engine's
steps one call each (`native_tick` False, their reference): one UnscentedFilter each, the same
config but the switch, fed through `step()` the same 500 noisy frames with gaps, a repeated frame,
frames far off (the guard's restarts), a prediction that diverges inside the native call, and late
frames' replays. States, covariances, qacc and flags agree to 1e-9, absolute (NIS relative
past 1)."""

from __future__ import annotations

import dataclasses
from collections import Counter

import mujoco
import numpy as np
import pytest

from jitdyn.server.estimation.config import Engine, EstimatorConfig
from jitdyn.server.estimation.interface import Estimate, Measurement
from jitdyn.server.estimation.native.tick import NativeTick
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.estimation.ukf import NativeSnapshot, UnscentedFilter
from jitdyn.server.runtime.costs import snapshot_bytes
from tests.server.test_native import REPEATED, REPLAYED, SKIPPED, flatten, frames_for
from tests.server.test_ukf import config_for, pendulum

TOL = 1e-9
# A covariance blown past the guard's limit before these ticks: the prediction diverges.
BLOWN = {200, 330}


def run(
    model: mujoco.MjModel, config: EstimatorConfig, frames: list[Measurement]
) -> tuple[list[np.ndarray], Counter[str], int]:
    """Every answer of a session fed through step(), flattened, the branches seen, and the size of
    its last snapshot (snapshot_bytes)."""
    out: list[np.ndarray] = []
    seen: Counter[str] = Counter()

    def answer(estimate: Estimate) -> None:
        out.extend(flatten(estimate))
        seen.update(k for k in ("reinitialised", "adapted", "absorbed") if getattr(estimate, k))
        seen["forecast"] += estimate.forecast_weights is not None

    with WorkerPool(1) as pool:
        f = UnscentedFilter(model, config, pool=pool)
        f.initialise(frames[0])
        snapshot = f.snapshot()
        for k in range(1, len(frames)):
            if k in REPLAYED:  # tick k - 3's frame came late: back before it, and forward again
                f.restore(snapshot)
                for j in range(k - 3, k):
                    answer(f.step(ctrl=frames[j].ctrl, m=frames[j]))
                seen["replayed"] += 1
            if k % 10 == 0:
                answer(f.glance(2 * config.dt))
            if k in SKIPPED:
                answer(f.predict(ctrl=frames[k].ctrl))
                continue
            if k + 3 in REPLAYED:
                snapshot = f.snapshot()
            if k in BLOWN:
                f.parts.kf.P = f.parts.kf.P * 1e16
            estimate = f.step(ctrl=frames[k].ctrl, m=frames[k])
            answer(estimate)
            if k in BLOWN:  # started again from the last frame, then updated: P back near P0
                assert estimate.covariance is not None
                seen["blown"] += float(np.max(np.diagonal(estimate.covariance))) < 1e6
            if k in REPEATED:
                answer(f.update(frames[k]))
        seen["repairs"] = f.covariance_repairs
        size = snapshot_bytes(f.snapshot())
    return out, seen, size


@pytest.mark.parametrize(
    ("scenario", "noise_model"),
    [("PASSIVE", "FIXED"), ("PASSIVE", "ADAPTIVE"), ("CONTROLLED", "ADAPTIVE"), ("EXTERNAL", "FIXED"),
     ("DRIVEN", "ADAPTIVE")],
)  # fmt: skip
def test_a_tick_in_one_call_is_the_steps_one_call_each(scenario: str, noise_model: str) -> None:
    model = pendulum(2)
    # The JITDYN preset: the native engine, the forecast combination in DRIVEN.
    one_call = config_for(model, scenario, noise_model=noise_model)
    assert one_call.engine == Engine.NATIVE and one_call.native_tick
    steps = dataclasses.replace(one_call, native_tick=False)
    with WorkerPool(1) as pool:
        native = UnscentedFilter(model, one_call, pool=pool)
        assert NativeTick.of(native.parts) is not None
        native.initialise(Measurement(qpos=np.zeros(2), qvel=np.zeros(2)))
        assert isinstance(native.snapshot(), NativeSnapshot)
        assert NativeTick.of(UnscentedFilter(model, steps, pool=pool).parts) is None
    frames = frames_for(model, one_call)
    (got, seen, size), (expected, seen_steps, size_steps) = (
        run(model, one_call, frames),
        run(model, steps, frames),
    )
    # The native snapshot says its size: x, P, sigmas_f and the combiner's as the steps' do, and
    # the adapter's state, which their opaque AdapterState does not report.
    assert size >= size_steps > 0 and (size > size_steps) == (noise_model == "ADAPTIVE"), (size, size_steps)
    assert seen == seen_steps
    assert len(got) == len(expected)
    for i, (a, b) in enumerate(zip(got, expected, strict=True)):
        # flatten's fourth entry is the NIS: relative past 1 too (a far-off frame's, 1.4e4, by
        # 4e-9: the noise share's dot product is Eigen's, not numpy's).
        rtol = TOL if i % 6 == 3 else 0.0
        np.testing.assert_allclose(a, b, rtol=rtol, atol=TOL, err_msg=f"output {i} ({scenario})")
    # The branches the two are held equal on.
    assert seen["replayed"] == len(REPLAYED)
    assert seen["blown"] == len(BLOWN), seen
    if scenario in ("CONTROLLED", "EXTERNAL"):
        assert seen["reinitialised"] > 0, seen  # the guard's restart after an update
    if noise_model == "ADAPTIVE":
        assert min(seen["adapted"], seen["absorbed"]) > 0, seen
    if scenario == "DRIVEN":
        assert seen["forecast"] > 0, seen
