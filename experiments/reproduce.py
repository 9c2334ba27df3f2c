"""`jitdyn experiments`: the thesis' chapter 4 reproduced through a real jitdyn server, and taken
further (dead reckoning over gaps, late and lost frames, real-time delay); needs jitdyn[experiments]::

    jitdyn experiments                          # everything, full length, an in-process server
    jitdyn experiments table_4_2 gaps --quick   # two experiments, CI-sized
    python -m jitdyn.experiments --help

Writes report.md, one CSV per table and PNG plots into --out.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import logging
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from datetime import UTC, datetime
from pathlib import Path

from jitdyn.experiments.definitions import EXPERIMENTS, Context, Experiment
from jitdyn.experiments.report import Section, write_report
from jitdyn.mujoco_log import route_mujoco_messages
from jitdyn.settings import SettingError, add_arguments, resolve

__all__ = ["EXPERIMENTS", "main", "parser", "run_experiments"]


def parser() -> argparse.ArgumentParser:
    lines = "\n".join(f"  {e.name:<11} {e.help}" for e in EXPERIMENTS.values())
    p = argparse.ArgumentParser(
        prog="jitdyn experiments",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=(
            "Reproduce the experiments of the thesis jitdyn comes from (chapter 4) through a real jitdyn "
            "server, with the thesis' numbers beside ours, each run with the thesis' hyperparameters "
            "(preset THESIS) and jitdyn's (JITDYN)."
        ),
        epilog=(
            f"experiments (default: all, in this order):\n{lines}\n\n"
            "Without --server, an in-process server is started on a loopback port (and, for fig_4_16, one "
            "per worker count); its stored sessions go to --data (default: a temporary folder, removed "
            "after).\n\n"
            "environment:\n"
            "  JITDYN_SERVER       the server to run against, as --server (a flag wins)\n"
            "  JITDYN_SECRET       hex HMAC key of the in-process server's subject pseudonyms; without it,\n"
            "                      JITDYN_SECRET_FILE or ~/.config/jitdyn/secret.key, created at first start\n"
            "  MUJOCO_GL           MuJoCo's GL backend: one MuJoCo cannot start with is a usage error\n\n"
            "exit codes: 0 done (report.md written in --out), 1 an experiment or the server failed (one line\n"
            "on stderr says why), 2 usage error, 130 interrupted"
        ),
    )
    p.add_argument("names", nargs="*", metavar="NAME", help="experiments to run (default: all)")
    p.add_argument("--quick", action="store_true", help="short runs, small enough for CI (under a minute)")
    p.add_argument(
        "--out", type=Path, default=Path("experiments-out"), help="output folder (default: %(default)s)"
    )
    add_arguments(p, "experiments")  # --server, with JITDYN_SERVER
    p.add_argument("--data", type=Path, help="data root of the in-process server (keeps its sessions)")
    p.add_argument(
        "--workers", type=int, default=2, help="workers of the in-process server (default: %(default)s)"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the objects' initial states and the network")
    p.add_argument(
        "--no-progress",
        action="store_true",
        help="no progress bars (they are drawn on stderr, when it is a terminal)",
    )
    p.add_argument("-v", "--verbose", action="store_true", help="log more")
    return p


def _git(*args: str) -> str | None:
    try:
        out = subprocess.run(
            ["git", *args],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=5,
            check=False,
        )
    except OSError:
        return None
    return out.stdout if out.returncode == 0 else None


def _git_commit() -> str:
    """The checkout's commit, read when the run starts (a commit landing during a long run must not
    relabel it), and whether the code that runs differs from it."""
    commit = (_git("rev-parse", "--short", "HEAD") or "").strip()
    if not commit:
        return "unknown"
    changed = _git("status", "--porcelain", "--untracked-files=no")
    return f"{commit} with uncommitted changes" if changed else commit


def _header(
    args: argparse.Namespace, names: Sequence[str], elapsed: float, *, began: datetime, commit: str
) -> str:
    import mujoco

    mode = "quick (CI-sized runs: the numbers are not the full experiment's)" if args.quick else "full"
    server = args.server or f"in-process, {args.workers} workers"
    return "\n".join(
        [
            "# jitdyn experiments: the thesis' chapter 4, reproduced",
            "",
            f"- run: started {began.strftime('%Y-%m-%d %H:%M UTC')}, commit {commit}, {mode}",
            (
                f"- server: {server}; MuJoCo {mujoco.__version__}; Python {platform.python_version()}; "
                f"{os.cpu_count()} CPUs ({platform.machine()})"
            ),
            f"- experiments: {', '.join(names)}; seed {args.seed}; {elapsed:.0f} s",
            (
                "- estimates are the filter state the server answered at each tick (posterior when the frame was "
                "there), against the client's MuJoCo truth; 'THESIS' and 'JITDYN' are the estimator presets"
            ),
            (
                "- NEES verdict: 'pessimistic' (covariance too large), 'consistent' or 'optimistic' (too small), by "
                "the 95 % interval of the average NEES over the run's ticks"
            ),
            "",
        ]
    )


@contextlib.contextmanager
def _local_server(data_root: Path, workers: int) -> Iterator[str]:
    # Imported here: running against --server needs no server code.
    from jitdyn.server.transport.app import ServerConfig
    from jitdyn.server.transport.background import BackgroundServer

    config = ServerConfig(address="127.0.0.1:0", data_root=data_root, workers=workers, shutdown_grace=1.0)
    with BackgroundServer(config) as running:
        yield running.address


def run_experiments(
    experiments: Sequence[Experiment],
    *,
    address: str,
    out: Path,
    quick: bool,
    progress: bool,
    seed: int,
    servers: object | None,
) -> list[Section]:
    from jitdyn.client import Client

    sections: list[Section] = []
    with Client(address, timeout=120) as client:
        client.wait_ready(timeout=30)
        ctx = Context(client=client, out=out, quick=quick, progress=progress, seed=seed, servers=servers)  # type: ignore[arg-type]
        for experiment in experiments:
            if progress:
                print(f"[experiments] {experiment.name}: {experiment.title}", file=sys.stderr, flush=True)
            ctx.notes.clear()
            section = experiment.run(ctx)
            sections.append(dataclasses.replace(section, notes=(*section.notes, *ctx.notes)))
    return sections


def main(argv: Sequence[str] | None = None, *, verbose: bool = False) -> int:
    args = parser().parse_args(argv)
    try:
        args.server = resolve({"server": args.server} if "server" in args else {}, os.environ).server
    except SettingError as error:
        parser().error(str(error))
    if args.verbose and not verbose:
        logging.getLogger().setLevel(logging.INFO)
    route_mujoco_messages()
    unknown = [n for n in args.names if n not in EXPERIMENTS]
    if unknown:
        parser().error(f"unknown experiment(s) {unknown}; choose from {list(EXPERIMENTS)}")
    if args.workers < 1:
        parser().error(f"--workers must be >= 1, got {args.workers}")
    names = list(dict.fromkeys(args.names)) or list(EXPERIMENTS)
    experiments = [EXPERIMENTS[n] for n in names]
    out: Path = args.out
    # Checked before the first experiment: a folder that cannot take the report would fail a
    # full run at its end, after a quarter of an hour.
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        parser().error(f"--out {out}: cannot create the output folder ({error.strerror or error})")
    if not os.access(out, os.W_OK | os.X_OK):
        parser().error(f"--out {out}: the output folder is not writable")
    started, began, commit = time.perf_counter(), datetime.now(UTC), _git_commit()
    with contextlib.ExitStack() as stack:
        if args.server:
            address, servers = args.server, None
        else:
            root = args.data or Path(
                stack.enter_context(tempfile.TemporaryDirectory(prefix="jitdyn-experiments-"))
            )
            address = stack.enter_context(_local_server(root / "main", args.workers))
            counter = iter(range(1_000_000))

            def servers(workers: int) -> contextlib.AbstractContextManager[str]:
                return _local_server(root / f"workers-{workers}-{next(counter)}", workers)

        sections = run_experiments(
            experiments,
            address=address,
            out=out,
            quick=args.quick,
            progress=not args.no_progress,
            seed=args.seed,
            servers=servers,
        )
    report = write_report(
        out, sections, header=_header(args, names, time.perf_counter() - started, began=began, commit=commit)
    )
    print(f"report: {report}")
    return 0
