"""`jitdyn sessions render`: the sessions of tests/cli/test_plot.py (real sessions over real gRPC:
LOCKSTEP with gaps and a late frame, REALTIME, empty, FAILED) and a MyoSuite elbow, rendered by the
command as a user runs it with MuJoCo's offscreen renderer through OSMesa: PNG frames that differ,
videos with one frame a drawn tick, and one line, never a traceback, for each thing that can be wrong."""

# ruff: noqa: F811  (tests take the imported fixture `stored` by its name)
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import pytest

from jitdyn.client import Client, FrameData, SessionOptions

sys.path.insert(0, str(Path(__file__).parent))
# The sessions of test_plot.py; its `stored` fixture made once for this module too.
from test_plot import Stored, jitdyn, png_size, stored  # noqa: F401

# Renders through OSMesa take 3-10 s each: run with -m slow (README, Getting started).
pytestmark = pytest.mark.slow

PIL = pytest.importorskip("PIL.Image")


@pytest.fixture(autouse=True)
def osmesa(monkeypatch: pytest.MonkeyPatch) -> None:
    """Software GL, whatever MUJOCO_GL the machine running the tests has."""
    monkeypatch.setenv("MUJOCO_GL", "osmesa")


def render(*args: str, cwd: Path | None = None, preamble: str = "") -> subprocess.CompletedProcess[str]:
    return jitdyn("sessions", "render", *args, cwd=cwd, preamble=preamble)


def ok(result: subprocess.CompletedProcess[str]) -> subprocess.CompletedProcess[str]:
    assert result.returncode == 0, result.stdout + result.stderr
    assert "Traceback" not in result.stderr, result.stderr
    return result


def one_line_error(result: subprocess.CompletedProcess[str]) -> str:
    assert result.returncode == 1, result.stdout + result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("jitdyn sessions render: "), result.stderr
    return lines[0].removeprefix("jitdyn sessions render: ")


def pixels(path: Path) -> np.ndarray:
    with PIL.open(path) as image:
        return np.asarray(image.convert("RGB"), dtype=np.int16)


@pytest.fixture(scope="module")
def myoelbow(server: Any) -> str:
    """A PASSIVE myoelbow session of 20 ticks of 20 ms, its elbow swinging from 1.2 rad."""
    from jitdyn.client.myo import pack_myo_model

    mjcf, assets = pack_myo_model("myoelbow")
    model = mujoco.MjModel.from_xml_string(mjcf, assets)
    data = mujoco.MjData(model)
    data.qpos[:] = 1.2
    with Client(server.address, timeout=60) as client:
        client.register_model(name="myoelbow", mjcf=mjcf, assets=assets)
        options = SessionOptions(model_name="myoelbow", scenario="PASSIVE", dt=0.02)
        with client.open_session(options) as session:
            for k in range(20):
                session.send_frame(FrameData(seq=k, t=k * 0.02, qpos=data.qpos, qvel=data.qvel))
                for _ in range(10):
                    mujoco.mj_step(model, data)
            return session.opened.session_id


def test_a_png_shows_the_tick_asked_for_and_frames_differ(stored: Stored, tmp_path: Path) -> None:
    frames = {}
    for at in ("100ms", "1.5s"):
        out = tmp_path / f"{at}.png"
        result = ok(render(stored.lockstep, "--data", str(stored.data), "--out", str(out), "--frame", at))
        assert result.stdout == f"rendered {stored.lockstep} to {out}\n"
        assert png_size(out) == (640, 480)
        frames[at] = pixels(out)
    assert (
        "the frame of tick 31 at t = 1.500 s, MEASURED: answered from its own frame, on time" in result.stderr
    )
    moved = np.abs(frames["100ms"] - frames["1.5s"]).sum(axis=2) > 30
    assert 0.002 < moved.mean() < 0.5, moved.mean()  # the pendulum moved; the sky and floor did not
    sky = frames["1.5s"][:40].reshape(-1, 3).mean(axis=0)
    assert sky.min() > 120 and sky[2] > sky[0], sky  # a light blue sky, not MuJoCo's black


def test_the_caption_says_what_answered_the_tick(stored: Stored, tmp_path: Path) -> None:
    out = tmp_path / "late.png"
    # Tick 12 (t 0.6 s) was skipped, then its frame came late: PREDICTED when due, then CORRECTED.
    result = ok(render(stored.lockstep, "--data", str(stored.data), "--out", str(out), "--frame", "0.6s"))
    assert "tick 13 at t = 0.600 s, PREDICTED, then CORRECTED: its frame came late" in result.stderr
    result = ok(render(stored.lockstep, "--data", str(stored.data), "--out", str(out), "--frame", "0.5s"))
    assert "tick 11 at t = 0.500 s, PREDICTED: no frame for this tick (a gap)" in result.stderr


def test_a_gif_has_a_frame_every_drawn_tick_and_says_it_was_decimated(stored: Stored, tmp_path: Path) -> None:
    out = tmp_path / "realtime.gif"
    result = ok(render(stored.realtime, "--data", str(stored.data), "--out", str(out)))
    # Ticks of 25 ms are 40 a second; a GIF shows at most 12.5: every 4th tick, 100 ms each. (The
    # server's clock ends the session a tick or two after the 30 frames sent.)
    said = re.search(
        r"decimated: every 4 ticks one frame, (\d+) frames of (\d+) ticks, at 10 frames a second",
        result.stderr,
    )
    assert said, result.stderr
    frames, ticks = int(said[1]), int(said[2])
    assert ticks >= 30 and frames == (ticks + 3) // 4, (frames, ticks)
    with PIL.open(out) as gif:
        assert gif.n_frames == frames and gif.info["duration"] == 100
        assert gif.size == (480, 360)


def test_a_ten_second_gif_is_small(server: Any, tmp_path: Path) -> None:
    from jitdyn.registry import builtin_model_path

    model = mujoco.MjModel.from_xml_path(str(builtin_model_path("pendulum_3")))
    data = mujoco.MjData(model)
    data.qpos[:] = [0.8, -0.4, 0.3]
    options = SessionOptions(model_name="pendulum_3", scenario="PASSIVE", dt=0.05, clock="LOCKSTEP")
    with Client(server.address, timeout=60) as client, client.open_session(options) as session:
        for k in range(200):
            session.send_frame(FrameData(seq=k, t=k * 0.05, qpos=data.qpos, qvel=data.qvel))
            mujoco.mj_step(model, data, round(0.05 / model.opt.timestep))
    out = tmp_path / "ten.gif"
    ok(render(session.opened.session_id, "--data", str(server.services.data_root), "--out", str(out)))
    with PIL.open(out) as gif:
        assert gif.n_frames == 100 and gif.info["duration"] == 100, (gif.n_frames, gif.info)  # every 2nd tick
    assert out.stat().st_size < 1_000_000, out.stat().st_size


def test_an_mp4_of_a_failed_session_plays_in_real_time(stored: Stored, tmp_path: Path) -> None:
    import imageio_ffmpeg

    out = tmp_path / "failed.mp4"
    result = ok(render(stored.failed, "--data", str(stored.data), "--out", str(out)))
    assert f"session {stored.failed}: pendulum_2 v1, PASSIVE LOCKSTEP, FAILED, ticks 40" in result.stderr
    assert "40 frames, one a tick, at 20 frames a second (real time)" in result.stderr
    assert imageio_ffmpeg.count_frames_and_secs(str(out)) == (40, 2.0)
    assert os.listdir(tmp_path) == ["failed.mp4"]  # no temporary file left beside it


def test_a_myosuite_elbow_renders_with_its_meshes(myoelbow: str, stored: Stored, tmp_path: Path) -> None:
    out = tmp_path / "elbow.png"
    result = ok(render(myoelbow, "--data", str(stored.data), "--out", str(out), "--frame", "0.2s"))
    assert "myoelbow v1, PASSIVE LOCKSTEP, COMPLETE, ticks 20" in result.stderr
    image = pixels(out)[:-60]  # above the caption
    sky, floor = np.array([190, 210, 235]), image[-1].mean(axis=0)
    # The arm's bones and muscles: many pixels that are neither the sky's blue nor the floor's grey.
    body = (np.abs(image - sky).sum(axis=2) > 60) & (np.abs(image - floor).sum(axis=2) > 60)
    assert body.mean() > 0.01, body.mean()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["0e0529f0-0000-4000-8000-000000000000", "--out", "x.png"],
            r"NotFound: no session '0e0529f0-0000-4000-8000-000000000000' in \S+; list them with `jitdyn sessions list`",
        ),
        (
            ["{empty}", "--out", "x.gif"],
            r"FailedPrecondition: session {empty} \(COMPLETE\) is empty: no tick was answered, nothing to render",
        ),
        (
            ["{lockstep}", "--out", "x.jpg"],
            r"InvalidArgument: --out must name a \.mp4, \.gif, \.png file, got 'x\.jpg'",
        ),
        (
            ["{lockstep}", "--out", "x.png", "--frame", "2.5s"],
            r"InvalidArgument: --frame 2\.5s is outside session {lockstep}, whose ticks run from 0 s to 1\.95 s",
        ),
        (
            ["{lockstep}", "--out", "x.mp4", "--frame", "1s"],
            r"InvalidArgument: --frame picks the one frame of a \.png; --out x\.mp4 is a video",
        ),
    ],
)
def test_mistakes_are_one_line(stored: Stored, args: list[str], message: str, tmp_path: Path) -> None:
    ids = {"empty": stored.empty, "lockstep": stored.lockstep}
    result = render(*(a.format(**ids) for a in args), "--data", str(stored.data), cwd=tmp_path)
    line = one_line_error(result)
    assert re.fullmatch(message.format(**ids), line), line
    assert os.listdir(tmp_path) == []


def test_without_the_extra_it_names_it(stored: Stored, tmp_path: Path) -> None:
    result = render(
        stored.lockstep,
        "--data",
        str(stored.data),
        "--out",
        "x.png",
        cwd=tmp_path,
        preamble="sys.modules['PIL'] = None",
    )
    assert one_line_error(result) == (
        "needs Pillow (frames and captions), which is not installed: pip install 'jitdyn[render]'"
    )


# What a machine without libosmesa6 does: every name PyOpenGL and the command try fails to load.
NO_OSMESA = """
import ctypes
class _NoOSMesa(ctypes.CDLL):
    def __init__(self, name, *args, **kwargs):
        if name and 'OSMesa' in str(name):
            raise OSError(f'{name}: cannot open shared object file: No such file or directory')
        super().__init__(name, *args, **kwargs)
ctypes.CDLL = _NoOSMesa
"""


def test_without_libosmesa_it_names_the_debian_package(
    stored: Stored, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("MUJOCO_GL")  # the command's default, osmesa
    result = render(
        stored.lockstep, "--data", str(stored.data), "--out", "x.png", cwd=tmp_path, preamble=NO_OSMESA
    )
    assert one_line_error(result) == (
        "FailedPrecondition: rendering with MUJOCO_GL=osmesa needs libOSMesa.so, which is not installed: "
        "apt-get install libosmesa6 (Debian, Ubuntu), or --gl egl on a GPU host"
    )
    assert os.listdir(tmp_path) == []


def test_render_explains_itself() -> None:
    result = jitdyn("sessions", "render", "--help")
    assert result.returncode == 0 and "usage: jitdyn sessions render" in result.stdout
    assert "--frame T" in result.stdout and "libosmesa6" in result.stdout


@pytest.mark.parametrize(
    ("flag", "environ", "chosen"),
    [
        (None, {}, "osmesa"),
        (None, {"MUJOCO_GL": "EGL "}, "egl"),
        ("osmesa", {"MUJOCO_GL": "egl"}, "osmesa"),
        ("egl", {}, "egl"),
    ],
)
def test_the_gl_is_the_flag_then_mujoco_gl_then_osmesa(
    flag: str | None, environ: dict[str, str], chosen: str
) -> None:
    from jitdyn.cli.render import choose_gl

    assert choose_gl(flag, environ).name == chosen


def test_a_mujoco_gl_that_cannot_render_offscreen_is_named() -> None:
    from jitdyn.cli.render import choose_gl
    from jitdyn.errors import InvalidArgument

    with pytest.raises(
        InvalidArgument, match=r"^MUJOCO_GL in the environment must be osmesa or egl .*, got 'glx'$"
    ):
        choose_gl(None, {"MUJOCO_GL": "glx"})


def test_an_elbow_is_seen_in_profile_with_the_arm_before_its_skeleton() -> None:
    from jitdyn.cli.scene import session_view
    from jitdyn.client.myo import pack_myo_model
    from jitdyn.registry import builtin_model_path

    model = mujoco.MjModel.from_xml_string(*pack_myo_model("myoelbow"))
    view = session_view(model, np.linspace(0.3, 1.5, 20)[:, None])
    assert view.azimuth in (0.0, 180.0), view  # along the elbow's axis, x
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    camera_x = view.center[0] - view.distance(45.0, 4 / 3) * np.cos(np.radians(view.azimuth))
    torso = data.xpos[model.body("torso").id]
    assert abs(camera_x - view.center[0]) < abs(camera_x - torso[0]), (camera_x, view.center, torso)
    pendulum = mujoco.MjModel.from_xml_path(str(builtin_model_path("pendulum_3")))
    assert session_view(pendulum, np.zeros((2, 3))).azimuth == 90.0  # the pendulums' swing, as before
