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

__all__ = ["Caption", "Pixels", "SessionScene", "View", "dressed_model", "session_view"]

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


@dataclass(frozen=True)
class View:
    """Where the camera looks: the box (centre, half sizes, m) the moving bodies stay in over the
    session, and the height of the lowest geom (m), for a floor. With a floating base the centre is
    relative to the root's (x, y), which the camera follows."""

    center: npt.NDArray[np.float64]  # (3,)
    half: npt.NDArray[np.float64]  # (3,)
    lowest: float
    follow: bool
    # MuJoCo's camera azimuth (degrees): 90 looks along +y; 0 and 180 along +x and -x.
    azimuth: float = 90.0

    @property
    def radius(self) -> float:
        return float(np.linalg.norm(self.half))

    def distance(self, fovy_degrees: float, aspect: float) -> float:
        """How far the camera must stand for the box to fill most of its frame."""
        across, depth = (self.half[0], self.half[1]) if self.azimuth == 90.0 else (self.half[1], self.half[0])
        tan_y = math.tan(math.radians(fovy_degrees) / 2)
        fit = max(self.half[2] / tan_y, across / (tan_y * aspect))
        return 1.15 * float(fit) + 0.5 * float(depth)


def _moving(model: mujoco.MjModel) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.intp]]:
    """(ngeom,) the geoms of bodies that have a joint or hang from one that has, and the bodies
    those hang from, whose origins (a shoulder for an elbow) the view includes: the motion is seen
    against them. Their geoms are left out: a skeleton's whole torso would dwarf a hand."""
    moving = np.zeros(model.nbody, dtype=bool)
    for body in range(1, model.nbody):  # a parent's index is below its children's
        moving[body] = model.body_jntnum[body] > 0 or moving[model.body_parentid[body]]
    anchors = np.unique(model.body_parentid[moving])
    return np.asarray(moving[model.geom_bodyid], dtype=bool), anchors[(anchors > 0) & ~moving[anchors]]


def session_view(model: mujoco.MjModel, poses: npt.NDArray[np.float64], *, samples: int = 500) -> View:
    """The view of the bodies moving through `poses` (k, nq), up to `samples` of them evenly spread."""
    follow = bool(np.any(model.jnt_type == mujoco.mjtJoint.mjJNT_FREE))
    moving, anchors = _moving(model)
    moving &= model.geom_type != mujoco.mjtGeom.mjGEOM_PLANE
    solid = model.geom_type != mujoco.mjtGeom.mjGEOM_PLANE
    data = mujoco.MjData(model)
    poses = poses[np.isfinite(poses).all(axis=1)]
    chosen = poses[np.linspace(0, len(poses) - 1, min(samples, len(poses))).astype(int)] if len(poses) else []
    lows, highs, bottoms = [], [], []  # per pose: the moving geoms' box, the lowest geom
    reach = model.geom_rbound[:, None]
    for qpos in [model.qpos0, *chosen]:
        data.qpos[:] = qpos
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        shift = np.array([*data.subtree_com[1][:2], 0.0]) if follow else np.zeros(3)
        if moving.any():
            points = np.concatenate([data.geom_xpos[moving] - reach[moving], data.xpos[anchors]])
            lows.append((points - shift).min(axis=0))
            points = np.concatenate([data.geom_xpos[moving] + reach[moving], data.xpos[anchors]])
            highs.append((points - shift).max(axis=0))
        if solid.any():
            bottoms.append(float((data.geom_xpos[solid, 2] - model.geom_rbound[solid]).min()))
    if not moving.any():  # nothing moves: the whole model, as MuJoCo frames it
        center, half = np.asarray(model.stat.center, dtype=np.float64), np.full(3, float(model.stat.extent))
    else:
        # A few diverged predictions far away must not shrink the body to a dot: 1 % of the poses
        # may leave the frame when there are a hundred or more.
        cut = 1.0 if len(lows) >= 100 else 0.0
        lo, hi = np.percentile(lows, cut, axis=0), np.percentile(highs, 100 - cut, axis=0)
        center, half = (lo + hi) / 2, np.maximum((hi - lo) / 2, 1e-3)
    lowest = float(np.percentile(bottoms, 1.0 if len(bottoms) >= 100 else 0.0)) if bottoms else math.nan
    lowest = lowest if np.isfinite(lowest) else float(center[2] - half[2])
    return View(center=center, half=half, lowest=lowest, follow=follow, azimuth=_azimuth(model, center))


def _azimuth(model: mujoco.MjModel, center: npt.NDArray[np.float64]) -> float:
    """Look along the hinges' axes, where the motion is seen in profile: along y (the pendulums',
    the biped's) unless they point along x (a MyoSuite elbow's); then from the side the moving
    bodies are on, so that they stand in front of the rest (the arm before its skeleton's torso)."""
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    hinges = model.jnt_type == mujoco.mjtJoint.mjJNT_HINGE
    axes = np.abs(data.xaxis[hinges]).sum(axis=0)
    if not (hinges.any() and axes[0] > axes[1] and axes[0] > axes[2]):
        return 90.0
    moving, _ = _moving(model)
    still = ~moving & (model.geom_type != mujoco.mjtGeom.mjGEOM_PLANE)
    rest = float(data.geom_xpos[still, 0].mean()) if still.any() else float(center[0])
    return 0.0 if center[0] < rest else 180.0


def _add_sky(spec: mujoco.MjSpec) -> None:
    spec.add_texture(
        name="jitdyn_sky",
        type=mujoco.mjtTexture.mjTEXTURE_SKYBOX,
        builtin=mujoco.mjtBuiltin.mjBUILTIN_GRADIENT,
        rgb1=_SKY[0],
        rgb2=_SKY[1],
        width=256,
        height=256,
    )


def _add_floor(spec: mujoco.MjSpec, view: View) -> None:
    spec.add_texture(
        name="jitdyn_floor",
        type=mujoco.mjtTexture.mjTEXTURE_2D,
        builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
        rgb1=_FLOOR[0],
        rgb2=_FLOOR[1],
        width=512,
        height=512,
    )
    # Squares of a fifth of the box's size, however large the floor.
    repeat = 2.5 / max(float(view.half.max()), 1e-3)
    material = spec.add_material(name="jitdyn_floor", texrepeat=[repeat, repeat], texuniform=True)
    material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "jitdyn_floor"
    spec.worldbody.add_geom(
        name="jitdyn_floor",
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        size=[100 * view.radius, 100 * view.radius, 0.05],
        pos=[*view.center[:2], view.lowest - 0.25 * view.radius],
        fromto=[math.nan] * 6,  # a default class may give geoms a fromto, which a plane refuses
        material="jitdyn_floor",
        rgba=[1, 1, 1, 1],
        contype=0,
        conaffinity=0,
        group=0,
    )


def _add_sun(spec: mujoco.MjSpec) -> None:
    """A light from high above for the whole floor: a model's own spot lights light its bodies
    only, and the floor beyond them went black."""
    spec.worldbody.add_light(
        name="jitdyn_sun",
        type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
        dir=[0.0, 0.4, -1.0],
        diffuse=[0.45, 0.45, 0.45],
        specular=[0.05, 0.05, 0.05],
        castshadow=False,
    )


def _has_sun(spec: mujoco.MjSpec) -> bool:
    return any(light.type == mujoco.mjtLightType.mjLIGHT_DIRECTIONAL for light in spec.lights)


def dressed_model(
    mjcf: str, assets: Mapping[str, bytes], poses: npt.NDArray[np.float64]
) -> tuple[mujoco.MjModel, View]:
    """The model with a sky and a floor where it had none (below its lowest geom over `poses`
    (k, nq), touching nothing), and the view of its moving bodies. Compiled from memory only."""
    # Included XML files are assets to the registry, `include` to MjSpec.
    included = {name: data for name, data in assets.items() if name.lower().endswith(".xml")}
    spec = mujoco.MjSpec.from_string(mjcf, include=included, assets=dict(assets))
    view = session_view(spec.compile(), poses)
    if not _has_skybox(spec):
        _add_sky(spec)
    if not _has_floor(spec):
        _add_floor(spec, view)
    if not _has_sun(spec):
        _add_sun(spec)
    return spec.compile(), view


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
      model: the dressed model (dressed_model).
      view: what the camera frames (dressed_model, session_view).
      size: (width, height) of a frame in pixels, caption included.
    """

    def __init__(self, model: mujoco.MjModel, *, view: View, size: tuple[int, int]) -> None:
        width, height = size
        self._model = model
        model.vis.global_.offwidth = max(int(model.vis.global_.offwidth), width)
        model.vis.global_.offheight = max(int(model.vis.global_.offheight), height)
        # A 1024 shadow map looks the same at this size as MuJoCo's default 4096, and OSMesa draws a
        # frame about 1.4 times as fast with it (median of 4 rounds, pendulum_3, loaded 2-core host).
        model.vis.quality.shadowsize = min(int(model.vis.quality.shadowsize), 1024)
        self._size = (width, height - _CAPTION_HEIGHT)
        self._renderer = mujoco.Renderer(model, height=height - _CAPTION_HEIGHT, width=width)
        self._answered = mujoco.MjData(model)
        self._ghost = mujoco.MjData(model)
        self._option = mujoco.MjvOption()
        self._perturb = mujoco.MjvPerturb()
        self._camera = mujoco.MjvCamera()
        self._camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        self._camera.lookat[:] = view.center
        aspect = self._size[0] / self._size[1]
        self._camera.distance = view.distance(float(model.vis.global_.fovy), aspect)
        self._camera.azimuth, self._camera.elevation = view.azimuth, -12.0
        # A floating base (the biped) walks away from where it started: the camera follows its root.
        self._view = view
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
        if self._view.follow:
            self._camera.lookat[:2] = self._view.center[:2] + self._answered.subtree_com[1][:2]
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
