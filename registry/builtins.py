"""The built-in models: the MJCF files of models/, found in a checkout and in an installed wheel
(where pyproject.toml installs models/ as the package jitdyn.models)."""

from __future__ import annotations

import dataclasses
import importlib.resources
import re
from pathlib import Path

__all__ = ["BUILTIN_NAMES", "BuiltinModel", "builtin_model_path", "builtin_models"]

# name -> the family tag; the order is the order of registration.
_FAMILIES = {
    "pendulum_1": "pendulum",
    "pendulum_2": "pendulum",
    "pendulum_3": "pendulum",
    "biped": "biped",
}
BUILTIN_NAMES = tuple(_FAMILIES)
_COMMENT = re.compile(r"<!--(.*?)-->", re.DOTALL)


@dataclasses.dataclass(frozen=True, kw_only=True)
class BuiltinModel:
    """A built-in model: its MJCF, and the description its leading XML comment gives."""

    name: str
    mjcf: str
    description: str
    tags: tuple[str, ...]


def builtin_model_path(name: str) -> Path:
    """The MJCF file of the built-in model `name` (e.g. "pendulum_3"), installed or in the checkout."""
    if name not in _FAMILIES:
        raise ValueError(f"no built-in model is named {name!r}; built-in models: {', '.join(_FAMILIES)}")
    filename = f"{name}.xml"
    try:
        resource = importlib.resources.files("jitdyn.models").joinpath(filename)
        if isinstance(resource, Path) and resource.is_file():
            return resource
    except ModuleNotFoundError:
        pass  # a checkout that is not installed
    return Path(__file__).resolve().parents[1] / "models" / filename


def _description(name: str, mjcf: str) -> str:
    match = _COMMENT.search(mjcf)
    text = " ".join(match.group(1).split()) if match else ""
    text = text.removeprefix(f"{name}:").strip()
    return text[:1].upper() + text[1:]


def builtin_models() -> list[BuiltinModel]:
    """Every built-in model, read from its file."""
    models = []
    for name, family in _FAMILIES.items():
        mjcf = builtin_model_path(name).read_text(encoding="utf-8")
        models.append(
            BuiltinModel(name=name, mjcf=mjcf, description=_description(name, mjcf), tags=("builtin", family))
        )
    return models
