"""MkDocs hooks of the manual (mkdocs.yml).

- The SDK's reference (mkdocstrings) reads the package `jitdyn` as installed: its folders are
  mapped into one namespace (pyproject.toml's package-dir), so the hook lays that namespace out as
  a tree of symlinks, as scripts/check.py does for mypy, where mkdocs.yml's `paths` points.
- The decisions' index (docs/decisions/index.md) is written from the decision pages themselves, so
  a new page is listed without an edit there.
"""

from __future__ import annotations

import importlib.util
import shutil
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
NAMESPACE = ROOT / ".cache" / "docs-namespace"  # mkdocs.yml: mkdocstrings' paths


def on_startup(command: str, dirty: bool) -> None:
    """Before any plugin reads its configuration: mkdocstrings drops a `paths` entry missing then."""
    spec = importlib.util.spec_from_file_location("jitdyn_check", ROOT / "scripts" / "check.py")
    assert spec is not None and spec.loader is not None
    check = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(check)
    shutil.rmtree(NAMESPACE, ignore_errors=True)
    NAMESPACE.mkdir(parents=True)
    check.namespace_tree(NAMESPACE)


def decisions_index(docs: Path = ROOT / "docs") -> str:
    """docs/decisions/index.md: every page of docs/decisions/ with its title, in number order."""
    lines = [
        "# Decisions",
        "",
        "One short page per decision with a history: what was tried, what it measured, why the rest",
        "lost. The code that a decision shaped links its page in one line. This index is written by",
        "scripts/mkdocs_hooks.py from the pages themselves (tests/test_manual.py holds it to them).",
        "",
    ]
    for page in sorted((docs / "decisions").glob("[0-9]*.md")):
        title = page.read_text(encoding="utf-8").splitlines()[0].lstrip("# ").strip()
        lines.append(f"- [{title}]({page.name})")
    return "\n".join(lines) + "\n"


def on_pre_build(config: Any) -> None:
    """Refresh the decisions' index before the pages are read."""
    index = Path(config["docs_dir"]) / "decisions" / "index.md"
    content = decisions_index(Path(config["docs_dir"]))
    if not index.is_file() or index.read_text(encoding="utf-8") != content:
        index.write_text(content, encoding="utf-8")
