"""A session's model drawn by MuJoCo's offscreen renderer: the answered pose solid, the measured pose
beside it as a translucent ghost (a second MjData added to the same scene), a caption below.

    with SessionScene(model, size=(640, 480)) as scene:
        pixels = scene.draw(answered_qpos, measured_qpos, caption=Caption(...))   # (height, width, 3)

Needs MUJOCO_GL set before mujoco was first imported (jitdyn.cli.render starts the process that
imports this with it set). The model is dressed for the picture only: a sky and a floor are added
when it has none, which changes no joint, body or dof.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Final, Self

import mujoco
import numpy as np
import numpy.typing as npt
from PIL import Image, ImageDraw, ImageFont

__all__ = ["Caption", "Pixels", "SessionScene", "dressed_model"]

Pixels = npt.NDArray[np.uint8]

# The ghost: the measured pose, tinted blue and mostly transparent.
GHOST_RGBA: Final = (0.25, 0.45, 1.0, 0.35)
_SKY: Final = ((0.55, 0.7, 0.88), (0.93, 0.96, 1.0))
_FLOOR: Final = ((0.78, 0.8, 0.83), (0.66, 0.69, 0.74))
_CAPTION_HEIGHT: Final = 58
_FONT_SIZE: Final = 15


def _has_skybox(spec: mujoco.MjSpec) -> bool:
    return any(texture.type == mujoco.mjtTexture.mjTEXTURE_SKYBOX for texture in spec.textures)


def _has_floor(spec: mujoco.MjSpec) -> bool:
    return any(geom.type == mujoco.mjtGeom.mjGEOM_PLANE for geom in spec.worldbody.find_all("geom"))


def dressed_model(mjcf: str, assets: Mapping[str, bytes]) -> tuple[mujoco.MjModel, mujoco.MjModel]:
    """The model as registered, and the same model with a sky and a floor where it had none (the
    floor one extent below its centre, touching nothing). Compiled from memory only."""
    spec = mujoco.MjSpec.from_string(mjcf, assets=dict(assets))
    bare = spec.compile()
    if not _has_skybox(spec):
        spec.add_texture(
            name="jitdyn_sky",
            type=mujoco.mjtTexture.mjTEXTURE_SKYBOX,
            builtin=mujoco.mjtBuiltin.mjBUILTIN_GRADIENT,
            rgb1=_SKY[0],
            rgb2=_SKY[1],
            width=256,
            height=256,
        )
    if not _has_floor(spec):
        spec.add_texture(
            name="jitdyn_floor",
            type=mujoco.mjtTexture.mjTEXTURE_2D,
            builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
            rgb1=_FLOOR[0],
            rgb2=_FLOOR[1],
            width=512,
            height=512,
        )
        material = spec.add_material(name="jitdyn_floor", texrepeat=[10, 10])
        material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "jitdyn_floor"
        extent = float(bare.stat.extent)
        spec.worldbody.add_geom(
            name="jitdyn_floor",
            type=mujoco.mjtGeom.mjGEOM_PLANE,
            size=[8 * extent, 8 * extent, 0.05],
            pos=[*bare.stat.center[:2], bare.stat.center[2] - extent],
            fromto=[math.nan] * 6,  # a default class may give geoms a fromto, which a plane refuses
            material="jitdyn_floor",
            rgba=[1, 1, 1, 1],
            contype=0,
            conaffinity=0,
            group=0,
        )
    return bare, spec.compile()


@dataclass(frozen=True)
class Caption:
    """The lines under a frame: a header, then the tick's source in its colour, then a key."""

    header: str
    source: str
    color: tuple[int, int, int]
    key: str


def _font(size: int) -> ImageFont.FreeTypeFont | ImageFont.ImageFont:
    try:
        return ImageFont.load_default(size=size)
    except (ImportError, TypeError, OSError):  # Pillow without FreeType draws its bitmap font
        return ImageFont.load_default()


class SessionScene:
    """An offscreen renderer of one model; a context manager, `close()` safe twice.

    Args:
      model: the dressed model (dressed_model), whose stat frames the camera.
      framing: the model whose stat.center and stat.extent the camera looks at (the bare model: the
        floor would widen the extent).
      size: (width, height) of a frame in pixels, caption included.
    """

    def __init__(self, model: mujoco.MjModel, *, framing: mujoco.MjModel, size: tuple[int, int]) -> None:
        width, height = size
        self._model = model
        model.vis.global_.offwidth = max(int(model.vis.global_.offwidth), width)
        model.vis.global_.offheight = max(int(model.vis.global_.offheight), height)
        self._size = (width, height - _CAPTION_HEIGHT)
        self._renderer = mujoco.Renderer(model, height=height - _CAPTION_HEIGHT, width=width)
        self._answered = mujoco.MjData(model)
        self._ghost = mujoco.MjData(model)
        self._option = mujoco.MjvOption()
        self._perturb = mujoco.MjvPerturb()
        self._camera = mujoco.MjvCamera()
        self._camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        self._camera.lookat[:] = framing.stat.center
        self._camera.distance = 2.0 * float(framing.stat.extent)
        self._camera.azimuth, self._camera.elevation = 90.0, -12.0
        # A floating base (the biped) walks away from where it started: the camera follows its root.
        self._follow = bool(np.any(model.jnt_type == mujoco.mjtJoint.mjJNT_FREE))
        self._font = _font(_FONT_SIZE)
        self._closed = False

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._renderer.close()

    def _pose(self, data: mujoco.MjData, qpos: npt.NDArray[np.float64]) -> None:
        data.qpos[:] = qpos
        mujoco.mj_fwdPosition(self._model, data)  # kinematics, tendons and muscles' paths

    def draw(
        self, qpos: npt.NDArray[np.float64], ghost: npt.NDArray[np.float64] | None, *, caption: Caption
    ) -> Pixels:
        """The frame of one tick: `qpos` (nq,) solid, `ghost` (nq,) translucent when given (and
        finite), the caption below; (height, width, 3) uint8."""
        self._pose(self._answered, qpos)
        if self._follow:
            self._camera.lookat[:2] = self._answered.subtree_com[1][:2]
        self._renderer.update_scene(self._answered, self._camera, self._option)
        if ghost is not None and np.isfinite(ghost).all():
            self._pose(self._ghost, ghost)
            scene = self._renderer.scene
            first = scene.ngeom
            mujoco.mjv_addGeoms(
                self._model, self._ghost, self._option, self._perturb, mujoco.mjtCatBit.mjCAT_DYNAMIC, scene
            )
            for k in range(first, scene.ngeom):
                scene.geoms[k].rgba[:] = GHOST_RGBA
        return self._captioned(self._renderer.render(), caption)

    def _captioned(self, pixels: Pixels, caption: Caption) -> Pixels:
        width, height = self._size
        image = Image.new("RGB", (width, height + _CAPTION_HEIGHT), (32, 34, 38))
        image.paste(Image.fromarray(pixels), (0, 0))
        draw = ImageDraw.Draw(image)
        line = _FONT_SIZE + 3
        y = height + 2
        draw.text((8, y), caption.header, fill=(210, 212, 216), font=self._font)
        draw.rectangle((8, y + line + 3, 20, y + line + 15), fill=caption.color)
        draw.text((26, y + line), caption.source, fill=(255, 255, 255), font=self._font)
        draw.text((8, y + 2 * line), caption.key, fill=(170, 190, 255), font=self._font)
        return np.asarray(image, dtype=np.uint8)
