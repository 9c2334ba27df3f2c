"""The first hour with jitdyn, as issue 12 found it: one test per item of its "Found" list, each run
as a user runs the command (a separate process, a real server on a loopback port)."""

from __future__ import annotations

import csv
import io
import json
import os
import re
import secrets
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from _cli import jitdyn, listed

ROOT = Path(__file__).resolve().parents[2]


def ok(result: subprocess.CompletedProcess[str]) -> str:
    assert result.returncode == 0, result.stdout + result.stderr
    return result.stdout


def one_line_error(result: subprocess.CompletedProcess[str], code: int) -> str:
    """The one stderr line a failed command prints: no traceback, the documented exit code."""
    assert result.returncode == code, result.stdout + result.stderr
    assert "Traceback" not in result.stderr, result.stderr
    lines = [
        line
        for line in result.stderr.splitlines()
        if not line.startswith("usage:") and line.startswith("jitdyn")
    ]
    assert len(lines) == 1, result.stderr
    return lines[0]


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[str, str, Path]:
    """One local demo session (its stdout and stderr, and its data folder), run from an empty folder."""
    work = tmp_path_factory.mktemp("work")
    result = jitdyn(
        "demo", "--seconds", "1.5", "--model", "pendulum_2", "--data", str(work / "data"), cwd=work
    )
    return ok(result), result.stderr, work / "data"


# -- Found 1: options only before the subcommand -----------------------------------------------------


@pytest.mark.slow  # 4-6 s of subprocesses
def test_group_options_work_after_the_action(server: Any, tmp_path: Path) -> None:
    listing = ok(jitdyn("models", "list", "--server", server.address, "-v"))
    assert re.search(r"sha256:[0-9a-f]{64}  pendulum_1 v1", listing), listing
    registered = ok(jitdyn("models", "register", "--myo", "myoelbow", "--server", server.address))
    assert re.search(
        r"(registered|already registered \(identical content\)): sha256:\S+  myoelbow v\d", registered
    )
    assert "--server HOST:PORT" in ok(jitdyn("models", "show", "--help"))
    empty = tmp_path / "data"
    ok(jitdyn("demo", "--seconds", "0.5", "--data", str(empty), "--server", server.address))
    sessions = ok(jitdyn("sessions", "list", "--data", str(server.services.data_root)))
    assert "pendulum_3" in sessions, sessions
    assert not empty.exists(), "the demo against --server made a local data folder"


# -- Found 2: tracebacks for ordinary mistakes, and the exit codes ------------------------------------


def test_serve_on_a_busy_port_says_so_and_creates_nothing(tmp_path: Path) -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        result = jitdyn("serve", "--address", f"127.0.0.1:{port}", "--data", str(tmp_path / "data"))
    assert one_line_error(result, 1) == (
        f"jitdyn serve: FailedPrecondition: cannot listen on 127.0.0.1:{port}: the address is in use "
        "(another jitdyn serve?) or not an address of this machine; choose another with --address "
        "HOST:PORT (port 0 picks a free one)"
    )
    assert result.stderr.count("\n") == 1, result.stderr  # not even gRPC's own log line
    assert not (tmp_path / "data").exists()


def test_demo_of_a_model_not_registered_says_so_and_creates_nothing(tmp_path: Path) -> None:
    result = jitdyn("demo", "--model", "myoelbow", "--data", str(tmp_path / "data"), cwd=tmp_path)
    assert one_line_error(result, 1) == (
        f"jitdyn demo: FailedPrecondition: no model 'myoelbow' here: {tmp_path / 'data'} does not exist, so "
        "only the built-in models (pendulum_1, pendulum_2, pendulum_3, biped) are registered; register it "
        "first (jitdyn models register) or give --data of the folder that holds it"
    )
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow  # 4-6 s of subprocesses
def test_verbose_before_experiments() -> None:
    assert "usage: jitdyn experiments" in ok(jitdyn("-v", "experiments", "--help"))
    result = jitdyn("-v", "experiments", "table_9_9")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "unknown experiment(s) ['table_9_9']" in result.stderr


def test_the_command_line_parses_without_loading_the_engine() -> None:
    """`jitdyn --help` and a flag's usage error answered in about 0.3 s, not 2 s: parsing the
    arguments imports neither MuJoCo nor the SQL, Parquet and SciPy stacks; only a command that
    runs does."""
    heavy = ("mujoco", "numpy", "scipy", "sqlalchemy", "pyarrow", "filterpy")
    code = (
        "import sys, jitdyn.cli; jitdyn.cli.build_parser().parse_args(['demo', '--seconds', '1s']); "
        f"print(sorted(m for m in {heavy!r} if m in sys.modules))"
    )
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert loaded.stdout.strip() == "[]", loaded.stdout + loaded.stderr


def test_a_mujoco_gl_that_mujoco_cannot_start_with_is_named() -> None:
    """MUJOCO_GL (osmesa, egl or glfw, for rendering) is read by MuJoCo's import; a value it cannot
    start with is one line naming the variable, not a traceback from every command."""
    result = jitdyn("sessions", "list", env={"MUJOCO_GL": "bogus"})
    assert one_line_error(result, 2).startswith(
        "jitdyn sessions list: environment variable MUJOCO_GL=bogus: MuJoCo does not start with it ("
    ), result.stderr
    assert "or unset MUJOCO_GL" in result.stderr


def test_an_output_folder_that_cannot_be_made_is_named_before_anything_runs(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a folder", encoding="utf-8")
    result = jitdyn("experiments", "--out", str(blocker / "out"), "table_4_2")
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    assert f"--out {blocker / 'out'}: cannot create the output folder (Not a directory)" in result.stderr


def test_a_bad_environment_variable_is_named() -> None:
    result = jitdyn("sessions", "list", env={"JITDYN_WORKERS": "abc"})
    assert one_line_error(result, 2) == (
        "jitdyn sessions list: environment variable JITDYN_WORKERS: expected a whole number >= 1, got 'abc'"
    )


def test_a_bad_model_reference_is_a_usage_error(server: Any) -> None:
    result = jitdyn("models", "show", "x:abc", "--server", server.address)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert (
        "jitdyn models show: error: argument model: expected a model id (sha256:...), NAME or NAME:VERSION "
        "with VERSION a whole number >= 1, got 'x:abc'" in result.stderr
    )


def test_errors_exit_1_and_usage_errors_exit_2(server: Any) -> None:
    missing = jitdyn("models", "show", "no_such_model", "--server", server.address)
    assert one_line_error(missing, 1).startswith("jitdyn models show: NotFound: ")
    assert jitdyn("models", "frobnicate").returncode == 2
    assert "exit codes: 0 done, 1 the command failed" in ok(jitdyn("--help"))


# -- Found 3: silent surprises -----------------------------------------------------------------------


def test_a_duration_without_a_unit_is_refused() -> None:
    result = jitdyn("demo", "--latency", "35")
    assert result.returncode == 2
    assert (
        "argument --latency: a duration needs a unit (us, ms or s): write 35ms or 35s, got '35'"
        in result.stderr
    )


def test_register_takes_a_file_or_myo_not_both(server: Any) -> None:
    model = str(ROOT / "models" / "pendulum_2.xml")
    result = jitdyn("models", "register", model, "--myo", "myoelbow", "--server", server.address)
    assert result.returncode == 2 and "argument --myo: not allowed with argument file" in result.stderr
    neither = jitdyn("models", "register", "--server", server.address)
    assert neither.returncode == 2 and "one of the arguments file --myo is required" in neither.stderr


def test_identical_content_under_a_new_name_is_refused_plainly(server: Any) -> None:
    model = str(ROOT / "models" / "pendulum_2.xml")
    result = jitdyn(
        "models", "register", model, "--name", "mypend", "--tag", "test", "--server", server.address
    )
    line = one_line_error(result, 1)
    assert re.fullmatch(
        r"jitdyn models register: not registered: identical content is already registered as pendulum_2 v1 "
        r"\(sha256:[0-9a-f]{64}\), and the name 'mypend' and the tag 'test' were not added \(the registry "
        r"keeps one name per content\); use `jitdyn models show pendulum_2:1`, or change the content",
        line,
    ), line
    shown = jitdyn("models", "show", "mypend", "--server", server.address)
    assert shown.returncode == 1 and "NotFound" in shown.stderr


def test_experiments_take_the_server_from_the_environment(server: Any, tmp_path: Path) -> None:
    out = tmp_path / "out"
    ok(
        jitdyn(
            "experiments",
            "network",
            "--quick",
            "--out",
            str(out),
            env={"JITDYN_SERVER": server.address},
        )
    )
    report = (out / "report.md").read_text(encoding="utf-8")
    assert f"- server: {server.address};" in report, report[:600]


def test_workers_default_is_one_definition() -> None:
    code = (
        "import os\n"
        "from jitdyn.server.transport.app import ServerConfig\n"
        "from jitdyn.settings import resolve\n"
        "from jitdyn.settings import default_workers\n"
        "print(ServerConfig().workers, ServerConfig.from_settings(resolve({}, {})).workers, os.cpu_count(),\n"
        "      ServerConfig.from_settings(resolve({}, {'JITDYN_WORKERS': '3'})).workers,\n"
        "      default_workers(os.cpu_count()), default_workers(2 * os.cpu_count()))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.split()
    # One server process: a worker per CPU; a process per CPU (serve's default): one each, never 0.
    assert out[0] == out[1] == out[2] and out[3] == "3" and out[4] == out[5] == "1", out
    help_text = " ".join(ok(jitdyn("serve", "--help")).split())
    assert (
        "threads propagating sigma points, shared by all sessions (env JITDYN_WORKERS; default the CPU "
        "count, shared among --processes (one each at one process per CPU))" in help_text
    )


# -- Found 4: output a person has to decode ----------------------------------------------------------


def test_sessions_query_prints_an_aligned_table_or_csv_or_json(demo_run: tuple[str, str, Path]) -> None:
    _, _, data = demo_run
    sql = "SELECT model, count(DISTINCT seq) AS ticks FROM frames WHERE kind = 'result' GROUP BY model"
    table = ok(jitdyn("sessions", "query", sql, "--data", str(data))).splitlines()
    assert table[0] == "model       ticks", table
    assert table[1] == "----------  -----"
    assert re.fullmatch(r"pendulum_2  +\d+", table[2]), table
    assert "pyarrow" not in "\n".join(table)
    rows = list(
        csv.reader(io.StringIO(ok(jitdyn("sessions", "query", sql, "--format", "csv", "--data", str(data)))))
    )
    assert rows[0] == ["model", "ticks"] and rows[1][0] == "pendulum_2"
    line = ok(jitdyn("sessions", "query", sql, "--format", "json", "--data", str(data))).strip()
    assert json.loads(line)["model"] == "pendulum_2"


def test_demo_summary_and_sessions_list_agree(demo_run: tuple[str, str, Path]) -> None:
    out, _, data = demo_run
    counts = re.search(r"server's summary, as `jitdyn sessions list` shows it: (ticks .*)", out)
    assert counts, out
    (row,) = listed(ok(jitdyn("sessions", "list", "--data", str(data))))
    said = dict(re.findall(r"(\w+) +(\d+)", counts.group(1)))
    assert said == {name: row[name] for name in said} and len(said) == 6, (said, row)
    assert "counts once in ticks and once in each of predicted and corrected" in out


def test_demo_says_where_the_session_is_stored(demo_run: tuple[str, str, Path], server: Any) -> None:
    out, _, data = demo_run
    stored = re.search(r"stored: (\S+\.parquet)$", out, re.MULTILINE)
    assert stored and Path(stored.group(1)).is_absolute() and Path(stored.group(1)).is_file(), out
    assert Path(stored.group(1)).is_relative_to(data.resolve())


def test_the_clock_offset_is_explained(demo_run: tuple[str, str, Path]) -> None:
    out, _, _ = demo_run
    assert re.search(
        r"clock sync: round trip \d+\.\d\d ms, offset [-+]\d+\.\d\d ms \(the server's session clock minus "
        r"this client's: each starts its clock at `opened`",
        out,
    ), out


def test_the_readme_query_counts_ticks_as_the_index_does(demo_run: tuple[str, str, Path]) -> None:
    _, _, data = demo_run
    page = (ROOT / "docs" / "data.md").read_text(encoding="utf-8")
    sql = re.search(r"jitdyn sessions query \"(SELECT[^\"]+)\"", page)
    assert sql, "the manual's data page shows a `jitdyn sessions query` example"
    rows = list(
        csv.DictReader(
            io.StringIO(ok(jitdyn("sessions", "query", sql.group(1), "--format", "csv", "--data", str(data))))
        )
    )
    (listing,) = listed(ok(jitdyn("sessions", "list", "--data", str(data))))
    assert sum(int(r["ticks"]) for r in rows) == int(listing["ticks"]), (rows, listing)


def test_sto_export_has_a_legend_of_source(demo_run: tuple[str, str, Path], tmp_path: Path) -> None:
    _, _, data = demo_run
    session_id = listed(ok(jitdyn("sessions", "list", "--data", str(data))))[0]["id"]
    ok(
        jitdyn(
            "sessions",
            "export",
            session_id,
            "--format",
            "sto",
            "--out",
            str(tmp_path / "s.sto"),
            "--data",
            str(data),
        )
    )
    header = (tmp_path / "s.sto").read_text().split("endheader")[0]
    assert "source=1 MEASURED, 2 PREDICTED, 3 CORRECTED" in header


# -- Found 5: litter and noise -----------------------------------------------------------------------

_UNSTABLE = """
import logging, os, sys
from pathlib import Path
logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")
from jitdyn.client import Client, FrameData, SessionOptions
from jitdyn.mujoco_log import warning_counts
from jitdyn.server.transport.app import ServerConfig
from jitdyn.server.transport.background import BackgroundServer
with BackgroundServer(ServerConfig(address="127.0.0.1:0", data_root=Path("data"), workers=1)) as server:
    with Client(server.address) as client:
        with client.open_session(SessionOptions(model_name="pendulum_1", dt=0.05)) as session:
            session.send_frame(FrameData(seq=0, t=0.0, qpos=[0.3], qvel=[1e30]))
            for k in range(1, 4):
                session.skip(k)
        with client.open_session(SessionOptions(model_name="pendulum_1", dt=0.05)) as calm:
            calm.send_frame(FrameData(seq=0, t=0.0, qpos=[0.3], qvel=[0.0]))
            calm.skip(1)
    index = server.services.index
    unstable = index.get(session.opened.session_id, tenant="").summary.stats.get("mujoco_warnings", 0)
    quiet = index.get(calm.opened.session_id, tenant="").summary.stats.get("mujoco_warnings", 0)
    print("per session", unstable, quiet)
print(sum(warning_counts().values()))
"""


def test_mujoco_warnings_go_to_logging_not_to_a_file(tmp_path: Path) -> None:
    env = dict(os.environ, JITDYN_SECRET=secrets.token_hex(32))
    result = subprocess.run(
        [sys.executable, "-c", _UNSTABLE],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    assert int(result.stdout.split()[-1]) > 0, "MuJoCo did not warn: the test proves nothing"
    # Counted per session: the unstable one has them, the calm one none.
    unstable, quiet = (int(n) for n in re.search(r"per session (\d+) (\d+)", result.stdout).groups())  # type: ignore[union-attr]
    assert unstable > 0 and quiet == 0, result.stdout
    assert re.search(r"session [0-9a-f-]{36}: MuJoCo warned \d+ times", result.stderr), result.stderr
    assert "jitdyn.mujoco: MuJoCo: Nan, Inf or huge value in QVEL" in result.stderr, result.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]
    assert not list((tmp_path / "data").rglob("MUJOCO_LOG.TXT"))


def test_progress_is_not_drawn_into_redirected_output(demo_run: tuple[str, str, Path]) -> None:
    out, err, _ = demo_run
    assert "\r" not in out and "\r" not in err
    assert "ticks answered" not in out + err


def test_benchmarks_speak_of_targets_not_issues() -> None:
    for module in ("benchmarks.storage", "benchmarks.ukf_cycle", "benchmarks.forecast"):
        help_text = subprocess.run(
            [sys.executable, "-m", module, "--help"], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout
        assert not re.search(r"issue \d", help_text), (module, help_text)
    assert not re.search(r"\(issue \d", (ROOT / "benchmarks" / "RESULTS.md").read_text(encoding="utf-8"))


# -- Found 6: weight ---------------------------------------------------------------------------------


def test_the_base_install_is_the_server() -> None:
    from importlib.metadata import requires

    requirements = requires("jitdyn") or []
    base = {re.split(r"[<>=\[ ;]", r)[0].lower() for r in requirements if "extra ==" not in r}
    assert not base & {"duckdb", "myo-sim", "matplotlib", "tqdm", "grpcio-status", "pandas"}, base
    extras = {m.group(1) for r in requirements if (m := re.search(r'extra == "([a-z]+)"', r))}
    assert {"query", "myo", "experiments", "postgres", "all"} <= extras, extras


@pytest.mark.parametrize(
    ("hidden", "command", "message"),
    [
        (
            "duckdb",
            ["sessions", "query", "SELECT 1"],
            "jitdyn sessions query: needs DuckDB, which is not installed: pip install 'jitdyn[query]'",
        ),
        (
            "myo_sim",
            ["models", "register", "--myo", "myoelbow", "--server", "127.0.0.1:1"],
            "jitdyn models register: needs myo-sim (MyoSuite models), which is not installed: pip install 'jitdyn[myo]'",
        ),
        (
            "matplotlib",
            ["experiments", "--quick"],
            "jitdyn experiments: needs matplotlib (plots), which is not installed: pip install 'jitdyn[experiments]'",
        ),
    ],
)
def test_a_missing_extra_is_named(hidden: str, command: list[str], message: str, tmp_path: Path) -> None:
    (tmp_path / "index.sqlite").touch()  # `sessions` finds a data folder; the extra is checked first
    data = ["--data", str(tmp_path)] if command[0] == "sessions" else []
    result = jitdyn(*command, *data, preamble=f"sys.modules[{hidden!r}] = None  # as if not installed")
    assert one_line_error(result, 1) == message


# -- Must have 7: settings in one place --------------------------------------------------------------


def test_the_readme_lists_every_setting() -> None:
    from jitdyn.settings import settings_table

    assert settings_table() in (ROOT / "docs" / "cli.md").read_text(encoding="utf-8")
