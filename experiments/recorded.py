"""Research objects whose truth is recorded human motion, replayed on chains with human segment
parameters::

    obj = research_object("isen_gait", Scenario.EXTERNAL)   # reads biomdp's installed package data
    truth = obj.reset(seed=0)            # frame 0 of the replay (100 Hz)
    truth = obj.step()                   # the next one

Four motions from three recordings by three measuring systems, read at run time from two packages'
data (nothing of them is copied into this repository). From biomdp 0.11.2's (MIT licence, by its
authors; `pip install --no-deps biomdp==0.11.2`):
- "cmj", a countermovement jump (Vicon, 200 Hz), below;
- "isen_gait" and "isen_tasks", from biomdp/tests/datasets/iSen_angles.csv: the sagittal hip and knee
  angles of both legs measured by iSen inertial sensors at 100 Hz over 36 s. From 26 s to the end
  the subject steps in a steady rhythm (a cycle of about 0.75 s): "isen_gait", repetitive. From 7
  to 25 s the legs do a sequence of different movements, none repeated in the same way:
  "isen_tasks", the recording that is not repetitive. Columns "Flexo-extensión cadera
  derecha::Y", "... rodilla derecha::Y", "... cadera izquierda::Y", "... rodilla izquierda::Y",
  their first occurrence (the angle block; later blocks are their velocities and accelerations),
  degrees. Replayed on both legs hanging from a fixed pelvis (hip and knee hinges, the foot fixed
  to the shank), de Leva's segments as below.

From scikit-kinematics 0.10.4's (BSD-3-Clause, Thomas Haslwanter; its wheel installs them as
tests/data of site-packages):
- "xsens_gait", from walking_xsens_upperLeg.txt and walking_xsens_lowerLeg.txt: two Xsens inertial
  sensors, one on a thigh and one on the shank below it, sampled together at 120 Hz for 29 s; the
  subject stands for 3.5 s, then walks steadily (a stride of about 1.3 s). The sagittal axis is
  each sensor's z (its gyroscope's largest swing). Each segment's sagittal angle is its z rate
  integrated from the standing pose (zero), less the rate's mean while standing (0.5-3 s) and a
  constant drift fitted over the walk (what a gyroscope bias that changes after the standing leaves:
  1.4 and 0.6 degrees a second); hip flexion is the thigh's angle (the pelvis taken as upright),
  knee flexion the thigh's less the shank's. The walk, from 5 s to the end (24 s), resampled to
  100 Hz (cubic spline), is replayed on one leg from a fixed pelvis (hip and knee hinges, the foot
  fixed to the shank), de Leva's segments as below.

The jump:

The recording: biomdp 0.11.2 (MIT licence, by its authors; `pip install --no-deps biomdp==0.11.2`)
ships a Vicon export, biomdp/tests/datasets/vicon_CMJ_kinem_kinet_emg.csv, whose "Model Outputs" block
holds joint angles at 200 Hz. We read it at run time from the installed package (nothing of it is
copied into this repository) and take AngArtHip_R, AngArtKnee_R and AngArtAnkle_R, component x
(flexion, degrees), leaving out the first 3 frames, whose signs flip. Every second sample gives
frames at 100 Hz; qd and qdd are central differences of the 200 Hz angles.

The chain: the hip fixed in space (the pelvis' own motion in the jump is not replayed), thigh,
shank and foot as rigid bodies with three hinges about the sagittal axis, one motor per hinge (so
the model is "driven" and a session that names no scenario estimates the unknown force). Segment
masses, lengths, centres of mass and sagittal radii of gyration: de Leva P. (1996), "Adjustments to
Zatsiorsky-Seluyanov's segment inertia parameters", J. Biomech. 29(9):1223-1230, table 4 (males),
for a 75 kg subject (the recording does not give the subject's mass).
"""

from __future__ import annotations

import csv
import dataclasses
import importlib.metadata
import importlib.util
import math
from pathlib import Path
from typing import Final

import numpy as np
from scipy.interpolate import CubicSpline

from jitdyn.experiments.objects import ModelSource, ResearchObject, Scenario, TrueState, make_object

__all__ = [
    "BODY_MASS",
    "COLUMNS",
    "ISEN_COLUMNS",
    "RECORDINGS",
    "SUBJECT",
    "RecordedJump",
    "RecordedMotion",
    "load_isen",
    "load_recording",
    "load_xsens",
    "recorded_isen",
    "recording_path",
    "research_object",
    "xsens_path",
]

COLUMNS: Final = ("AngArtHip_R", "AngArtKnee_R", "AngArtAnkle_R")
BODY_MASS: Final = 75.0  # kg
_RATE: Final = 200.0  # Hz, the "Model Outputs" block's
_DROP: Final = 3  # leading frames whose signs flip
ISEN_COLUMNS: Final = (
    "Flexo-extensión cadera derecha::Y",
    "Flexo-extensión rodilla derecha::Y",
    "Flexo-extensión cadera izquierda::Y",
    "Flexo-extensión rodilla izquierda::Y",
)
_ISEN_RATE: Final = 100.0  # Hz (its time column steps by 0.0099973 s: read as 100 Hz)
# The parts of the iSen recording replayed (s): steady stepping, and movements not repeated.
_ISEN_PARTS: Final = {"isen_gait": (26.0, 36.3), "isen_tasks": (7.0, 25.0)}

_XSENS_FILES: Final = ("walking_xsens_upperLeg.txt", "walking_xsens_lowerLeg.txt")  # thigh, shank
_XSENS_RATE: Final = 120.0  # Hz, the files' "Sample rate"
_XSENS_STILL: Final = (0.5, 3.0)  # s: the subject stands
_XSENS_WALK: Final = 5.0  # s: steady walking from here to the end

# de Leva 1996, table 4, males: mass (fraction of body mass), length (m), centre of mass from the
# proximal joint (fraction of length), sagittal radius of gyration about it (fraction of length).
_SEGMENTS: Final = {
    "thigh": (0.1416, 0.4222, 0.4095, 0.329),
    "shank": (0.0433, 0.4340, 0.4459, 0.255),
    "foot": (0.0137, 0.2581, 0.4415, 0.257),
}


def recording_path(name: str = "vicon_CMJ_kinem_kinet_emg.csv") -> Path:
    """A file of biomdp's test datasets inside the installed package (FileNotFoundError saying how
    to install it)."""
    spec = importlib.util.find_spec("biomdp")
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError(
            "the recorded motions need biomdp 0.11.2: pip install --no-deps biomdp==0.11.2 "
            "(or the 'experiments' extra of jitdyn)"
        )
    path = Path(next(iter(spec.submodule_search_locations))) / "tests" / "datasets" / name
    if not path.is_file():
        raise FileNotFoundError(f"biomdp is installed but has no {path.name}; biomdp 0.11.2 ships it")
    return path


def xsens_path(name: str) -> Path:
    """A file of scikit-kinematics' test data, which its wheel installs as tests/data beside the
    package (FileNotFoundError saying how to install it)."""
    try:
        dist = importlib.metadata.distribution("scikit-kinematics")
    except importlib.metadata.PackageNotFoundError:
        raise FileNotFoundError(
            "the recorded walk needs scikit-kinematics 0.10.4's data: pip install --no-deps "
            "scikit-kinematics==0.10.4"
        ) from None
    path = Path(str(dist.locate_file(f"tests/data/{name}")))
    if not path.is_file():
        raise FileNotFoundError(
            f"scikit-kinematics {dist.version} is installed but has no tests/data/{name}; 0.10.4 ships it"
        )
    return path


def load_xsens(paths: tuple[Path, Path] | None = None) -> np.ndarray:
    """(T, 2) hip and knee flexion in radians at 100 Hz of the walk the Xsens thigh and shank
    sensors recorded (see the module docstring for how the angles follow from the sensors)."""
    thigh, shank = paths or tuple(xsens_path(n) for n in _XSENS_FILES)
    segments = [_sagittal_angle(p) for p in (thigh, shank)]
    if segments[0].shape != segments[1].shape:
        raise ValueError(f"the two sensors must have as many samples, got {[a.shape[0] for a in segments]}")
    t = np.arange(segments[0].shape[0]) / _XSENS_RATE
    walk = t >= _XSENS_WALK
    angles = np.column_stack([segments[0], segments[0] - segments[1]])[walk]
    grid = np.arange(0.0, t[walk][-1] - _XSENS_WALK, 1.0 / _ISEN_RATE)
    return np.asarray(CubicSpline(t[walk] - _XSENS_WALK, angles)(grid))


def _sagittal_angle(path: Path) -> np.ndarray:
    """(T,) one sensor's sagittal angle (rad): its z rate integrated, the standing mean and a
    constant drift over the walk taken out."""
    lines = path.read_text(encoding="utf-8").splitlines()
    header = next((i for i, line in enumerate(lines) if line.startswith("Counter")), None)
    if header is None:
        raise ValueError(f"{path.name} has no 'Counter' header line")
    names = lines[header].split()
    if "Gyr_Z" not in names:
        raise ValueError(f"{path.name} has no column Gyr_Z")
    column = names.index("Gyr_Z")
    rate = np.array([float(line.split()[column]) for line in lines[header + 1 :] if line.strip()])
    t = np.arange(rate.shape[0]) / _XSENS_RATE
    if t[-1] < _XSENS_WALK + 10.0 or not np.all(np.isfinite(rate)):
        raise ValueError(f"{path.name} must hold a finite walk of 10 s or more, got {t[-1]:.1f} s")
    still = (t >= _XSENS_STILL[0]) & (t < _XSENS_STILL[1])
    angle = np.cumsum(rate - rate[still].mean()) / _XSENS_RATE
    walk = t >= _XSENS_WALK
    drift = np.polyfit(t[walk], angle[walk], 1)[0]
    return np.asarray(angle - drift * t)


def load_isen(part: str, path: Path | None = None) -> np.ndarray:
    """(T, 4) right hip, right knee, left hip, left knee flexion in radians at 100 Hz, of the part
    of the iSen recording named ("isen_gait" or "isen_tasks")."""
    if part not in _ISEN_PARTS:
        raise ValueError(f"part must be one of {sorted(_ISEN_PARTS)}, got {part!r}")
    text = (path or recording_path("iSen_angles.csv")).read_text(encoding="utf-8-sig")
    rows = list(csv.reader(text.splitlines()))
    header = rows[0]
    columns = []
    for wanted in ISEN_COLUMNS:
        if wanted not in header:
            raise ValueError(f"the iSen recording has no column {wanted!r}")
        columns.append(header.index(wanted))  # the first: the angle block
    start, end = _ISEN_PARTS[part]
    first, last = round(start * _ISEN_RATE), round(end * _ISEN_RATE)
    degrees = np.array([[float(r[c]) for c in columns] for r in rows[1 + first : 1 + last]])
    if degrees.shape[0] < 10 or not np.all(np.isfinite(degrees)):
        raise ValueError(f"the iSen angles must be finite, got {degrees.shape[0]} rows")
    return np.asarray(np.radians(degrees))


def load_recording(path: Path | None = None) -> np.ndarray:
    """(T, 3) hip, knee, ankle flexion in radians at 200 Hz, the first 3 frames left out."""
    lines = (path or recording_path()).read_text(encoding="utf-8-sig").splitlines()
    try:
        start = lines.index("Model Outputs")
    except ValueError:
        raise ValueError("the recording has no 'Model Outputs' block") from None
    names = lines[start + 2].split(",")
    columns = []
    for wanted in COLUMNS:
        matches = [i for i, n in enumerate(names) if n.endswith(":" + wanted)]
        if len(matches) != 1:
            raise ValueError(f"the recording must have one column {wanted}, found {len(matches)}")
        columns.append(matches[0])  # component x (flexion) is the first of x, y, z
    rows = []
    for line in lines[start + 5 :]:
        if not line.strip():
            break
        cells = line.split(",")
        rows.append([float(cells[c]) for c in columns])
    degrees = np.array(rows)[_DROP:]
    if degrees.shape[0] < 10 or not np.all(np.isfinite(degrees)):
        raise ValueError(f"the recording's angles must be finite, got {degrees.shape[0]} rows")
    return np.asarray(np.radians(degrees))


def chain_mjcf(
    body_mass: float = BODY_MASS, *, name: str = "cmj_leg", joints: tuple[str, str, str] | None = None
) -> str:
    """The hip-knee-ankle chain (see the module docstring); timestep 2 ms. joints: other names for
    its hip, knee and ankle hinges (a model whose joints say no role)."""
    hip, knee, ankle = joints or ("hip_flexion_r", "knee_flexion_r", "ankle_flexion_r")

    def inertial(segment: str, axis: tuple[float, float, float]) -> str:
        return _inertial(segment, axis, body_mass)

    thigh, shank = _SEGMENTS["thigh"][1], _SEGMENTS["shank"][1]
    foot = _SEGMENTS["foot"][1]
    # Hip flexion moves the thigh forward (+x): axis -y; knee flexion moves the shank back: +y;
    # ankle dorsiflexion lifts the toes: -y.
    return f"""<mujoco model="{name}">
  <option timestep="0.002" gravity="0 0 -9.81"/>
  <worldbody>
    <body name="thigh" pos="0 0 1">
      <joint name="{hip}" type="hinge" axis="0 -1 0"/>
      {inertial("thigh", (0.0, 0.0, -1.0))}
      <geom type="capsule" fromto="0 0 0 0 0 -{thigh}" size="0.06" contype="0" conaffinity="0" mass="0"/>
      <body name="shank" pos="0 0 -{thigh}">
        <joint name="{knee}" type="hinge" axis="0 1 0"/>
        {inertial("shank", (0.0, 0.0, -1.0))}
        <geom type="capsule" fromto="0 0 0 0 0 -{shank}" size="0.04" contype="0" conaffinity="0" mass="0"/>
        <body name="foot" pos="0 0 -{shank}">
          <joint name="{ankle}" type="hinge" axis="0 -1 0"/>
          {inertial("foot", (1.0, 0.0, 0.0))}
          <geom type="capsule" fromto="0 0 0 {foot} 0 0" size="0.03" contype="0" conaffinity="0" mass="0"/>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor joint="{hip}"/><motor joint="{knee}"/><motor joint="{ankle}"/>
  </actuator>
</mujoco>
"""


def _inertial(segment: str, axis: tuple[float, float, float], body_mass: float) -> str:
    fraction, length, com, radius = _SEGMENTS[segment]
    mass = fraction * body_mass
    inertia = mass * (radius * length) ** 2
    pos = " ".join(f"{com * length * a:.6f}" for a in axis)
    return f'<inertial pos="{pos}" mass="{mass:.6f}" diaginertia="{inertia:.6e} {inertia:.6e} {inertia * 0.1:.6e}"/>'


def legs_mjcf(
    body_mass: float = BODY_MASS,
    *,
    sides: tuple[str, ...] = ("r", "l"),
    name: str = "isen_legs",
    plain: bool = False,
) -> str:
    """Legs ("r", "l") from a fixed pelvis: hip and knee hinges (sagittal), the foot fixed to the
    shank at a right angle; de Leva's segments (see the module docstring); timestep 2 ms. plain:
    the hinges named upper_<side> and lower_<side>, names that say no role."""
    thigh, shank, foot = (_SEGMENTS[s][1] for s in ("thigh", "shank", "foot"))
    hip, knee = ("upper", "lower") if plain else ("hip_flexion", "knee_flexion")
    legs = []
    for side, y in (("r", -0.09), ("l", 0.09)):
        if side not in sides:
            continue
        legs.append(
            f"""    <body name="thigh_{side}" pos="0 {y} 1">
      <joint name="{hip}_{side}" type="hinge" axis="0 -1 0"/>
      {_inertial("thigh", (0.0, 0.0, -1.0), body_mass)}
      <geom type="capsule" fromto="0 0 0 0 0 -{thigh}" size="0.06" contype="0" conaffinity="0" mass="0"/>
      <body name="shank_{side}" pos="0 0 -{thigh}">
        <joint name="{knee}_{side}" type="hinge" axis="0 1 0"/>
        {_inertial("shank", (0.0, 0.0, -1.0), body_mass)}
        <geom type="capsule" fromto="0 0 0 0 0 -{shank}" size="0.04" contype="0" conaffinity="0" mass="0"/>
        <body name="foot_{side}" pos="0 0 -{shank}">
          {_inertial("foot", (1.0, 0.0, 0.0), body_mass)}
          <geom type="capsule" fromto="0 0 0 {foot} 0 0" size="0.03" contype="0" conaffinity="0" mass="0"/>
        </body>
      </body>
    </body>"""
        )
    motors = "".join(f'<motor joint="{j}_{side}"/>' for side in sides for j in (hip, knee))
    body = "\n".join(legs)
    return f"""<mujoco model="{name}">
  <option timestep="0.002" gravity="0 0 -9.81"/>
  <worldbody>
{body}
  </worldbody>
  <actuator>
    {motors}
  </actuator>
</mujoco>
"""


class RecordedMotion(ResearchObject):
    """Recorded angles (T, nv) at `rate` Hz replayed on the model `source`, frames every `dt`.

    The truth is the recording, not a simulation: `step` takes the next sample; the forces that
    moved the body are whatever inverse dynamics says, and the server never sees them. qd and qdd
    are central differences of the recorded angles.
    """

    def __init__(
        self,
        source: ModelSource,
        angles: np.ndarray,
        *,
        rate: float,
        dt: float = 0.01,
        scenario: Scenario = Scenario.EXTERNAL,
        description: str = "",
    ) -> None:
        if scenario is not Scenario.EXTERNAL:
            raise ValueError(
                f"a recorded motion is driven by the person: EXTERNAL only, got {scenario.value}"
            )
        super().__init__(source, scenario=scenario, dt=dt, jitter=0.0)
        q = np.asarray(angles, dtype=float)
        if q.ndim != 2 or q.shape[1] != self.nv:
            raise ValueError(f"angles must be (T, {self.nv}) for {source.name}, got {q.shape}")
        h = 1.0 / rate
        qd = np.gradient(q, h, axis=0)
        qdd = np.gradient(qd, h, axis=0)
        stride = round(dt * rate)
        if stride < 1 or not math.isclose(stride / rate, dt):
            raise ValueError(f"dt must be a whole multiple of the recording's {1 / rate} s, got {dt}")
        self._q, self._qd, self._qdd = q[::stride], qd[::stride], qdd[::stride]
        self.seconds = (self._q.shape[0] - 1) * dt
        self.description = description

    def reset(self, seed: int) -> TrueState:
        self._tick = 0
        self._reset_done = True
        return self._sample()

    def step(self, ctrl: np.ndarray | None = None) -> TrueState:
        if not self._reset_done:
            raise RuntimeError("step before reset: call reset(seed) first")
        if ctrl is not None:
            raise ValueError("ctrl must be None: the recording drives itself")
        if self._tick + 1 >= self._q.shape[0]:
            raise IndexError(f"the recording ends at {self.seconds:.3f} s")
        self._tick += 1
        return self._sample()

    def control(self, t: float, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        return np.zeros(self.nu)

    def _initial_state(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        return self._q[0].copy(), self._qd[0].copy()

    def _sample(self) -> TrueState:
        k = self._tick
        return TrueState(
            t=self.t,
            qpos=self._q[k].copy(),
            qvel=self._qd[k].copy(),
            qacc=self._qdd[k].copy(),
            ctrl=np.zeros(self.nu),
        )


class RecordedJump(RecordedMotion):
    """The right leg of the recorded countermovement jump (see the module docstring), 100 Hz frames."""

    def __init__(
        self,
        scenario: Scenario = Scenario.EXTERNAL,
        *,
        dt: float = 0.01,
        angles: np.ndarray | None = None,
        roles: bool = True,
    ) -> None:
        name, joints = ("cmj_leg", None) if roles else ("cmj_leg_plain", ("upper_r", "lower_r", "foot_r"))
        source = ModelSource(name=name, mjcf=chain_mjcf(name=name, joints=joints), builtin=False)
        q = load_recording() if angles is None else np.asarray(angles, dtype=float)
        super().__init__(source, q, rate=_RATE, dt=dt, scenario=scenario)
        self.description = (
            f"right hip, knee and ankle flexion of a recorded countermovement jump (biomdp 0.11.2, Vicon, "
            f"{_RATE:g} Hz, {self.seconds:.2f} s) replayed at {1 / dt:g} Hz on a de Leva (1996) leg of a "
            f"{BODY_MASS:g} kg male, hip fixed"
        )


def recorded_isen(part: str, scenario: Scenario = Scenario.EXTERNAL, *, roles: bool = True) -> RecordedMotion:
    """A part of the iSen recording ("isen_gait", "isen_tasks") on both legs, 100 Hz frames."""
    name = "isen_legs" if roles else "isen_legs_plain"
    source = ModelSource(name=name, mjcf=legs_mjcf(name=name, plain=not roles), builtin=False)
    what = "steady stepping" if part == "isen_gait" else "a sequence of different leg movements"
    obj = RecordedMotion(source, load_isen(part), rate=_ISEN_RATE, scenario=scenario)
    obj.description = (
        f"{what}: hip and knee flexion of both legs (biomdp 0.11.2, iSen inertial sensors, "
        f"{_ISEN_RATE:g} Hz, {obj.seconds:.2f} s) on de Leva (1996) legs of a {BODY_MASS:g} kg male, "
        "pelvis fixed"
    )
    return obj


def recorded_xsens(scenario: Scenario = Scenario.EXTERNAL, *, roles: bool = True) -> RecordedMotion:
    """The walk the Xsens sensors recorded (see the module docstring) on one leg, 100 Hz frames."""
    name = "xsens_leg" if roles else "xsens_leg_plain"
    source = ModelSource(name=name, mjcf=legs_mjcf(sides=("r",), name=name, plain=not roles), builtin=False)
    obj = RecordedMotion(source, load_xsens(), rate=_ISEN_RATE, scenario=scenario)
    obj.description = (
        f"steady walking: hip and knee flexion of one leg (scikit-kinematics 0.10.4, Xsens inertial "
        f"sensors on the thigh and shank, {_XSENS_RATE:g} Hz, {obj.seconds:.2f} s) on a de Leva (1996) "
        f"leg of a {BODY_MASS:g} kg male, pelvis fixed"
    )
    return obj


# The recorded motions by name, and whether each is repetitive (what a learned predictor can learn).
RECORDINGS: Final = {"cmj": False, "isen_gait": True, "isen_tasks": False, "xsens_gait": True}
# Whose motion each recording is, as the prior of human motion names its subjects: the prior that
# scores it leaves that person out. The jump's person is not among them (biomdp does not say who
# jumped; the prior holds no jump).
SUBJECT: Final = {"isen_gait": "isen", "isen_tasks": "isen", "xsens_gait": "xsens"}


def research_object(name: str, scenario: Scenario, *, roles: bool = True) -> ResearchObject:
    """Any research object by name: the simulated ones of experiments/objects.py, or a recorded
    motion of RECORDINGS. A recorded motion's model says its joints' roles by their names and
    leaves its own person out of the prior (tag prior.without.<subject>); roles False: its joints
    named so that they say none (no prior: the session's own history alone)."""
    if name == "cmj":
        obj: ResearchObject = RecordedJump(scenario, roles=roles)
    elif name in _ISEN_PARTS:
        obj = recorded_isen(name, scenario, roles=roles)
    elif name == "xsens_gait":
        obj = recorded_xsens(scenario, roles=roles)
    else:
        return make_object(name, scenario)
    subject = SUBJECT.get(name)
    if roles and subject is not None:
        obj.source = dataclasses.replace(obj.source, tags=(f"prior.without.{subject}",))
    return obj
