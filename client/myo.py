"""MyoSuite models (the myo-sim package) packed for the registry: one MJCF text and the bytes of every
mesh and texture it reads, under clean relative asset names.

    mjcf, assets = pack_myo_model("myohand")
    RegisterModelRequest(name="myohand", mjcf=mjcf, assets=assets)

Static models ("myoelbow", ...) are packed from their XML files, numbers kept as written. Models
myo-sim composes with MjSpec ("myohand", ...) are written out by MuJoCo (`MjSpec.to_xml`), which
keeps 6 significant digits. Either way the registry compiles the same nq, nv, nu, na, qpos0 and body
masses as myo-sim does (tests/registry/test_myo.py).

`registrable_myo_models()` lists the models that pack and compile here, found by packing and
compiling every model myo-sim names (a minute; kept in the user's cache folder per version of
myo-sim, MuJoCo and this module).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import posixpath
import re
import sys
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, TextIO

import defusedxml.ElementTree as DET

__all__ = [
    "MyoModel",
    "myo_model_names",
    "pack_myo_model",
    "registrable_myo_models",
    "resolve_myo_name",
]

_MESHDIR_ELEMENTS = frozenset({"mesh", "skin", "hfield", "flexcomp"})
_NAMED_BY_FILE = frozenset({"mesh", "skin", "hfield", "texture"})
_DIR_ATTRIBUTES = ("assetdir", "meshdir", "texturedir")
# The default class that myo-sim's attach(prefix="") leaves unnamed in the written XML.
_UNNAMED_CLASS = "myosim_main"
_BODIES = frozenset({"body", "worldbody", "frame"})


def myo_model_names() -> list[str]:
    """The names `pack_myo_model` accepts: myo-sim's composed and static models."""
    import myo_sim

    return sorted(set(myo_sim._composed_models()) | set(myo_sim.REGISTRY))


@dataclass(frozen=True)
class MyoModel:
    """A myo-sim model that packs and compiles: its name, the other names myo-sim gives the same
    content, and its dimensions."""

    name: str
    aliases: tuple[str, ...]
    nq: int
    nv: int
    nu: int
    na: int

    def line(self) -> str:
        """One line of `jitdyn models register --myo list`."""
        also = f" (also {', '.join(self.aliases)})" if self.aliases else ""
        return f"{self.name:<18} nq={self.nq} nv={self.nv} nu={self.nu} na={self.na}{also}"


def registrable_myo_models(
    *, cache_dir: Path | None = None, progress: TextIO | None = sys.stderr
) -> list[MyoModel]:
    """The myo-sim models that pack and compile here, by name, each content once.

    Every name myo-sim knows is packed (`pack_myo_model`) and compiled by MuJoCo; names that pack
    the same content are one model, named by the shortest "myo..." name. The answer is read from
    `cache_dir` (default: $XDG_CACHE_HOME/jitdyn or ~/.cache/jitdyn) when it was found with the
    same myo-sim, MuJoCo and this module, else found now (a minute) and written there; a note goes
    to `progress` then.
    """
    directory = cache_dir or Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "jitdyn"
    cache = directory / f"myo-models-{_discovery_key()}.json"
    try:
        return [MyoModel(**{**m, "aliases": tuple(m["aliases"])}) for m in json.loads(cache.read_text())]
    except (OSError, ValueError, TypeError, KeyError):
        pass
    if progress is not None:
        print(f"finding the myo-sim models that compile (once; cached in {directory})", file=progress)
    models = _discover_myo_models()
    try:
        directory.mkdir(parents=True, exist_ok=True)
        cache.write_text(json.dumps([asdict(m) for m in models], indent=1))
    except OSError:
        pass  # an unwritable cache only costs the next call the same minute
    return models


def resolve_myo_name(text: str, *, cache_dir: Path | None = None) -> str:
    """The myo-sim name `text` means (names are matched ignoring case: "myoHand" is "myohand").

    Raises:
      ValueError: no myo-sim model is called so; the message lists those that compile.
    """
    name = text.strip().lower()
    if name in myo_model_names():
        return name
    models = registrable_myo_models(cache_dir=cache_dir)
    raise ValueError(
        f"no myo-sim model is named {text!r}; models that compile: {', '.join(m.name for m in models)} "
        "(`jitdyn models register --myo list` shows them with their other names)"
    )


def _discovery_key() -> str:
    """What the list of compiling models depends on: myo-sim's and MuJoCo's versions and this code."""
    from importlib.metadata import version

    import mujoco

    code = hashlib.sha256(Path(__file__).read_bytes()).hexdigest()[:12]
    return f"{version('myo-sim')}-{mujoco.__version__}-{code}"


def _discover_myo_models() -> list[MyoModel]:
    """Pack and compile every model myo-sim names; group the names by the content they pack."""
    import mujoco

    from jitdyn.registry import content_id

    by_content: dict[str, list[str]] = {}
    compiled: dict[str, mujoco.MjModel] = {}
    for name in myo_model_names():
        try:
            mjcf, assets = pack_myo_model(name)
            key = content_id(mjcf, assets)
            if key not in compiled:
                compiled[key] = mujoco.MjModel.from_xml_string(mjcf, assets)
        except (ValueError, RuntimeError, OSError):
            continue  # myo-sim cannot build it, it cannot be packed, or MuJoCo does not compile it
        by_content.setdefault(key, []).append(name)
    models = []
    for key, names in by_content.items():
        names.sort(key=lambda n: (not n.startswith("myo"), len(n), n))
        m = compiled[key]
        models.append(MyoModel(names[0], tuple(sorted(names[1:])), m.nq, m.nv, m.nu, m.na))
    return sorted(models, key=lambda m: m.name)


def pack_myo_model(name: str) -> tuple[str, dict[str, bytes]]:
    """The MJCF of the myo-sim model `name` (e.g. "myoelbow", "myohand") and its assets.

    Raises:
      ValueError: `name` is not a myo-sim model.
    """
    import myo_sim

    if name in myo_sim._composed_models():
        postures = myo_sim.list_postures(name)
        # myo-sim's own composition warns about attaching with an empty prefix; handled below.
        with _empty_prefix_unsaid():
            spec = myo_sim.load_spec(name, build_kwargs={"postures": True} if postures else None)
        return _pack_spec(spec, name)
    if name in myo_sim.REGISTRY:
        return _pack_file(Path(myo_sim.get_xml_path(name)))
    raise ValueError(f"no myo-sim model is named {name!r}; models: {', '.join(myo_model_names())}")


_EMPTY_PREFIX = "Attaching a spec with an empty prefix"


@contextlib.contextmanager
def _empty_prefix_unsaid() -> Iterator[None]:
    """Meanwhile, MuJoCo's warning about a spec attached with an empty prefix is not said, neither as
    a Python warning nor on the `jitdyn.mujoco` log (jitdyn.mujoco_log): packing handles it."""

    def other(record: logging.LogRecord) -> bool:
        return _EMPTY_PREFIX not in record.getMessage()

    log = logging.getLogger("jitdyn.mujoco")
    log.addFilter(other)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", _EMPTY_PREFIX, UserWarning)
            yield
    finally:
        log.removeFilter(other)


class _Assets:
    """Asset names for files on disk: one per file, its own file name where that is free.

    MuJoCo's virtual file system matches a file by its last path part, ignoring case, so no two
    assets may share it; a second file of the same name gets a numbered one.
    """

    def __init__(self) -> None:
        self.data: dict[str, bytes] = {}
        self._by_path: dict[Path, str] = {}
        self._keys: set[str] = set()

    def add(self, path: Path, folder: str) -> str:
        path = path.resolve()
        if path in self._by_path:
            return self._by_path[path]
        stem, suffix = posixpath.splitext(path.name)
        candidate, n = path.name, 1
        while candidate.lower() in self._keys:
            n += 1
            candidate = f"{stem}_{n}{suffix}"
        name = f"{folder}/{candidate}"
        self._keys.add(candidate.lower())
        self.data[name] = path.read_bytes()
        self._by_path[path] = name
        return name


def _name_from_file(element_name: str, original: str, packed: str) -> str | None:
    """The name MuJoCo gives an unnamed mesh, skin, hfield or texture: its file name without the
    extension; returned only when packing changed it."""
    if element_name:
        return None
    original_stem = posixpath.splitext(posixpath.basename(original))[0]
    return original_stem if posixpath.splitext(posixpath.basename(packed))[0] != original_stem else None


# -- static XML files ------------------------------------------------------------------------------

_COMMENT = re.compile(r"<!--(.*?)-->", re.DOTALL)


def _parse_file(path: Path) -> ET.Element:
    # Some myo-sim files have "--" inside comments, which XML forbids and MuJoCo's parser allows.
    text = _COMMENT.sub(
        lambda match: "<!--" + match.group(1).replace("--", "- -") + "-->", path.read_text("utf-8")
    )
    root: ET.Element = DET.fromstring(text)
    return root


def _pack_file(path: Path) -> tuple[str, dict[str, bytes]]:
    """Pack a static MJCF file and the files it includes, rewriting only file names and directories."""
    model_dir = path.parent
    assets = _Assets()
    root = _parse_file(path)
    # (element, directory of the file it is in), with includes expanded in document order.
    elements: list[tuple[ET.Element, Path]] = []
    included: list[tuple[str, ET.Element]] = []
    stack: list[tuple[ET.Element, Path]] = [(root, model_dir)]
    while stack:
        element, directory = stack.pop()
        elements.append((element, directory))
        children = [(child, directory) for child in element]
        if element.tag == "include":
            # MuJoCo looks beside the main file first, then beside the including file.
            file = element.get("file", "")
            disk = model_dir / file if (model_dir / file).exists() else directory / file
            name = assets.add(disk, "xml")
            del assets.data[name]  # written below, once its own references are rewritten
            element.set("file", name)
            document = _parse_file(disk)
            included.append((name, document))
            children = [(child, disk.parent) for child in document]
        stack.extend(reversed(children))
    meshdir = texturedir = ""
    for element, _ in elements:
        if element.tag == "compiler":
            if "assetdir" in element.attrib:
                meshdir = texturedir = element.get("assetdir", "")
            meshdir = element.get("meshdir", meshdir)
            texturedir = element.get("texturedir", texturedir)
            for attribute in _DIR_ATTRIBUTES:
                element.attrib.pop(attribute, None)
    for element, _ in elements:
        if element.tag in _MESHDIR_ELEMENTS or element.tag == "texture":
            file_dir, folder = (
                (meshdir, "meshes") if element.tag in _MESHDIR_ELEMENTS else (texturedir, "textures")
            )
            for attribute, value in list(element.attrib.items()):
                if attribute.startswith("file") and value:
                    packed = assets.add(model_dir / file_dir / value, folder)
                    element.set(attribute, packed)
                    if attribute == "file" and element.tag in _NAMED_BY_FILE:
                        implied = _name_from_file(element.get("name", ""), value, packed)
                        if implied:
                            element.set("name", implied)
    # Serialized only now: included documents share the rewritten elements.
    for name, document in included:
        assets.data[name] = ET.tostring(document, encoding="unicode").encode("utf-8")
    return ET.tostring(root, encoding="unicode"), assets.data


# -- models composed with MjSpec -------------------------------------------------------------------


def _pack_spec(spec: Any, name: str) -> tuple[str, dict[str, bytes]]:
    """Pack a composed MjSpec through MuJoCo's XML writer."""
    model_dir = Path(spec.modelfiledir or ".")
    assets = _Assets()
    renamed = _name_attached_main_defaults(spec, name)
    for kind, directory, folder in (
        ("meshes", spec.meshdir, "meshes"),
        ("hfields", spec.meshdir, "meshes"),
        ("skins", spec.meshdir, "meshes"),
        ("textures", spec.texturedir, "textures"),
    ):
        for element in getattr(spec, kind):
            if not element.file:
                continue
            packed = assets.add(model_dir / directory / element.file, folder)
            implied = _name_from_file(element.name, element.file, packed)
            if implied:
                element.name = implied
            element.file = packed
    spec.meshdir = ""
    spec.texturedir = ""
    spec.assets = dict(assets.data)  # to_xml compiles the spec first, from these
    with _empty_prefix_unsaid():
        mjcf = spec.to_xml()
    if renamed:
        mjcf = _class_unclassed_elements(mjcf)
    top = DET.fromstring(mjcf).find("default")
    if top is not None and any(
        "class" not in default.attrib for default in top.iter("default") if default is not top
    ):
        raise ValueError(
            f"cannot pack {name!r}: MuJoCo writes one of its default classes without a name, so the "
            "model cannot be written as one MJCF"
        )
    return mjcf, assets.data


def _name_attached_main_defaults(spec: Any, name: str) -> bool:
    """Name the "main" default class of a spec attached with an empty prefix.

    myo-sim attaches its fragments with prefix "", which leaves two default classes named "main";
    MuJoCo's writer then writes the attached one without a name and its elements without a class,
    so a reload would give them the root defaults (other contype, tendon width, ...). Named, the
    class is written; `_class_unclassed_elements` then points its elements at it. Several such
    classes cannot be told apart in the written XML: ValueError.
    """
    root = spec.default
    attached: list[Any] = []
    for kind in (
        "bodies",
        "geoms",
        "sites",
        "joints",
        "actuators",
        "meshes",
        "materials",
        "cameras",
        "lights",
    ):
        for element in getattr(spec, kind, ()):
            for attribute in ("classname", "childclass"):
                default = getattr(element, attribute, None)
                if default is None or isinstance(default, str) or default is root or default.name != "main":
                    continue
                if not any(default is seen for seen in attached):
                    attached.append(default)
    if len(attached) > 1:
        raise ValueError(
            f"cannot pack {name!r}: it attaches {len(attached)} specs with an empty prefix; MuJoCo cannot write their "
            "default classes back as one MJCF"
        )
    for default in attached:
        default.name = _UNNAMED_CLASS
    return bool(attached)


def _classable(tag: str, parent: str) -> bool:
    """Whether an element of `tag` under `parent` takes a default class."""
    return (
        (tag in {"geom", "site", "joint", "camera", "light"} and parent in _BODIES)
        or (tag in {"mesh", "material", "texture"} and parent == "asset")
        or parent in {"actuator", "equality"}
        or (tag in {"spatial", "fixed"} and parent == "tendon")
        or (tag == "pair" and parent == "contact")
    )


def _class_unclassed_elements(mjcf: str) -> str:
    """Give `_UNNAMED_CLASS` to the elements MuJoCo wrote without a class outside any childclass:
    the writer compared them with that class, so it is theirs."""
    root = DET.fromstring(mjcf)
    stack: list[tuple[ET.Element, bool]] = [(root, False)]
    while stack:
        element, inherits = stack.pop()
        for child in element:
            if child.tag == "default":
                continue
            if not inherits and "class" not in child.attrib and _classable(child.tag, element.tag):
                child.set("class", _UNNAMED_CLASS)
            stack.append((child, inherits or "childclass" in child.attrib))
    return ET.tostring(root, encoding="unicode")
