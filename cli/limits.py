"""`jitdyn serve`'s flags for the limits that protect a server from its clients: per session
(server/runtime/limits.py) and per model and tenant (registry/limits.py). Every refusal names the
flag that raises its limit."""

from __future__ import annotations

import argparse
import re
from typing import Any

from jitdyn.registry.limits import DEFAULT_LIMITS, RegistryLimits
from jitdyn.server.runtime.limits import DEFAULT_STREAM_LIMITS, StreamLimits

__all__ = ["add_limit_arguments", "limit_settings"]

_MIB = 1024 * 1024


_SIZE = re.compile(r"^\s*([0-9]*\.?[0-9]+)\s*([kmg]?)(?:i?b)?\s*$", re.IGNORECASE)


def _bytes(text: str) -> int:
    """'64MiB', '2GiB', '512k', '1000' -> bytes."""
    match = _SIZE.match(text)
    value = int(float(match.group(1)) * 1024 ** " kmg".index(match.group(2).lower() or " ")) if match else 0
    if value < 1:
        raise argparse.ArgumentTypeError(
            f"expected a positive size like 64MiB, 2GiB or 1000000, got {text!r}"
        )
    return value


def add_limit_arguments(parser: argparse.ArgumentParser) -> None:
    stream, registry = DEFAULT_STREAM_LIMITS, DEFAULT_LIMITS
    group = parser.add_argument_group("limits per session, model and tenant")
    group.add_argument(
        "--max-history-bytes",
        type=_bytes,
        default=stream.max_history_bytes,
        help=f"memory of one session's late-frame history (default {stream.max_history_bytes // _MIB}MiB)",
    )
    group.add_argument(
        "--max-clock-offset",
        type=float,
        default=stream.max_clock_offset,
        help=f"seconds a REALTIME client's clock may be from the session's (default {stream.max_clock_offset:g})",
    )
    group.add_argument(
        "--idle-timeout",
        type=float,
        default=stream.idle_timeout,
        help=f"seconds a session may send nothing before it is ended (default {stream.idle_timeout:g})",
    )
    group.add_argument(
        "--max-tick-share",
        type=float,
        default=stream.max_tick_share,
        help="largest share of dt a REALTIME tick's estimated cost may take (default "
        f"{stream.max_tick_share:g})",
    )
    group.add_argument(
        "--compile-timeout",
        type=float,
        default=registry.compile_timeout,
        help=f"seconds a model may take to compile (default {registry.compile_timeout:g})",
    )
    group.add_argument(
        "--max-compiled-bytes",
        type=_bytes,
        default=registry.max_compiled_bytes,
        help=f"memory of one compiled model (default {registry.max_compiled_bytes // _MIB}MiB)",
    )
    group.add_argument(
        "--compile-memory-bytes",
        type=_bytes,
        default=registry.compile_memory_bytes,
        help=f"address space of a compile worker (default {registry.compile_memory_bytes // _MIB}MiB)",
    )
    group.add_argument(
        "--model-cache-bytes",
        type=_bytes,
        default=registry.cache_bytes,
        help=f"memory of the compiled models kept (default {registry.cache_bytes // _MIB}MiB)",
    )
    group.add_argument(
        "--max-models-per-tenant",
        type=int,
        default=registry.max_models_per_tenant,
        help=f"models one tenant may register (default {registry.max_models_per_tenant})",
    )
    group.add_argument(
        "--max-tenant-bytes",
        type=_bytes,
        default=registry.max_tenant_bytes,
        help=f"MJCF and asset bytes one tenant may store (default {registry.max_tenant_bytes // _MIB}MiB)",
    )


def limit_settings(args: argparse.Namespace) -> dict[str, Any]:
    """The ServerConfig fields the limit flags set."""
    return {
        "stream_limits": StreamLimits(
            max_history_bytes=args.max_history_bytes,
            max_clock_offset=args.max_clock_offset,
            idle_timeout=args.idle_timeout,
            max_tick_share=args.max_tick_share,
        ),
        "registry_limits": RegistryLimits(
            compile_timeout=args.compile_timeout,
            max_compiled_bytes=args.max_compiled_bytes,
            compile_memory_bytes=args.compile_memory_bytes,
            cache_bytes=args.model_cache_bytes,
            max_models_per_tenant=args.max_models_per_tenant,
            max_tenant_bytes=args.max_tenant_bytes,
        ),
    }
