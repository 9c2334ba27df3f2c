"""`jitdyn sessions render ID --out FILE`: one stored session replayed by MuJoCo's offscreen
renderer, as an MP4, a GIF or one PNG frame, the answered pose solid and the measured one a ghost.

    rendered = render_session(RenderRequest(session_id=sid, data_root=root, index_url=url, out=Path("s.mp4")))
    rendered.path, rendered.notes

MuJoCo chooses its GL backend (MUJOCO_GL) once, when it is first imported, and the CLI has imported
it long before: the frames are drawn by a child process (jitdyn.cli.render_child) started with MUJOCO_GL
set, after this module has checked the system library it needs. Why: docs/decisions/0131-session-render.md.
"""

from __future__ import annotations

import ctypes
import dataclasses
import json
import os
import subprocess
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from jitdyn import errors
from jitdyn.cli.extras import require_extra
from jitdyn.errors import FailedPrecondition, InvalidArgument, JitdynError

__all__ = ["FORMATS", "GL_BACKENDS", "GlBackend", "RenderRequest", "Rendered", "choose_gl", "render_session"]

FORMATS: Final = (".mp4", ".gif", ".png")


@dataclass(frozen=True)
class GlBackend:
    """An offscreen GL backend of MuJoCo on Linux: the shared library it opens, and the Debian
    package that installs it."""

    name: str
    libraries: tuple[str, ...]
    package: str


GL_BACKENDS: Final = {
    backend.name: backend
    for backend in (
        # PyOpenGL opens these names, in this order (OpenGL/platform/ctypesloader.py).
        GlBackend("osmesa", ("libOSMesa.so", "libOSMesa.so.8", "libOSMesa.so.6"), "libosmesa6"),
        GlBackend("egl", ("libEGL.so", "libEGL.so.1"), "libegl1"),
    )
}
DEFAULT_GL: Final = "osmesa"


@dataclass(frozen=True)
class RenderRequest:
    """What to render, as the child process receives it (JSON).

    `frame` is the time of the one frame a PNG shows (s, on the session's clock; None: the middle of
    the session); `size` is (width, height) in pixels.
    """

    session_id: str
    data_root: Path
    index_url: str
    out: Path
    frame: float | None = None
    size: tuple[int, int] = (640, 480)

    def to_json(self) -> str:
        values = dataclasses.asdict(self)
        values["data_root"], values["out"] = str(self.data_root), str(self.out)
        return json.dumps(values)

    @classmethod
    def from_json(cls, text: str) -> RenderRequest:
        values = json.loads(text)
        values["data_root"], values["out"] = Path(values["data_root"]), Path(values["out"])
        values["size"] = tuple(values["size"])
        return cls(**values)


@dataclass(frozen=True)
class Rendered:
    """What was written: the file, and the lines that tell the user what they see."""

    path: Path
    notes: tuple[str, ...]


def choose_gl(requested: str | None, environ: Mapping[str, str]) -> GlBackend:
    """The backend: --gl, else an existing MUJOCO_GL, else osmesa (software, any machine)."""
    name = requested or environ.get("MUJOCO_GL", "").strip().lower() or DEFAULT_GL
    if name not in GL_BACKENDS:
        where = "--gl" if requested else "MUJOCO_GL in the environment"
        raise InvalidArgument(
            f"{where} must be {' or '.join(GL_BACKENDS)} (offscreen rendering), got {name!r}"
        )
    return GL_BACKENDS[name]


def _check_library(backend: GlBackend) -> None:
    for library in backend.libraries:
        try:
            ctypes.CDLL(library)
        except OSError:
            continue
        return
    other = "--gl egl on a GPU host" if backend.name == "osmesa" else "--gl osmesa"
    raise FailedPrecondition(
        f"rendering with MUJOCO_GL={backend.name} needs {backend.libraries[0]}, which is not installed: "
        f"apt-get install {backend.package} (Debian, Ubuntu), or {other}"
    )


def _check_out(out: Path, frame: float | None) -> None:
    suffix = out.suffix.lower()
    if suffix not in FORMATS:
        raise InvalidArgument(f"--out must name a {', '.join(FORMATS)} file, got {out.name!r}")
    if frame is not None and suffix != ".png":
        raise InvalidArgument(f"--frame picks the one frame of a .png; --out {out.name} is a video")
    if not out.parent.is_dir():
        raise InvalidArgument(f"the folder of --out {out} does not exist")
    require_extra("PIL", what="Pillow (frames and captions)", extra="render")
    if suffix == ".mp4":
        require_extra("imageio_ffmpeg", what="imageio-ffmpeg (MP4 video)", extra="render")


def _raise(error: Mapping[str, Any]) -> None:
    """Raise again, in this process, the error the child process answered with."""
    if error["type"] == "OSError":
        raise OSError(str(error["message"]))
    kind = getattr(errors, str(error["type"]), None)
    if isinstance(kind, type) and issubclass(kind, JitdynError):
        raise kind(str(error["message"]))
    raise RuntimeError(f"{error['type']}: {error['message']}")


def render_session(
    request: RenderRequest, *, gl: str | None = None, environ: Mapping[str, str] | None = None
) -> Rendered:
    """Render the session to `request.out` (.mp4, .gif or .png) in a child process; `gl` the backend.

    Raises InvalidArgument for a bad --out, --frame or --gl, MissingExtra without jitdyn[render],
    FailedPrecondition without the GL library (naming its package) or for a session with no tick,
    NotFound for an unknown session.
    """
    environ = os.environ if environ is None else environ
    _check_out(request.out, request.frame)
    backend = choose_gl(gl, environ)
    _check_library(backend)
    child = dict(environ)
    # Both are read once, at import: MuJoCo's context and PyOpenGL's platform must agree.
    child["MUJOCO_GL"] = child["PYOPENGL_PLATFORM"] = backend.name
    done = subprocess.run(
        [sys.executable, "-m", "jitdyn.cli.render_child"],
        input=request.to_json(),
        stdout=subprocess.PIPE,  # the answer, as JSON; progress and MuJoCo's own errors go to stderr
        text=True,
        env=child,
        check=False,
    )
    answer = json.loads(done.stdout) if done.stdout.strip() else None
    if done.returncode != 0 or answer is None:
        raise RuntimeError(f"the render process ended with exit code {done.returncode}")
    if "error" in answer:
        _raise(answer["error"])
    return Rendered(path=Path(answer["path"]), notes=tuple(answer["notes"]))
