"""jitdyn's model registry: validation, content addressing, storage of MJCF and assets, built-ins.

from jitdyn.registry import ModelRegistry, ModelMetadata
with ModelRegistry(engine=engine, data_root=root) as registry:
    info, created = registry.register(name="arm", mjcf=xml, assets={"arm.stl": data})
"""

from jitdyn.registry.builtins import BUILTIN_NAMES, BuiltinModel, builtin_model_path, builtin_models
from jitdyn.registry.compile import ModelCompiler, compile_model
from jitdyn.registry.content_id import content_id
from jitdyn.registry.info import (
    ActuatorInfo,
    JointInfo,
    ModelInfo,
    ModelMetadata,
    describe_model,
)
from jitdyn.registry.limits import DEFAULT_LIMITS, RegistryLimits
from jitdyn.registry.registry import DEFAULT_PAGE_SIZE, MAX_PAGE_SIZE, ModelRegistry

__all__ = [
    "BUILTIN_NAMES",
    "DEFAULT_LIMITS",
    "DEFAULT_PAGE_SIZE",
    "MAX_PAGE_SIZE",
    "ActuatorInfo",
    "BuiltinModel",
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
