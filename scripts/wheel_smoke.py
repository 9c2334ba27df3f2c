"""Smoke-test a normal (non-editable) install, as a user gets it from `pip install jitdyn`.

    python scripts/wheel_smoke.py            # build the wheel, install it into a fresh venv, try it

From a folder outside the checkout (so nothing of the checkout is importable by accident), with the
base install only (what the server needs): every command's --help, a short demo, `import
jitdyn.client, jitdyn.server`, that the extras' packages are not there and the commands that need
them say which extra to install, that no generic top-level name (`server`, `client`, `registry`,
`storage`, `experiments`, `cli`, `models`) was installed, and that nothing is left in the working
folder (no MUJOCO_LOG.TXT). CI runs it; it takes about a minute, most of it pip.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
GENERIC = ("server", "client", "registry", "storage", "experiments", "cli", "models")
# Packages of the extras, which a base install must not pull in. (matplotlib is not among them:
# filterpy, which the server needs, requires it.)
EXTRAS_ONLY = ("duckdb", "myo_sim", "tqdm")
NEEDS_EXTRA = (
    (["experiments", "--quick"], "experiments"),
    (["sessions", "query", "SELECT 1", "--data", "."], "query"),
    (["models", "register", "--myo", "myoelbow"], "myo"),
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
        print("building the wheel", flush=True)
        run(
            [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(tmp / "dist"), str(ROOT)],
            cwd=tmp,
        )
        wheel = next((tmp / "dist").glob("jitdyn-*.whl"))
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
