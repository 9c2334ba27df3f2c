"""deploy/kubernetes/secret.yaml applied as shipped: whichever of its values is still a placeholder
(`replace-...`), `jitdyn serve` refuses to start, in one line that names it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

SECRET = Path(__file__).resolve().parents[2] / "deploy" / "kubernetes" / "secret.yaml"
PLACEHOLDERS: dict[str, str] = yaml.safe_load(SECRET.read_text())["stringData"]


@pytest.mark.parametrize("name", sorted(PLACEHOLDERS))
def test_each_placeholder_of_the_secret_stops_serve_in_one_line(name: str, tmp_path: Path) -> None:
    placeholder = PLACEHOLDERS[name]
    environment = {k: v for k, v in os.environ.items() if not k.startswith(("JITDYN_", "AWS_", "PG"))}
    environment["JITDYN_SECRET_FILE"] = str(tmp_path / "secret.key")
    arguments = ["--address=127.0.0.1:0", f"--data={tmp_path / 'data'}", "--processes=1"]
    if name == "api-keys":
        keys = tmp_path / "api-keys"
        keys.write_text(placeholder)
        keys.chmod(0o600)
        arguments.append(f"--api-keys={keys}")
        setting = f"--api-keys {keys}:1: the key"
        shown = placeholder.split()[0]
    else:
        environment[name] = placeholder
        setting = f"environment variable {name}"
        shown = placeholder
    done = subprocess.run(
        [sys.executable, "-m", "jitdyn.cli", "serve", *arguments],
        env=environment,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 1
    assert (done.stdout + done.stderr).splitlines() == [
        (
            f"jitdyn serve: FailedPrecondition: {setting} is still the placeholder {shown!r} of "
            "deploy/kubernetes/secret.yaml; set the real value in the Secret"
        )
    ]
    assert not (tmp_path / "data").exists()
