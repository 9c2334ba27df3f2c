"""The forecast combination in the native engine (forecast.cc, matching.cc, prior.cc) behind the
surface of estimation/forecast.py's ForecastCombiner, for a DRIVEN session with the default
predictors (MODEL, the IEEE 1278 extrapolators, LEARNED) and, for a model whose joints have leg
roles, the prior of human motion (PRIOR, estimation/prior.py)::

    forecasts = NativeCombiner(process, dt=0.02, steps_per_tick=10, horizon=25, prior=matcher)
    forecasts.advance()
    forecasts.observe(z_qpos, z_qvel, mean_qpos=q, mean_qvel=qd, act=act, force=f, rate=None)
    answer = forecasts.forecast()               # CombinedForecast or None

The numbers are ForecastCombiner's with `learner=True` and the same prior
(tests/server/test_native_forecast.py holds them to 1e-9). The prior's library goes to the engine
once per choice of a leg's joints (a PriorTable, shared by every session of that library). A
predictor family the native engine lacks stays in Python: a combination with it is the Python
ForecastCombiner's (estimation/foresight.py chooses;
docs/decisions/0208-the-forecast-in-the-native-engine.md,
docs/decisions/0218-the-prior-in-the-native-engine.md).
"""

from __future__ import annotations

from collections.abc import Callable

import mujoco
import numpy as np

from jitdyn.server.estimation.forecast import LEARNED, PREDICTORS, CombinedForecast
from jitdyn.server.estimation.native import CombinerState, _ukf
from jitdyn.server.estimation.predictors import PRIOR
from jitdyn.server.estimation.prior import PriorLibrary, PriorMatcher

__all__ = ["NATIVE_PREDICTORS", "NativeCombiner"]

# The predictors forecast.cc computes before LEARNED, in the weights' order: a combination whose
# families (estimation/predictors.py) name others is the Python ForecastCombiner's.
NATIVE_PREDICTORS: tuple[str, ...] = ("MODEL", "STATIC", "CONSTANT_VELOCITY", "CONSTANT_ACCELERATION")


# The library's arrays the engine holds, per library and choice of a leg's joints, with the library
# (which keeps its id from being reused).
_TABLES: dict[tuple[int, tuple[int, ...]], tuple[PriorLibrary, _ukf.PriorTable]] = {}


def _array(value: np.ndarray | None) -> np.ndarray | None:
    return None if value is None else np.asarray(value, dtype=np.float64)


def prior_table(library: PriorLibrary, columns: np.ndarray) -> _ukf.PriorTable:
    """The engine's copy of `library` over its `columns` (J,) of the prior's joints: q, qd, each
    row's clip's end, the candidates and their scaled features; made once, then shared."""
    key = (id(library), tuple(int(c) for c in columns))
    found = _TABLES.get(key)
    if found is None:
        index = library.index(columns, (True,) * 4)
        q, v = library.columns(columns)
        table = _ukf.PriorTable(
            rate=library.rate,
            q=q,
            v=v,
            last=np.asarray(library.last, dtype=np.int64),
            rows=np.asarray(index.rows, dtype=np.int64),
            features=index.features[0],
            spread=library.spread[columns].ravel(),
        )
        found = _TABLES[key] = (library, table)
    return found[1]


_Legs = list[tuple[_ukf.PriorTable, list[int], list[float]]]


def _prior_arguments(
    prior: PriorMatcher | None, horizon: int
) -> tuple[_Legs, list[np.ndarray], list[np.ndarray]]:
    """The Combiner's prior arguments: its legs (table, dofs, signs) and the library's scores at
    every horizon 0..horizon (forecast.py's _prior_scores; none when the library has none)."""
    if prior is None:
        return [], [], []
    legs = [
        (prior_table(prior.library, columns), [int(d) for d in dofs], [float(s) for s in signs])
        for columns, dofs, signs in prior.joints()
    ]
    if prior.scores_at(prior.dt) is None:
        return legs, [], []
    cov, cov_v = np.zeros((2, horizon + 1, 4, 4))
    for h in range(1, horizon + 1):
        scored = prior.scores_at(h * prior.dt)
        assert scored is not None
        cov[h], cov_v[h] = scored
    return legs, list(cov), list(cov_v)


class NativeCombiner:
    """ForecastCombiner's interface over forecast.cc (module docstring). process: the filter's
    process model (warm start off, actuation off), which it keeps alive while the engine holds its
    pointer; prior: the session's matcher of the prior of human motion (its library, legs and dt),
    whose matching the engine does from then on."""

    def __init__(
        self,
        process: mujoco.MjModel,
        *,
        dt: float,
        steps_per_tick: int,
        horizon: int,
        prior: PriorMatcher | None = None,
    ) -> None:
        if PREDICTORS != NATIVE_PREDICTORS:
            raise ValueError(f"the native combination computes {NATIVE_PREDICTORS}, not {PREDICTORS}")
        if prior is not None and prior.dt != float(dt):
            raise ValueError(f"the prior's matcher has dt {prior.dt}, the combiner {float(dt)}")
        self._model = process
        legs, cov, cov_v = _prior_arguments(prior, max(1, int(horizon)))
        self._combiner = _ukf.Combiner(
            process._address,
            dt=float(dt),
            steps_per_tick=int(steps_per_tick),
            horizon=int(horizon),
            legs=legs,
            prior_cov=cov,
            prior_cov_v=cov_v,
        )
        self._predictors = (*PREDICTORS, LEARNED) + (PRIOR.names if prior is not None else ())

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
