"""Smoke-test a normal (non-editable) install, as a user gets it from `pip install jitdyn`.

    python scripts/wheel_smoke.py            # build the wheel, install it into a fresh venv, try it

The wheel is built as deploy/Dockerfile's builder stage builds it: from what its COPY lines copy,
laid out as they lay it out, with its `pip wheel --no-deps` (so the image builds from what the
Dockerfile copies; one compile of the native engine serves both checks). From a folder outside the checkout (so nothing of the checkout is importable by accident), with the
base install only (what the server needs): every command's --help, a short demo, `import
jitdyn.client, jitdyn.server`, that the extras' packages are not there and the commands that need
them say which extra to install, that no generic top-level name (`server`, `client`, `registry`,
`storage`, `experiments`, `cli`, `models`) was installed, and that nothing is left in the working
folder (no MUJOCO_LOG.TXT). tests/test_wheel.py runs it (marked slow); it takes two to three
minutes, most of them the compile.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOCKERFILE = ROOT / "deploy" / "Dockerfile"
GENERIC = ("server", "client", "registry", "storage", "experiments", "cli", "models")
# Packages of the extras, which a base install must not pull in. (matplotlib is not among them:
# filterpy, which the server needs, requires it.)
EXTRAS_ONLY = ("duckdb", "myo_sim", "tqdm", "ezc3d", "pylsl")
NEEDS_EXTRA = (
    (["experiments", "--quick"], "experiments"),
    (["sessions", "query", "SELECT 1", "--data", "."], "query"),
    (["models", "register", "--myo", "myoelbow"], "myo"),
    (["lsl", "--name", "leg", "--model", "pendulum_3"], "lab"),
)

# Run inside the fresh venv: every leaf of the CLI's parser, so a new command cannot be forgotten.
LIST_COMMANDS = """
import argparse
from jitdyn.cli import build_parser
def walk(parser, path):
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    yield path
    for action in subs:
        for name, child in action.choices.items():
            yield from walk(child, [*path, name])
for path in walk(build_parser(), []):
    print(" ".join(path))
"""


def dockerfile_instructions() -> list[tuple[str, str]]:
    """deploy/Dockerfile as (KEYWORD, the rest) pairs: continuation lines joined, comments left out."""
    text = re.sub(r"\\\n", " ", DOCKERFILE.read_text())
    lines = [line.strip() for line in text.splitlines()]
    return [
        (parts[0].upper(), parts[1] if len(parts) > 1 else "")
        for parts in (line.split(None, 1) for line in lines if line and not line.startswith("#"))
    ]


def docker_context(dest: Path) -> Path:
    """`dest`, holding what the Dockerfile's builder stage copies from the checkout, as it lays it
    out (without compiled modules or caches, which .dockerignore keeps out)."""
    for kind, value in dockerfile_instructions():
        if kind != "COPY" or value.startswith("--from"):
            continue
        *sources, target = value.split()
        for source in sources:
            origin = ROOT / source.rstrip("/")
            if origin.is_dir():
                ignore = shutil.ignore_patterns("__pycache__", "*.so")
                shutil.copytree(origin, dest / target.rstrip("/"), ignore=ignore)
            else:
                dest.mkdir(parents=True, exist_ok=True)
                shutil.copy(origin, dest / origin.name)
    return dest


def run(args: list[str], *, cwd: Path, env: dict[str, str] | None = None, expect_ok: bool = True) -> str:
    started = time.monotonic()
    result = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, check=False, timeout=600)
    shown = " ".join(Path(a).name if a.startswith("/") else a.split("\n")[0][:60] for a in args)
    print(f"  [{time.monotonic() - started:5.1f} s] {shown} -> exit {result.returncode}", flush=True)
    if (result.returncode == 0) != expect_ok:
        sys.stderr.write(result.stdout + result.stderr)
        raise SystemExit(f"wheel smoke test failed: {shown} exited {result.returncode}")
    return result.stdout + result.stderr


def main() -> int:
    with tempfile.TemporaryDirectory(prefix="jitdyn-wheel-") as tmp_name:
        tmp = Path(tmp_name)
        print("building the wheel from what deploy/Dockerfile copies", flush=True)
        context = docker_context(tmp / "src")
        run(
            [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(tmp / "dist"), "."],
            cwd=context,
        )
        wheel = next((tmp / "dist").glob("jitdyn-*.whl"))
        listing = run([sys.executable, "-m", "zipfile", "-l", str(wheel)], cwd=tmp)
        for inside in (
            "jitdyn/server/transport/app.py",
            "jitdyn/cli/main.py",
            "jitdyn/server/estimation/native/_ukf.",
        ):
            if inside not in listing:
                raise SystemExit(f"the wheel built from the Dockerfile's context lacks {inside}")
        print(f"installing {wheel.name} into a fresh venv", flush=True)
        run([sys.executable, "-m", "venv", str(tmp / "venv")], cwd=tmp)
        python = str(tmp / "venv" / "bin" / "python")
        jitdyn = str(tmp / "venv" / "bin" / "jitdyn")
        run([python, "-m", "pip", "install", "-q", str(wheel)], cwd=tmp)

        work = tmp / "elsewhere"
        work.mkdir()
        env = dict(os.environ, JITDYN_SECRET="ab" * 32, PYTHONPATH="")
        print("importing", flush=True)
        run(
            [python, "-c", "import jitdyn.client, jitdyn.server, jitdyn.experiments.demo, jitdyn.cli"],
            cwd=work,
            env=env,
        )
        for name in (*GENERIC, *EXTRAS_ONLY):
            run([python, "-c", f"import {name}"], cwd=work, env=env, expect_ok=False)
        print("every command's --help", flush=True)
        commands = run([python, "-c", LIST_COMMANDS], cwd=work, env=env).splitlines()
        for command in commands:
            if command == "experiments":
                continue  # its parser lives with the experiments, in jitdyn[experiments]: below
            out = run([jitdyn, *command.split(), "--help"], cwd=work, env=env)
            if "usage:" not in out:
                raise SystemExit(f"`jitdyn {command} --help` printed no usage")
        print("commands that need an extra say which", flush=True)
        for command, extra in NEEDS_EXTRA:
            out = run([jitdyn, *command], cwd=work, env=env, expect_ok=False)
            if f"pip install 'jitdyn[{extra}]'" not in out or "Traceback" in out:
                raise SystemExit(f"`jitdyn {' '.join(command)}` did not name jitdyn[{extra}]:\n{out}")
        print("a short demo", flush=True)
        out = run([jitdyn, "demo", "--seconds", "2", "--data", str(work / "data")], cwd=work, env=env)
        if "stored:" not in out:
            raise SystemExit(f"the demo did not say where it stored the session:\n{out}")
        leftovers = sorted(p.name for p in work.iterdir() if p.name != "data")
        if leftovers:
            raise SystemExit(f"the demo left files in the working folder: {leftovers}")
    print("wheel smoke test passed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
