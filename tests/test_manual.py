"""The manual (mkdocs.yml over docs/) builds with --strict: a dead link, a missing page of the nav,
an anchor that is not there or a reference mkdocstrings cannot resolve fails the build."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_the_manual_builds_strict(tmp_path: Path) -> None:
    pytest.importorskip("mkdocs", reason="the docs extra: pip install -e '.[docs]'")
    built = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert built.returncode == 0, built.stdout + built.stderr
    site = tmp_path / "site"
    assert (site / "index.html").is_file()
    # The SDK's reference is generated from its docstrings, and the decisions' index from the pages.
    reference = (site / "reference" / "sdk" / "index.html").read_text(encoding="utf-8")
    assert "open_session" in reference and "SessionOptions" in reference
    decisions = (site / "decisions" / "index.html").read_text(encoding="utf-8")
    pages = sorted((ROOT / "docs" / "decisions").glob("[0-9]*.md"))
    assert pages and all(page.stem in decisions for page in pages)


def test_the_decisions_index_lists_every_decision() -> None:
    """docs/decisions/index.md is what scripts/mkdocs_hooks.py writes from the pages (a build
    refreshes it; commit the refreshed file)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("mkdocs_hooks", ROOT / "scripts" / "mkdocs_hooks.py")
    assert spec is not None and spec.loader is not None
    pytest.importorskip("mkdocs", reason="the docs extra: pip install -e '.[docs]'")
    hooks = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hooks)
    index = (ROOT / "docs" / "decisions" / "index.md").read_text(encoding="utf-8")
    assert index == hooks.decisions_index(), "docs/decisions/index.md is stale: run `mkdocs build`"
