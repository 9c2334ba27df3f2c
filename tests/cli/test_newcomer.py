"""What a newcomer tripped on, trying jitdyn as a new user would: one test per item, each run as a
user runs the command (a separate process, a real server on a loopback port)."""

from __future__ import annotations

import os
import secrets
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

# A base install, as far as the commands can tell: every extra's module hidden.
BASE_INSTALL = "\n".join(
    f"sys.modules[{name!r}] = None" for name in ("matplotlib", "PIL", "tqdm", "myo_sim", "biomdp", "duckdb")
)


def jitdyn(
    *args: str, cwd: Path | None = None, env: dict[str, str] | None = None, preamble: str = ""
) -> subprocess.CompletedProcess[str]:
    """`jitdyn ARGS` in a fresh process, no JITDYN_* setting but a secret; `preamble` runs first."""
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


def one_line_error(result: subprocess.CompletedProcess[str], code: int) -> str:
    """The one `jitdyn ...` line a failed command prints on stderr, with no traceback."""
    assert result.returncode == code, result.stdout + result.stderr
    assert "Traceback" not in result.stderr, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.startswith("jitdyn")]
    assert len(lines) == 1, result.stderr
    return lines[0]


# -- --help works without the extra; running says which to install ----------------------------------


@pytest.mark.parametrize(
    "command",
    [
        ["experiments"],
        ["-v", "experiments"],
        ["sessions", "query"],
        ["sessions", "plot"],
        ["models", "register"],
    ],
)
def test_help_needs_no_extra(command: list[str]) -> None:
    result = jitdyn(*command, "--help", preamble=BASE_INSTALL)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith(f"usage: jitdyn {' '.join(c for c in command if c != '-v')}"), (
        result.stdout
    )
    assert "pip install" not in result.stdout + result.stderr


def test_running_experiments_without_the_extra_names_it(tmp_path: Path) -> None:
    result = jitdyn("experiments", "--quick", "--out", str(tmp_path / "out"), preamble=BASE_INSTALL)
    assert one_line_error(result, 1) == (
        "jitdyn experiments: needs matplotlib (plots), which is not installed: pip install 'jitdyn[experiments]'"
    )
