"""`jitdyn replay FILE` as a lab runs it: recordings of real people written as an OpenSim .mot, a
C3D (ezc3d) and a CSV, and biomdp's own Vicon C3D, replayed into sessions of a real `jitdyn serve`;
what the server stored is read back from its Parquet and compared with the file. Then the files
and maps it refuses, each in one line."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import numpy as np
import pytest
from _cli import jitdyn, ok, one_line_error, stored_frames

from jitdyn.experiments.recorded import load_isen, load_recording, recording_path

ezc3d = pytest.importorskip("ezc3d")

JUMP_RATE = 200.0  # Hz, the Vicon jump's "Model Outputs"
# The jump's three angles, as biomdp's Vicon export names them, and as Plug-in Gait would.
VICON = {"AngArtHip_R": "RHipAngles", "AngArtKnee_R": "RKneeAngles", "AngArtAnkle_R": "RAnkleAngles"}


def replay(*args: str) -> subprocess.CompletedProcess[str]:
    return jitdyn("replay", *args)


def line_of(stdout: str, start: str) -> str:
    found = [line for line in stdout.splitlines() if line.startswith(start)]
    assert len(found) == 1, stdout
    return found[0]


def vicon_block(block: str, names: list[str]) -> dict[str, np.ndarray]:
    """{name: (T, 3)} of the named x, y, z columns of a block of biomdp's Vicon export (angles in
    degrees, markers in mm), its first 3 frames left out as recorded.py does (their signs flip)."""
    lines = recording_path().read_text(encoding="utf-8-sig").splitlines()
    start = lines.index(block)
    header = lines[start + 2].split(",")
    rows = []
    for line in lines[start + 5 :]:
        if not line.strip():
            break
        rows.append(line.split(","))
    found = {}
    for name in names:
        column = header.index(f"S03:{name}")
        # An empty cell is a marker the cameras lost: NaN, as C3D stores it.
        found[name] = np.array([[float(row[column + i] or "nan") for i in range(3)] for row in rows[3:]])
    return found


def write_mot(path: Path, columns: dict[str, np.ndarray], *, rate: float) -> None:
    """An OpenSim motion file as its inverse kinematics writes one: degrees, inDegrees=yes."""
    n = len(next(iter(columns.values())))
    header = f"jump\nversion=1\nnRows={n}\nnColumns={len(columns) + 1}\ninDegrees=yes\nendheader\n"
    rows = np.column_stack([np.arange(n) / rate, *columns.values()])
    body = "\n".join("\t".join(f"{v:.8f}" for v in row) for row in rows)
    path.write_text(header + "\t".join(["time", *columns]) + "\n" + body + "\n", encoding="utf-8")


def write_c3d(path: Path, points: dict[str, np.ndarray], *, rate: float, angles: list[str]) -> None:
    """A C3D with these points (T, 3), the `angles` among them listed in POINT:ANGLES, in degrees."""
    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = [rate]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = tuple(points)
    data = np.ones((4, len(points), len(next(iter(points.values())))))
    for i, values in enumerate(points.values()):
        data[:3, i, :] = values.T
    c3d["data"]["points"] = data
    c3d.add_parameter("POINT", "ANGLES", angles)
    c3d.add_parameter("POINT", "ANGLE_UNITS", ["deg"])
    c3d.write(str(path))


def test_an_opensim_mot_of_a_jump_drives_pendulum_3_through_a_map(
    leg_server: str, leg_data: Path, tmp_path: Path
) -> None:
    """Degrees as the header says, the knee's sign flipped by the map, the unmapped hinge held at
    rest, the ankle's column left out and said so; 200 Hz replayed at pendulum_3's 25 ms timestep."""
    jump = np.degrees(load_recording())
    mot = tmp_path / "jump.mot"
    write_mot(
        mot,
        {"hip_flexion_r": jump[:, 0], "knee_angle_r": jump[:, 1], "ankle_angle_r": jump[:, 2]},
        rate=JUMP_RATE,
    )
    mapping = tmp_path / "pendulum.map"
    mapping.write_text(
        "# the jump's hip and knee on the pendulum\nhinge_1 = hip_flexion_r\nhinge_2 = -knee_angle_r  # flexion bends it back\n"
    )
    stdout = ok(
        replay(
            str(mot),
            "--model",
            "pendulum_3",
            "--map",
            str(mapping),
            "--clock",
            "lockstep",
            "--server",
            leg_server,
        )
    )
    ticks = len(jump) // 5 + (1 if len(jump) % 5 else 0)
    assert f"replaying {mot}: {len(jump)} samples at 200 Hz, rotations in degrees (inDegrees=yes)" in stdout
    assert line_of(stdout, "joints:") == (
        "joints: hinge_1 <- hip_flexion_r, hinge_2 <- -knee_angle_r; held at rest (no column): hinge_3; "
        "unused columns: ankle_angle_r"
    )
    assert line_of(stdout, "resampled").startswith(
        f"resampled to 40 Hz (dt 25 ms, {ticks} ticks): a session's dt is a whole multiple of the model's timestep, 25 ms"
    )
    assert re.search(
        rf"^session \S+: pendulum_3 v1 \(3 dof\), driven .*, dt 25 ms, {ticks} ticks, LOCKSTEP",
        stdout,
        re.MULTILINE,
    )
    assert f"frames sent {ticks}, lost on the emulated network 0, rejected 0" in stdout
    seqs, qpos = stored_frames(stdout, leg_data)
    np.testing.assert_array_equal(seqs, np.arange(ticks))
    # Every 5th sample is a tick: the spline through the samples is the file there.
    expected = np.radians(jump[::5, :2]) * [1.0, -1.0]
    np.testing.assert_allclose(qpos[:, :2], expected, atol=1e-7)
    assert np.all(qpos[:, 2] == 0.0)


def test_a_c3d_of_plug_in_gait_angles_drives_a_leg_by_name_in_realtime(
    leg_server: str, leg_data: Path, tmp_path: Path
) -> None:
    """The jump's hip, knee and ankle angles (x, y, z) as Plug-in Gait names its points, and a real
    marker beside them, written by ezc3d; each x (flexion) drives the leg's joint of its motion's
    name with no map, over an emulated network on the file's clock."""
    angles = vicon_block("Model Outputs", list(VICON))
    points = {VICON[name]: values for name, values in angles.items()}
    points["Right_KneeExt"] = vicon_block("Trajectories", ["Right_KneeExt"])["Right_KneeExt"]
    c3d = tmp_path / "jump.c3d"
    write_c3d(c3d, points, rate=JUMP_RATE, angles=list(VICON.values()))
    stdout = ok(
        replay(str(c3d), "--model", "cmj_leg", "--dt", "10ms", "--start", "1s", "--end", "3s", "--latency", "30ms",
               "--jitter", "5ms", "--loss", "5%", "--server", leg_server)
    )  # fmt: skip
    assert "rotations in degrees (POINT:ANGLE_UNITS deg); left out: 1 point not angles" in stdout
    assert line_of(stdout, "joints:") == (
        "joints: hip_flexion_r <- RHipAngles.x, knee_flexion_r <- RKneeAngles.x, ankle_flexion_r <- "
        "RAnkleAngles.x; held at rest (no column): none; unused columns: RHipAngles.y, RHipAngles.z, "
        "RKneeAngles.y, RKneeAngles.z, RAnkleAngles.y, RAnkleAngles.z"
    )
    assert "resampled to 100 Hz (dt 10 ms, 201 ticks)" in stdout
    # REALTIME, or LOCKSTEP (said so) on a machine too busy to be admitted.
    assert (
        "network: latency 30 ms, jitter 5 ms, loss 5% (seeded 0)" in stdout or "running it LOCKSTEP" in stdout
    )
    assert "frames sent 201, lost on the emulated network" in stdout
    seqs, qpos = stored_frames(stdout, leg_data)
    first = round(1.0 * JUMP_RATE)  # --start 1s
    expected = np.radians(np.column_stack([angles[name][first : first + 401 : 2, 0] for name in VICON]))
    np.testing.assert_allclose(qpos, expected[seqs], atol=1e-7)
    assert len(seqs) >= 201 * 0.8  # those the emulated network did not lose


def test_biomdp_s_own_vicon_c3d_replays_its_modeled_angles(
    leg_server: str, leg_data: Path, tmp_path: Path
) -> None:
    """A C3D Vicon Nexus wrote: its angles are modeled outputs (USERMO3-9, named by their
    descriptions) in radians without POINT:ANGLE_UNITS, so --angles rad; at cmj_leg's 2 ms
    timestep its 5 ms samples are replayed at 6 ms, on the spline between them."""
    c3d = recording_path("vicon_CMJ_kinem_kinet_emg.c3d")
    mapping = tmp_path / "leg.map"
    mapping.write_text(
        "".join(
            f"{joint}_r = {name}.x\n"
            for joint, name in zip(("hip_flexion", "knee_flexion", "ankle_flexion"), VICON, strict=True)
        )
    )
    stdout = ok(
        replay(str(c3d), "--model", "cmj_leg", "--map", str(mapping), "--angles", "rad", "--start", "20ms",
               "--end", "2s", "--clock", "lockstep", "--server", leg_server)
    )  # fmt: skip
    assert (
        f"replaying {c3d}: 397 samples at 200 Hz, rotations in radians (--angles rad); left out: 35 points not angles"
        in stdout
    )
    assert line_of(stdout, "joints:").startswith(
        "joints: hip_flexion_r <- AngArtHip_R.x, knee_flexion_r <- AngArtKnee_R.x, ankle_flexion_r <- "
        "AngArtAnkle_R.x; held at rest (no column): none; unused columns: AngSegPELVIS_LR.x,"
    )
    assert "resampled to 166.667 Hz (dt 6 ms, 331 ticks)" in stdout
    seqs, qpos = stored_frames(stdout, leg_data)
    np.testing.assert_array_equal(seqs, np.arange(331))
    file = ezc3d.c3d(str(c3d))
    labels = list(file["parameters"]["POINT"]["LABELS"]["value"])
    times = 0.02 + seqs * 0.006
    for j, label in enumerate(("USERMO7", "USERMO8", "USERMO9")):  # hip, knee, ankle
        recorded = file["data"]["points"][0, labels.index(label), :]
        # Within a linear interpolation's error of the smooth jump: the spline is not it.
        np.testing.assert_allclose(qpos[:, j], np.interp(times, np.arange(1600) / 200, recorded), atol=2e-3)


def test_a_csv_of_walking_drives_the_leg_by_name(leg_server: str, leg_data: Path, tmp_path: Path) -> None:
    """iSen's steady stepping (right hip and knee, radians at 100 Hz) as a CSV with a header: the
    columns named as the leg's joints drive them; the ankle, with no column, is held at rest."""
    walk = load_isen("isen_gait")[:300, :2]
    csv = tmp_path / "walk.csv"
    rows = [f"{k / 100:.2f},{hip:.9f},{knee:.9f}" for k, (hip, knee) in enumerate(walk)]
    csv.write_text("\n".join(["time,hip_flexion_r,knee_flexion_r", *rows]) + "\n", encoding="utf-8")
    stdout = ok(
        replay(str(csv), "--model", "cmj_leg", "--dt", "10ms", "--clock", "lockstep", "--server", leg_server)
    )
    assert "rotations in radians (radians, a CSV's default (--angles deg if not))" in stdout
    assert line_of(stdout, "joints:") == (
        "joints: hip_flexion_r <- hip_flexion_r, knee_flexion_r <- knee_flexion_r; held at rest (no column): "
        "ankle_flexion_r; unused columns: none"
    )
    seqs, qpos = stored_frames(stdout, leg_data)
    np.testing.assert_allclose(qpos[:, :2], walk[seqs], atol=1e-8)


# -- what it refuses ---------------------------------------------------------------------------------

JUMP_MOT = "jump\nversion=1\ninDegrees=yes\nendheader\ntime\thip_flexion_r\tknee_angle_r\n0\t10\t20\n0.005\t11\t21\n0.01\t12\t22\n"


@pytest.mark.parametrize(
    ("files", "args", "message"),
    [
        (
            {"walk.txt": "time,a\n0,1\n"},
            ["walk.txt"],
            "{d}/walk.txt: replay reads .mot, .sto, .c3d, .csv files, not '.txt'",
        ),
        (
            {"jump.mot": JUMP_MOT.replace("endheader\n", "")},
            ["jump.mot"],
            "{d}/jump.mot: no 'endheader' line; an OpenSim .mot or .sto file has a header that ends with one",
        ),
        (
            {"jump.mot": JUMP_MOT, "leg.map": "hinge_1 hip_flexion_r\n"},
            ["jump.mot", "--map", "leg.map"],
            "--map {d}/leg.map, line 1: expected JOINT = COLUMN (or -COLUMN), got 'hinge_1 hip_flexion_r'",
        ),
        (
            {"jump.mot": JUMP_MOT, "leg.map": "# hip\nhinge_1 = hip_flexion_r\nhinge_2 = knee_flexion_r\n"},
            ["jump.mot", "--map", "leg.map"],
            (
                "--map {d}/leg.map, line 3: the recording has no column 'knee_flexion_r'; its columns are "
                "hip_flexion_r, knee_angle_r"
            ),
        ),
        (
            {"jump.mot": JUMP_MOT, "leg.map": "knee = knee_angle_r\n"},
            ["jump.mot", "--map", "leg.map"],
            "--map {d}/leg.map, line 1: pendulum_3 v1 has no joint 'knee'; its joints are hinge_1, hinge_2, hinge_3",
        ),
        (
            {"jump.mot": JUMP_MOT},
            ["jump.mot"],
            (
                "no column of the recording names a joint of pendulum_3 v1: its joints are hinge_1, hinge_2, "
                "hinge_3, the columns hip_flexion_r, knee_angle_r; map them with --map FILE (lines JOINT = COLUMN)"
            ),
        ),
        ({"jump.mot": JUMP_MOT}, ["jump.mot", "--map", "none.map"], "--map {d}/none.map: no such file"),
        (
            {"jump.mot": JUMP_MOT.replace("0.005\t11", "0.005\televen")},
            ["jump.mot"],
            "{d}/jump.mot, line 7: not a row of numbers: '0.005 eleven 21'",
        ),
        (
            {"jump.c3d": "not a c3d"},
            ["jump.c3d"],
            "{d}/jump.c3d: not a C3D file ezc3d reads (File must be a valid c3d file",
        ),
    ],
)
def test_what_replay_refuses_it_says_in_one_line(
    leg_server: str, tmp_path: Path, files: dict[str, str], args: list[str], message: str
) -> None:
    for name, text in files.items():
        (tmp_path / name).write_text(text, encoding="utf-8")
    named = [str(tmp_path / a) if a.endswith((".txt", ".mot", ".map", ".c3d")) else a for a in args]
    result = replay(*named, "--model", "pendulum_3", "--server", leg_server)
    assert one_line_error(result, 1).startswith(
        f"jitdyn replay: InvalidArgument: {message.format(d=tmp_path)}"
    )


def test_a_c3d_without_the_lab_extra_names_it(tmp_path: Path) -> None:
    c3d = recording_path("vicon_CMJ_kinem_kinet_emg.c3d")
    result = jitdyn(
        "replay", str(c3d), "--model", "cmj_leg", preamble="sys.modules['ezc3d'] = None  # not installed"
    )
    assert one_line_error(result, 1) == (
        "jitdyn replay: needs ezc3d (C3D files), which is not installed: pip install 'jitdyn[lab]'"
    )


def test_a_whole_recording_with_its_wild_first_frames_replays_without_numeric_warnings(
    tmp_path: Path,
) -> None:
    """biomdp's jump from its first frame (before the motion, its angles jump) on a DRIVEN
    pendulum_3 with frames lost: the forecast's probes under the wild force those frames imply
    diverge. Each is left out of the scores, and nothing but the summary reaches the terminal (a
    numpy overflow warning did)."""
    mapping = tmp_path / "pendulum.map"
    mapping.write_text("hinge_1 = AngArtHip_R.x\nhinge_2 = AngArtKnee_R.x\nhinge_3 = AngArtAnkle_R.x\n")
    result = replay(
        str(recording_path("vicon_CMJ_kinem_kinet_emg.c3d")), "--model", "pendulum_3", "--map", str(mapping),
        "--angles", "rad", "--clock", "lockstep", "--loss", "10%", "--scenario", "driven",
        "--data", str(tmp_path / "data"),
    )  # fmt: skip
    stdout = ok(result)
    assert "Warning:" not in result.stderr and "Traceback" not in result.stderr, result.stderr
    assert re.search(r"ticks +320 +measured +287 +predicted +33 ", stdout), stdout
