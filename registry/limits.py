"""What the registry accepts: the size, compile-time and state-dimension limits on a model.

    limits = RegistryLimits(max_mjcf_bytes=1 << 20, compile_timeout=5.0)
    registry = ModelRegistry(engine=engine, data_root=root, limits=limits)

Going over a limit raises `jitdyn.errors.ResourceExhausted` with a message that names the value, the
limit and the setting (the field below), so an operator knows what to raise.
"""

from __future__ import annotations

import dataclasses
import math

from jitdyn.errors import ResourceExhausted
from jitdyn.settings import DEFAULTS

__all__ = [
    "DEFAULT_COMPILE_TIMEOUT",
    "DEFAULT_LIMITS",
    "DEFAULT_MAX_ASSETS",
    "DEFAULT_MAX_ASSET_BYTES",
    "DEFAULT_MAX_MJCF_BYTES",
    "DEFAULT_MAX_NV",
    "RegistryLimits",
]

DEFAULT_MAX_MJCF_BYTES = 8 * 1024 * 1024
DEFAULT_MAX_ASSETS = 1000
DEFAULT_MAX_ASSET_BYTES = 64 * 1024 * 1024
DEFAULT_COMPILE_TIMEOUT = DEFAULTS.compile_timeout
DEFAULT_MAX_NV = 500
# The limits `jitdyn serve` has a flag for: their defaults are those settings' (jitdyn.settings).
DEFAULT_MAX_COMPILED_BYTES = DEFAULTS.max_compiled_bytes
DEFAULT_COMPILE_MEMORY_BYTES = DEFAULTS.compile_memory_bytes
DEFAULT_CACHE_BYTES = DEFAULTS.model_cache_bytes
DEFAULT_MAX_MODELS_PER_TENANT = DEFAULTS.max_models_per_tenant
DEFAULT_MAX_TENANT_BYTES = DEFAULTS.max_tenant_bytes


# The `jitdyn serve` flags of the limits that have one (jitdyn.settings, group LIMITS).
_FLAGS = {
    "compile_timeout": "--compile-timeout",
    "max_compiled_bytes": "--max-compiled-bytes",
    "compile_memory_bytes": "--compile-memory-bytes",
    "cache_bytes": "--model-cache-bytes",
    "max_models_per_tenant": "--max-models-per-tenant",
    "max_tenant_bytes": "--max-tenant-bytes",
}


@dataclasses.dataclass(frozen=True, kw_only=True)
class RegistryLimits:
    """Limits on one registered model.

    Attributes:
      max_mjcf_bytes: size of the MJCF text, UTF-8 encoded, in bytes.
      max_assets: number of assets (meshes, textures, included XML, ...).
      max_asset_bytes: total size of the assets' contents, in bytes.
      compile_timeout: wall time MuJoCo may spend compiling the model, in seconds.
      max_nv: degrees of freedom (the size of qvel); the estimator's state grows with it.
      max_compiled_bytes: memory of one compiled model (mj_sizeModel), in bytes: a few bytes of MJCF
        can ask for a huge height field (--max-compiled-bytes).
      compile_memory_bytes: address space of a compile worker process (RLIMIT_AS), in bytes
        (--compile-memory-bytes).
      cache_bytes: memory of the compiled models a server keeps, least recently used dropped first,
        in bytes (--model-cache-bytes).
      max_models_per_tenant: models (versions) one tenant may register (--max-models-per-tenant).
      max_tenant_bytes: MJCF and asset bytes one tenant may store (--max-tenant-bytes).
    """

    max_mjcf_bytes: int = DEFAULT_MAX_MJCF_BYTES
    max_assets: int = DEFAULT_MAX_ASSETS
    max_asset_bytes: int = DEFAULT_MAX_ASSET_BYTES
    compile_timeout: float = DEFAULT_COMPILE_TIMEOUT
    max_nv: int = DEFAULT_MAX_NV
    max_compiled_bytes: int = DEFAULT_MAX_COMPILED_BYTES
    compile_memory_bytes: int = DEFAULT_COMPILE_MEMORY_BYTES
    cache_bytes: int = DEFAULT_CACHE_BYTES
    max_models_per_tenant: int = DEFAULT_MAX_MODELS_PER_TENANT
    max_tenant_bytes: int = DEFAULT_MAX_TENANT_BYTES

    def __post_init__(self) -> None:
        for field in (
            "max_mjcf_bytes",
            "max_assets",
            "max_asset_bytes",
            "max_nv",
            "max_compiled_bytes",
            "compile_memory_bytes",
            "cache_bytes",
            "max_models_per_tenant",
            "max_tenant_bytes",
        ):
            value = getattr(self, field)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"RegistryLimits.{field} must be a positive integer, got {value!r}")
        timeout = self.compile_timeout
        if (
            isinstance(timeout, bool)
            or not isinstance(timeout, (int, float))
            or not (math.isfinite(timeout) and timeout > 0)
        ):
            raise ValueError(
                f"RegistryLimits.compile_timeout must be a positive number of seconds, got {timeout!r}"
            )

    def check(self, setting: str, what: str, value: int, unit: str = "") -> None:
        """Raise ResourceExhausted when `value` is over the limit `setting` (a field name)."""
        limit = getattr(self, setting)
        if value > limit:
            flag = f", {_FLAGS[setting]}" if setting in _FLAGS else ""
            raise ResourceExhausted(
                f"{what} is {value}{unit}, over the limit of {limit}{unit} (registry setting {setting}{flag})"
            )


DEFAULT_LIMITS = RegistryLimits()
