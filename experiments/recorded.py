"""A research object whose truth is recorded human motion: the right leg's sagittal angles of a
countermovement jump, replayed on a hip-knee-ankle chain with human segment parameters::

    obj = RecordedJump()                 # reads the recording from the installed biomdp package
    truth = obj.reset(seed=0)            # frame 0 of the replay (100 Hz)
    truth = obj.step()                   # the next one

The recording: biomdp 0.11.2 (MIT licence, by its authors; `pip install --no-deps biomdp==0.11.2`)
ships a Vicon export, tests/datasets/vicon_CMJ_kinem_kinet_emg.csv, whose "Model Outputs" block
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

import importlib.util
import math
from pathlib import Path
from typing import Final

import numpy as np

from jitdyn.experiments.objects import ModelSource, ResearchObject, Scenario, TrueState, make_object

__all__ = ["BODY_MASS", "COLUMNS", "RecordedJump", "load_recording", "recording_path", "research_object"]

COLUMNS: Final = ("AngArtHip_R", "AngArtKnee_R", "AngArtAnkle_R")
BODY_MASS: Final = 75.0  # kg
_RATE: Final = 200.0  # Hz, the "Model Outputs" block's
_DROP: Final = 3  # leading frames whose signs flip

# de Leva 1996, table 4, males: mass (fraction of body mass), length (m), centre of mass from the
# proximal joint (fraction of length), sagittal radius of gyration about it (fraction of length).
_SEGMENTS: Final = {
    "thigh": (0.1416, 0.4222, 0.4095, 0.329),
    "shank": (0.0433, 0.4340, 0.4459, 0.255),
    "foot": (0.0137, 0.2581, 0.4415, 0.257),
}


def recording_path() -> Path:
    """The CSV inside the installed biomdp package (FileNotFoundError saying how to install it)."""
    spec = importlib.util.find_spec("biomdp")
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError(
            "the recorded jump needs biomdp 0.11.2: pip install --no-deps biomdp==0.11.2 "
            "(or the 'experiments' extra of jitdyn)"
        )
    path = (
        Path(next(iter(spec.submodule_search_locations)))
        / "tests"
        / "datasets"
        / "vicon_CMJ_kinem_kinet_emg.csv"
    )
    if not path.is_file():
        raise FileNotFoundError(f"biomdp is installed but has no {path.name}; biomdp 0.11.2 ships it")
    return path


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


def chain_mjcf(body_mass: float = BODY_MASS) -> str:
    """The hip-knee-ankle chain (see the module docstring); timestep 2 ms."""

    def inertial(segment: str, axis: tuple[float, float, float]) -> str:
        fraction, length, com, radius = _SEGMENTS[segment]
        mass = fraction * body_mass
        inertia = mass * (radius * length) ** 2
        pos = " ".join(f"{com * length * a:.6f}" for a in axis)
        return (
            f'<inertial pos="{pos}" mass="{mass:.6f}" '
            f'diaginertia="{inertia:.6e} {inertia:.6e} {inertia * 0.1:.6e}"/>'
        )

    thigh, shank = _SEGMENTS["thigh"][1], _SEGMENTS["shank"][1]
    foot = _SEGMENTS["foot"][1]
    # Hip flexion moves the thigh forward (+x): axis -y; knee flexion moves the shank back: +y;
    # ankle dorsiflexion lifts the toes: -y.
    return f"""<mujoco model="cmj_leg">
  <option timestep="0.002" gravity="0 0 -9.81"/>
  <worldbody>
    <body name="thigh" pos="0 0 1">
      <joint name="hip_flexion_r" type="hinge" axis="0 -1 0"/>
      {inertial("thigh", (0.0, 0.0, -1.0))}
      <geom type="capsule" fromto="0 0 0 0 0 -{thigh}" size="0.06" contype="0" conaffinity="0" mass="0"/>
      <body name="shank" pos="0 0 -{thigh}">
        <joint name="knee_flexion_r" type="hinge" axis="0 1 0"/>
        {inertial("shank", (0.0, 0.0, -1.0))}
        <geom type="capsule" fromto="0 0 0 0 0 -{shank}" size="0.04" contype="0" conaffinity="0" mass="0"/>
        <body name="foot" pos="0 0 -{shank}">
          <joint name="ankle_flexion_r" type="hinge" axis="0 -1 0"/>
          {inertial("foot", (1.0, 0.0, 0.0))}
          <geom type="capsule" fromto="0 0 0 {foot} 0 0" size="0.03" contype="0" conaffinity="0" mass="0"/>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor joint="hip_flexion_r"/><motor joint="knee_flexion_r"/><motor joint="ankle_flexion_r"/>
  </actuator>
</mujoco>
"""


class RecordedJump(ResearchObject):
    """The right leg of a recorded countermovement jump (see the module docstring), 100 Hz frames.

    The truth is the recording, not a simulation: `step` takes the next sample; the forces that
    moved the leg are whatever inverse dynamics says, and the server never sees them.
    """

    def __init__(
        self, scenario: Scenario = Scenario.EXTERNAL, *, dt: float = 0.01, angles: np.ndarray | None = None
    ) -> None:
        if scenario is not Scenario.EXTERNAL:
            raise ValueError(
                f"the recorded jump is driven by the person: EXTERNAL only, got {scenario.value}"
            )
        source = ModelSource(name="cmj_leg", mjcf=chain_mjcf(), builtin=False)
        super().__init__(source, scenario=scenario, dt=dt, jitter=0.0)
        q = load_recording() if angles is None else np.asarray(angles, dtype=float)
        h = 1.0 / _RATE
        qd = np.gradient(q, h, axis=0)
        qdd = np.gradient(qd, h, axis=0)
        stride = round(dt * _RATE)
        if stride < 1 or not math.isclose(stride / _RATE, dt):
            raise ValueError(f"dt must be a whole multiple of the recording's {1 / _RATE} s, got {dt}")
        self._q, self._qd, self._qdd = q[::stride], qd[::stride], qdd[::stride]
        self.seconds = (self._q.shape[0] - 1) * dt
        self.description = (
            f"right hip, knee and ankle flexion of a recorded countermovement jump (biomdp 0.11.2, Vicon, "
            f"{_RATE:g} Hz, {self.seconds:.2f} s) replayed at {1 / dt:g} Hz on a de Leva (1996) leg of a "
            f"{BODY_MASS:g} kg male, hip fixed"
        )

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


def research_object(name: str, scenario: Scenario) -> ResearchObject:
    """Any research object by name: the simulated ones of experiments/objects.py, or "cmj", the
    recorded jump (which reads biomdp's file, so only when asked for)."""
    if name == "cmj":
        return RecordedJump(scenario)
    return make_object(name, scenario)
