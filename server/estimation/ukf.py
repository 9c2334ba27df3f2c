"""jitdyn's unscented Kalman filter, built whole from an `EstimatorConfig`, with MuJoCo as the
process model. The numeric steps of a tick (sigma points, propagation, unscented transform,
update, tidying) are a FilterCore (estimation/core.py): the compiled engine's, or the Python one's
(filterpy's UnscentedKalmanFilter or its faster FastUKF, the sigma points propagated in one batched
call by estimation/process.py); this module runs a tick through them and keeps the rest: the
divergence guard, the adaptive noise, the forecast combination, the estimate.

    estimator = UnscentedFilter(model, config, pool=pool)
    estimator.initialise(Measurement(qpos=q0, qvel=v0))
    prior = estimator.predict(ctrl=None)                              # a tick without its frame
    estimator.advance(ctrl=None)                                      # a tick with its frame
    posterior = estimator.update(Measurement(qpos=q1, qvel=v1))      # posterior.nis

The scenarios are the thesis' (experiments/thesis.py holds its numbers):
- PASSIVE, x = [q, qd]: the sigma points move under the model's own forces, no control.
- CONTROLLED, x = [q, qd, qdd]: the control of the tick acts; qdd of a propagated point is the
  qacc MuJoCo computed in its last physics step (the qdd it started with plays no part).
- EXTERNAL, x = [q, qd]: the generalized force that acted is restored by mj_inverse from the
  latest frame (qacc from the frame, else the backward difference of qvel over the ticks since the
  frame before) and held, as qfrc_applied, over every prediction until the next frame. Actuators
  are off in the process model: their forces are part of the restored force.

DRIVEN with Forecast.COMBINED (PRESET_JITDYN's default): a tick without a frame is answered by the
combination of the model's rollout, IEEE 1278's extrapolators and motion matching over the
session's own past that scored best on the session's own frames (estimation/forecast.py, fed
and read by estimation/foresight.py); its
variance over [q, qd] is the larger of the combination's scored error and the filter's prediction,
and its unknown force the inverse dynamics of the forecast motion (the filter's own mean and
covariance go on predicting under their own force, unchanged). DRIVEN with SIMPLEX_LINEAR_FORCE: estimation/linear_force.py.

Muscle activations (act, na of them) are physics state but not filter state: every sigma point
starts a tick from the same act, and the filter keeps the weighted mean of the propagated acts
(clipped to the actuators' ranges). In EXTERNAL, with actuation off, act simply stays.

Numerics: P is symmetrised after every step and repaired (nearest positive definite matrix by
eigenvalue clipping) when its Cholesky factorisation fails; when to start again from a frame (the
divergence guard, wrong_model RESTART) is estimation/guard.py's, and the estimate says so.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

import mujoco
import numpy as np
from filterpy.kalman import unscented_transform

from jitdyn.errors import FailedPrecondition, InvalidArgument
from jitdyn.server.estimation.adaptive import NoiseAdapter, NoiseSnapshot
from jitdyn.server.estimation.batched import BatchedUKF, tangent_unscented_transform
from jitdyn.server.estimation.config import Engine, EstimatorConfig, check_against_model
from jitdyn.server.estimation.core import FilterCore, PythonCore
from jitdyn.server.estimation.fast import FastUKF
from jitdyn.server.estimation.forecast import CombinedForecast, CombinerSnapshot
from jitdyn.server.estimation.foresight import Foresight
from jitdyn.server.estimation.guard import Guard, GuardState
from jitdyn.server.estimation.interface import (
    Estimate,
    Measurement,
    check_measurement,
    check_vector,
    read_only,
)
from jitdyn.server.estimation.layout import derivative_order, force_blocks, linear_force_applies
from jitdyn.server.estimation.linear_force import LinearForceUKF
from jitdyn.server.estimation.manifold import SplitManifold, has_manifold
from jitdyn.server.estimation.native import AdapterState
from jitdyn.server.estimation.native.adaptive import NativeNoiseAdapter
from jitdyn.server.estimation.native.filter import NativeUKF
from jitdyn.server.estimation.noise import UkfNoise
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.estimation.process import SigmaProcess
from jitdyn.server.estimation.propagate import Inputs, Propagator, process_model
from jitdyn.server.estimation.sigma import (
    MerweScaled,
    RobustCholesky,
    Simplex,
    UniformSpherical,
    make_sigma_points,
)
from jitdyn.vocabulary import (
    Channel,
    EstimatorKind,
    NoiseModel,
    Scenario,
    SigmaScheme,
    WrongModel,
)

__all__ = ["FilterSnapshot", "UnscentedFilter"]

# What moves the sigma points besides the model's own forces, per scenario.
_INPUTS: Final = {
    Scenario.PASSIVE: Inputs.NONE,
    Scenario.CONTROLLED: Inputs.CTRL,
    Scenario.EXTERNAL: Inputs.QFRC,
    Scenario.DRIVEN: Inputs.QFRC,
}


_SPANS_KEPT = 16  # process noises kept by span: a horizon, and a glance at each tick of a late window


@dataclass(frozen=True)
class FilterSnapshot:
    """An UnscentedFilter's whole mutable state; arrays are read-only copies."""

    owner: int  # id() of the filter it came from
    initialised: bool
    x: np.ndarray
    P: np.ndarray
    sigmas_f: np.ndarray  # the prior's sigma points, which update() uses
    act: np.ndarray
    ctrl: np.ndarray
    qfrc: np.ndarray
    last: Measurement | None
    last_qvel: np.ndarray
    ticks_since_update: int
    guard: GuardState
    adapter: NoiseSnapshot | AdapterState | None
    forecasts: CombinerSnapshot | None


class UnscentedFilter:
    """The UKF estimator of one session (see the module docstring). Implements `Estimator`."""

    def __init__(self, model: mujoco.MjModel, config: EstimatorConfig, *, pool: WorkerPool) -> None:
        if config.estimator != EstimatorKind.UKF:
            raise InvalidArgument(
                f"config.estimator must be UKF for an UnscentedFilter, got {config.estimator}"
            )
        check_against_model(model, config)
        self._config = config
        self._scenario = Scenario(config.scenario)
        self._model = process_model(model, scenario=self._scenario)
        self._data = mujoco.MjData(self._model)  # for mj_forward / mj_inverse at single states
        m = self._model
        self._nq, self._nv, self._na, self._nu = int(m.nq), int(m.nv), int(m.na), int(m.nu)
        self._order = derivative_order(self._scenario)
        self._fblocks = force_blocks(self._scenario, config.force_model)  # DRIVEN: f, or f and fd
        self._driven = self._fblocks > 0
        self._n = (self._order + self._fblocks) * self._nv  # tangent dimension: filterpy's dim_x
        self._size = self._nq + (self._order - 1 + self._fblocks) * self._nv  # len(x)
        self._controlled = self._scenario == Scenario.CONTROLLED
        self._z_index, z_size, self._z_tangent = self._measurement_layout()
        self._manifold = has_manifold(m)
        self._x_manifold = SplitManifold(m, rest=self._size - self._nq) if self._manifold else None
        self._sqrt = RobustCholesky()
        # SIMPLEX_LINEAR_FORCE keeps the force out of the points where it applies; else it is SIMPLEX.
        self._linear_force = config.sigma_points == SigmaScheme.SIMPLEX_LINEAR_FORCE and linear_force_applies(
            m, self._scenario, config.force_model
        )
        self._points = self._sigma_points()
        self._propagator = Propagator(
            m,
            pool=pool,
            nsigma=self._points.num_sigmas(),
            nstep=config.steps_per_tick,
            inputs=_INPUTS[self._scenario],
            want_qacc=self._controlled,
        )
        # Plain vectors keep filterpy's own transform (and its arithmetic, bit for bit).
        self._ut = tangent_unscented_transform if self._manifold else unscented_transform
        self._process = SigmaProcess(
            m, self._data, propagator=self._propagator, points=self._points, size=self._size,
            fblocks=self._fblocks, controlled=self._controlled, steps_per_tick=config.steps_per_tick,
        )  # fmt: skip
        self._kf: FilterCore = self._filter(z_size)
        self._noise = UkfNoise.of(m, self._data, config)
        self._Q = self._noise.process_noise(config.dt)
        self._kf.Q = self._Q
        self._kf.R = config.r * np.eye(self._z_tangent)
        self._P0 = self._noise.initial_covariance()
        self._adapter = self._noise_adapter()
        restart = config.wrong_model == WrongModel.RESTART
        self._guard = Guard(m=self._z_tangent, restart=restart, driven=self._driven)
        self._extrapolation_Q: dict[int, np.ndarray] = {config.steps_per_tick: self._Q}
        self._act_bounds = self._activation_bounds()
        self._foresight = Foresight.of(m, config, fblocks=self._fblocks, manifold=self._manifold)
        self._no_ctrl, self._no_force = np.zeros(self._nu), np.zeros(self._nv)
        self._clear()

    def _measurement_layout(self) -> tuple[slice | np.ndarray, int, int]:
        """Where the measurement sits in x, how many entries of x it has, and its tangent
        dimension: qpos, then qvel, then qacc (CONTROLLED only: the other states have no qdd)."""
        nq, nv = self._nq, self._nv
        index = list(range(nq))
        z_tangent = nv
        if Channel.QVEL in self._config.measured:
            index += range(nq, nq + nv)
            z_tangent += nv
        if self._controlled and Channel.QACC in self._config.measured:
            index += range(nq + nv, nq + 2 * nv)
            z_tangent += nv
        # A slice when the measured entries are contiguous (qpos and qvel): cheaper than fancy
        # indexing in filterpy's per-point measurement loop.
        contiguous = index == list(range(len(index)))
        return (slice(0, len(index)) if contiguous else np.array(index)), len(index), z_tangent

    def _sigma_points(self) -> MerweScaled | Simplex | UniformSpherical:
        config = self._config
        linear = config.sigma_points == SigmaScheme.SIMPLEX_LINEAR_FORCE
        return make_sigma_points(
            SigmaScheme.SIMPLEX if linear else config.sigma_points,
            n=self._order * self._nv if self._linear_force else self._n,
            alpha=config.alpha,
            beta=config.beta,
            kappa=config.kappa,
            sqrt=self._sqrt,
            add=self._x_manifold.add if self._x_manifold is not None else None,
        )

    def _filter(self, z_size: int) -> FilterCore:
        """The engine's filter over this state and measurement: the native one, or filterpy's (or
        its faster FastUKF, or the LinearForceUKF) with the process model in Python."""
        x_manifold = self._x_manifold
        z_manifold = SplitManifold(self._model, rest=z_size - self._nq) if self._manifold else None
        kwargs: dict[str, object] = {
            "dim_x": self._n,
            "dim_z": self._z_tangent,
            "dt": self._config.dt,
            "hx": self._hx,
            "fx": None,
            "points": self._points,
            "sqrt_fn": self._sqrt,
            "x_mean_fn": x_manifold.mean if x_manifold is not None else None,
            "z_mean_fn": z_manifold.mean if z_manifold is not None else None,
            "residual_x": x_manifold.residual if x_manifold is not None else None,
            "residual_z": z_manifold.residual if z_manifold is not None else None,
            "state_add": x_manifold.add if x_manifold is not None else None,
        }
        process = self._process
        inner: BatchedUKF
        if self._linear_force:
            inner = LinearForceUKF(
                motion=self._order * self._nv,
                propagate_forced=process.propagate_linear_force,
                response=process.force_response,
                z_index=self._z_index,
                propagate=process.propagate,
                vector=True,
                **kwargs,
            )
        elif self._config.engine == Engine.NATIVE:
            return NativeUKF(
                self._model,
                points=self._points,
                z_index=self._z_index,
                nstep=self._config.steps_per_tick,
                inputs=_INPUTS[self._scenario],
                fblocks=self._fblocks,
                controlled=self._controlled,
                manifold=x_manifold,
            )
        elif self._config.engine == Engine.FAST:
            inner = FastUKF(
                propagate=process.propagate, vector=not self._manifold, z_index=self._z_index, **kwargs
            )
        else:
            inner = BatchedUKF(propagate=process.propagate, vector=not self._manifold, **kwargs)
        return PythonCore(inner, process=process, ut=self._ut, model=self._model, data=self._data)

    def _noise_adapter(self) -> NoiseAdapter | NativeNoiseAdapter | None:
        if self._config.noise_model != NoiseModel.ADAPTIVE:
            return None
        adapter = NativeNoiseAdapter if self._config.engine == Engine.NATIVE else NoiseAdapter
        return adapter(
            r0=np.full(self._z_tangent, self._config.r),
            q0=self._Q,
            adapt_q=self._noise.adapt_q_mask(),
            inflate=self._driven,
        )

    def _clear(self) -> None:
        """The mutable state of a filter not yet initialised; snapshot() copies all of it."""
        self._initialised = False
        x = np.zeros(self._size)
        x[: self._nq] = self._model.qpos0
        self._kf.x = x
        self._kf.P = self._P0.copy()
        self._act = np.zeros(self._na)
        self._ctrl = np.zeros(self._nu)
        self._qfrc = np.zeros(self._nv)
        self._last: Measurement | None = None
        self._last_qvel = np.zeros(self._nv)
        self._ticks_since_update = 0
        self._guard.reset()

    @property
    def adapter(self) -> NoiseAdapter | NativeNoiseAdapter | None:
        """The adaptive noise model; None with NoiseModel.FIXED."""
        return self._adapter

    # -- Estimator ------------------------------------------------------------------------------

    @property
    def config(self) -> EstimatorConfig:
        return self._config

    @property
    def state_dimension(self) -> int:
        return self._n

    @property
    def state_size(self) -> int:
        return self._size

    @property
    def nsigma(self) -> int:
        return int(self._points.num_sigmas())

    @property
    def covariance_repairs(self) -> int:
        """How often an indefinite covariance had to be repaired, since construction."""
        return self._sqrt.repairs + self._kf.repairs

    def forget(self) -> None:
        """Back to the uninitialised filter: the next initialise() keeps nothing of this one (a
        re-initialisation keeps a DRIVEN filter's force)."""
        self._initialised = False

    def initialise(self, m: Measurement) -> None:
        m = check_measurement(m, self._model, self._config.measured)
        self._act = np.zeros(self._na)
        self._ctrl = m.ctrl.copy() if m.ctrl is not None else np.zeros(self._nu)
        self._qfrc = np.zeros(self._nv)
        if self._adapter is not None:
            self._adapter.reset()
        self._guard.reset()
        self._start_from(m, qvel_fallback=np.zeros(self._nv))
        if self._scenario == Scenario.EXTERNAL and m.qacc is not None:
            self._qfrc = self._inverse(m.qpos, self._last_qvel, m.qacc)
        if self._foresight is not None:
            self._foresight.reset()
            self._foresight.observe(m, x=self._kf.x, act=self._act)
        self._initialised = True

    def predict(self, *, ctrl: np.ndarray | None) -> Estimate:
        reinitialised = self._predict(ctrl, "predict")
        estimate = self._estimate(reinitialised=reinitialised)
        if self._foresight is not None and not reinitialised:
            estimate = self._combined(estimate)
        return estimate

    def advance(self, *, ctrl: np.ndarray | None) -> None:
        self._predict(ctrl, "advance")

    def _predict(self, ctrl: np.ndarray | None, what: str) -> bool:
        """One tick of prediction; whether the divergence guard restarted the filter."""
        self._require_initialised(what)
        if self._controlled and ctrl is not None:
            self._ctrl = check_vector(ctrl, self._nu, "ctrl").copy()
        if self._adapter is not None:
            # The first tick after a frame is an ordinary tick; the next ones are a gap's.
            self._kf.Q = self._adapter.Q if self._ticks_since_update == 0 else self._adapter.Q_gap
        if self._foresight is not None:
            self._foresight.advance()
        self._kf.set_inputs(act=self._act, ctrl=self._ctrl, qfrc=self._qfrc)
        self._kf.predict()
        self._act = self._clip_act(self._kf.propagated_act)
        self._ticks_since_update += 1
        reinitialised = False
        finite = self._tidy_covariance()
        if self._guard.diverged(finite=finite, largest_variance=self._largest_variance()):
            # No new measurement to start from: the last one is the best that is known.
            if self._last is None:
                raise RuntimeError("unreachable: an initialised filter has a last measurement")
            self._reinitialise(self._last)
            reinitialised = True
        return reinitialised

    def update(self, m: Measurement) -> Estimate:
        self._require_initialised("update")
        m = check_measurement(m, self._model, self._config.measured)
        z = np.concatenate(
            [m.qpos] + [getattr(m, c) for c in (Channel.QVEL, Channel.QACC) if self._measures(c)]
        )
        if self._adapter is not None:
            self._kf.R = self._adapter.R
        prior = self._gap_prior()
        # What the gap's answers were worth: the frame against the answer it ends (before the
        # correction changes the prior).
        gap_nis = self._answer_nis(z, None) if prior is not None and self._foresight is not None else None
        nis = self._correct(z)
        if prior is not None:
            self._observe_gap(gap_nis, nis)
        widened = prior is not None and self._guard.far_out(nis)
        if prior is not None and widened:
            nis = self._correct_widened(z, prior)
        finite = self._tidy_covariance()
        self._guard.count(nis)
        adapted, absorbed = self._adapt(nis, finite=finite)
        # Still finite after _adapt: it adds P0's finite diagonal block, and a sum that overflows
        # is a variance past the guard's limit, a restart either way.
        reinitialised = self._guard.restart_due(finite=finite, largest_variance=self._largest_variance())
        if reinitialised:
            self._restart(m)
        else:
            self._accept(m)
        if self._foresight is not None:
            self._foresight.observe(m, x=self._kf.x, act=self._act)
        if m.ctrl is not None:
            self._ctrl = m.ctrl.copy()  # held by predict(ctrl=None)
        return self._estimate(
            nis=nis, reinitialised=reinitialised, adapted=adapted, absorbed=absorbed or widened
        )

    def _gap_prior(self) -> tuple[np.ndarray, np.ndarray] | None:
        """A copy of the prior (x, P) when this frame ends a gap and the noise adapts, else None."""
        if self._adapter is None or self._ticks_since_update <= 1:
            return None
        return self._kf.x.copy(), self._kf.P.copy()

    def _observe_gap(self, gap_nis: float | None, nis: float | None) -> None:
        """The adaptive noise learns from the frame that ends a gap: its NIS against the gap's last
        answer (`gap_nis`, the combination's), or against the filter's prediction (`nis`)."""
        if self._adapter is None:
            return
        gap_nis = nis if self._foresight is None or gap_nis is None else gap_nis
        if gap_nis is not None:
            self._adapter.observe_gap(nis=gap_nis, m=self._z_tangent)

    def _correct_widened(self, z: np.ndarray, prior: tuple[np.ndarray, np.ndarray]) -> float | None:
        """The frame that ends a gap, past the divergence guard's NIS limit, used again against the
        prior widened as an absorption widens it: [q, qd] follow the frame, the force its evidence
        (docs/decisions/0022-widen-after-a-gap.md)."""
        x, P = prior
        k = self._order * self._nv
        P[:k, :k] += self._P0[:k, :k]
        self._kf.x, self._kf.P = x, P
        if not self._linear_force:
            self._kf.sigmas_f = self._points.sigma_points(x, P)  # what filterpy's update uses
        return self._correct(z)

    def _tidy_covariance(self) -> bool:
        """P symmetrised, and repaired when indefinite, while the filter is finite; whether it is
        (the tidying keeps a finite P finite: one check serves the whole step)."""
        return self._kf.tidy()

    def _adapt(self, nis: float | None, *, finite: bool) -> tuple[bool, bool]:
        """The adaptive noise learns from this update (finite: x and P are): whether it adapted, and
        whether its NIS window asked for an absorption (which widens P on [q, qd] while the guard
        allows)."""
        if self._adapter is None or not finite or nis is None:
            return False, False
        kf = self._kf
        verdict = self._adapter.observe(
            innovation=np.asarray(kf.y),
            consecutive=self._ticks_since_update == 1,
            gain=np.asarray(kf.K),
            nis=nis,
            noise_share=float(np.diagonal(kf.SI) @ np.diagonal(kf.R)) / self._z_tangent,
        )
        if not verdict.absorb:
            if self._adapter.window_full:
                self._guard.settle()
            return verdict.adapted, False
        if self._guard.absorb():
            # The model is wrong, not the noise: forget what P says was known, and let Q follow
            # the corrections the filter has to make. Only q and qd widen: a force spread as wide
            # as P0 throws the sigma points of a pendulum over (measured, docs/experiments.md).
            k = self._order * self._nv
            P = np.array(kf.P)
            P[:k, :k] += self._P0[:k, :k]
            kf.P = P
            self._adapter.absorbed()
        return verdict.adapted, True

    def _restart(self, m: Measurement) -> None:
        """The guard's restart after an update: from this frame, the noise and the guard as new."""
        self._reinitialise(m)
        if self._adapter is not None:
            self._adapter.reset()
        self._guard.reset()

    def _accept(self, m: Measurement) -> None:
        """The frame becomes the last one: the force it restores (EXTERNAL), and no gap since."""
        qvel = m.qvel if m.qvel is not None else self._kf.x[self._nq : self._nq + self._nv]
        if self._scenario == Scenario.EXTERNAL:
            self._qfrc = self._restored_force(m, qvel)
        self._last = m
        self._last_qvel = np.array(qvel)
        self._ticks_since_update = 0

    def _correct(self, z: np.ndarray) -> float | None:
        """The filter's update with measurement z; its NIS, None when not finite."""
        try:
            self._kf.update(z)
            nis = self._kf.nis
        except np.linalg.LinAlgError:
            # An innovation covariance that cannot be inverted: nothing of this update is usable.
            self._kf.x = np.full(self._size, np.nan)
            nis = float("nan")
        return nis if np.isfinite(nis) else None

    def extrapolate(self, seconds: float) -> Estimate:
        self._require_initialised("extrapolate")
        nstep = self._steps_in(seconds)
        if nstep == 0:
            return self._estimate()
        Q = self._noise_over(nstep)
        self._process.set_inputs(act=self._act, ctrl=self._ctrl, qfrc=self._qfrc)
        linear = self._kf.inner if isinstance(self._kf, PythonCore) else None
        if isinstance(linear, LinearForceUKF):
            sigmas_f = linear.sigmas_f
            x, P = linear.prior(linear.x, linear.P, nstep=nstep)
            linear.sigmas_f = sigmas_f
            P = P + Q
        else:
            sigmas = self._points.sigma_points(self._kf.x, self._kf.P)
            propagated = self._process.propagate(sigmas, nstep=nstep)
            x, P = self._ut(
                propagated, self._points.Wm, self._points.Wc, Q, self._kf.x_mean, self._kf.residual_x
            )
        P = _symmetric(P)
        act = self._clip_act(self._process.propagated_act)
        return self._make_estimate(x, P, act=act)

    def glance(self, seconds: float) -> Estimate:
        """The mean alone carried through the physics (one point for the sigma set's 2n + 1) and P
        grown by the process noise of the span: no unscented transform, no forecast combination.
        For a few ticks, while a late frame may still come, the mean is what the sigma set's would
        be to second order."""
        self._require_initialised("glance")
        nstep = self._steps_in(seconds)
        if nstep == 0:
            return self._estimate()
        nq, nv = self._nq, self._nv
        x = self._kf.x
        force = x[nq + nv : nq + 2 * nv] if self._driven else None
        rate = x[nq + 2 * nv : nq + 3 * nv] if self._fblocks == 2 else None
        out = self._propagator(
            x[None, :nq],
            x[None, nq : nq + nv],
            act=self._act,
            ctrl=self._ctrl,
            qfrc=self._qfrc if force is None else force[None, :],
            qfrc_rate=None if rate is None else rate[None, :],
            nstep=nstep,
        )
        ahead = np.array(x, dtype=np.float64)
        ahead[:nq], ahead[nq : nq + nv] = out.qpos[0], out.qvel[0]
        if self._controlled and out.qacc is not None:
            ahead[nq + nv :] = out.qacc[0]
        if rate is not None:
            ahead[nq + nv : nq + 2 * nv] += nstep * float(self._model.opt.timestep) * rate
        act = self._clip_act(out.act[0]) if self._na else self._act
        return self._make_estimate(ahead, _symmetric(self._kf.P + self._noise_over(nstep)), act=act)

    def _steps_in(self, seconds: float) -> int:
        if (
            isinstance(seconds, bool)
            or not isinstance(seconds, (int, float))
            or not 0.0 <= seconds < float("inf")
        ):
            raise InvalidArgument(f"seconds must be finite and >= 0, got {seconds!r}")
        return round(seconds / float(self._model.opt.timestep))

    def _noise_over(self, nstep: int) -> np.ndarray:
        """The process noise of nstep physics steps (the adapter's factors applied)."""
        Q = self._extrapolation_Q.get(nstep)
        if Q is None:
            Q = self._noise.process_noise(nstep * float(self._model.opt.timestep))
            if len(self._extrapolation_Q) >= _SPANS_KEPT:
                self._extrapolation_Q = {self._config.steps_per_tick: self._Q}
            self._extrapolation_Q[nstep] = Q
        return self._adapter.q_for(Q) if self._adapter is not None else Q

    def snapshot(self) -> FilterSnapshot:
        kf = self._kf
        return FilterSnapshot(
            owner=id(self),
            initialised=self._initialised,
            x=read_only(kf.x),
            P=read_only(kf.P),
            sigmas_f=read_only(kf.sigmas_f),
            act=read_only(self._act),
            ctrl=read_only(self._ctrl),
            qfrc=read_only(self._qfrc),
            last=self._last,  # immutable: check_measurement made it read-only
            last_qvel=read_only(self._last_qvel),
            ticks_since_update=self._ticks_since_update,
            guard=self._guard.state,
            adapter=self._adapter.snapshot() if self._adapter is not None else None,
            forecasts=self._foresight.snapshot() if self._foresight is not None else None,
        )

    def restore(self, snap: object) -> None:
        if not isinstance(snap, FilterSnapshot) or snap.owner != id(self):
            raise InvalidArgument(f"snap must be a snapshot of this estimator, got {type(snap).__name__}")
        kf = self._kf
        kf.x, kf.P, kf.sigmas_f = snap.x.copy(), snap.P.copy(), snap.sigmas_f.copy()
        self._initialised = snap.initialised
        self._act, self._ctrl, self._qfrc = snap.act.copy(), snap.ctrl.copy(), snap.qfrc.copy()
        self._last = snap.last
        self._last_qvel = snap.last_qvel.copy()
        self._ticks_since_update = snap.ticks_since_update
        self._guard.restore(snap.guard)
        adapter, saved = self._adapter, snap.adapter
        # Each engine's adapter takes its own snapshots (two branches for the type checker).
        if isinstance(adapter, NativeNoiseAdapter) and isinstance(saved, AdapterState):  # noqa: SIM114
            adapter.restore(saved)
        elif isinstance(adapter, NoiseAdapter) and isinstance(saved, NoiseSnapshot):
            adapter.restore(saved)
        if self._foresight is not None and snap.forecasts is not None:
            self._foresight.restore(snap.forecasts)

    # -- internals ------------------------------------------------------------------------------

    def _measures(self, channel: Channel) -> bool:
        if channel == Channel.QACC:
            return self._controlled and Channel.QACC in self._config.measured
        return channel in self._config.measured

    def _hx(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(x[self._z_index])

    def _require_initialised(self, what: str) -> None:
        if not self._initialised:
            raise FailedPrecondition(
                f"{what} needs an initialised estimator: call initialise() with the first frame"
            )

    def _largest_variance(self) -> float:
        return self._kf.largest_variance()

    def _combined(self, estimate: Estimate) -> Estimate:
        """Over a gap: the forecast combination's answer (estimation/foresight.py), when its weights
        are learnt."""
        if self._foresight is None or self._ticks_since_update == 0:
            return estimate
        answer = self._forecast()
        if answer is None:
            return estimate
        # The unknown force answered is the one under which the physics follows the forecast: the
        # inverse dynamics of its q, qd and qdd (so torques over a gap agree with the motion).
        force = self._inverse(answer.qpos, answer.qvel, answer.qacc)
        return self._foresight.combined(estimate, answer, force=force)

    def _forecast(self, *, ended: bool = False) -> CombinedForecast | None:
        """The combination's answer now (ended: the gap's last), net of the frames' noise."""
        if self._foresight is None:
            return None
        r = self._adapter.r_diagonal if self._adapter is not None else None
        return self._foresight.answer(r_diagonal=r, measures_qvel=self._measures(Channel.QVEL), ended=ended)

    def _answer_nis(self, z: np.ndarray, nis: float | None) -> float | None:
        """The NIS of the frame z that ends a gap against the gap's last answer, or `nis` where the
        filter answered (Foresight.gap_nis)."""
        assert self._foresight is not None
        # The gap's last answer: mu learns what the answers given were worth (past the scored
        # horizon they were the filter's, and `_forecast` says None).
        answer = self._forecast(ended=True) if self._x_manifold is None else None
        return self._foresight.gap_nis(z, P=self._kf.P, R=self._kf.R, answer=answer, nis=nis)

    def _activation_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        low = np.full(self._na, -np.inf)
        high = np.full(self._na, np.inf)
        m = self._model
        for i in range(m.nu):
            adr = int(m.actuator_actadr[i])
            if adr < 0:
                continue
            num = int(m.actuator_actnum[i])
            limited = bool(m.actuator_actlimited[i]) or int(m.actuator_dyntype[i]) == int(
                mujoco.mjtDyn.mjDYN_MUSCLE
            )
            if limited:
                # Muscles clamp their activation to [0, 1] in MuJoCo whatever actlimited says.
                bounds = m.actuator_actrange[i] if m.actuator_actlimited[i] else (0.0, 1.0)
                low[adr : adr + num], high[adr : adr + num] = bounds
        return low, high

    def _clip_act(self, act: np.ndarray) -> np.ndarray:
        # Negative Merwe weights can put a weighted mean of activations outside their range.
        return np.clip(act, *self._act_bounds) if self._na else act

    def _start_from(self, m: Measurement, *, qvel_fallback: np.ndarray) -> None:
        """x from the measurement (unmeasured qvel: qvel_fallback), P = P0."""
        nq, nv = self._nq, self._nv
        qvel = m.qvel if m.qvel is not None else qvel_fallback
        x = np.empty(self._size)
        x[:nq] = m.qpos
        x[nq : nq + nv] = qvel
        if self._controlled:
            x[nq + nv :] = m.qacc if m.qacc is not None else self._forward(m.qpos, qvel, self._act)
        if self._driven:
            # The force that would give the frame's qacc (none measured: hold the body still);
            # a re-initialisation keeps the force it had, when that is still finite.
            previous = self._kf.x[nq + nv :] if self._initialised else None
            if previous is not None and np.all(np.isfinite(previous)):
                x[nq + nv :] = previous
            else:
                qacc = m.qacc if m.qacc is not None else np.zeros(nv)
                x[nq + nv :] = 0.0
                x[nq + nv : nq + 2 * nv] = self._inverse(m.qpos, qvel, qacc)
        self._kf.x = x
        self._kf.P = self._P0.copy()
        if self._linear_force:  # the points span [q, qd]
            k = 2 * self._nv
            self._kf.sigmas_f = self._points.sigma_points(
                self._kf.x[: self._nq + self._nv], self._kf.P[:k, :k]
            )
        else:
            self._kf.sigmas_f = self._points.sigma_points(self._kf.x, self._kf.P)
        self._last = m
        self._last_qvel = np.array(qvel)
        self._ticks_since_update = 0
        self._guard.start()

    def _reinitialise(self, m: Measurement) -> None:
        """The divergence guard: back to the measurement, with what is still finite of the rest."""
        qvel = self._kf.x[self._nq : self._nq + self._nv]
        fallback = qvel.copy() if np.all(np.isfinite(qvel)) else np.zeros(self._nv)
        for name in ("_act", "_ctrl", "_qfrc"):
            value = getattr(self, name)
            if not np.all(np.isfinite(value)):
                setattr(self, name, np.zeros_like(value))
        self._start_from(m, qvel_fallback=fallback)

    def _restored_force(self, m: Measurement, qvel: np.ndarray) -> np.ndarray:
        """EXTERNAL: the generalized force that produced the frame's motion (mj_inverse)."""
        if m.qacc is not None:
            qacc = m.qacc
        elif self._ticks_since_update > 0:
            qacc = (qvel - self._last_qvel) / (self._ticks_since_update * self._config.dt)
        else:
            return self._qfrc  # a second frame for the same tick: nothing new to difference
        force = self._inverse(m.qpos, qvel, qacc)
        return force if np.all(np.isfinite(force)) else self._qfrc

    def _inverse(self, qpos: np.ndarray, qvel: np.ndarray, qacc: np.ndarray) -> np.ndarray:
        d = self._data
        d.qpos[:], d.qvel[:], d.qacc[:], d.act[:] = qpos, qvel, qacc, self._act
        mujoco.mj_inverse(self._model, d)
        return np.array(d.qfrc_inverse)

    def _forward(
        self, qpos: np.ndarray, qvel: np.ndarray, act: np.ndarray, *, force: np.ndarray | None = None
    ) -> np.ndarray:
        """qacc at a state under the scenario's inputs (warm start is off: no hidden state);
        DRIVEN: under `force`, the estimated unknown force."""
        ctrl = self._ctrl if self._controlled else self._no_ctrl
        if force is None:
            force = self._qfrc if self._scenario == Scenario.EXTERNAL else self._no_force
        return self._kf.forward(qpos, qvel, act=act, ctrl=ctrl, qfrc=force)

    def _estimate(
        self,
        *,
        nis: float | None = None,
        reinitialised: bool = False,
        adapted: bool = False,
        absorbed: bool = False,
    ) -> Estimate:
        return self._make_estimate(
            self._kf.x,
            self._kf.P,
            act=self._act,
            nis=nis,
            reinitialised=reinitialised,
            adapted=adapted,
            absorbed=absorbed,
        )

    def _make_estimate(
        self,
        x: np.ndarray,
        P: np.ndarray,
        *,
        act: np.ndarray,
        nis: float | None = None,
        reinitialised: bool = False,
        adapted: bool = False,
        absorbed: bool = False,
    ) -> Estimate:
        nq, nv = self._nq, self._nv
        state = read_only(x)
        qpos, qvel = state[:nq], state[nq : nq + nv]  # views of a read-only copy are read-only
        if self._controlled:
            qacc = state[nq + nv :]
        elif np.isfinite(state).all():
            force = state[nq + nv : nq + 2 * nv] if self._driven else None
            qacc = read_only(self._forward(qpos, qvel, act, force=force))
        else:
            qacc = read_only(np.full(nv, np.nan))
        return Estimate(
            qpos=qpos,
            qvel=qvel,
            qacc=qacc,
            state=state,
            covariance=read_only(P),
            nis=nis,
            reinitialised=reinitialised,
            adapted=adapted,
            absorbed=absorbed,
            scenario=self._scenario.value,
        )


def _symmetric(P: np.ndarray) -> np.ndarray:
    return np.asarray(0.5 * (P + P.T))
