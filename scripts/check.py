"""Lint and type-check the installed namespace, as CI does: ruff (lint and format) over the
repository, then mypy strict over `jitdyn` with every first-party import resolved.

    python scripts/check.py

mypy cannot follow setuptools' editable finder, and our folders (server/, client/, ...) are
installed under `jitdyn` by `package-dir`, so this assembles the namespace as the wheel lays it
out, as a tree of symlinks read from pyproject.toml, and checks that tree as package `jitdyn`.
"""

from __future__ import annotations

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
    "models",
    "tests",
    "benchmarks",
    "scripts",
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


def _tool(name: str) -> str:
    return str(Path(sysconfig.get_path("scripts")) / name)


def main() -> int:
    failed = False
    for args in (["check", *RUFF_PATHS], ["format", "--check", *RUFF_PATHS]):
        print(f"$ ruff {' '.join(args[:2])} ...", flush=True)
        failed |= subprocess.run([_tool("ruff"), *args], cwd=ROOT, check=False).returncode != 0
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
