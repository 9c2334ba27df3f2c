"""The recordings of human walking that the prior of human motion learns from, read from the
packages that ship them (experiments/prior_build.py builds the prior from these)::

    legs = walking_legs(archives=fetch_archives(cache))    # {subject: [(T, 3) hip, knee, ankle]}

Every leg is sagittal hip flexion, knee flexion and ankle dorsiflexion in radians at 100 Hz (NaN
where the recording has no ankle), low-passed at LOWPASS Hz. Six people, five packages:
- "isen": biomdp 0.11.2 (MIT), iSen inertial sensors, both legs' hip and knee, steady stepping
  (experiments/recorded.py, "isen_gait");
- "xsens": scikit-kinematics 0.10.4 (BSD-3-Clause), Xsens sensors on a thigh and a shank, one leg's
  hip and knee, 24 s of walking (experiments/recorded.py, "xsens_gait");
- "fukuchi", "parkinson", "stroke": gaitkit 1.5.0 (MIT; its data from Fukuchi et al. 2018, PeerJ,
  CC-BY 4.0; PhysioNet's Gait in Parkinson's Disease, ODC-By 1.0; Van Criekinge et al. 2023,
  Scientific Data, CC-BY 4.0), one overground trial each (2.5-4.5 s), both legs' hip, knee and
  ankle from its 3D landmarks;
- "moore": GaitAnalysisToolKit 0.2.0 (Apache-2.0; subject 7 of Moore et al. 2015, PeerJ, CC0),
  3 s of treadmill walking, the right leg's sagittal markers.
Why these and not others: docs/decisions/0185-a-prior-of-human-motion.md.
"""

from __future__ import annotations

import hashlib
import io
import json
import subprocess
import sys
import tarfile
from pathlib import Path
from typing import Final

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.signal import butter, filtfilt

from jitdyn.experiments.objects import ModelSource, Scenario
from jitdyn.experiments.recorded import BODY_MASS, RecordedMotion, chain_mjcf, load_isen, load_xsens

__all__ = [
    "ARCHIVES",
    "LOWPASS",
    "RATE",
    "SUBJECTS",
    "WALKS",
    "default_cache",
    "fetch_archives",
    "recorded_walk",
    "walking_legs",
]

RATE: Final = 100.0  # Hz, the prior's
LOWPASS: Final = 10.0  # Hz: a gait analysis' usual cut-off for joint angles
# The source archives read directly (sdists: gaitkit's wheel would build C code, and
# GaitAnalysisToolKit's needs none of its own dependencies to read one text file), and their sha256.
ARCHIVES: Final = {
    "gaitkit-1.5.0.tar.gz": "gaitkit==1.5.0",
    "GaitAnalysisToolKit-0.2.0.tar.gz": "GaitAnalysisToolKit==0.2.0",
}
# Who each subject is: the package, its licence, and the data's own source and licence.
SUBJECTS: Final = {
    "isen": "biomdp 0.11.2 (MIT): iSen inertial sensors, steady stepping, both legs' hip and knee",
    "xsens": "scikit-kinematics 0.10.4 (BSD-3-Clause): Xsens sensors, walking, one leg's hip and knee",
    "fukuchi": "gaitkit 1.5.0 (MIT): Fukuchi et al. 2018 (CC-BY 4.0), a healthy adult, overground",
    "parkinson": "gaitkit 1.5.0 (MIT): PhysioNet Gait in Parkinson's Disease (ODC-By 1.0), overground",
    "stroke": "gaitkit 1.5.0 (MIT): Van Criekinge et al. 2023 (CC-BY 4.0), a stroke survivor, overground",
    "moore": "GaitAnalysisToolKit 0.2.0 (Apache-2.0): Moore et al. 2015 subject 7 (CC0), treadmill",
}
# The subjects whose walks are short trials replayed as research objects ("<subject>_walk").
WALKS: Final = ("fukuchi", "parkinson", "stroke", "moore")
_GAITKIT: Final = {
    "fukuchi": "example_healthy.json",
    "parkinson": "example_parkinson.json",
    "stroke": "example_stroke.json",
}
_MOORE: Final = "GaitAnalysisToolKit-0.2.0/gaitanalysis/octave/2d_inverse_dynamics/test/rawdata.txt"


def fetch_archives(cache: Path) -> dict[str, Path]:
    """The source archives in `cache`, downloaded there by pip (`pip download --no-deps
    --no-binary :all: --no-build-isolation`: with isolation, pip builds the sdists' build
    dependencies from source too, numpy among them, and fails where an index lacks one of theirs) when
    missing; their sha256 printed, so a build says what it read."""
    cache.mkdir(parents=True, exist_ok=True)
    found = {}
    for name, requirement in ARCHIVES.items():
        path = cache / name
        if not path.is_file():
            command = [sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:"]
            command.append("--no-build-isolation")
            subprocess.run([*command, "-d", str(cache), requirement], check=True, capture_output=True)
        if not path.is_file():
            raise FileNotFoundError(f"pip download {requirement} left no {name} in {cache}")
        found[name] = path
    return found


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def default_cache() -> Path:
    """Where the downloaded sdists are kept unless told: ~/.cache/jitdyn/prior-sources."""
    return Path.home() / ".cache" / "jitdyn" / "prior-sources"


def walking_legs(archives: dict[str, Path], *, only: str | None = None) -> dict[str, list[np.ndarray]]:
    """{subject: legs} (only: that subject's), each leg (T, 3) hip flexion, knee flexion, ankle
    dorsiflexion (rad, 100 Hz; NaN for no ankle), low-passed."""
    wanted = list(SUBJECTS) if only is None else [only]
    if only is not None and only not in SUBJECTS:
        raise ValueError(f"no subject {only!r}; the subjects are {', '.join(SUBJECTS)}")
    legs = {subject: _legs(subject, archives) for subject in wanted}
    return {subject: [_lowpass(leg) for leg in each] for subject, each in legs.items()}


def _legs(subject: str, archives: dict[str, Path]) -> list[np.ndarray]:
    if subject == "isen":
        isen = load_isen("isen_gait")  # right hip, right knee, left hip, left knee
        nan = np.full((isen.shape[0], 1), np.nan)
        return [np.hstack([isen[:, 0:2], nan]), np.hstack([isen[:, 2:4], nan])]
    if subject == "xsens":
        xsens = load_xsens()
        return [np.hstack([xsens, np.full((xsens.shape[0], 1), np.nan)])]
    if subject in _GAITKIT:
        with tarfile.open(archives["gaitkit-1.5.0.tar.gz"]) as tar:
            member = tar.extractfile(f"gaitkit-1.5.0/src/gaitkit/data/{_GAITKIT[subject]}")
            if member is None:
                raise FileNotFoundError(f"gaitkit-1.5.0.tar.gz has no {_GAITKIT[subject]}")
            return _gaitkit_legs(json.load(member))
    with tarfile.open(archives["GaitAnalysisToolKit-0.2.0.tar.gz"]) as tar:
        member = tar.extractfile(_MOORE)
        if member is None:
            raise FileNotFoundError(f"GaitAnalysisToolKit-0.2.0.tar.gz has no {_MOORE}")
        return [_moore_leg(member.read().decode("utf-8"))]


def _lowpass(leg: np.ndarray) -> np.ndarray:
    b, a = butter(2, LOWPASS / (RATE / 2.0))
    out = np.array(leg)
    known = ~np.isnan(leg[0])
    out[:, known] = filtfilt(b, a, leg[:, known], axis=0)
    return out


def _resampled(values: np.ndarray, rate: float) -> np.ndarray:
    """(T, k) at `rate` Hz to RATE by a cubic spline."""
    t = np.arange(values.shape[0]) / rate
    grid = np.arange(0.0, t[-1] + 1e-9, 1.0 / RATE)
    return np.asarray(CubicSpline(t, values)(grid))


def _sagittal(points: dict[str, np.ndarray]) -> np.ndarray:
    """(T, 3) hip flexion, knee flexion, ankle dorsiflexion from (T, 2) sagittal points (along the
    walk, up) of hip, knee, ankle, heel, toe: each segment's angle from the vertical, positive when
    its distal end is ahead (ahead: where the toes point from the heel); knee flexion is the thigh's
    less the shank's; dorsiflexion the foot's pitch (toes up) less the shank's angle, from its
    median (the pelvis taken as upright, as in experiments/recorded.py)."""
    facing = np.sign(np.median(points["toe"][:, 0] - points["heel"][:, 0]))
    points = {part: p * np.array([facing, 1.0]) for part, p in points.items()}

    def pitch(a: str, b: str) -> np.ndarray:  # angle of b below a, from the downward vertical
        d = points[b] - points[a]
        return np.asarray(np.arctan2(d[:, 0], -d[:, 1]))

    thigh, shank = pitch("hip", "knee"), pitch("knee", "ankle")
    foot = points["toe"] - points["heel"]
    ankle = np.arctan2(foot[:, 1], foot[:, 0]) - shank
    return np.column_stack([thigh, thigh - shank, ankle - np.median(ankle)])


def _gaitkit_legs(trial: dict[str, object]) -> list[np.ndarray]:
    """Both legs of a gaitkit example trial, from its landmarks (mm, any axes): the vertical axis is
    the one along which the hips stand highest above the ankles, the one along the walk the hips'
    largest travel among the others."""
    frames = trial["angle_frames"]
    assert isinstance(frames, list)
    names = [
        f"{side}_{part}" for side in ("left", "right") for part in ("hip", "knee", "ankle", "heel", "toe")
    ]
    xyz = {n: np.array([f["landmark_positions"][n] for f in frames], dtype=float) for n in names}
    height = (xyz["left_hip"] + xyz["right_hip"] - xyz["left_ankle"] - xyz["right_ankle"]).mean(axis=0)
    vertical = int(np.argmax(np.abs(height)))
    pelvis = (xyz["left_hip"] + xyz["right_hip"]) / 2.0
    travel = pelvis[-1] - pelvis[0]
    others = [i for i in range(3) if i != vertical]
    ahead = others[int(np.argmax(np.abs(travel[others])))]
    up = np.sign(height[vertical])
    rate = float(trial["fps"])  # type: ignore[arg-type]
    legs = []
    for side in ("left", "right"):
        points = {
            part: np.column_stack([xyz[f"{side}_{part}"][:, ahead], up * xyz[f"{side}_{part}"][:, vertical]])
            for part in ("hip", "knee", "ankle", "heel", "toe")
        }
        legs.append(_resampled(_sagittal(points), rate))
    return legs


def _moore_leg(text: str) -> np.ndarray:
    """The right leg of GaitAnalysisToolKit's rawdata.txt (100 Hz; X forward, Y up, m): greater
    trochanter, lateral knee, lateral malleolus, heel and fifth metatarsal head; the few samples a
    marker was lost for, bridged linearly."""
    lines = [line for line in text.splitlines() if line.strip()]
    header = lines[0].lstrip("%").split()
    data = np.loadtxt(io.StringIO("\n".join(lines[1:])))
    rows = np.arange(data.shape[0])
    for j in range(data.shape[1]):  # a marker lost for a few frames: bridged linearly
        lost = np.isnan(data[:, j])
        if lost.all():
            raise ValueError(f"rawdata.txt's column {header[j]} holds no number")
        data[lost, j] = np.interp(rows[lost], rows[~lost], data[~lost, j])
    column = {name: i for i, name in enumerate(header)}
    markers = {"hip": "RGTRO", "knee": "RLEK", "ankle": "RLM", "heel": "RHEE", "toe": "RMT5"}
    points = {part: data[:, [column[f"{m}.PosX"], column[f"{m}.PosY"]]] for part, m in markers.items()}
    return _sagittal(points)


def recorded_walk(
    subject: str, scenario: Scenario = Scenario.EXTERNAL, *, roles: bool = True
) -> RecordedMotion:
    """A walk of WALKS, the right leg's hip, knee and ankle flexion at 100 Hz on the hip-knee-ankle
    chain (its sdist downloaded by pip when missing); its model leaves its person out of the prior
    (tag prior.without.<subject>); roles False: its joints say no role."""
    leg = walking_legs(fetch_archives(default_cache()), only=subject)[subject][-1]
    name = f"{subject}_leg" if roles else f"{subject}_leg_plain"
    joints = None if roles else ("upper_r", "lower_r", "foot_r")
    tags = (f"prior.without.{subject}",) if roles else ()
    source = ModelSource(name=name, mjcf=chain_mjcf(name=name, joints=joints), builtin=False, tags=tags)
    obj = RecordedMotion(source, leg, rate=RATE, scenario=scenario)
    obj.description = (
        f"walking: the right hip, knee and ankle flexion of {SUBJECTS[subject]} ({obj.seconds:.2f} s, "
        f"100 Hz) on a de Leva (1996) leg of a {BODY_MASS:g} kg male, hip fixed"
    )
    return obj
