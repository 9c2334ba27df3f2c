"""The command line as a user runs it, for the cli tests: `jitdyn ARGS` in a fresh process."""

from __future__ import annotations

import os
import secrets
import subprocess
import sys
from pathlib import Path


def jitdyn(
    *args: str, cwd: Path | None = None, env: dict[str, str] | None = None, preamble: str = ""
) -> subprocess.CompletedProcess[str]:
    """`jitdyn ARGS` in a fresh process, no JITDYN_* setting but a secret and `env`; `preamble`
    runs first (to hide an installed extra, say)."""
    environ = {k: v for k, v in os.environ.items() if not k.startswith("JITDYN_")}
    environ.update(JITDYN_SECRET=secrets.token_hex(32), **(env or {}))
    code = f"import sys\n{preamble}\nfrom jitdyn.cli import main\nsys.exit(main(sys.argv[1:]))"
    return subprocess.run(
        [sys.executable, "-c", code, *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=environ,
        timeout=300,
        check=False,
    )


def listed(table: str) -> list[dict[str, str]]:
    """The rows of `jitdyn sessions list`'s table (a header, a rule, the rows) by column header."""
    lines = table.splitlines()
    spans, start = [], 0
    for dashes in lines[1].split("  "):
        spans.append((start, start + len(dashes)))
        start += len(dashes) + 2
    headers = [lines[0][a:b].strip() for a, b in spans]
    return [{h: line[a:b].strip() for h, (a, b) in zip(headers, spans, strict=True)} for line in lines[2:]]
