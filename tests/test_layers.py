"""The layering of docs/architecture.md (The parts), read from the imports of the installed `jitdyn` package.

    cli > experiments > client > server (transport > runtime > estimation) > registry, storage
        > jitdyn.v1, jitdyn.errors, jitdyn.checksum
    compliance > jitdyn.v1 (the conformance suite speaks the contract only: no server, no SDK)

Every import statement counts, those inside functions too: a lazy import is still a dependency.
The modules are found through the installed package (`jitdyn.__path__` and its subpackages), so
this checks what `pip install` put on the path, not the folders of the checkout.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import pkgutil
from collections.abc import Iterator
from pathlib import Path

import pytest

import jitdyn

# The layer of each module prefix; the longest prefix wins.
LAYERS = {
    "jitdyn": "contract",
    "jitdyn.v1": "contract",
    "jitdyn.models": "contract",
    "jitdyn.registry": "registry",
    "jitdyn.storage": "storage",
    "jitdyn.server": "server",
    "jitdyn.server.estimation": "estimation",
    "jitdyn.server.runtime": "runtime",
    "jitdyn.server.transport": "transport",
    "jitdyn.client": "client",
    "jitdyn.experiments": "experiments",
    "jitdyn.cli": "cli",
    "jitdyn.compliance": "compliance",
}
_BELOW_SERVER = {"contract", "registry", "storage"}
# What each layer may import of ours (besides itself).
ALLOWED = {
    "contract": {"contract"},
    "registry": {"contract", "storage"},  # its `models` table lives in storage's one SQL schema
    "storage": {"contract"},
    "estimation": {"contract"},
    "runtime": _BELOW_SERVER | {"estimation"},
    "transport": _BELOW_SERVER | {"estimation", "runtime"},
    "server": _BELOW_SERVER | {"estimation", "runtime", "transport"},
    "client": {"contract", "registry"},
    "experiments": _BELOW_SERVER | {"server", "estimation", "runtime", "transport", "client"},
    "cli": set(LAYERS.values()),
    "compliance": {"contract"},
}
# Third-party packages a layer must not import: estimation and the runtime know nothing of the wire.
FORBIDDEN_EXTERNAL = {
    "estimation": ("grpc", "google.protobuf"),
    "runtime": ("grpc", "google.protobuf"),
}


def layer_of(module: str) -> str | None:
    best = None
    for prefix in LAYERS:
        if (module == prefix or module.startswith(prefix + ".")) and (
            best is None or len(prefix) > len(best)
        ):
            best = prefix
    return None if best is None else LAYERS[best]


def installed_modules() -> dict[str, Path]:
    """Every module of the installed `jitdyn` and its source file, generated code included.

    Walked from each subpackage's own `__path__`: an editable install maps them to folders of the
    checkout that are not under src/jitdyn, so a walk of `jitdyn.__path__` alone would miss them.
    """
    found = {"jitdyn": Path(str(jitdyn.__file__))}
    for package in LAYERS:
        spec = importlib.util.find_spec(package)
        assert spec is not None and spec.origin is not None, f"{package} is not installed"
        found[package] = Path(spec.origin)
        paths = spec.submodule_search_locations or []
        for info in pkgutil.walk_packages(list(paths), prefix=package + "."):
            if info.name.endswith("__main__"):
                continue
            sub = importlib.util.find_spec(info.name)
            assert sub is not None and sub.origin is not None, info.name
            found[info.name] = Path(sub.origin)
    return found


def imports_of(module: str, path: Path) -> Iterator[tuple[str, int]]:
    """(imported module, line) for every import in `path`, relative ones resolved. A compiled
    module (the native engine) has no Python source to read: it imports nothing of ours."""
    if path.suffix != ".py":
        return
    is_package = path.name == "__init__.py"
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".") if is_package else module.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            yield target, node.lineno
            for alias in node.names:  # `from jitdyn.v1 import dynamics_pb2` imports a module
                yield f"{target}.{alias.name}", node.lineno


MODULES = installed_modules()


def test_the_installed_package_is_the_whole_tree() -> None:
    # Guard against a walk that silently finds nothing (a broken finder would make the rest vacuous).
    for expected in (
        "jitdyn.cli.main",
        "jitdyn.server.estimation.ukf",
        "jitdyn.server.transport.app",
        "jitdyn.client._client",
        "jitdyn.experiments.definitions",
        "jitdyn.storage.recorder",
        "jitdyn.registry.registry",
        "jitdyn.v1.dynamics_pb2",
        "jitdyn.compliance.streaming",
    ):
        assert expected in MODULES
    assert all(layer_of(name) is not None for name in MODULES)


def violations() -> list[str]:
    found = []
    for module, path in sorted(MODULES.items()):
        layer = layer_of(module)
        assert layer is not None
        for target, line in imports_of(module, path):
            where = f"{module} (line {line}) imports {target}"
            if target == "jitdyn" or target.startswith("jitdyn."):
                if target not in MODULES and target.rsplit(".", 1)[0] in MODULES:
                    continue  # `from pkg import name` where name is not a module
                other = layer_of(target)
                if other is not None and other != layer and other not in ALLOWED[layer]:
                    found.append(f"{where}: {layer} may not import {other}")
            for banned in FORBIDDEN_EXTERNAL.get(layer, ()):
                if target == banned or target.startswith(banned + "."):
                    found.append(f"{where}: {layer} may not import {banned}")
    return found


def test_layers_import_downwards_only() -> None:
    assert violations() == []


def test_no_import_cycles() -> None:
    graph: dict[str, set[str]] = {name: set() for name in MODULES}
    for module, path in MODULES.items():
        for target, _ in imports_of(module, path):
            if target in MODULES and target != module:
                graph[module].add(target)
    # A package's __init__ re-exporting its own modules is not a cycle of design; drop those edges.
    for module, targets in graph.items():
        graph[module] = {t for t in targets if not module.startswith(t + ".")}
    cycles = _strongly_connected(graph)
    assert cycles == [], f"import cycles: {cycles}"


def _strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's algorithm; the components with more than one module."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    result: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in graph[node]:
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                top = stack.pop()
                on_stack.discard(top)
                component.append(top)
                if top == node:
                    break
            if len(component) > 1:
                result.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return result


@pytest.mark.parametrize(
    ("module", "source", "expected"),
    [
        (
            "jitdyn.storage.index",
            "from jitdyn.server.runtime.session import SessionRuntime",
            "storage may not import runtime",
        ),
        ("jitdyn.registry.info", "import jitdyn.client._client", "registry may not import client"),
        ("jitdyn.server.estimation.ukf", "import grpc", "estimation may not import grpc"),
        (
            "jitdyn.server.estimation.ukf",
            "from jitdyn.server.transport import status",
            "estimation may not import transport",
        ),
        (
            "jitdyn.client._client",
            "from jitdyn.experiments import netem",
            "client may not import experiments",
        ),
        ("jitdyn.errors", "from jitdyn.storage import layout", "contract may not import storage"),
        (
            "jitdyn.compliance.wire",
            "from jitdyn.server.transport import app",
            "compliance may not import transport",
        ),
        ("jitdyn.compliance.suite", "from jitdyn.client import Client", "compliance may not import client"),
    ],
)
def test_the_check_catches_an_upward_import(tmp_path: Path, module: str, source: str, expected: str) -> None:
    fake = tmp_path / "fake.py"
    fake.write_text(source + "\n")
    saved = MODULES[module]
    MODULES[module] = fake
    try:
        assert any(expected in v for v in violations()), violations()
    finally:
        MODULES[module] = saved


def test_the_cycle_check_finds_a_cycle() -> None:
    assert _strongly_connected({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_modules_import() -> None:
    # The walk found them; each must also import (a missing package in pyproject would fail here).
    for name in MODULES:
        if name.endswith(("compile_worker", "migrations.env")):
            continue  # run as a script in its own process, and by Alembic
        importlib.import_module(name)
