"""The forecast combination in the native engine (forecast.cc, matching.cc) behind the surface of
estimation/forecast.py's ForecastCombiner, for a DRIVEN session with the default predictors (MODEL,
the IEEE 1278 extrapolators, LEARNED) and no prior of human motion::

    forecasts = NativeCombiner(process, dt=0.02, steps_per_tick=10, horizon=25)
    forecasts.advance()
    forecasts.observe(z_qpos, z_qvel, mean_qpos=q, mean_qvel=qd, act=act, force=f, rate=None)
    answer = forecasts.forecast()               # CombinedForecast or None

The numbers are ForecastCombiner's with `learner=True` (tests/server/test_native_forecast.py holds
them to 1e-9). The prior (estimation/prior.py, for models whose joints have leg roles) and any
predictor family the native engine lacks stay in Python: a combination with them is the Python
ForecastCombiner's (estimation/foresight.py chooses;
docs/decisions/0208-the-forecast-in-the-native-engine.md).
"""

from __future__ import annotations

from collections.abc import Callable

import mujoco
import numpy as np

from jitdyn.server.estimation.forecast import LEARNED, PREDICTORS, CombinedForecast
from jitdyn.server.estimation.native import CombinerState, _ukf

__all__ = ["NATIVE_PREDICTORS", "NativeCombiner"]

# The predictors forecast.cc computes before LEARNED, in the weights' order: a combination whose
# families (estimation/predictors.py) name others is the Python ForecastCombiner's.
NATIVE_PREDICTORS: tuple[str, ...] = ("MODEL", "STATIC", "CONSTANT_VELOCITY", "CONSTANT_ACCELERATION")


def _array(value: np.ndarray | None) -> np.ndarray | None:
    return None if value is None else np.asarray(value, dtype=np.float64)


class NativeCombiner:
    """ForecastCombiner's interface over forecast.cc (module docstring). process: the filter's
    process model (warm start off, actuation off), which it keeps alive while the engine holds its
    pointer."""

    def __init__(self, process: mujoco.MjModel, *, dt: float, steps_per_tick: int, horizon: int) -> None:
        self._model = process
        self._combiner = _ukf.Combiner(
            process._address, dt=float(dt), steps_per_tick=int(steps_per_tick), horizon=int(horizon)
        )
        if PREDICTORS != NATIVE_PREDICTORS:
            raise ValueError(f"the native combination computes {NATIVE_PREDICTORS}, not {PREDICTORS}")
        self._predictors = (*PREDICTORS, LEARNED)

    @property
    def native(self) -> _ukf.Combiner:
        """The compiled combiner, for native/tick.py."""
        return self._combiner

    @property
    def horizon(self) -> int:
        return int(self._combiner.horizon)

    @property
    def nv(self) -> int:
        return int(self._combiner.nv)

    @property
    def na(self) -> int:
        return int(self._combiner.na)

    @property
    def predictors(self) -> tuple[str, ...]:
        """The predictors' names in the order of the weights."""
        return self._predictors

    def reset(self) -> None:
        """Forget every score and probe (motion matching keeps the frames it has seen)."""
        self._combiner.reset()

    def advance(self) -> None:
        self._combiner.advance()

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
        self._combiner.observe(
            np.asarray(qpos, dtype=np.float64),
            np.asarray(qvel, dtype=np.float64),
            mean_qpos=np.asarray(mean_qpos, dtype=np.float64),
            mean_qvel=np.asarray(mean_qvel, dtype=np.float64),
            act=np.asarray(act, dtype=np.float64),
            force=np.asarray(force, dtype=np.float64),
            rate=_array(rate),
        )

    def forecast(
        self,
        *,
        noise_q: np.ndarray | None = None,
        noise_qd: np.ndarray | None = None,
        ended: bool = False,
    ) -> CombinedForecast | None:
        """ForecastCombiner.forecast's answer (its docstring says what the arguments are)."""
        answer = self._combiner.forecast(noise_q=_array(noise_q), noise_qd=_array(noise_qd), ended=ended)
        if answer is None:
            return None
        weights, qpos, qvel, qacc, var_q, var_qd = answer
        weights.flags.writeable = False
        return CombinedForecast(
            weights=weights,
            qpos=qpos,
            qvel=qvel,
            qacc=qacc,
            var_q=var_q,
            var_qd=var_qd,
            predictors=self._predictors,
        )

    def fill_window(self, frames: Callable[[int], tuple[np.ndarray, np.ndarray]]) -> int:
        """ForecastCombiner.fill_window: motion matching's window of frames (q, qd) = frames(tick)
        recorded, nothing scored; the tick reached."""
        first = int(self._combiner.tick) + 1
        window = int(self._combiner.window)
        q, v = np.empty((2, window, self.nv))
        for k in range(window):
            q[k], v[k] = frames(first + k)
        return int(self._combiner.fill_window(q, v))

    def snapshot(self) -> CombinerState:
        return self._combiner.snapshot()

    def restore(self, snap: CombinerState) -> None:
        self._combiner.restore(snap)
