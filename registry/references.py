"""Every file an MJCF can make MuJoCo read, checked against the request's assets before MuJoCo runs.

MuJoCo reads a file named in the MJCF from the assets given to it, and from the server's file system
when no asset matches: an untrusted MJCF could read /etc/passwd as a height field. `check_model`
parses the MJCF (defusedxml: no DTD, no entities, so no XML bombs) and every XML file it includes or
attaches, resolves each file reference as MuJoCo does (`<include file>`, `<model file>`, the `file*`
attributes of mesh, skin, hfield, flexcomp and texture, under the compiler's meshdir, texturedir,
assetdir and strippath) and requires the resolved name to be an asset. It returns the text MuJoCo
must compile: the documents as parsed here, re-serialized, so that MuJoCo's XML parser (tinyxml2)
cannot read a different file name out of the same bytes than this module checked.

MuJoCo's virtual file system matches a file by its last path part alone, ignoring ASCII case; asset
names must therefore differ in that part (`check_asset_names`).
"""

from __future__ import annotations

import dataclasses
import posixpath
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Mapping

import defusedxml
import defusedxml.ElementTree as DET

from jitdyn.errors import InvalidArgument, ResourceExhausted

__all__ = ["CheckedModel", "MissingAsset", "asset_key", "check_asset_names", "check_model"]

# tinyxml2, MuJoCo's XML parser, refuses documents nested deeper than this.
_MAX_DEPTH = 500
_MAX_ASSET_NAME = 1024
# Elements whose file attributes MuJoCo resolves under compiler meshdir (at compile time) and
# texturedir; all of them honour compiler strippath.
_MESHDIR_ELEMENTS = frozenset({"mesh", "skin", "hfield", "flexcomp"})
_TEXTUREDIR_ELEMENTS = frozenset({"texture"})
_DIR_ATTRIBUTES = ("assetdir", "meshdir", "texturedir")
_LISTED_ASSETS = 10


class MissingAsset(InvalidArgument):
    """A file reference that names no asset: `referrer` (an element, where it is) refers to
    `name`, the asset MuJoCo would read first."""

    def __init__(self, message: str, *, referrer: str, name: str) -> None:
        super().__init__(message)
        self.referrer, self.name = referrer, name


@dataclasses.dataclass(frozen=True)
class CheckedModel:
    """An MJCF whose every file reference is an asset, ready for MuJoCo.

    Attributes:
      mjcf: the main document as parsed and checked, re-serialized.
      assets: the request's assets, the XML ones it includes or attaches re-serialized likewise.
    """

    mjcf: str
    assets: dict[str, bytes]


def asset_key(name: str) -> str:
    """The key MuJoCo's virtual file system files an asset under: its last part, ASCII lower case."""
    base = name.rsplit("/", 1)[-1]
    return base.translate(_ASCII_LOWER)


_ASCII_LOWER = str.maketrans("ABCDEFGHIJKLMNOPQRSTUVWXYZ", "abcdefghijklmnopqrstuvwxyz")


def _path_problem(value: str) -> str | None:
    """Why `value` cannot name a file among the assets, or None when it can."""
    if value == "":
        return "is empty"
    if value.startswith("/"):
        return "is an absolute path; files must be assets, named by relative paths"
    if "\\" in value:
        return "contains '\\'; directories are separated by '/'"
    if ":" in value:
        return "contains ':', which MuJoCo reads as a drive or a URI scheme"
    if any(ord(char) < 0x20 or ord(char) == 0x7F for char in value):
        return "contains a control character"
    if ".." in value.split("/"):
        return "goes up a directory ('..'); files must be assets, inside the request"
    return None


def _join(*parts: str) -> str:
    """MuJoCo's path combination (user_util FilePath) for relative, checked parts: '/' between the
    non-empty parts, '.' and empty parts dropped."""
    pieces = [piece for part in parts for piece in part.split("/") if piece not in ("", ".")]
    return "/".join(pieces)


def check_asset_names(assets: Mapping[str, bytes]) -> None:
    """InvalidArgument unless every asset name is a clean relative path and no two share the part
    MuJoCo's virtual file system matches files by."""
    by_key: dict[str, str] = {}
    for name, data in assets.items():
        if not isinstance(name, str):
            raise InvalidArgument(f"asset names must be strings, got {name!r}")
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise InvalidArgument(f"asset {name!r} must be bytes, got {type(data).__name__}")
        problem = _path_problem(name)
        if problem is None and len(name) > _MAX_ASSET_NAME:
            problem = f"is {len(name)} characters long, over {_MAX_ASSET_NAME}"
        if problem is None and any(part in ("", ".") for part in name.split("/")):
            problem = "has an empty or '.' part; names are relative paths like 'meshes/arm.stl'"
        if problem is not None:
            raise InvalidArgument(f"asset name {name!r} {problem}")
        key = asset_key(name)
        if key in by_key:
            raise InvalidArgument(
                f"assets {by_key[key]!r} and {name!r} have the same file name ignoring case; MuJoCo "
                "finds an asset by its file name alone, so the file names of assets must differ"
            )
        by_key[key] = name


@dataclasses.dataclass
class _Document:
    """One parsed XML document: the main MJCF or an asset it includes or attaches."""

    source: str  # "" for the main MJCF, else the asset name
    root: ET.Element
    lines: dict[ET.Element, int]
    root_line: int

    def serialize(self) -> str:
        # Blank lines stand in for the prolog ElementTree drops, so MuJoCo's line numbers in its
        # error messages still point into the registrant's text.
        return "\n" * (self.root_line - 1) + ET.tostring(self.root, encoding="unicode")


class _LineTreeBuilder(ET.TreeBuilder):
    """A TreeBuilder that remembers each element's line and refuses tinyxml2's excess depth."""

    def __init__(self, source: str) -> None:
        super().__init__(insert_comments=True, insert_pis=True)
        self.source = source
        self.parser: DET.DefusedXMLParser | None = None
        self.lines: dict[ET.Element, int] = {}
        self.depth = 0

    def start(self, tag: str, attrs: dict[str, str]) -> ET.Element:
        self.depth += 1
        line = self.parser.parser.CurrentLineNumber if self.parser is not None else 0
        if self.depth > _MAX_DEPTH:
            raise InvalidArgument(
                f"{_describe_source(self.source)} nests elements deeper than {_MAX_DEPTH} (line {line}), "
                "more than MuJoCo's XML parser reads"
            )
        element = super().start(tag, attrs)
        self.lines[element] = line
        return element

    def end(self, tag: str) -> ET.Element:
        self.depth -= 1
        return super().end(tag)


def _describe_source(source: str) -> str:
    return "the MJCF" if source == "" else f"asset {source!r}"


def _parse(text: str | bytes, source: str) -> _Document:
    builder = _LineTreeBuilder(source)
    parser = DET.DefusedXMLParser(target=builder, forbid_dtd=True)
    builder.parser = parser
    try:
        parser.feed(text)
        root = parser.close()
    except ET.ParseError as error:
        raise InvalidArgument(f"{_describe_source(source)} is not well-formed XML: {error}") from None
    except defusedxml.DefusedXmlException as error:
        raise InvalidArgument(
            f"{_describe_source(source)} declares a DTD or entities ({type(error).__name__}); MJCF needs "
            "neither and the registry refuses them"
        ) from None
    for element in root.iter():
        if not isinstance(element.tag, str):
            continue  # comments and processing instructions
        if element.tag.startswith("{") or any(name.startswith("{") for name in element.attrib):
            raise InvalidArgument(
                f"{_describe_source(source)} uses XML namespaces (line {builder.lines.get(element, 0)}); "
                "MJCF has none"
            )
    return _Document(source=source, root=root, lines=builder.lines, root_line=builder.lines.get(root, 1))


def _tag(element: ET.Element) -> str:
    # MuJoCo compares the names of include, compiler and the root ignoring case; so does this module,
    # for every element, which can only make it check more.
    return element.tag.lower() if isinstance(element.tag, str) else ""


@dataclasses.dataclass
class _Placed:
    """An element of a model with where it came from: the document and the include's directory."""

    element: ET.Element
    document: _Document
    include_dir: str  # directory of the included file the element came from; "" in the main text


@dataclasses.dataclass
class _Dirs:
    """The compiler settings that decide where MuJoCo looks for files (last setting wins, as in
    MuJoCo's compiler section parser: assetdir sets both directories, meshdir and texturedir one)."""

    meshdir: str = ""
    texturedir: str = ""
    strippath: bool = False
    settings: dict[str, str] = dataclasses.field(default_factory=dict)


class _Checker:
    def __init__(self, assets: Mapping[str, bytes], *, max_documents: int) -> None:
        self.assets = assets
        self.max_documents = max_documents
        self.documents = 0
        self.canonical: dict[str, bytes] = {}

    # -- naming things in messages ------------------------------------------------------------

    def _where(self, placed: _Placed) -> str:
        element = placed.element
        name = element.get("name")
        what = f"{_tag(element)} {name!r}" if name else _tag(element)
        line = placed.document.lines.get(element)
        where = f"line {line}" if line else ""
        if placed.document.source:
            where = f"{where} of {placed.document.source!r}" if where else f"in {placed.document.source!r}"
        return f"{what} ({where})" if where else what

    def _listing(self) -> str:
        names = sorted(self.assets)
        if not names:
            return "the request has no assets"
        shown = ", ".join(repr(name) for name in names[:_LISTED_ASSETS])
        more = f", ... ({len(names)} in all)" if len(names) > _LISTED_ASSETS else ""
        return f"assets: {shown}{more}"

    # -- resolution ---------------------------------------------------------------------------

    def _resolve(
        self,
        placed: _Placed,
        attribute: str,
        *,
        model_dir: str,
        directory: str,
        directory_setting: str,
        strip: bool,
    ) -> str:
        """The asset an element's file attribute names, as MuJoCo resolves it; InvalidArgument when
        the reference leaves the assets."""
        value = placed.element.get(attribute, "")
        problem = _path_problem(value)
        if problem is not None:
            raise InvalidArgument(
                f"{self._where(placed)} attribute {attribute} refers to file {value!r}, which {problem}"
            )
        name = value.rsplit("/", 1)[-1] if strip else value
        # MuJoCo first looks relative to the model's directory; inside an included file it then
        # tries the included file's directory (xml_util ResolveFilePath, xml.cc IncludeXML).
        candidates = [_join(model_dir, directory, name)]
        if placed.include_dir and not strip:
            candidates += [
                _join(model_dir, directory, placed.include_dir, name),
                _join(placed.include_dir, name),
            ]
        for candidate in candidates:
            if candidate in self.assets:
                return candidate
        how = ""
        if candidates[0] != value:
            how = f" ({directory_setting} {directory!r} + {name!r})" if directory else f" (from {value!r})"
        others = [other for other in dict.fromkeys(candidates[1:]) if other != candidates[0]]
        nor = f"; nor is {' or '.join(repr(other) for other in others)}" if others else ""
        raise MissingAsset(
            f"{self._where(placed)} attribute {attribute} refers to file {candidates[0]!r}{how}, which is not "
            f"among the request's assets{nor} ({self._listing()})",
            referrer=self._where(placed),
            name=candidates[0],
        )

    def _parse_asset(self, name: str) -> _Document:
        self.documents += 1
        if self.documents > self.max_documents:
            raise ResourceExhausted(
                f"the MJCF includes or attaches XML files {self.documents - 1} times or more, over the limit "
                f"of {self.max_documents - 1} (registry setting max_assets)"
            )
        document = _parse(bytes(self.assets[name]), name)
        self.canonical[name] = document.serialize().encode("utf-8")
        return document

    def _expand(self, document: _Document, *, model_dir: str) -> list[_Placed]:
        """The model's elements in document order with its includes replaced by their content, as
        MuJoCo's IncludeXML does before it parses anything else."""
        placed: list[_Placed] = []
        included: set[str] = set()
        stack: list[_Placed] = [_Placed(document.root, document, "")]
        while stack:
            item = stack.pop()
            placed.append(item)
            if _tag(item.element) == "include" and item.element is not document.root:
                children = self._include(item, model_dir=model_dir, included=included)
            else:
                children = [
                    _Placed(child, item.document, item.include_dir)
                    for child in item.element
                    if isinstance(child.tag, str)
                ]
            stack.extend(reversed(children))
        return placed

    def _include(self, item: _Placed, *, model_dir: str, included: set[str]) -> list[_Placed]:
        if len(item.element):
            raise InvalidArgument(f"{self._where(item)} has child elements; an include must be empty")
        if "file" not in item.element.attrib:
            raise InvalidArgument(f"{self._where(item)} has no file attribute")
        name = self._resolve(
            item, "file", model_dir=model_dir, directory="", directory_setting="", strip=False
        )
        if name in included:
            raise InvalidArgument(
                f"{self._where(item)} includes {name!r} a second time; MuJoCo includes a file once"
            )
        included.add(name)
        document = self._parse_asset(name)
        # The included root is dropped; its children take the include's place.
        return [
            _Placed(child, document, posixpath.dirname(name))
            for child in document.root
            if isinstance(child.tag, str)
        ]

    def _dirs(self, placed: Iterable[_Placed]) -> _Dirs:
        dirs = _Dirs()
        for item in placed:
            if _tag(item.element) != "compiler":
                continue
            for attribute, value in item.element.attrib.items():
                lowered = attribute.lower()
                if lowered in _DIR_ATTRIBUTES:
                    problem = _path_problem(value) if value else None
                    if problem is not None:
                        raise InvalidArgument(
                            f"{self._where(item)} attribute {attribute}={value!r} {problem}"
                        )
                    dirs.settings[lowered] = value
                    if lowered == "assetdir":
                        dirs.meshdir = dirs.texturedir = value
                    elif lowered == "meshdir":
                        dirs.meshdir = value
                    else:
                        dirs.texturedir = value
                elif lowered == "strippath":
                    dirs.strippath = value.strip().lower() == "true"
        return dirs

    # -- models -------------------------------------------------------------------------------

    def check(self, document: _Document, *, model_dir: str, chain: tuple[str, ...]) -> None:
        placed = self._expand(document, model_dir=model_dir)
        dirs = self._dirs(placed)
        for item in placed:
            tag = _tag(item.element)
            if tag == "include":
                continue
            if tag == "model":
                self._child_model(item, model_dir=model_dir, chain=chain)
                continue
            for attribute in item.element.attrib:
                if not attribute.lower().startswith("file"):
                    continue
                if tag in _MESHDIR_ELEMENTS:
                    directory, setting, strip = dirs.meshdir, "compiler meshdir", dirs.strippath
                elif tag in _TEXTUREDIR_ELEMENTS:
                    directory, setting, strip = dirs.texturedir, "compiler texturedir", dirs.strippath
                else:
                    directory, setting, strip = "", "", False
                self._resolve(
                    item,
                    attribute,
                    model_dir=model_dir,
                    directory=directory,
                    directory_setting=setting,
                    strip=strip,
                )

    def _child_model(self, item: _Placed, *, model_dir: str, chain: tuple[str, ...]) -> None:
        """A `<model file>` asset: MuJoCo parses it as a model of its own, in its own directory."""
        content_type = item.element.get("content_type", "")
        if content_type not in ("", "text/xml"):
            raise InvalidArgument(
                f"{self._where(item)} has content_type {content_type!r}; the registry attaches MJCF models only"
            )
        name = self._resolve(
            item, "file", model_dir=model_dir, directory="", directory_setting="", strip=False
        )
        if name in chain:
            raise InvalidArgument(f"{self._where(item)} attaches {name!r}, which attaches itself")
        document = self._parse_asset(name)
        if _tag(document.root) != "mujoco":
            raise InvalidArgument(
                f"asset {name!r} (attached by {self._where(item)}) is a <{document.root.tag}> document; "
                "the registry attaches MJCF (<mujoco>) models only"
            )
        self.check(document, model_dir=posixpath.dirname(name), chain=(*chain, name))


def check_model(mjcf: str, assets: Mapping[str, bytes], *, max_documents: int) -> CheckedModel:
    """Check that every file `mjcf` makes MuJoCo read is one of `assets`; return what to compile.

    `assets` must have passed `check_asset_names`. `max_documents` bounds how many XML documents the
    model may make MuJoCo parse (includes and attached models, counted every time).

    Raises:
      InvalidArgument: the MJCF or an XML asset is not well-formed or not MJCF, or a file reference
        is absolute, leaves the assets or names no asset.
      ResourceExhausted: more than `max_documents` XML documents.
    """
    document = _parse(mjcf, "")
    if _tag(document.root) != "mujoco":
        raise InvalidArgument(
            f"the MJCF's root element is <{document.root.tag}>; the registry takes MJCF, whose root is <mujoco>"
        )
    checker = _Checker(assets, max_documents=max_documents + 1)
    checker.documents = 1
    checker.check(document, model_dir="", chain=())
    compiled_assets = {name: bytes(data) for name, data in assets.items()}
    compiled_assets.update(checker.canonical)
    return CheckedModel(mjcf=document.serialize(), assets=compiled_assets)
