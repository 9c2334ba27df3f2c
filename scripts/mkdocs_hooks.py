"""MkDocs hooks of the manual (mkdocs.yml): the decisions' index is written from the decision pages
themselves, so a new page is listed without an edit here."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mkdocs.structure.files import File, Files


def on_files(files: Files, config: Any) -> Files:
    """Add decisions/index.md: every page of docs/decisions/ with its title, in number order."""
    docs = Path(config["docs_dir"])
    lines = [
        "# Decisions",
        "",
        "One short page per decision with a history: what was tried, what it measured, why the rest",
        "lost. The code that a decision shaped links its page in one line.",
        "",
    ]
    for page in sorted((docs / "decisions").glob("[0-9]*.md")):
        title = page.read_text(encoding="utf-8").splitlines()[0].lstrip("# ").strip()
        lines.append(f"- [{title}]({page.name})")
    files.append(File.generated(config, "decisions/index.md", content="\n".join(lines) + "\n"))
    return files
