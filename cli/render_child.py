"""The child process of `jitdyn sessions render` (jitdyn.cli.render starts it with MUJOCO_GL set):
reads one RenderRequest as JSON on stdin, draws the session tick by tick (cli/scene.py) into an MP4,
a GIF or one PNG, and answers one JSON object on stdout: {"path", "notes"} or {"error": {"type",
"message"}}. Progress goes to stderr when it is a terminal.

    python -m jitdyn.cli.render_child < request.json
"""

from __future__ import annotations

import json
import math
import os
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np

from jitdyn.cli.render import Rendered, RenderRequest
from jitdyn.cli.scene import Caption, Pixels, SessionScene, dressed_model
from jitdyn.errors import FailedPrecondition, InvalidArgument, JitdynError, NotFound
from jitdyn.registry.store import session_model
from jitdyn.storage.db import open_index
from jitdyn.storage.index import SessionIndex, SessionRow
from jitdyn.storage.stored import read_stored
from jitdyn.storage.summary import format_counts
from jitdyn.storage.timeline import TIMELINE_COLUMNS, Timeline, session_timeline
from jitdyn.vocabulary import Source

__all__ = ["MAX_FPS", "draw", "main", "video_stride"]

# Frames a second of a video at most: an MP4 plays 30 smoothly; a GIF counts in hundredths of a
# second and stores every frame whole but for its changed box, so 12.5 (80 ms a frame) keeps a 10 s
# GIF small (docs/decisions/0180).
MAX_FPS: Final = {".mp4": 30.0, ".gif": 12.5}
# A GIF's frames are scaled by this, and drawn in one palette of this many colours, without
# dithering: unchanged pixels then stay identical from frame to frame and are not stored again.
_GIF_SCALE: Final = 0.75
_GIF_COLORS: Final = 192
# Colours of the sources, as in `sessions plot` (matplotlib's tab:blue, tab:orange, tab:green).
_COLORS: Final = {
    Source.MEASURED: (31, 119, 180),
    Source.PREDICTED: (255, 127, 14),
    Source.CORRECTED: (44, 160, 44),
}


@dataclass(frozen=True)
class _Session:
    row: SessionRow
    timeline: Timeline
    mjcf: str
    assets: dict[str, bytes]


def _load(request: RenderRequest) -> _Session:
    engine = open_index(request.index_url)
    try:
        try:
            row = SessionIndex(engine).get(request.session_id, tenant="")
        except NotFound:
            raise NotFound(
                f"no session {request.session_id!r} in {request.data_root.resolve()}; "
                "list them with `jitdyn sessions list`"
            ) from None
        _, table = read_stored(
            row, data_root=request.data_root, environ=os.environ, purpose="render", columns=TIMELINE_COLUMNS
        )
        timeline = session_timeline(table)
        if len(timeline.t) == 0:
            rejected = len(timeline.rejections.t)
            why = f"its {rejected} frames were all rejected" if rejected else "no tick was answered"
            raise FailedPrecondition(
                f"session {row.session_id} ({row.status}) is empty: {why}, nothing to render"
            )
        mjcf, assets = session_model(engine, request.data_root, row)
    finally:
        engine.dispose()
    return _Session(row=row, timeline=timeline, mjcf=mjcf, assets=assets)


def video_stride(dt: float, max_fps: float) -> int:
    """Every how many ticks a video draws one frame, so that it plays in real time at most `max_fps`."""
    return max(1, math.ceil(1.0 / (dt * max_fps) - 1e-9))


def _source(timeline: Timeline, i: int) -> tuple[str, tuple[int, int, int]]:
    """What answered tick `i`, in words, and its colour."""
    source = Source(str(timeline.source[i]))
    if timeline.corrected[i]:
        delay = float(timeline.frame_delay[i])
        late = f" {delay * 1e3:.0f} ms" if math.isfinite(delay) and delay > 0 else ""
        return f"{source}, then CORRECTED: its frame came{late} late", _COLORS[Source.CORRECTED]
    if source == Source.MEASURED:
        return "MEASURED: answered from its own frame, on time", _COLORS[source]
    if not timeline.framed[i]:
        return f"{source}: no frame for this tick (a gap)", _COLORS[source]
    return str(source), _COLORS[source]


def _caption(session: _Session, i: int) -> Caption:
    row, timeline = session.row, session.timeline
    text, color = _source(timeline, i)
    measured = timeline.frame_qpos[i]
    return Caption(
        header=(
            f"{row.model_name} v{row.model_version}  ·  {row.scenario} {row.clock}  ·  {row.status}  ·  "
            f"t {timeline.t[i]:.3f} s  ·  tick {i + 1} of {len(timeline.t)}"
        ),
        source=text,
        color=color,
        key="solid: the server's answer   ·   blue ghost: the measured frame"
        if np.isfinite(measured).all()
        else "solid: the server's answer   ·   no measured frame: no ghost",
    )


def _frames(scene: SessionScene, session: _Session, ticks: list[int]) -> Iterator[Pixels]:
    timeline = session.timeline
    answered = np.where(np.isnan(timeline.answered_qpos), 0.0, timeline.answered_qpos)
    progress = sys.stderr.isatty() and len(ticks) > 1
    for done, i in enumerate(ticks, start=1):
        yield scene.draw(answered[i], timeline.frame_qpos[i], caption=_caption(session, i))
        if progress:
            print(
                f"\rrendering: {done}/{len(ticks)} frames ({100 * done // len(ticks)}%)",
                end="",
                file=sys.stderr,
            )
    if progress:
        print(file=sys.stderr)


def _png_tick(session: _Session, frame: float | None) -> tuple[int, str]:
    t, dt = session.timeline.t, session.row.dt
    if frame is None:
        i = len(t) // 2
        return i, (
            f"the frame of tick {i + 1} at t = {t[i]:.3f} s, the middle of the session (choose another "
            f"with --frame), {_source(session.timeline, i)[0]}"
        )
    if not t[0] - dt / 2 <= frame <= t[-1] + dt / 2:
        raise InvalidArgument(
            f"--frame {frame:g}s is outside session {session.row.session_id}, whose ticks run from "
            f"{t[0]:g} s to {t[-1]:g} s"
        )
    i = int(np.argmin(np.abs(t - frame)))
    return i, f"the frame of tick {i + 1} at t = {t[i]:.3f} s, {_source(session.timeline, i)[0]}"


def _write_png(path: Path, frames: Iterator[Pixels], fps: float) -> None:
    from PIL import Image

    Image.fromarray(next(frames)).save(path, format="PNG")


def _write_gif(path: Path, frames: Iterator[Pixels], fps: float) -> None:
    from PIL import Image

    def scaled(pixels: Pixels) -> Image.Image:
        image = Image.fromarray(pixels)
        size = (round(image.width * _GIF_SCALE), round(image.height * _GIF_SCALE))
        return image.resize(size, Image.Resampling.LANCZOS)

    first = scaled(next(frames))
    # The palette of the first frame and the sources' colours, which a later caption shows.
    sample = Image.new("RGB", (first.width, first.height + 3 * 8))
    sample.paste(first)
    for i, color in enumerate(_COLORS.values()):
        sample.paste(color, (0, first.height + 8 * i, first.width, first.height + 8 * (i + 1)))
    palette = sample.quantize(colors=_GIF_COLORS, method=Image.Quantize.MEDIANCUT)

    def paletted(image: Image.Image) -> Image.Image:
        return image.quantize(palette=palette, dither=Image.Dither.NONE)

    rest = (paletted(scaled(pixels)) for pixels in frames)
    paletted(first).save(
        path,
        format="GIF",
        save_all=True,
        append_images=rest,
        duration=round(1000 / fps),
        loop=0,
        optimize=True,
    )


def _write_mp4(path: Path, frames: Iterator[Pixels], fps: float) -> None:
    import imageio_ffmpeg

    first = next(frames)
    height, width = first.shape[:2]
    writer = imageio_ffmpeg.write_frames(
        str(path), (width, height), fps=fps, codec="libx264", pix_fmt_out="yuv420p", macro_block_size=8
    )
    writer.send(None)  # start ffmpeg
    try:
        writer.send(np.ascontiguousarray(first))
        for pixels in frames:
            writer.send(np.ascontiguousarray(pixels))
    finally:
        writer.close()


_WRITERS: Final[dict[str, Callable[[Path, Iterator[Pixels], float], None]]] = {
    ".png": _write_png,
    ".gif": _write_gif,
    ".mp4": _write_mp4,
}


def _plan(request: RenderRequest, session: _Session) -> tuple[list[int], float, str]:
    """The ticks drawn, the frames a second, and what to tell the user about them."""
    suffix = request.out.suffix.lower()
    n, dt = len(session.timeline.t), session.row.dt
    if suffix == ".png":
        i, note = _png_tick(session, request.frame)
        return [i], 1.0, note
    stride = video_stride(dt, MAX_FPS[suffix])
    ticks = list(range(0, n, stride))
    fps = 1.0 / (dt * stride)
    if stride == 1:
        return ticks, fps, f"{len(ticks)} frames, one a tick, at {fps:g} frames a second (real time)"
    return (
        ticks,
        fps,
        (
            f"decimated: every {stride} ticks one frame, {len(ticks)} frames of {n} ticks, at {fps:.4g} "
            f"frames a second (real time; the caption says the source of each drawn tick)"
        ),
    )


def draw(request: RenderRequest) -> Rendered:
    """Draw the session of `request` into `request.out`, written whole or not at all."""
    session = _load(request)
    ticks, fps, note = _plan(request, session)
    try:
        timeline = session.timeline
        # Every tick, whichever are drawn: a PNG is framed as the video of the same session is.
        poses = np.concatenate([timeline.answered_qpos, timeline.frame_qpos])
        dressed, view = dressed_model(session.mjcf, session.assets, poses)
    except ValueError as error:  # MuJoCo's compile error: the registry compiled it, this copy did not
        raise FailedPrecondition(
            f"the model of session {session.row.session_id} ({session.row.model_id}) does not compile "
            f"for drawing: {' '.join(str(error).split())}"
        ) from None
    target = request.out
    tmp = target.with_name(f".{target.stem}.tmp{target.suffix}")
    try:
        with SessionScene(dressed, view=view, size=request.size) as scene:
            _WRITERS[target.suffix.lower()](tmp, _frames(scene, session, ticks), fps)
        os.replace(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)
    row = session.row
    told = (
        f"session {row.session_id}: {row.model_name} v{row.model_version}, {row.scenario} {row.clock}, "
        f"{row.status}, {' '.join(format_counts(row.summary).split())}"
    )
    return Rendered(path=target, notes=(told, note))


def _answer(request_text: str) -> dict[str, Any]:
    try:
        rendered = draw(RenderRequest.from_json(request_text))
    except JitdynError as error:
        return {"error": {"type": type(error).__name__, "message": str(error)}}
    except OSError as error:
        where = f" {error.filename}" if error.filename else ""
        return {"error": {"type": "OSError", "message": f"{error.strerror or error}:{where}"}}
    return {"path": str(rendered.path), "notes": list(rendered.notes)}


def main() -> int:
    from jitdyn.mujoco_log import route_mujoco_messages

    # The answer has stdout to itself: whatever else writes there (ffmpeg, a C library) goes to stderr.
    answer_fd = os.dup(1)
    os.dup2(2, 1)
    route_mujoco_messages()
    answer = _answer(sys.stdin.read())
    with os.fdopen(answer_fd, "w", encoding="utf-8") as out:
        out.write(json.dumps(answer) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
