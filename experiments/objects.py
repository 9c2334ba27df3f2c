"""Simulated research objects: the ground truth of the thesis' experiments, run by MuJoCo on the
client side with the same model file the server uses::

    obj = make_object("pendulum_3", Scenario.CONTROLLED)
    truth = obj.reset(seed=0)                      # TrueState at t = 0
    ctrl = obj.control(truth.t, est_qpos, est_qvel)  # CONTROLLED: the law, applied to the filter's estimate
    truth = obj.step(ctrl)                         # one frame period later

PASSIVE objects take no control; EXTERNAL objects drive themselves with the same law applied to their
own true state (the subject's control, which the server never sees); CONTROLLED objects take the
control the caller computed from the filter's estimate, as the thesis' server-side controller did.
"""

from __future__ import annotations

import importlib.resources
import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import mujoco
import numpy as np

from jitdyn.vocabulary import Scenario

__all__ = [
    "OBJECTS",
    "Biped",
    "ModelSource",
    "MyoElbow",
    "MyoHand",
    "Pendulum",
    "ResearchObject",
    "Scenario",
    "TrueState",
    "UnstableSimulation",
    "load_source",
    "make_object",
    "qpos_limits",
]


@dataclass(frozen=True, slots=True)
class TrueState:
    """The true state of an object at the tick's time `t`.

    `ctrl` is the control applied over the interval that ended at `t` (zeros at t = 0): what a
    frame of tick t carries. `qacc` is MuJoCo's `data.qacc` after the tick's last physics step,
    the convention of the server's CONTROLLED state (and of any MuJoCo user): with RK4 it is the
    acceleration at the new state, with Euler and implicit integrators the one at the start of the
    last step (one timestep earlier). At t = 0 it is mj_forward's at the initial state.
    """

    t: float
    qpos: np.ndarray  # (nq,)
    qvel: np.ndarray  # (nv,)
    qacc: np.ndarray  # (nv,)
    ctrl: np.ndarray  # (nu,)


@dataclass(frozen=True)
class ModelSource:
    """Where a model comes from: its server-side name and the MJCF (plus assets) both sides compile."""

    name: str
    mjcf: str
    assets: Mapping[str, bytes] = field(default_factory=dict)
    builtin: bool = True  # the server knows it by name; otherwise the client registers it inline
    tags: tuple[str, ...] = ()  # registered with it: joint roles, the prior's subject left out

    def compile(self) -> mujoco.MjModel:
        return mujoco.MjModel.from_xml_string(self.mjcf, dict(self.assets))


_BUILTINS = ("pendulum_1", "pendulum_2", "pendulum_3", "biped")
_MYO = ("myoelbow", "myohand")


def load_source(name: str) -> ModelSource:
    """The model `name` ("pendulum_1".."pendulum_3", "biped", "myoelbow", "myohand") as the server has it."""
    if name in _BUILTINS:
        resource = importlib.resources.files("jitdyn.models") / f"{name}.xml"
        if not resource.is_file():
            raise FileNotFoundError(f"built-in model {name!r} not found: no {name}.xml in jitdyn.models")
        return ModelSource(name=name, mjcf=resource.read_text(encoding="utf-8"))
    if name in _MYO:
        # The client registers MyoSuite models inline from the same packed MJCF it simulates, so
        # truth and estimator compile byte-identical input.
        from jitdyn.client.myo import pack_myo_model

        mjcf, assets = pack_myo_model(name)
        return ModelSource(name=name, mjcf=mjcf, assets=assets, builtin=False)
    raise ValueError(f"model must be one of {_BUILTINS + _MYO}, got {name!r}")


_INSTABILITY_WARNINGS = tuple(
    int(w)
    for w in (
        mujoco.mjtWarning.mjWARN_BADCTRL,
        mujoco.mjtWarning.mjWARN_BADQPOS,
        mujoco.mjtWarning.mjWARN_BADQVEL,
        mujoco.mjtWarning.mjWARN_BADQACC,
    )
)


def qpos_limits(model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    """(nq,) lower and upper bounds of each qpos coordinate: the range of a limited hinge or slide
    joint, else -inf and inf (ball and free joints' coordinates, unlimited joints)."""
    lo = np.full(model.nq, -np.inf)
    hi = np.full(model.nq, np.inf)
    # jnt_type holds numpy ints, which never equal the mjtJoint enum: compare them as ints.
    scalar = np.isin(model.jnt_type, [int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)])
    bounded = scalar & model.jnt_limited.astype(bool)
    addresses = model.jnt_qposadr[bounded]
    lo[addresses], hi[addresses] = model.jnt_range[bounded].T
    return lo, hi


class UnstableSimulation(RuntimeError):
    """The truth left the finite numbers (a control law fed a diverged estimate, typically)."""

    def __init__(self, t: float, message: str) -> None:
        super().__init__(message)
        self.t = t


class ResearchObject(ABC):
    """A MuJoCo simulation of one model in one scenario, advanced one frame period at a time."""

    description: str = ""  # the motion, for reports

    def __init__(self, source: ModelSource, *, scenario: Scenario, dt: float, jitter: float) -> None:
        if scenario is Scenario.DRIVEN:
            raise ValueError(
                "DRIVEN is how a filter models an unknown force, not a motion: simulate the object "
                "PASSIVE, CONTROLLED or EXTERNAL"
            )
        self.source = source
        self.scenario = scenario
        self.model = source.compile()
        # A truth that blows up must say so, not be put back at qpos0 by MuJoCo's auto-reset.
        self.model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_AUTORESET)
        steps = dt / self.model.opt.timestep
        if dt <= 0 or abs(steps - round(steps)) > 1e-9 * max(1.0, steps):
            raise ValueError(
                f"dt must be a positive whole multiple of the model's timestep {self.model.opt.timestep}, got {dt}"
            )
        self.dt = dt
        self.steps_per_tick = round(steps)
        self.jitter = jitter
        self._data = mujoco.MjData(self.model)
        # The controller's own MjData: its inverse dynamics at an estimate must not touch the truth.
        self._scratch = mujoco.MjData(self.model)
        self._tick = 0
        self._last_ctrl = np.zeros(self.model.nu)
        self._reset_done = False

    @property
    def name(self) -> str:
        return self.source.name

    @property
    def nq(self) -> int:
        return int(self.model.nq)

    @property
    def nv(self) -> int:
        return int(self.model.nv)

    @property
    def nu(self) -> int:
        return int(self.model.nu)

    @property
    def t(self) -> float:
        return self._tick * self.dt

    def reset(self, seed: int) -> TrueState:
        """Back to the initial state, perturbed as the object says (`_initial_state`) from `seed`."""
        mujoco.mj_resetData(self.model, self._data)
        qpos, qvel = self._initial_state(np.random.default_rng(seed))
        self._data.qpos[:] = qpos
        self._data.qvel[:] = qvel
        self._tick = 0
        self._last_ctrl = np.zeros(self.nu)
        self._reset_done = True
        mujoco.mj_forward(self.model, self._data)
        return self._state()

    def step(self, ctrl: np.ndarray | None = None) -> TrueState:
        """Advances one frame period with `ctrl` held (CONTROLLED), or with the object's own control.

        PASSIVE: `ctrl` must be None (no actuation). EXTERNAL: must be None; the object applies
        `control` to its own true state. CONTROLLED: required, shape (nu,).
        """
        if not self._reset_done:
            raise RuntimeError("step before reset: call reset(seed) first")
        if self.scenario is Scenario.CONTROLLED:
            if ctrl is None:
                raise ValueError(
                    "ctrl is required in the CONTROLLED scenario (computed from the filter's estimate)"
                )
            u = np.asarray(ctrl, dtype=float)
            if u.shape != (self.nu,):
                raise ValueError(f"ctrl must have shape ({self.nu},), got {u.shape}")
        elif ctrl is not None:
            raise ValueError(
                f"ctrl must be None in the {self.scenario.value} scenario: the object drives itself"
            )
        elif self.scenario is Scenario.EXTERNAL:
            u = self.control(self.t, self._data.qpos.copy(), self._data.qvel.copy())
        else:
            u = np.zeros(self.nu)
        u = self._clip(u)
        if not np.all(np.isfinite(u)):
            raise UnstableSimulation(self.t, f"the control at t = {self.t:.4g} s is not finite: {u.tolist()}")
        self._data.ctrl[:] = u
        mujoco.mj_step(self.model, self._data, self.steps_per_tick)
        self._tick += 1
        self._last_ctrl = u
        d = self._data
        # MuJoCo flags NaN, inf or huge ctrl, qpos, qvel or qacc with a warning and carries on
        # (ctrl zeroed); for a ground truth that is the end of the run.
        flagged = sum(int(d.warning[w].number) for w in _INSTABILITY_WARNINGS)
        if flagged or not (np.all(np.isfinite(d.qpos)) and np.all(np.isfinite(d.qvel))):
            raise UnstableSimulation(self.t, f"the simulation became unstable by t = {self.t:.4g} s")
        return self._state()

    @abstractmethod
    def control(self, t: float, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        """The control law: the ctrl (nu,) to hold from time t, given a state (true or estimated)."""

    @abstractmethod
    def _initial_state(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """The initial (qpos, qvel): a fixed state, perturbed by `rng` as the object documents."""

    def _jittered(self, qpos: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """qpos + N(0, jitter^2) on every coordinate, kept inside the joint limits."""
        q = qpos + self.jitter * rng.standard_normal(self.nq)
        lo, hi = self._qpos_limits()
        return np.clip(q, lo, hi)

    def _state(self) -> TrueState:
        d = self._data
        return TrueState(
            t=self.t, qpos=d.qpos.copy(), qvel=d.qvel.copy(), qacc=d.qacc.copy(), ctrl=self._last_ctrl.copy()
        )

    def _clip(self, u: np.ndarray) -> np.ndarray:
        limited = self.model.actuator_ctrllimited.astype(bool)
        if not limited.any():
            return u
        lo, hi = self.model.actuator_ctrlrange[:, 0], self.model.actuator_ctrlrange[:, 1]
        return np.where(limited, np.clip(u, lo, hi), u)

    def _qpos_limits(self) -> tuple[np.ndarray, np.ndarray]:
        return qpos_limits(self.model)

    def _computed_torque(self, qpos: np.ndarray, qvel: np.ndarray, qacc_desired: np.ndarray) -> np.ndarray:
        """Generalized forces that give `qacc_desired` at (qpos, qvel): M qacc + bias, by mj_inverse."""
        s = self._scratch
        s.qpos[:] = qpos
        s.qvel[:] = qvel
        s.qacc[:] = qacc_desired
        mujoco.mj_inverse(self.model, s)
        return np.array(s.qfrc_inverse)


class Pendulum(ResearchObject):
    """An n-link pendulum (n = 1..3): gravity only (PASSIVE), or moved to the symmetrical position
    every second by a computed-torque law (CONTROLLED, EXTERNAL).

    PASSIVE starts at rest with the first hinge at +theta0 (the chain straight, tilted) and swings
    freely. The controlled scenarios start at rest at -theta0; the target of the first hinge is
    +theta0 during [0, 1) s, -theta0 during [1, 2) s, and so on, the other hinges 0 (the chain held
    straight): qacc* = wn^2 (q* - q) - 2 zeta wn qd, tau = M(q) qacc* + bias(q, qd).
    """

    def __init__(
        self,
        n: int,
        scenario: Scenario,
        *,
        dt: float = 0.05,
        theta0: float = math.pi / 4,
        wn: float = 5.0,
        zeta: float = 1.0,
        period: float = 1.0,
        jitter: float = 0.01,
        source: ModelSource | None = None,
    ) -> None:
        if n not in (1, 2, 3):
            raise ValueError(f"n must be 1, 2 or 3 links, got {n}")
        super().__init__(source or load_source(f"pendulum_{n}"), scenario=scenario, dt=dt, jitter=jitter)
        if self.nu != self.nv:
            raise ValueError(f"the pendulum needs one motor per hinge: nu must be {self.nv}, got {self.nu}")
        self.theta0, self.wn, self.zeta, self.period = theta0, wn, zeta, period
        if scenario is Scenario.PASSIVE:
            self.description = f"released at rest, first hinge at {theta0:.3f} rad, gravity only"
        else:
            self.description = (
                f"computed torque (wn {wn} rad/s, zeta {zeta}) to the symmetrical position every {period} s: "
                f"first hinge +/-{theta0:.3f} rad, the others 0"
            )

    def target(self, t: float) -> np.ndarray:
        """q* at time t: the first hinge at +theta0 in even periods, -theta0 in odd ones."""
        q = np.zeros(self.nq)
        # A tolerance so that t = k * period computed as k * dt lands in period k, not k - 1.
        q[0] = self.theta0 if math.floor(t / self.period + 1e-9) % 2 == 0 else -self.theta0
        return q

    def control(self, t: float, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        qacc = self.wn**2 * (self.target(t) - qpos) - 2.0 * self.zeta * self.wn * qvel
        # Motors have gear 1 on every hinge, so the torque is the control.
        return self._computed_torque(qpos, qvel, qacc)

    def _initial_state(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        q = np.zeros(self.nq)
        q[0] = self.theta0 if self.scenario is Scenario.PASSIVE else -self.theta0
        return self._jittered(q, rng), np.zeros(self.nv)


class _MyoObject(ResearchObject):
    """A MyoSuite model moved by muscle excitations the server never sees: EXTERNAL only."""

    model_name: str

    def __init__(self, scenario: Scenario, *, dt: float, jitter: float, source: ModelSource | None) -> None:
        if scenario is not Scenario.EXTERNAL:
            raise ValueError(f"{self.model_name} runs only in the EXTERNAL scenario, got {scenario.value}")
        super().__init__(source or load_source(self.model_name), scenario=scenario, dt=dt, jitter=jitter)

    def _actuators(self, names: Sequence[str]) -> list[int]:
        """The indices of the actuators called `names`, in that order."""
        actuators = [self.model.actuator(i).name for i in range(self.nu)]
        return [actuators.index(n) for n in names]


class MyoElbow(_MyoObject):
    """MyoSuite's elbow (1 joint, 6 muscles), raising and lowering the forearm gradually.

    The flexion target follows a raised cosine from `low` to `high` and back every `period`
    seconds; a PD law on the true state splits into flexor (BIClong, BICshort, BRA) and extensor
    (TRIlong, TRIlat, TRImed) excitations over a small co-contraction. Only EXTERNAL.
    """

    model_name = "myoelbow"
    _FLEXORS = ("BIClong", "BICshort", "BRA")
    _EXTENSORS = ("TRIlong", "TRIlat", "TRImed")

    def __init__(
        self,
        scenario: Scenario = Scenario.EXTERNAL,
        *,
        dt: float = 0.002,
        low: float = 0.3,
        high: float = 1.5,
        period: float = 4.0,
        kp: float = 5.0,
        kd: float = 0.5,
        tone: float = 0.05,
        jitter: float = 0.01,
        source: ModelSource | None = None,
    ) -> None:
        super().__init__(scenario, dt=dt, jitter=jitter, source=source)
        self._flexors = self._actuators(self._FLEXORS)
        self._extensors = self._actuators(self._EXTENSORS)
        self.low, self.high, self.period, self.kp, self.kd, self.tone = low, high, period, kp, kd, tone
        self.description = (
            f"elbow flexion {low}-{high} rad and back every {period} s (raised cosine), "
            f"PD (kp {kp}, kd {kd}) on flexor/extensor excitations"
        )

    def target(self, t: float) -> float:
        return self.low + (self.high - self.low) * 0.5 * (1.0 - math.cos(2.0 * math.pi * t / self.period))

    def control(self, t: float, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        u = self.kp * (self.target(t) - float(qpos[0])) - self.kd * float(qvel[0])
        ctrl = np.full(self.nu, self.tone)
        ctrl[self._flexors] += max(u, 0.0)
        ctrl[self._extensors] += max(-u, 0.0)
        return np.asarray(np.clip(ctrl, 0.0, 1.0))

    def _initial_state(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        return self._jittered(np.array([self.low]), rng), np.zeros(1)


class MyoHand(_MyoObject):
    """MyoSuite's hand (23 joints, 39 muscles), bending the fingers in turn.

    Open-loop excitations: finger f (index to little) flexes (FDS and FDP up to `flex`) during half
    of every `period`, each finger a quarter period after the previous one (a wave), with its
    extensor (EDC) up to `extend` while it is not flexing; every other muscle holds `tone`. Only
    EXTERNAL.
    """

    model_name = "myohand"

    def __init__(
        self,
        scenario: Scenario = Scenario.EXTERNAL,
        *,
        dt: float = 0.002,
        period: float = 2.0,
        flex: float = 0.5,
        extend: float = 0.6,
        tone: float = 0.02,
        jitter: float = 0.0,
        source: ModelSource | None = None,
    ) -> None:
        super().__init__(scenario, dt=dt, jitter=jitter, source=source)
        self._fingers = [
            tuple(self._actuators((f"FDS{f}_r", f"FDP{f}_r", f"EDC{f}_r"))) for f in (2, 3, 4, 5)
        ]
        self.period, self.flex, self.extend, self.tone = period, flex, extend, tone
        self.description = f"fingers 2-5 flex in turn (a wave, period {period} s): FDS/FDP up to {flex}, EDC up to {extend} between"

    def control(self, t: float, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        ctrl = np.full(self.nu, self.tone)
        for i, (fds, fdp, edc) in enumerate(self._fingers):
            phase = (t / self.period - i / 4.0) % 1.0
            bump = math.sin(2.0 * math.pi * phase) ** 2 if phase < 0.5 else 0.0
            ctrl[fds] = ctrl[fdp] = self.tone + self.flex * bump
            ctrl[edc] = self.tone + self.extend * (1.0 - bump)
        return ctrl

    def _initial_state(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        return self._jittered(self.model.qpos0.copy(), rng), np.zeros(self.nv)


class Biped(ResearchObject):
    """The planar biped (6 joints, contact), rocking in an A-frame stance for as long as it runs.

    It starts at rest with the legs splayed +/-`splay` rad and both feet on the ground (root_z set
    so; the seed perturbs the splay by N(0, jitter^2)). Every tick, PD laws hold the hips at
    +/-splay + `sway` sin(2 pi f t) (both legs lean the same way, so the hip rocks sideways) and the
    absorbers at +/-`stroke` sin(2 pi f t) (one leg shortens while the other lengthens, so the hip
    bobs), plus the absorber spring's force at the target. The law uses the state it is given: the
    filter's estimate in CONTROLLED, the truth in EXTERNAL. It does not walk: with a 10 g hip the
    legs cannot be swung without a fall; rocking runs indefinitely (checked for 60 s).
    """

    def __init__(
        self,
        scenario: Scenario,
        *,
        dt: float = 0.005,
        splay: float = 0.3,
        sway: float = 0.2,
        stroke: float = 0.08,
        frequency: float = 0.5,
        hip_gains: tuple[float, float] = (100.0, 10.0),
        absorber_gains: tuple[float, float] = (1000.0, 30.0),
        jitter: float = 0.01,
        source: ModelSource | None = None,
    ) -> None:
        if scenario is Scenario.PASSIVE:
            raise ValueError("the biped cannot move passively (it only falls): use CONTROLLED or EXTERNAL")
        super().__init__(source or load_source("biped"), scenario=scenario, dt=dt, jitter=jitter)
        names = [self.model.joint(j).name for j in range(self.model.njnt)]
        expected = ["root_x", "root_z", "left_hip", "left_absorber", "right_hip", "right_absorber"]
        if names != expected:
            raise ValueError(f"the biped's joints must be {expected}, got {names}")
        self.splay, self.sway, self.stroke, self.frequency = splay, sway, stroke, frequency
        self.hip_gains, self.absorber_gains = hip_gains, absorber_gains
        absorber = self.model.joint("left_absorber").id
        self._spring = float(self.model.jnt_stiffness[absorber])
        self.description = (
            f"A-frame stance (legs +/-{splay} rad) rocking at {frequency} Hz: hips sway +/-{sway} rad, "
            f"absorbers +/-{stroke} m in antiphase (PD)"
        )

    def control(self, t: float, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        phase = math.sin(2.0 * math.pi * self.frequency * t)
        kp, kd = self.hip_gains
        ks, ds = self.absorber_gains
        hips = (self.splay + self.sway * phase, -self.splay + self.sway * phase)
        strokes = (self.stroke * phase, -self.stroke * phase)
        u = np.empty(4)
        # Actuators in the model's order: left hip, left absorber, right hip, right absorber.
        for leg, (hip, stroke) in enumerate(zip(hips, strokes)):
            h, s = 2 + 2 * leg, 3 + 2 * leg
            u[2 * leg] = kp * (hip - qpos[h]) - kd * qvel[h]
            u[2 * leg + 1] = ks * (stroke - qpos[s]) - ds * qvel[s] + self._spring * stroke
        return u

    def _initial_state(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        splay = self.splay + self.jitter * float(rng.standard_normal())
        q = np.zeros(self.nq)
        q[2], q[4] = splay, -splay
        # Feet on the ground: at qpos = 0 the straight legs stand on it, so the hip drops by the
        # height a splayed leg loses.
        q[1] = math.cos(splay) - 1.0
        return q, np.zeros(self.nv)


# The objects of the thesis, by the name experiments use.
OBJECTS: dict[str, Callable[[Scenario], ResearchObject]] = {
    "pendulum_1": lambda s: Pendulum(1, s),
    "pendulum_2": lambda s: Pendulum(2, s),
    "pendulum_3": lambda s: Pendulum(3, s),
    "biped": lambda s: Biped(s),
    "myoelbow": lambda s: MyoElbow(s),
    "myohand": lambda s: MyoHand(s),
}


def make_object(name: str, scenario: Scenario) -> ResearchObject:
    """The research object `name` in `scenario`, with the thesis' frame period (the recorded
    jump, "cmj", is experiments/recorded.py's `research_object`)."""
    try:
        factory = OBJECTS[name]
    except KeyError:
        raise ValueError(f"object must be one of {sorted(OBJECTS)}, got {name!r}") from None
    return factory(scenario)
