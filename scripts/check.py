"""Lint and type-check the installed namespace, as CI does: ruff (lint and format) over the
repository, then mypy strict over `jitdyn` with every first-party import resolved.

    python scripts/check.py

It also holds the server's functions short: none past MAX_FUNCTION_LINES lines (its `def` to its
last line) or with more than MAX_POSITIONAL positional parameters (self and cls aside); past that,
a function is hiding a step or a value object.

mypy cannot follow setuptools' editable finder, and our folders (server/, client/, ...) are
installed under `jitdyn` by `package-dir`, so this assembles the namespace as the wheel lays it
out, as a tree of symlinks read from pyproject.toml, and checks that tree as package `jitdyn`.
"""

from __future__ import annotations

import ast
import os
import subprocess
import sys
import sysconfig
import tempfile
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RUFF_PATHS = [
    "src",
    "server",
    "client",
    "registry",
    "storage",
    "experiments",
    "cli",
    "compliance",
    "models",
    "tests",
    "benchmarks",
    "scripts",
    "deploy",
]


def namespace_tree(into: Path) -> Path:
    """Symlink each mapped package of pyproject.toml into `into`/jitdyn/...; returns `into`."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    package_dir: dict[str, str] = config["package-dir"]
    base = into / "jitdyn"
    base.mkdir(parents=True)
    for entry in (ROOT / package_dir["jitdyn"]).iterdir():
        (base / entry.name).symlink_to(entry)
    for package, folder in sorted(package_dir.items()):
        if package == "jitdyn":
            continue
        target = into.joinpath(*package.split("."))
        target.symlink_to(ROOT / folder, target_is_directory=True)
    return into


# Where functions are held short, and how short.
SHORT_FUNCTION_PATHS = ["server"]
MAX_FUNCTION_LINES = 60
MAX_POSITIONAL = 6


def long_functions(paths: list[str] = SHORT_FUNCTION_PATHS) -> list[str]:
    """`path:line name: why` for every function under `paths` that is too long or takes too many
    positional parameters."""
    found = []
    for folder in paths:
        for path in sorted((ROOT / folder).rglob("*.py")):
            tree = ast.parse(path.read_text(), filename=str(path))
            for node in ast.walk(tree):
                if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    continue
                where = f"{path.relative_to(ROOT)}:{node.lineno} {node.name}"
                lines = (node.end_lineno or node.lineno) - node.lineno + 1
                if lines > MAX_FUNCTION_LINES:
                    found.append(f"{where}: {lines} lines, more than {MAX_FUNCTION_LINES}")
                positional = [a.arg for a in (*node.args.posonlyargs, *node.args.args)]
                positional = [a for a in positional if a not in ("self", "cls")]
                if len(positional) > MAX_POSITIONAL:
                    found.append(
                        f"{where}: {len(positional)} positional parameters, more than {MAX_POSITIONAL}"
                    )
    return found


def _tool(name: str) -> str:
    return str(Path(sysconfig.get_path("scripts")) / name)


def main() -> int:
    failed = False
    for args in (["check", *RUFF_PATHS], ["format", "--check", *RUFF_PATHS]):
        print(f"$ ruff {' '.join(args[:2])} ...", flush=True)
        failed |= subprocess.run([_tool("ruff"), *args], cwd=ROOT, check=False).returncode != 0
    print(f"$ function lengths in {', '.join(SHORT_FUNCTION_PATHS)}/ ...", flush=True)
    for problem in long_functions():
        print(problem)
        failed = True
    with tempfile.TemporaryDirectory(prefix="jitdyn-typecheck-") as tmp:
        tree = namespace_tree(Path(tmp))
        print("$ mypy --strict -p jitdyn (the installed layout)", flush=True)
        env = dict(os.environ, MYPYPATH=str(tree))
        result = subprocess.run(
            [_tool("mypy"), "--config-file", str(ROOT / "pyproject.toml"), "-p", "jitdyn"],
            cwd=tree,
            env=env,
            check=False,
        )
        failed |= result.returncode != 0
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
