"""The forecast combination as the UKF answers a gap with it (DRIVEN, Forecast.COMBINED): what it is
fed on each frame, the answer it gives over a gap in place of the filter's prediction, and the NIS
of the frame that ends the gap against that answer. The combination itself is
estimation/forecast.py's; UnscentedFilter (estimation/ukf.py) calls this at the steps of a tick::

    foresight = Foresight.of(model, config, driven=True, manifold=False)   # None: the filter answers
    foresight.observe(m, x=posterior_mean, act=act)          # on a frame, after its update
    foresight.advance()                                      # every tick
    answer = foresight.answer(r_diagonal=r, measures_qvel=True)
    estimate = foresight.combined(estimate, answer, force=inverse_dynamics_of_answer)
    nis = foresight.gap_nis(z, P=P, R=R, answer=foresight.answer(..., ended=True), nis=nis)

The answer's variance over [q, qd] is, per component, the larger of the combination's scored error
and the filter's prediction's (answer_scale), and its unknown force the inverse dynamics of the
forecast motion; the filter's own mean and covariance go on predicting under their own force.

Which combiner: with the NATIVE engine, the native one (native/combiner.py, the same numbers at a
fraction of the cost), the prior of human motion included (models whose joints have leg roles);
the Python ForecastCombiner, its reference, with the FAST and FILTERPY engines, with a predictor
family the native engine lacks, or when the config asks for it (`native_forecast=False`)
(docs/decisions/0208-the-forecast-in-the-native-engine.md,
docs/decisions/0218-the-prior-in-the-native-engine.md).
"""

from __future__ import annotations

import dataclasses
from typing import Final

import mujoco
import numpy as np

from jitdyn.errors import InvalidArgument
from jitdyn.server.estimation import predictors
from jitdyn.server.estimation.config import Engine, EstimatorConfig
from jitdyn.server.estimation.forecast import CombinedForecast, CombinerSnapshot, ForecastCombiner
from jitdyn.server.estimation.interface import Estimate, Measurement, read_only
from jitdyn.server.estimation.native import CombinerState
from jitdyn.server.estimation.native.combiner import NATIVE_PREDICTORS, NativeCombiner
from jitdyn.server.estimation.prior import PriorMatcher, legs_of, library
from jitdyn.vocabulary import Forecast

__all__ = ["FORECAST_HORIZON", "Foresight", "answer_scale", "native_combination"]

# The longest gap the forecast combination learns its weights for, s (past it the filter answers).
FORECAST_HORIZON: Final = 0.5


def native_combination(config: EstimatorConfig) -> bool:
    """Whether a session combines its forecasts in the native engine (the prior included): its engine
    is NATIVE, the config does not ask for the Python combiner, and every predictor family is one
    the native engine computes (estimation/predictors.py's FAMILIES)."""
    return (
        config.engine == Engine.NATIVE
        and config.native_forecast
        and predictors.names(predictors.FAMILIES) == NATIVE_PREDICTORS
    )


def answer_scale(P: np.ndarray, answer: CombinedForecast, nv: int) -> np.ndarray:
    """(2 nv,) the factors on the rows and columns of P's [q, qd] block that give the combination's
    answer its variance: per component the larger of the combination's own (its scored errors at
    this horizon) and the filter's prediction's, the filter's correlations kept. The combination's
    alone was measured more optimistic than the filter's (median NEES / dim over the gap ticks 50
    against 0.6 on the pendulum, 2.3 against 0.95 on myoElbow with wearable frames): its scores
    never see the phase of the motion a gap starts at (no frames come there), and its weights are
    chosen to minimise the same scores."""
    k = 2 * nv
    predicted = np.diagonal(P)[:k]
    wanted = np.maximum(predicted, np.concatenate([answer.var_q, answer.var_qd]))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.asarray(np.where(predicted > 0.0, np.sqrt(wanted / predicted), 1.0))


def _scaled(P: np.ndarray, answer: CombinedForecast, nv: int) -> np.ndarray:
    """A copy of P with the answer's variances on its [q, qd] block (answer_scale)."""
    P = np.array(P)
    root = answer_scale(P, answer, nv)
    k = root.size
    P[:k, :] *= root[:, None]
    P[:, :k] *= root[None, :]
    return P


class Foresight:
    """One session's forecast combination, in the UKF's state layout (nq, nv; fblocks 1 or 2)."""

    def __init__(self, model: mujoco.MjModel, config: EstimatorConfig, *, fblocks: int) -> None:
        self._nq, self._nv, self._fblocks = int(model.nq), int(model.nv), fblocks
        legs = legs_of(config.roles)
        prior = None
        if legs:
            try:
                chosen = library(config.prior_without)
            except ValueError as error:
                raise InvalidArgument(f"model tag prior.without: {error}") from None
            prior = PriorMatcher(chosen, legs=legs, nv=self._nv, dt=config.dt)
        horizon = int(np.ceil(FORECAST_HORIZON / config.dt - 1e-9))
        self.combiner: ForecastCombiner | NativeCombiner
        if native_combination(config):
            self.combiner = NativeCombiner(
                model, dt=config.dt, steps_per_tick=config.steps_per_tick, horizon=horizon, prior=prior
            )
        else:
            self.combiner = ForecastCombiner(
                model,
                dt=config.dt,
                steps_per_tick=config.steps_per_tick,
                horizon=horizon,
                learner=True,
                prior=prior,
            )

    @classmethod
    def of(
        cls, model: mujoco.MjModel, config: EstimatorConfig, *, fblocks: int, manifold: bool
    ) -> Foresight | None:
        """The session's, or None where the filter answers gaps alone: another Forecast, a scenario
        without the unknown force, or a model with ball or free joints."""
        if config.forecast != Forecast.COMBINED or fblocks == 0 or manifold:
            return None
        return cls(model, config, fblocks=fblocks)

    def reset(self) -> None:
        self.combiner.reset()

    def advance(self) -> None:
        self.combiner.advance()

    def snapshot(self) -> CombinerSnapshot | CombinerState:
        return self.combiner.snapshot()

    def restore(self, snap: CombinerSnapshot | CombinerState) -> None:
        # Each combiner takes its own snapshots (two branches for the type checker).
        if isinstance(self.combiner, NativeCombiner) and isinstance(snap, CombinerState):  # noqa: SIM114
            self.combiner.restore(snap)
        elif isinstance(self.combiner, ForecastCombiner) and isinstance(snap, CombinerSnapshot):
            self.combiner.restore(snap)
        else:
            raise TypeError(f"a snapshot of another combiner: {type(snap).__name__}")

    def observe(self, m: Measurement, *, x: np.ndarray, act: np.ndarray) -> None:
        """Score the forecasts against frame m and start this tick's, from the posterior mean x."""
        if not np.all(np.isfinite(x)):
            return
        nq, nv = self._nq, self._nv
        qvel = m.qvel if m.qvel is not None else x[nq : nq + nv]
        self.combiner.observe(
            m.qpos,
            qvel,
            mean_qpos=x[:nq],
            mean_qvel=x[nq : nq + nv],
            act=act,
            force=x[nq + nv : nq + 2 * nv],
            rate=x[nq + 2 * nv : nq + 3 * nv] if self._fblocks == 2 else None,
        )

    def answer(
        self, *, r_diagonal: np.ndarray | None, measures_qvel: bool, ended: bool = False
    ) -> CombinedForecast | None:
        """The combination's answer now (ended: on the frame that ends a gap, the one its last tick
        gave), its variances net of the frames' noise (R's diagonal, when the noise adapts)."""
        nv = self._nv
        noise_q = noise_qd = None
        if r_diagonal is not None:
            noise_q = r_diagonal[:nv]
            if measures_qvel:
                noise_qd = r_diagonal[nv : 2 * nv]
        return self.combiner.forecast(noise_q=noise_q, noise_qd=noise_qd, ended=ended)

    def combined(self, estimate: Estimate, answer: CombinedForecast, *, force: np.ndarray) -> Estimate:
        """The filter's estimate over a gap with the combination's answer in its place: its q, qd
        and qdd, the force under which the physics follows them (`force`, the inverse dynamics of
        the answer; kept from the filter where it is not finite), and its variances."""
        assert estimate.covariance is not None, "a UKF's estimate carries its covariance"
        nq, nv = self._nq, self._nv
        state = np.array(estimate.state)
        state[:nq], state[nq : nq + nv] = answer.qpos, answer.qvel
        if np.all(np.isfinite(force)):
            state[nq + nv : nq + 2 * nv] = force
        frozen = read_only(state)
        return dataclasses.replace(
            estimate,
            qpos=frozen[:nq],
            qvel=frozen[nq : nq + nv],
            qacc=read_only(answer.qacc),
            state=frozen,
            covariance=read_only(_scaled(estimate.covariance, answer, nv)),
            forecast_weights=tuple(float(w) for w in answer.weights),
            forecast_predictors=answer.predictors,
        )

    def gap_nis(
        self,
        z: np.ndarray,
        *,
        P: np.ndarray,
        R: np.ndarray,
        answer: CombinedForecast | None,
        nis: float | None,
    ) -> float | None:
        """The NIS of the frame z that ends a gap against the gap's last answer (`answer`, the
        combination's with its covariance from the filter's prior P), or `nis`, the filter's own,
        where the filter answered (no answer: a gap past the scored horizon). One m x m solve, once
        a gap."""
        if answer is None:
            return nis
        nq, nv, m = self._nq, self._nv, z.size
        scaled = _scaled(P, answer, nv)
        mean = np.concatenate([answer.qpos, answer.qvel])[:m]
        S = scaled[:m, :m] + R
        y = z[: nq + nv][:m] - mean
        try:
            value = float(y @ np.linalg.solve(S, y))
        except np.linalg.LinAlgError:
            return nis
        return value if np.isfinite(value) else nis
