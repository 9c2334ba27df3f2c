"""The linearised filter: an EKF of the UKF's own state ([q, qd], and the unknown force f in
DRIVEN), noise (Q, P0, R) and process model (estimation/propagate.py), whose covariance is carried
by the tick's Jacobian, finite-differenced by MuJoCo's mjd_transitionFD as MuJoCo MPC's Kalman
estimator does; the UKF's own divergence guard and wrong_model restart (estimation/guard.py).
Why and where: docs/decisions/0210-the-linearised-filter-as-a-candidate.md.

    estimator = LinearisedFilter(model, config)     # config.estimator EKF; PASSIVE, EXTERNAL, DRIVEN
    estimator.initialise(Measurement(qpos=q0, qvel=v0))
    estimator.advance(ctrl=None)
    posterior = estimator.update(Measurement(qpos=q1, qvel=v1))

A tick (`PythonTick.predict`, and native/linearised.cc, held to it): the mean by the process
model's steps over the tick; at each step the Jacobian of [q, qd] by mjd_transitionFD (forward
differences; activations are inputs, as the UKF carries them: their rows and columns are dropped)
and, in DRIVEN, the force's columns by forward differences of the step (the force is held over the
tick); the tick's Jacobian A the product of the steps'; P = A P A' + Q. The update measures qpos
and qvel (H = [I 0]) with Joseph's form. States with ball or free joints are on the UKF's manifold:
mjd_transitionFD's columns and rows are tangent directions, as estimation/manifold.py's are.

The process model takes one implicitfast step of up to MAX_STEP seconds where the tick spans more
than one of the model's steps (`coarsening`): one linearisation a tick on myolegs_osl at 100 Hz.
EXTERNAL restores the force that acted from each frame by mj_inverse and holds it, as the UKF
does. Not run: CONTROLLED (its [q, qd, qdd] state), PASSIVE's wrong_model DRIVEN (the switch
to a DRIVEN filter is the UKF's), DRIVEN's INTEGRATED_RANDOM_WALK force, adaptive noise and the
forecast combination: a config that asks for one of them is refused (InvalidArgument).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import Final, Protocol

import mujoco
import numpy as np

from jitdyn.errors import FailedPrecondition, InvalidArgument
from jitdyn.server.estimation.config import Engine, EstimatorConfig, check_against_model
from jitdyn.server.estimation.guard import Guard, GuardState
from jitdyn.server.estimation.interface import (
    Estimate,
    Measurement,
    check_measurement,
    read_only,
)
from jitdyn.server.estimation.manifold import SplitManifold
from jitdyn.server.estimation.native.linearised import EPS, FORCE_EPS, NativeTick
from jitdyn.server.estimation.noise import UkfNoise
from jitdyn.server.estimation.propagate import process_model
from jitdyn.vocabulary import Channel, EstimatorKind, ForceModel, Forecast, NoiseModel, Scenario, WrongModel

__all__ = [
    "EPS",
    "FORCE_EPS",
    "MAX_STEP",
    "LinearisedFilter",
    "PythonTick",
    "coarsening",
    "ekf_process_model",
    "linearised_model",
]

# The longest step of a coarsened process model (s): one step a tick up to 100 Hz.
MAX_STEP: Final = 0.01


def coarsening(model: mujoco.MjModel, steps_per_tick: int) -> int:
    """The model's steps each of the EKF's process model spans: the largest divisor of the tick's
    steps whose step is at most MAX_STEP (1: the model's own step)."""
    timestep = float(model.opt.timestep)
    longest = max(1, math.floor(MAX_STEP / timestep + 1e-9))
    return max(c for c in range(1, min(longest, steps_per_tick) + 1) if steps_per_tick % c == 0)


def ekf_process_model(model: mujoco.MjModel, scenario: Scenario, coarsen: int) -> mujoco.MjModel:
    """The UKF's process model at `coarsen` of the model's steps a step, implicitfast when
    coarsened (the model's own integrator when not)."""
    private = process_model(model, scenario=scenario)
    private.opt.timestep = coarsen * float(model.opt.timestep)
    if coarsen != 1:
        private.opt.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    return private


def linearised_model(process: mujoco.MjModel) -> mujoco.MjModel:
    """What mjd_transitionFD linearises: the process model, but semi-implicit Euler for RK4 (which
    it refuses)."""
    if process.opt.integrator != mujoco.mjtIntegrator.mjINT_RK4:
        return process
    euler = copy.deepcopy(process)
    euler.opt.integrator = mujoco.mjtIntegrator.mjINT_EULER
    return euler


class TickCore(Protocol):
    """One engine of the filter's numeric work: a tick's prediction and an update."""

    def predict(
        self, x: np.ndarray, P: np.ndarray, act: np.ndarray, qfrc: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...

    def update(self, x: np.ndarray, P: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]: ...


class PythonTick:
    """The reference engine (module docstring), on its own mjData of `model`, the EKF's process
    model; `linearised` (`linearised_model`'s) is what mjd_transitionFD differentiates. Q (n, n),
    R (2 nv, 2 nv); nstep: the process model's steps a tick."""

    def __init__(
        self,
        model: mujoco.MjModel,
        *,
        linearised: mujoco.MjModel,
        driven: bool,
        nstep: int,
        Q: np.ndarray,
        R: np.ndarray,
    ) -> None:
        self.model, self.data = model, mujoco.MjData(model)
        self.linearised = linearised
        self.nq, self.nv, self.na = int(model.nq), int(model.nv), int(model.na)
        self.driven, self.nstep = driven, nstep
        self.n = (3 if driven else 2) * self.nv
        self.Q, self.R = Q, R
        self.manifold = SplitManifold(model, rest=self.n - self.nv)
        self._jacobian = np.zeros((2 * self.nv + self.na,) * 2)

    def _set(self, qpos: np.ndarray, qvel: np.ndarray, act: np.ndarray, qfrc: np.ndarray) -> None:
        d = self.data
        d.time = 0.0
        d.qpos[:], d.qvel[:], d.act[:], d.qfrc_applied[:] = qpos, qvel, act, qfrc

    def _tangent(
        self, qpos: np.ndarray, qvel: np.ndarray, qpos0: np.ndarray, qvel0: np.ndarray
    ) -> np.ndarray:
        """[qpos ⊖ qpos0, qvel - qvel0] (2 nv,)."""
        out = np.empty(2 * self.nv)
        mujoco.mj_differentiatePos(self.model, out[: self.nv], 1.0, qpos0, qpos)
        out[self.nv :] = qvel - qvel0
        return out

    def _force_columns(
        self,
        step: np.ndarray,
        start: tuple[np.ndarray, np.ndarray, np.ndarray],
        force: np.ndarray,
        nominal: tuple[np.ndarray, np.ndarray],
    ) -> None:
        """step[:2nv, 2nv:] (the force's columns): forward differences of the step from `start`
        (qpos, qvel, act) in each force component against the `nominal` step's (qpos, qvel). A
        force changes no position or velocity stage: those run once, and each column runs the
        acceleration stage and the integrator alone (RK4: the whole step)."""
        m, d, nv = self.model, self.data, self.nv
        qpos, qvel, act = start
        rk4 = m.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4
        self._set(qpos, qvel, act, force)
        mujoco.mj_forward(m, d)
        for i in range(nv):
            eps = FORCE_EPS * max(1.0, abs(float(force[i])))
            d.qfrc_applied[i] = force[i] + eps
            if rk4:
                mujoco.mj_step(m, d)
            else:
                mujoco.mj_forwardSkip(m, d, mujoco.mjtStage.mjSTAGE_VEL, 1)
                if m.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER:
                    mujoco.mj_Euler(m, d)
                else:
                    mujoco.mj_implicit(m, d)
            step[: 2 * nv, 2 * nv + i] = self._tangent(d.qpos, d.qvel, *nominal) / eps
            self._set(qpos, qvel, act, force)
            if rk4:
                mujoco.mj_forward(m, d)

    def predict(
        self, x: np.ndarray, P: np.ndarray, act: np.ndarray, qfrc: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x, P, act) a tick on: x (nq + n - nv,), P (n, n), act (na,); qfrc (nv,) the force held
        over the tick (PASSIVE: zeros; DRIVEN: unused, the state's f acts)."""
        m, d, nq, nv, n = self.model, self.data, self.nq, self.nv, self.n
        qpos, qvel = x[:nq].copy(), x[nq : nq + nv].copy()
        force = x[nq + nv :] if self.driven else qfrc
        A = np.eye(n)
        for _ in range(self.nstep):
            step = np.eye(n)
            self._set(qpos, qvel, act, force)
            mujoco.mjd_transitionFD(self.linearised, d, EPS, False, self._jacobian, None, None, None)
            step[: 2 * nv, : 2 * nv] = self._jacobian[: 2 * nv, : 2 * nv]
            self._set(qpos, qvel, act, force)
            mujoco.mj_step(m, d)
            qpos1, qvel1, act1 = d.qpos.copy(), d.qvel.copy(), d.act.copy()
            if self.driven:
                self._force_columns(step, (qpos, qvel, act), force, (qpos1, qvel1))
            A = step @ A
            qpos, qvel, act = qpos1, qvel1, act1
        out = x.copy()
        out[:nq], out[nq : nq + nv] = qpos, qvel
        prior = A @ P @ A.T + self.Q
        return out, 0.5 * (prior + prior.T), act

    def update(self, x: np.ndarray, P: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """(x, P, NIS) after the frame z = [qpos, qvel] (nq + nv,)."""
        nq, nv, k = self.nq, self.nv, 2 * self.nv
        S = P[:k, :k] + self.R
        gain = np.linalg.solve(S, P[:k, :]).T  # (n, 2 nv)
        y = self._tangent(z[:nq], z[nq:], x[:nq], x[nq : nq + nv])
        nis = float(y @ np.linalg.solve(S, y))
        joseph = np.eye(self.n)
        joseph[:, :k] -= gain
        posterior = joseph @ P @ joseph.T + gain @ self.R @ gain.T
        return self.manifold.add(x, gain @ y), posterior, nis


@dataclass(frozen=True)
class LinearisedSnapshot:
    """Everything a LinearisedFilter comes back to (read-only arrays)."""

    owner: int
    x: np.ndarray
    P: np.ndarray
    act: np.ndarray
    qfrc: np.ndarray
    last: Measurement | None
    last_qvel: np.ndarray
    since: int
    guard: GuardState
    restarts: int


class LinearisedFilter:
    """The EKF estimator of one session (module docstring). Implements `Estimator`.
    coarsen: the model's steps a process-model step (None: `coarsening`'s)."""

    def __init__(self, model: mujoco.MjModel, config: EstimatorConfig, *, coarsen: int | None = None) -> None:
        if config.estimator != EstimatorKind.EKF:
            raise InvalidArgument(
                f"config.estimator must be EKF for a LinearisedFilter, got {config.estimator}"
            )
        check_against_model(model, config)
        _check_supported(config)
        scenario = Scenario(config.scenario)
        coarsen = coarsening(model, config.steps_per_tick) if coarsen is None else coarsen
        if coarsen < 1 or config.steps_per_tick % coarsen:
            raise InvalidArgument(
                f"coarsen must divide the tick's {config.steps_per_tick} steps, got {coarsen}"
            )
        self._config, self._scenario = config, scenario
        self._model = model
        self._answers = process_model(model, scenario=scenario)  # qacc and restored forces
        self._data = mujoco.MjData(self._answers)
        self.nq, self.nv, self.na = int(model.nq), int(model.nv), int(model.na)
        self._driven = scenario == Scenario.DRIVEN
        noise = UkfNoise.of(model, self._data, config)
        self.n = noise.n
        self._noise = noise
        self.Q, self.P0 = noise.process_noise(config.dt), noise.initial_covariance()
        self.R = config.r * np.eye(2 * self.nv)
        tick_model = ekf_process_model(model, scenario, coarsen)
        nstep = config.steps_per_tick // coarsen
        self.core: TickCore
        engine = NativeTick if config.engine == Engine.NATIVE else PythonTick
        self.core = engine(
            tick_model,
            linearised=linearised_model(tick_model),
            driven=self._driven,
            nstep=nstep,
            Q=self.Q,
            R=self.R,
        )
        self._guard = Guard(
            m=2 * self.nv,
            restart=WrongModel(config.wrong_model) == WrongModel.RESTART,
            driven=self._driven,
        )
        self._x = np.zeros(self.nq + self.n - self.nv)
        self._x[: self.nq] = model.qpos0
        self._P = self.P0.copy()
        self._act, self._qfrc = np.zeros(self.na), np.zeros(self.nv)
        self._last: Measurement | None = None
        self._last_qvel, self._since = np.zeros(self.nv), 0
        self.restarts = 0  # the guard's restarts after an update, since construction

    # -- Estimator ------------------------------------------------------------------------------

    @property
    def config(self) -> EstimatorConfig:
        return self._config

    @property
    def state_dimension(self) -> int:
        return self.n

    @property
    def state_size(self) -> int:
        return self.nq + self.n - self.nv

    @property
    def qfrc(self) -> np.ndarray:
        """EXTERNAL: the restored force held over the ticks since the last frame (nv,)."""
        return read_only(self._qfrc)

    def initialise(self, m: Measurement) -> None:
        m = check_measurement(m, self._model, self._config.measured)
        self._act, self._qfrc = np.zeros(self.na), np.zeros(self.nv)
        if self._scenario == Scenario.EXTERNAL and m.qacc is not None:
            self._qfrc = self._inverse(m.qpos, _qvel(m), m.qacc)
        self._last = None
        self._guard.reset()
        self._start_from(m, keep_force=False)

    def predict(self, *, ctrl: np.ndarray | None) -> Estimate:
        return self._estimate(reinitialised=self._predict("predict"))

    def advance(self, *, ctrl: np.ndarray | None) -> None:
        self._predict("advance")

    def step(self, *, ctrl: np.ndarray | None, m: Measurement) -> Estimate:
        self.advance(ctrl=ctrl)
        return self.update(m)

    def update(self, m: Measurement) -> Estimate:
        self._require_initialised("update")
        m = check_measurement(m, self._model, self._config.measured)
        qvel = _qvel(m)
        x, P, nis = self.core.update(self._x, self._P, np.concatenate([m.qpos, qvel]))
        self._x, self._P = x, P
        finite = self._finite()
        shown = nis if math.isfinite(nis) else None
        self._guard.count(shown)
        if self._guard.restart_due(finite=finite, largest_variance=self._largest_variance()):
            self.restarts += 1
            self._reinitialise(m)
            self._guard.reset()
            return self._estimate(nis=shown, reinitialised=True)
        if self._scenario == Scenario.EXTERNAL:
            self._qfrc = self._restored_force(m, qvel)
        self._last, self._last_qvel, self._since = m, np.array(qvel), 0
        return self._estimate(nis=shown)

    def extrapolate(self, seconds: float) -> Estimate:
        """The mean carried through the UKF's process model at the model's steps, P grown by the
        process noise of the span (the estimate now for 0 s)."""
        self._require_initialised("extrapolate")
        if (
            isinstance(seconds, bool)
            or not isinstance(seconds, (int, float))
            or not 0.0 <= seconds < math.inf
        ):
            raise InvalidArgument(f"seconds must be finite and >= 0, got {seconds!r}")
        timestep = float(self._model.opt.timestep)
        nstep = round(seconds / timestep)
        if nstep == 0:
            return self._estimate()
        d, nq, nv = self._data, self.nq, self.nv
        d.time = 0.0
        d.qpos[:], d.qvel[:], d.act[:] = self._x[:nq], self._x[nq : nq + nv], self._act
        d.qfrc_applied[:] = self._force()
        mujoco.mj_step(self._answers, d, nstep)
        ahead = self._x.copy()
        ahead[:nq], ahead[nq : nq + nv] = d.qpos, d.qvel
        P = self._P + self._noise.process_noise(nstep * timestep)
        return self._make(ahead, 0.5 * (P + P.T), act=np.array(d.act))

    def glance(self, seconds: float) -> Estimate:
        return self.extrapolate(seconds)  # the mean alone already

    def snapshot(self) -> LinearisedSnapshot:
        return LinearisedSnapshot(
            owner=id(self),
            x=read_only(self._x),
            P=read_only(self._P),
            act=read_only(self._act),
            qfrc=read_only(self._qfrc),
            last=self._last,
            last_qvel=read_only(self._last_qvel),
            since=self._since,
            guard=self._guard.state,
            restarts=self.restarts,
        )

    def restore(self, snap: object) -> None:
        if not isinstance(snap, LinearisedSnapshot) or snap.owner != id(self):
            raise InvalidArgument(f"snap must be a snapshot of this estimator, got {type(snap).__name__}")
        self._x, self._P = np.array(snap.x), np.array(snap.P)
        self._act, self._qfrc = np.array(snap.act), np.array(snap.qfrc)
        self._last, self._last_qvel, self._since = snap.last, np.array(snap.last_qvel), snap.since
        self._guard.restore(snap.guard)
        self.restarts = snap.restarts

    # -- the steps ------------------------------------------------------------------------------

    def _predict(self, what: str) -> bool:
        """One tick; whether the divergence guard started the filter again from the last frame."""
        self._require_initialised(what)
        self._x, self._P, self._act = self.core.predict(self._x, self._P, self._act, self._force())
        self._since += 1
        if not self._guard.diverged(finite=self._finite(), largest_variance=self._largest_variance()):
            return False
        if self._last is None:
            raise RuntimeError("unreachable: an initialised filter has a last frame")
        self._reinitialise(self._last)
        return True

    def _reinitialise(self, m: Measurement) -> None:
        """Back to the frame, P = P0; what is not finite of the inputs back to zero."""
        if not np.all(np.isfinite(self._act)):
            self._act = np.zeros(self.na)
        if not np.all(np.isfinite(self._qfrc)):
            self._qfrc = np.zeros(self.nv)
        self._start_from(m, keep_force=True)

    def _start_from(self, m: Measurement, *, keep_force: bool) -> None:
        """x on the frame, P = P0 (estimation/guard_steps.py start_from); DRIVEN keeps its force
        when it is finite, else starts from none (not the UKF's force that holds the body still:
        docs/decisions/0210-the-linearised-filter-as-a-candidate.md)."""
        nq, nv = self.nq, self.nv
        qvel = _qvel(m)
        x = np.zeros(self.nq + self.n - nv)
        x[:nq], x[nq : nq + nv] = m.qpos, qvel
        if self._driven:
            previous = self._x[nq + nv :]
            if keep_force and np.all(np.isfinite(previous)):
                x[nq + nv :] = previous
        self._x, self._P = x, self.P0.copy()
        self._last, self._last_qvel, self._since = m, np.array(qvel), 0
        self._guard.start()

    def _force(self) -> np.ndarray:
        """The force the process model holds over a tick: EXTERNAL's restored one, else none
        (DRIVEN's is the state's)."""
        return self._qfrc if self._scenario == Scenario.EXTERNAL else np.zeros(self.nv)

    def _inverse(self, qpos: np.ndarray, qvel: np.ndarray, qacc: np.ndarray) -> np.ndarray:
        d = self._data
        d.qpos[:], d.qvel[:], d.qacc[:], d.act[:] = qpos, qvel, qacc, self._act
        mujoco.mj_inverse(self._answers, d)
        return np.array(d.qfrc_inverse)

    def _restored_force(self, m: Measurement, qvel: np.ndarray) -> np.ndarray:
        """EXTERNAL: the force that produced the frame's motion (answer.py restored_force's rule)."""
        if m.qacc is not None:
            qacc = m.qacc
        elif self._since > 0:
            qacc = (qvel - self._last_qvel) / (self._since * self._config.dt)
        else:
            return self._qfrc  # a second frame for the same tick: nothing new to difference
        force = self._inverse(m.qpos, qvel, qacc)
        return force if np.all(np.isfinite(force)) else self._qfrc

    def _finite(self) -> bool:
        return bool(np.all(np.isfinite(self._x)) and np.all(np.isfinite(self._P)))

    def _largest_variance(self) -> float:
        return float(self._P.diagonal().max())

    def _estimate(self, *, nis: float | None = None, reinitialised: bool = False) -> Estimate:
        return self._make(self._x, self._P, act=self._act, nis=nis, reinitialised=reinitialised)

    def _make(
        self,
        x: np.ndarray,
        P: np.ndarray,
        *,
        act: np.ndarray,
        nis: float | None = None,
        reinitialised: bool = False,
    ) -> Estimate:
        """The estimate of mean x and covariance P; qacc by mj_forward under the force that acts."""
        nq, nv = self.nq, self.nv
        state = read_only(x)
        qpos, qvel = state[:nq], state[nq : nq + nv]
        if np.isfinite(state).all():
            d = self._data
            d.qpos[:], d.qvel[:], d.act[:] = qpos, qvel, act
            d.qfrc_applied[:] = state[nq + nv :] if self._driven else self._force()
            mujoco.mj_forward(self._answers, d)
            qacc = read_only(d.qacc)
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
            scenario=self._scenario.value,
        )

    def _require_initialised(self, what: str) -> None:
        if self._last is None:
            raise FailedPrecondition(
                f"{what} needs an initialised estimator: call initialise() with the first frame"
            )


def _qvel(m: Measurement) -> np.ndarray:
    """A checked frame's qvel, which the filter measures (check_measurement requires it)."""
    if m.qvel is None:
        raise InvalidArgument("measurement.qvel must be set: the linearised filter measures qvel")
    return m.qvel


def _check_supported(config: EstimatorConfig) -> None:
    """What the linearised filter does not run, refused by name."""
    scenario = Scenario(config.scenario)
    refused = [
        (scenario == Scenario.CONTROLLED, f"scenario must be PASSIVE, EXTERNAL or DRIVEN, got {scenario}"),
        (
            WrongModel(config.wrong_model) == WrongModel.DRIVEN,
            "wrong_model must be KEEP or RESTART (PASSIVE's switch to DRIVEN is the UKF's), got DRIVEN",
        ),
        (
            scenario == Scenario.DRIVEN and ForceModel(config.force_model) != ForceModel.RANDOM_WALK,
            f"force_model must be RANDOM_WALK, got {config.force_model}",
        ),
        (
            NoiseModel(config.noise_model) != NoiseModel.FIXED,
            f"noise_model must be FIXED, got {config.noise_model}",
        ),
        (Forecast(config.forecast) != Forecast.FILTER, f"forecast must be FILTER, got {config.forecast}"),
        (Channel.QVEL not in config.measured, f"measured must include 'qvel', got {sorted(config.measured)}"),
    ]
    for bad, message in refused:
        if bad:
            raise InvalidArgument(f"the linearised filter (EKF) runs no such session: {message}")
