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


CA_SECRET = SECRET.parent / "ca-secret.yaml"


def _serve_refusal(tmp_path: Path, *arguments: str, environment: dict[str, str] | None = None) -> list[str]:
    """What `jitdyn serve ARGUMENTS` says before it stops (it must stop before making its folder)."""
    clean = {k: v for k, v in os.environ.items() if not k.startswith(("JITDYN_", "AWS_", "PG"))}
    clean["JITDYN_SECRET_FILE"] = str(tmp_path / "secret.key")
    done = subprocess.run(
        [
            sys.executable, "-m", "jitdyn.cli", "serve", "--address=127.0.0.1:0",
            f"--data={tmp_path / 'data'}", "--processes=1", *arguments,
        ],
        env={**clean, **(environment or {})},
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )  # fmt: skip
    assert done.returncode == 1
    assert not (tmp_path / "data").exists()
    return (done.stdout + done.stderr).splitlines()


@pytest.mark.parametrize("where", ["sslrootcert", "AWS_CA_BUNDLE"])
def test_the_ca_secrets_placeholder_or_no_ca_file_stops_serve_in_one_line(where: str, tmp_path: Path) -> None:
    placeholder = yaml.safe_load(CA_SECRET.read_text())["stringData"]["ca.crt"]
    ca = tmp_path / "ca.crt"
    ca.write_text(placeholder)
    missing = tmp_path / "missing" / "ca.crt"

    def refusal(path: Path) -> list[str]:
        if where == "sslrootcert":
            index = f"--index=postgresql+psycopg://jitdyn@127.0.0.1:1/jitdyn?sslmode=verify-full&sslrootcert={path}"
            return _serve_refusal(tmp_path, index)
        return _serve_refusal(
            tmp_path,
            "--data-root=s3://bucket",
            environment={"AWS_CA_BUNDLE": str(path), "AWS_ENDPOINT_URL": "https://127.0.0.1:1"},
        )

    setting = "--index sslrootcert" if where == "sslrootcert" else "environment variable AWS_CA_BUNDLE"
    assert refusal(ca) == [
        (
            f"jitdyn serve: FailedPrecondition: {setting} {ca} is still the placeholder {placeholder!r} of "
            "deploy/kubernetes/ca-secret.yaml; set your CA's certificate (PEM) in the Secret"
        )
    ]
    assert refusal(missing) == [
        f"jitdyn serve: InvalidArgument: {setting} {missing} cannot be read: No such file or directory"
    ]
