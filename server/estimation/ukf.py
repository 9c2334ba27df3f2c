"""jitdyn's unscented Kalman filter, built whole from an `EstimatorConfig`, with MuJoCo as the
process model. This module runs a tick through its steps, each in one place:

| step | both engines | Python core (PythonCore) | native core (native/ukf.cc) |
|---|---|---|---|
| the filter's pieces | estimation/parts.py | | |
| sigma points | | estimation/sigma.py | Ukf::SigmaPoints |
| propagation | | estimation/process.py, propagate.py | Ukf::Propagate |
| unscented transform | | estimation/fast.py, batched.py | Ukf::Predict |
| update | core.py correct | estimation/fast.py, batched.py | Ukf::Update |
| tidy, repair | | PythonCore.tidy | Ukf::Tidy |
| adaptive noise | estimation/adaptive_steps.py | estimation/adaptive.py | native/adaptive.cc |
| guard, restarts | estimation/guard.py, guard_steps.py | | |
| gap answers | estimation/gap.py, foresight.py | estimation/forecast.py, matching.py, prior.py | native/forecast.cc, matching.cc, prior.cc |
| estimate, dynamics | estimation/answer.py | PythonCore.forward | Ukf::Forward |
| extrapolate, glance | estimation/lookahead.py | | |
| snapshots (timewarp) | estimation/snapshot.py | | |

On the native engine a tick's steps on the native side run in one call (native/tick.py: predict
with its noise, clip and tidy; on a frame on time also the update, the adaptive noise's
observation and the estimate's qacc), the rest of the table in Python
(docs/decisions/0212-one-native-call-a-tick.md).

The engines differ by their FilterCore (estimation/core.py): the compiled one, or the Python one
(filterpy's UnscentedKalmanFilter or its faster FastUKF, the sigma points propagated in one
batched call by estimation/process.py). Dead reckoning, the estimator without a filter, is
estimation/deadreckoning.py. Why it is split so: docs/decisions/0195-the-filter-split-by-its-steps.md.

    estimator = UnscentedFilter(model, config, pool=pool)
    estimator.initialise(Measurement(qpos=q0, qvel=v0))
    prior = estimator.predict(ctrl=None)                              # a tick without its frame
    posterior = estimator.step(ctrl=None, m=Measurement(qpos=q1, qvel=v1))  # a tick with its frame

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

import mujoco
import numpy as np

from jitdyn.errors import FailedPrecondition, InvalidArgument
from jitdyn.server.estimation import adaptive_steps, gap, guard_steps
from jitdyn.server.estimation.adaptive import NoiseAdapter
from jitdyn.server.estimation.config import EstimatorConfig, check_against_model
from jitdyn.server.estimation.core import FilterCore, correct
from jitdyn.server.estimation.interface import Estimate, Measurement, check_measurement, check_vector
from jitdyn.server.estimation.lookahead import Lookahead
from jitdyn.server.estimation.native.adaptive import NativeNoiseAdapter
from jitdyn.server.estimation.native.tick import NativeTick, Step
from jitdyn.server.estimation.parts import FilterParts, build_parts
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.estimation.snapshot import (
    FilterSnapshot,
    NativeSnapshot,
    bookkeeping,
    restore_bookkeeping,
    restore_snapshot,
    take_snapshot,
)
from jitdyn.vocabulary import Channel, EstimatorKind, Scenario

__all__ = ["FilterSnapshot", "NativeSnapshot", "UnscentedFilter"]


class UnscentedFilter:
    """The UKF estimator of one session (see the module docstring). Implements `Estimator`."""

    def __init__(self, model: mujoco.MjModel, config: EstimatorConfig, *, pool: WorkerPool) -> None:
        if config.estimator != EstimatorKind.UKF:
            raise InvalidArgument(
                f"config.estimator must be UKF for an UnscentedFilter, got {config.estimator}"
            )
        check_against_model(model, config)
        self._config = config
        self._parts = parts = build_parts(model, config, pool=pool)
        self._layout, self._state, self._guard = parts.layout, parts.state, parts.guard
        self._answers = parts.answers
        self._lookahead = Lookahead(parts)
        self._tick = NativeTick.of(parts)
        x = np.zeros(parts.layout.size)
        x[: parts.layout.nq] = parts.model.qpos0
        parts.kf.x = x
        parts.kf.P = parts.P0.copy()
        self._guard.reset()

    @property
    def parts(self) -> FilterParts:
        """The filter's pieces (estimation/parts.py), for benchmarks that time one step alone."""
        return self._parts

    @property
    def _kf(self) -> FilterCore:
        """The engine's core (estimation/core.py)."""
        return self._parts.kf

    @property
    def adapter(self) -> NoiseAdapter | NativeNoiseAdapter | None:
        """The adaptive noise model; None with NoiseModel.FIXED."""
        return self._parts.adapter

    # -- Estimator ------------------------------------------------------------------------------

    @property
    def config(self) -> EstimatorConfig:
        return self._config

    @property
    def state_dimension(self) -> int:
        return self._layout.n

    @property
    def state_size(self) -> int:
        return self._layout.size

    @property
    def nsigma(self) -> int:
        return int(self._parts.points.num_sigmas())

    @property
    def covariance_repairs(self) -> int:
        """How often an indefinite covariance had to be repaired, since construction."""
        return self._parts.sqrt.repairs + self._kf.repairs

    def forget(self) -> None:
        """Back to the uninitialised filter: the next initialise() keeps nothing of this one (a
        re-initialisation keeps a DRIVEN filter's force)."""
        self._state.initialised = False

    def initialise(self, m: Measurement) -> None:
        parts, state, layout = self._parts, self._state, self._layout
        m = check_measurement(m, parts.model, self._config.measured)
        state.act = np.zeros(layout.na)
        state.ctrl = m.ctrl.copy() if m.ctrl is not None else np.zeros(layout.nu)
        state.qfrc = np.zeros(layout.nv)
        if parts.adapter is not None:
            parts.adapter.reset()
        self._guard.reset()
        guard_steps.start_from(parts, m, qvel_fallback=np.zeros(layout.nv))
        if layout.scenario == Scenario.EXTERNAL and m.qacc is not None:
            state.qfrc = self._answers.inverse(m.qpos, state.last_qvel, m.qacc)
        if parts.foresight is not None:
            parts.foresight.reset()
            parts.foresight.observe(m, x=parts.kf.x, act=state.act)
        state.initialised = True

    def predict(self, *, ctrl: np.ndarray | None) -> Estimate:
        reinitialised = self._predict(ctrl, "predict")
        estimate = self._answers.estimate(reinitialised=reinitialised)
        if self._parts.foresight is not None and not reinitialised:
            estimate = gap.combined(self._parts, estimate)
        return estimate

    def advance(self, *, ctrl: np.ndarray | None) -> None:
        self._predict(ctrl, "advance")

    def _predict(self, ctrl: np.ndarray | None, what: str) -> bool:
        """One tick of prediction; whether the divergence guard restarted the filter."""
        self._require_initialised(what)
        parts, state, kf = self._parts, self._state, self._parts.kf
        if self._layout.controlled and ctrl is not None:
            state.ctrl = check_vector(ctrl, self._layout.nu, "ctrl").copy()
        if self._tick is not None:
            kf.set_inputs(act=state.act, ctrl=state.ctrl, qfrc=state.qfrc)
            prediction = self._tick.advance(gap=state.ticks_since_update != 0)
            state.act = prediction.act
            state.ticks_since_update += 1
            if not prediction.diverged:
                return False
        else:
            if parts.adapter is not None:
                # The first tick after a frame is an ordinary tick; the next ones are a gap's.
                kf.Q = parts.adapter.Q if state.ticks_since_update == 0 else parts.adapter.Q_gap
            if parts.foresight is not None:
                parts.foresight.advance()
            kf.set_inputs(act=state.act, ctrl=state.ctrl, qfrc=state.qfrc)
            kf.predict()
            state.act = self._answers.clip_act(kf.propagated_act)
            state.ticks_since_update += 1
            finite = kf.tidy()
            if not self._guard.diverged(finite=finite, largest_variance=kf.largest_variance()):
                return False
        # No new measurement to start from: the last one is the best that is known.
        if state.last is None:
            raise RuntimeError("unreachable: an initialised filter has a last measurement")
        guard_steps.reinitialise(parts, state.last)
        return True

    def step(self, *, ctrl: np.ndarray | None, m: Measurement) -> Estimate:
        """advance(ctrl) then update(m), in one native call where the native tick runs a frame on
        time (estimation/native/tick.py); the same numbers either way."""
        if self._tick is None or self._state.ticks_since_update != 0 or not self._state.initialised:
            self.advance(ctrl=ctrl)
            return self.update(m)
        parts, state, kf, layout = self._parts, self._state, self._parts.kf, self._layout
        if layout.controlled and ctrl is not None:
            state.ctrl = check_vector(ctrl, layout.nu, "ctrl").copy()
        m = check_measurement(m, parts.model, self._config.measured)
        kf.set_inputs(act=state.act, ctrl=state.ctrl, qfrc=state.qfrc)
        step = self._tick.step(self._z(m), quiet=self._guard.quiet(), qvel=m.qvel)
        state.act = step.act
        state.ticks_since_update += 1
        if not step.updated:
            # The prediction diverged: the guard's restart from the last frame, then the update.
            if state.last is None:
                raise RuntimeError("unreachable: an initialised filter has a last measurement")
            guard_steps.reinitialise(parts, state.last)
            return self.update(m)
        return self._stepped(m, step)

    def _stepped(self, m: Measurement, step: Step) -> Estimate:
        """update()'s steps after a native tick's update: the guard, its restart, the frame kept."""
        parts, state, kf = self._parts, self._state, self._parts.kf
        self._guard.count(step.nis)
        adapted = absorbed = False
        largest = step.largest_variance
        if step.observed:
            adapted, absorbed = adaptive_steps.verdict_taken(parts, adapted=step.adapted, absorb=step.absorb)
            if absorbed:
                largest = kf.largest_variance()  # P widened
        reinitialised = self._guard.restart_due(finite=step.finite, largest_variance=largest)
        if reinitialised:
            guard_steps.restart(parts, m)
        else:
            self._accept(m)
        if reinitialised and step.observed_frame:
            raise RuntimeError("unreachable: the native tick observed a posterior the guard restarted")
        x = kf.x if reinitialised else step.x
        if parts.foresight is not None and not step.observed_frame:
            parts.foresight.observe(m, x=x, act=state.act)
        if m.ctrl is not None:
            state.ctrl = m.ctrl.copy()  # held by predict(ctrl=None)
        if reinitialised or absorbed:
            return self._answers.estimate(
                nis=step.nis, reinitialised=reinitialised, adapted=adapted, absorbed=absorbed
            )
        return self._answers.make(x, step.P, act=state.act, nis=step.nis, adapted=adapted, qacc=step.qacc)

    def _z(self, m: Measurement) -> np.ndarray:
        """The measurement vector of a checked frame: qpos, then the measured qvel and qacc."""
        layout = self._layout
        return np.concatenate(
            [m.qpos] + [getattr(m, c) for c in (Channel.QVEL, Channel.QACC) if layout.measures(c)]
        )

    def update(self, m: Measurement) -> Estimate:
        self._require_initialised("update")
        parts, state, kf, layout = self._parts, self._state, self._parts.kf, self._layout
        m = check_measurement(m, parts.model, self._config.measured)
        z = self._z(m)
        if parts.adapter is not None:
            kf.R = parts.adapter.R
        prior = adaptive_steps.gap_prior(parts)
        # What the gap's answers were worth: the frame against the answer it ends (before the
        # correction changes the prior).
        ends_scored_gap = prior is not None and parts.foresight is not None
        gap_nis = gap.answer_nis(parts, z, None) if ends_scored_gap else None
        nis = correct(kf, z, size=layout.size)
        if prior is not None:
            adaptive_steps.observe_gap(parts, gap_nis, nis)
        widened = prior is not None and self._guard.far_out(nis)
        if prior is not None and widened:
            nis = adaptive_steps.correct_widened(parts, z, prior)
        finite = kf.tidy()
        self._guard.count(nis)
        adapted, absorbed = adaptive_steps.adapt(parts, nis, finite=finite)
        # Still finite after adapt: it adds P0's finite diagonal block, and a sum that overflows
        # is a variance past the guard's limit, a restart either way.
        reinitialised = self._guard.restart_due(finite=finite, largest_variance=kf.largest_variance())
        if reinitialised:
            guard_steps.restart(parts, m)
        else:
            self._accept(m)
        if parts.foresight is not None:
            parts.foresight.observe(m, x=kf.x, act=state.act)
        if m.ctrl is not None:
            state.ctrl = m.ctrl.copy()  # held by predict(ctrl=None)
        return self._answers.estimate(
            nis=nis, reinitialised=reinitialised, adapted=adapted, absorbed=absorbed or widened
        )

    def _accept(self, m: Measurement) -> None:
        """The frame becomes the last one: the force it restores (EXTERNAL), and no gap since."""
        layout, state = self._layout, self._state
        qvel = m.qvel if m.qvel is not None else self._kf.x[layout.nq : layout.nq + layout.nv]
        if layout.scenario == Scenario.EXTERNAL:
            state.qfrc = self._answers.restored_force(m, qvel)
        state.last = m
        state.last_qvel = np.array(qvel)
        state.ticks_since_update = 0

    def extrapolate(self, seconds: float) -> Estimate:
        self._require_initialised("extrapolate")
        return self._lookahead.extrapolate(seconds)

    def glance(self, seconds: float) -> Estimate:
        """The mean alone carried through the physics, P grown by the span's process noise
        (estimation/lookahead.py)."""
        self._require_initialised("glance")
        return self._lookahead.glance(seconds)

    def snapshot(self) -> FilterSnapshot | NativeSnapshot:
        parts = self._parts
        if self._tick is not None:
            return NativeSnapshot(
                owner=id(self), kept=bookkeeping(self._state, self._guard), native=self._tick.snapshot()
            )
        return take_snapshot(
            id(self),
            self._state,
            parts.kf,
            guard=self._guard,
            adapter=parts.adapter,
            foresight=parts.foresight,
        )

    def restore(self, snap: object) -> None:
        if not isinstance(snap, FilterSnapshot | NativeSnapshot) or snap.owner != id(self):
            raise InvalidArgument(f"snap must be a snapshot of this estimator, got {type(snap).__name__}")
        parts = self._parts
        if isinstance(snap, NativeSnapshot):
            if self._tick is None:
                raise RuntimeError("unreachable: only a filter with a native tick takes NativeSnapshots")
            self._tick.restore(snap.native)
            restore_bookkeeping(snap.kept, self._state, self._guard)
            return
        if self._tick is not None:
            raise RuntimeError("unreachable: a filter with a native tick takes NativeSnapshots")
        restore_snapshot(
            snap, self._state, parts.kf, guard=self._guard, adapter=parts.adapter, foresight=parts.foresight
        )

    def _require_initialised(self, what: str) -> None:
        if not self._state.initialised:
            raise FailedPrecondition(
                f"{what} needs an initialised estimator: call initialise() with the first frame"
            )
