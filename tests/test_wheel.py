"""A normal (non-editable) install, as a user or deploy/Dockerfile gets it: scripts/wheel_smoke.py
builds the wheel from the Dockerfile's context (one more compile of the native engine, about two
minutes with pip), installs it into a fresh venv and tries every command from outside the checkout.
Marked slow, to keep CI's run short: run it on its own after a change of the build or the layout,

    .venv/bin/pytest -q -m slow tests/test_wheel.py
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parent.parent / "scripts" / "wheel_smoke.py"


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_the_built_wheel_installs_and_every_command_runs_outside_the_checkout() -> None:
    done = subprocess.run([sys.executable, str(SCRIPT)], capture_output=True, text=True, check=False)
    assert done.returncode == 0, f"{SCRIPT.name} failed:\n{done.stdout[-4000:]}\n{done.stderr[-4000:]}"
