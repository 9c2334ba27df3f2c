"""jitdyn's model registry: validation, content addressing, storage of MJCF and assets, built-ins.

from jitdyn.registry import ModelRegistry, ModelMetadata
with ModelRegistry(engine=engine, data_root=root) as registry:
    info, created = registry.register(name="arm", mjcf=xml, assets={"arm.stl": data})

Its names are imported on first use (PEP 562): `jitdyn.registry.limits` or `.builtins` alone, as
the command line's argument parsing needs them, do not pull in MuJoCo and SQLAlchemy.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

# Light, and named like its module: bound first, so that importing the module later keeps the name
# the function's.
from jitdyn.registry.content_id import content_id

if TYPE_CHECKING:
    from jitdyn.registry.builtins import BUILTIN_NAMES, BuiltinModel, builtin_model_path, builtin_models
    from jitdyn.registry.compile import ModelCompiler, compile_model
    from jitdyn.registry.costs import CandidateCost
    from jitdyn.registry.info import ActuatorInfo, JointInfo, ModelInfo, ModelMetadata, describe_model
    from jitdyn.registry.limits import DEFAULT_LIMITS, RegistryLimits
    from jitdyn.registry.registry import DEFAULT_PAGE_SIZE, MAX_PAGE_SIZE, ModelRegistry

_MODULE_OF = {
    "BUILTIN_NAMES": "builtins",
    "BuiltinModel": "builtins",
    "builtin_model_path": "builtins",
    "builtin_models": "builtins",
    "CandidateCost": "costs",
    "ModelCompiler": "compile",
    "compile_model": "compile",
    "ActuatorInfo": "info",
    "JointInfo": "info",
    "ModelInfo": "info",
    "ModelMetadata": "info",
    "describe_model": "info",
    "DEFAULT_LIMITS": "limits",
    "RegistryLimits": "limits",
    "DEFAULT_PAGE_SIZE": "registry",
    "MAX_PAGE_SIZE": "registry",
    "ModelRegistry": "registry",
}

__all__ = [
    "BUILTIN_NAMES",
    "DEFAULT_LIMITS",
    "DEFAULT_PAGE_SIZE",
    "MAX_PAGE_SIZE",
    "ActuatorInfo",
    "BuiltinModel",
    "CandidateCost",
    "JointInfo",
    "ModelCompiler",
    "ModelInfo",
    "ModelMetadata",
    "ModelRegistry",
    "RegistryLimits",
    "builtin_model_path",
    "builtin_models",
    "compile_model",
    "content_id",
    "describe_model",
]


def __getattr__(name: str) -> Any:
    module = _MODULE_OF.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value
