"""What a newcomer tripped on, trying jitdyn as a new user would: one test per item, each run as a
user runs the command (a separate process, a real server on a loopback port)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from _cli import jitdyn, one_line_error, serving

from jitdyn.errors import JitdynError

ROOT = Path(__file__).resolve().parents[2]

# A base install, as far as the commands can tell: every extra's module hidden.
BASE_INSTALL = "\n".join(
    f"sys.modules[{name!r}] = None" for name in ("matplotlib", "PIL", "tqdm", "myo_sim", "biomdp", "duckdb")
)


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


# -- every duration takes a unit; a bare number keeps its documented meaning --------------------------


def idle_session_ends_after(address: str) -> str:
    """What a server says to a LOCKSTEP session that sends nothing for 1.5 s after its open."""
    from jitdyn.client import Client, FrameData, SessionOptions

    with Client(address, resume=False, timeout=10) as client:
        session = client.open_session(SessionOptions(model_name="pendulum_1", dt=0.05))
        time.sleep(1.5)
        with pytest.raises(JitdynError) as ended:
            session.send_frame(FrameData(seq=0, t=0.0, qpos=[0.3], qvel=[0.0]))
    return str(ended.value)


@pytest.mark.parametrize(
    ("flags", "env", "said"),
    [
        (["--idle-timeout", "800ms"], {}, "for 0.8 s, the limit (--idle-timeout)"),
        (["--idle-timeout", "1"], {}, "for 1 s, the limit (--idle-timeout)"),  # bare: seconds, as always
        ([], {"JITDYN_IDLE_TIMEOUT": "0.6s"}, "for 0.6 s, the limit (--idle-timeout)"),
    ],
)
def test_serve_takes_the_idle_timeout_with_a_unit(
    flags: list[str], env: dict[str, str], said: str, tmp_path: Path
) -> None:
    with serving(*flags, data=tmp_path / "data", env=env) as address:
        assert said in idle_session_ends_after(address)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["serve", "--idle-timeout", "2min"],
            (
                "jitdyn serve: error: argument --idle-timeout: expected a duration > 0, like 60s, 500ms or "
                "60 (seconds), got '2min'"
            ),
        ),
        (
            ["serve", "--compile-timeout", "0s"],
            (
                "jitdyn serve: error: argument --compile-timeout: expected a duration > 0, like 60s, 500ms or "
                "60 (seconds), got '0s'"
            ),
        ),
        (
            ["demo", "--seconds", "2 h"],
            (
                "jitdyn demo: error: argument --seconds: expected a duration > 0, like 10s, 2500ms or 10 "
                "(seconds), got '2 h'"
            ),
        ),
        (
            ["demo", "--latency", "35"],
            (
                "jitdyn demo: error: argument --latency: a duration needs a unit (us, ms or s): write 35ms or "
                "35s, got '35'"
            ),
        ),
    ],
)
def test_a_bad_duration_is_one_line(args: list[str], message: str, tmp_path: Path) -> None:
    result = jitdyn(*args, "--data", str(tmp_path / "data"))
    assert one_line_error(result, 2) == message
    assert not (tmp_path / "data").exists()


def test_a_bad_limit_in_the_environment_is_named(tmp_path: Path) -> None:
    result = jitdyn("serve", "--data", str(tmp_path / "data"), env={"JITDYN_MAX_CLOCK_OFFSET": "5 min"})
    assert one_line_error(result, 2) == (
        "jitdyn serve: environment variable JITDYN_MAX_CLOCK_OFFSET: expected a duration > 0, like 60s, "
        "500ms or 60 (seconds), got '5 min'"
    )
    assert not (tmp_path / "data").exists()


def test_demo_seconds_take_a_unit(server: Any, tmp_path: Path) -> None:
    for seconds in ("500ms", "0.5"):
        out = jitdyn("demo", "--seconds", seconds, "--model", "pendulum_1", "--server", server.address)
        assert out.returncode == 0, out.stderr
        assert "answers received for 10 of the 10 ticks" in out.stdout, out.stdout


# -- a mistyped option, -v, id prefixes, the scenario as stored, the limit flags, models show ---------


def test_a_mistyped_option_shows_the_subcommands_usage() -> None:
    result = jitdyn("demo", "--lattency", "35ms")
    assert result.returncode == 2, result.stderr
    assert result.stderr.startswith("usage: jitdyn demo "), result.stderr
    assert result.stderr.splitlines()[-1] == (
        "jitdyn demo: error: unrecognized arguments: --lattency 35ms (did you mean --latency?)"
    )
    nested = jitdyn("sessions", "list", "--limt", "3")
    assert nested.stderr.startswith("usage: jitdyn sessions list "), nested.stderr
    assert "did you mean --limit?" in nested.stderr


@pytest.fixture(scope="module")
def sessions_data(server: Any) -> tuple[Path, list[str]]:
    """The server's data folder with LOCKSTEP sessions, until two ids start with the same digit
    (at most 17: there are 16)."""
    from jitdyn.client import Client, FrameData, SessionOptions

    ids: list[str] = []
    with Client(server.address, timeout=30) as client:
        while len({i[0] for i in ids}) == len(ids):
            options = SessionOptions(model_name="pendulum_1", dt=0.05, scenario="PASSIVE")
            with client.open_session(options) as session:
                session.send_frame(FrameData(seq=0, t=0.0, qpos=[0.3], qvel=[0.0]))
            ids.append(session.opened.session_id)
    return server.services.data_root, ids


def test_verbose_puts_no_migration_lines_before_a_listing(sessions_data: tuple[Path, list[str]]) -> None:
    data, ids = sessions_data
    result = jitdyn("-v", "sessions", "list", "--data", str(data))
    assert result.returncode == 0, result.stderr
    assert "alembic" not in result.stderr, result.stderr
    assert ids[-1] in result.stdout


def test_sessions_list_prints_the_scenario_as_stored(sessions_data: tuple[Path, list[str]]) -> None:
    data, ids = sessions_data
    listing = jitdyn("sessions", "list", "--data", str(data)).stdout
    line = next(line for line in listing.splitlines() if line.startswith(ids[0]))
    assert re.search(r" pendulum_1 v1  PASSIVE +LOCKSTEP +ticks", line), line


def test_a_session_id_prefix_is_accepted(sessions_data: tuple[Path, list[str]], tmp_path: Path) -> None:
    data, ids = sessions_data
    full, prefix = ids[0], ids[0][:8]
    shown = jitdyn("sessions", "show", prefix, "--data", str(data))
    assert shown.returncode == 0 and shown.stdout.startswith(full), shown.stdout + shown.stderr
    exported = jitdyn("sessions", "export", prefix, "--data", str(data), cwd=tmp_path)
    assert exported.stdout.strip() == f"exported {full} as csv to {full}.csv", exported.stderr
    assert (tmp_path / f"{full}.csv").is_file()
    plotted = jitdyn("sessions", "plot", prefix, "--data", str(data), cwd=tmp_path)
    assert plotted.stdout.strip() == f"plotted {full} to {full}.png", plotted.stderr
    assert (tmp_path / f"{full}.png").stat().st_size > 0


def test_an_ambiguous_prefix_lists_the_candidates(sessions_data: tuple[Path, list[str]]) -> None:
    data, ids = sessions_data
    digit = ids[-1][0]
    listing = jitdyn("sessions", "list", "--limit", "500", "--data", str(data)).stdout
    candidates = sorted(line.split()[0] for line in listing.splitlines() if line.startswith(digit))
    assert len(candidates) >= 2, listing
    shown = ", ".join(candidates[:5]) + (", ..." if len(candidates) > 5 else "")
    for action in ("show", "export", "plot"):
        result = jitdyn("sessions", action, digit, "--data", str(data))
        assert one_line_error(result, 1) == (
            f"jitdyn sessions {action}: InvalidArgument: session id prefix {digit!r} is ambiguous: it starts "
            f"{shown}; give more of it"
        )
    unknown = jitdyn("sessions", "show", "zz", "--data", str(data))
    assert one_line_error(unknown, 1) == "jitdyn sessions show: NotFound: session 'zz' not found"


def test_the_limit_flags_show_a_metavar_and_their_variable() -> None:
    from jitdyn.cli.limits import _LIMITS

    help_text = " ".join(jitdyn("serve", "--help").stdout.split())
    for limit in _LIMITS:
        assert f"{limit.flag} {limit.unit.metavar} " in help_text, limit.flag
        assert f"(env {limit.env}; default " in help_text, limit.flag
    assert "--idle-timeout DURATION how long a session may send nothing" in help_text
    assert "--max-history-bytes SIZE" in help_text and "IDLE_TIMEOUT (default" not in help_text


def test_models_show_prints_the_protos_names_and_its_zeros(server: Any) -> None:
    result = jitdyn("models", "show", "pendulum_1", "--server", server.address)
    assert result.returncode == 0, result.stderr
    shown = json.loads(result.stdout)
    assert shown["joints"][0] == {
        "name": "hinge_1",
        "type": "JOINT_TYPE_HINGE",
        "limited": False,
        "range_lower": 0.0,
        "range_upper": 0.0,
        "qpos_address": 0,
        "dof_address": 0,
    }
    assert shown["dimensions"]["na"] == 0 and shown["builtin"] is True
    assert not re.search(r'"[a-z]+[A-Z]\w*":', result.stdout), result.stdout


# -- late_compute and forecast_weights in `frames`; the `late` column explained ----------------------


def test_frames_hold_late_compute_and_the_forecast_weights(server: Any, tmp_path: Path) -> None:
    import mujoco
    import numpy as np

    from jitdyn.client import Client, FrameData, SessionOptions
    from jitdyn.registry import builtin_model_path

    model = mujoco.MjModel.from_xml_path(str(builtin_model_path("pendulum_1")))
    data = mujoco.MjData(model)
    data.qpos[0] = 0.6
    # No scenario on a model with a motor: DRIVEN, whose gaps the forecast combination answers.
    options = SessionOptions(model_name="pendulum_1", dt=0.05)
    with Client(server.address, timeout=30) as client, client.open_session(options) as session:
        for k in range(30):
            session.send_frame(FrameData(seq=k, t=k * 0.05, qpos=data.qpos.copy(), qvel=data.qvel.copy()))
            for _ in range(2):
                mujoco.mj_step(model, data)
        answers = {k: session.skip(k) for k in range(30, 34)}
    session_id = session.opened.session_id
    weights = {k: a.forecast_weights for k, a in answers.items() if getattr(a, "forecast_weights", None)}
    assert weights, "no gap was answered by the forecast combination: the test proves nothing"
    sql = (
        f"SELECT seq, source, late_compute, forecast_weights FROM frames WHERE session_id = '{session_id}' "
        "AND kind = 'result' ORDER BY seq"
    )
    result = jitdyn("sessions", "query", sql, "--format", "json", "--data", str(server.services.data_root))
    assert result.returncode == 0, result.stderr
    rows = [json.loads(line) for line in result.stdout.splitlines()]
    assert len(rows) == 34 and all(row["late_compute"] is False for row in rows)
    for row in rows:
        expected = weights.get(row["seq"])
        if expected is None:
            assert row["forecast_weights"] is None, row
        else:
            assert np.allclose(row["forecast_weights"], expected), (row, expected)


def test_the_late_column_is_explained() -> None:
    help_text = " ".join(jitdyn("sessions", "list", "--help").stdout.split())
    assert "late: ticks whose frame came after the tick was answered" in help_text, help_text
    readme = " ".join((ROOT / "README.md").read_text(encoding="utf-8").split())
    assert "`late` counts the ticks whose frame came after the tick was answered" in readme


def test_a_file_stored_before_those_columns_still_reads(tmp_path: Path) -> None:
    import pyarrow.parquet as pq

    data = tmp_path / "data"
    demo = jitdyn("demo", "--seconds", "0.5s", "--model", "pendulum_1", "--data", str(data), cwd=tmp_path)
    assert demo.returncode == 0, demo.stderr
    (stored,) = data.glob("frames/**/*.parquet")
    table = pq.read_table(stored)
    assert {"late_compute", "forecast_weights"} <= set(table.column_names)
    older = table.drop_columns(["late_compute", "forecast_weights"])
    pq.write_table(older.replace_schema_metadata(table.schema.metadata), stored)
    sql = "SELECT count(*) AS answers, count(late_compute) AS flagged FROM frames WHERE kind = 'result'"
    result = jitdyn("sessions", "query", sql, "--format", "json", "--data", str(data))
    assert result.returncode == 0, result.stderr
    counts = json.loads(result.stdout)
    assert counts["answers"] >= 10 and counts["flagged"] == 0, counts  # NULL: not known for this file
    session_id = stored.stem
    exported = jitdyn("sessions", "export", session_id[:8], "--data", str(data), cwd=tmp_path)
    assert exported.returncode == 0, exported.stderr
    header = (tmp_path / f"{session_id}.csv").read_text(encoding="utf-8").splitlines()[0]
    assert '"reinitialised","late_compute","compute_us"' in header, header


# -- the README's first SDK example does what a person expects ----------------------------------------


def readme_blocks(section: str) -> list[tuple[str, str]]:
    """The fenced blocks (language, code) of the README's `section`, in order."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    start = readme.index(f"\n## {section}\n")
    end = readme.find("\n## ", start + 1)
    return re.findall(r"```(\w+)\n(.*?)```", readme[start:end], re.DOTALL)


def test_the_first_sdk_example_falls_as_mujoco_does(server: Any, tmp_path: Path) -> None:
    import mujoco

    from jitdyn.registry import builtin_model_path

    blocks = readme_blocks("Python SDK")
    (language, code), (output_language, output) = blocks[0], blocks[1]
    assert (language, output_language) == ("python", "text")
    assert code.count('"127.0.0.1:50051"') == 1
    script = tmp_path / "example.py"
    script.write_text(code.replace('"127.0.0.1:50051"', repr(server.address)), encoding="utf-8")
    run = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, timeout=60, check=False
    )
    assert run.returncode == 0, run.stderr
    assert run.stdout == output, (run.stdout, output)
    # MuJoCo's own simulation of the pendulum let go at 0.3 rad, at the example's 50 ms ticks.
    model = mujoco.MjModel.from_xml_path(str(builtin_model_path("pendulum_1")))
    data = mujoco.MjData(model)
    data.qpos[0] = 0.3
    truth = []
    for _ in range(5):
        for _ in range(round(0.05 / model.opt.timestep)):
            mujoco.mj_step(model, data)
        truth.append(float(data.qpos[0]))
    predicted = [float(line.split()[2]) for line in run.stdout.splitlines()[1:]]
    assert len(predicted) == 5 and all(b < a for a, b in zip([0.3, *predicted], predicted, strict=False))
    assert max(abs(p - t) for p, t in zip(predicted, truth, strict=True)) < 0.012, (predicted, truth)
    readme = " ".join((ROOT / "README.md").read_text(encoding="utf-8").split())
    assert f"({', '.join(f'{t:.3f}' for t in truth[:4])} and {truth[4]:.3f} rad)" in readme, truth


# -- the demo: what the README promises, and the reasons of what it counts ----------------------------


def summary_counts(out: str) -> dict[str, int]:
    line = re.search(r"server's summary, as `jitdyn sessions list` shows it: (.*)", out)
    assert line, out
    return {name: int(value) for name, value in re.findall(r"([a-z]+) +(\d+)", line.group(1))}


def test_the_default_demo_shows_predictions_corrected(server: Any) -> None:
    readme = " ".join((ROOT / "README.md").read_text(encoding="utf-8").split())
    assert (
        "most ticks are answered PREDICTED by the estimator, then CORRECTED when their late frame arrives"
        in readme
    )
    result = jitdyn("demo", "--seconds", "3s", "--server", server.address)
    assert result.returncode == 0, result.stderr
    assert (
        "expect most ticks PREDICTED by the estimator, then CORRECTED when their frame arrives"
        in result.stdout
    )
    counts = summary_counts(result.stdout)
    assert counts["predicted"] > counts["measured"] and counts["corrected"] > 0, result.stdout
    if counts["rejected"]:  # a loaded machine: each rejection is explained
        assert re.search(r"^  rejected \d+: \d+ [A-Z_]+", result.stdout, re.MULTILINE), result.stdout


def test_the_demo_says_why_it_rejected(server: Any) -> None:
    # Frames 2.6 s late at 50 ms ticks are 52 ticks late, past the 50 the server keeps.
    result = jitdyn(
        "demo", "--model", "pendulum_1", "--latency", "2.6s", "--jitter", "0ms", "--loss", "0",
        "--seconds", "3s", "--server", server.address,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert (
        "past the 50 ticks (2500 ms) the server keeps to correct: expect every tick PREDICTED by the "
        "estimator and the frames rejected TOO_OLD" in result.stdout
    )
    assert "\n  rejected 60: 60 TOO_OLD\n" in result.stdout, result.stdout
    # "(history 50 ticks), got 0", or on a loaded machine that skipped a tick, that it did.
    assert re.search(
        r"^  TOO_OLD, as the server said of the first: frame 0: late frames are applied back to tick \d+",
        result.stdout,
        re.MULTILINE,
    ), result.stdout
    assert summary_counts(result.stdout)["rejected"] == 60


# -- the demo of any registered model -----------------------------------------------------------------

SWING = """<mujoco model="swing">
  <option timestep="0.005"/>
  <worldbody><body pos="0 0 1"><joint name="rope" type="hinge" axis="0 1 0" limited="true" range="-1.2 1.2"/>
    <geom type="capsule" fromto="0 0 0 0 0 -0.8" size="0.03" mass="2"/></body></worldbody>
</mujoco>
"""


def test_demo_takes_a_registered_myosuite_model(server: Any) -> None:
    registered = jitdyn("models", "register", "--myo", "myoelbow", "--server", server.address)
    assert registered.returncode == 0, registered.stderr
    model_id = re.search(r"(sha256:[0-9a-f]{64})  myoelbow v1", registered.stdout)
    assert model_id, registered.stdout
    for reference in ("myoelbow", model_id.group(1)):
        result = jitdyn("demo", "--model", reference, "--seconds", "1s", "--server", server.address)
        assert result.returncode == 0, result.stderr
        # No --scenario: the server's choice for a model with actuators, with its reason.
        assert re.search(r": myoelbow v1 \(1 dof\), driven \(.+\), dt 20 ms, 50 ticks", result.stdout), (
            result.stdout
        )
        assert summary_counts(result.stdout)["ticks"] >= 50, result.stdout


def test_demo_of_a_model_whose_mjcf_is_not_here_says_why(server: Any, tmp_path: Path) -> None:
    (tmp_path / "swing.xml").write_text(SWING, encoding="utf-8")
    registered = jitdyn("models", "register", str(tmp_path / "swing.xml"), "--server", server.address)
    assert registered.returncode == 0, registered.stderr
    result = jitdyn("demo", "--model", "swing", "--server", server.address)
    assert one_line_error(result, 1) == (
        f"jitdyn demo: FailedPrecondition: swing v1 is registered at {server.address}, but the demo simulates "
        "its truth here and has no copy of its MJCF: run the demo without --server, on the data folder that "
        "holds it (--data DIR)"
    )
    unknown = jitdyn("demo", "--model", "no_such_model:2", "--server", server.address)
    assert one_line_error(unknown, 1).startswith("jitdyn demo: NotFound: ")


def test_demo_of_a_model_registered_in_the_data_folder(tmp_path: Path) -> None:
    (tmp_path / "swing.xml").write_text(SWING, encoding="utf-8")
    data = tmp_path / "data"
    with serving(data=data) as address:
        registered = jitdyn("models", "register", str(tmp_path / "swing.xml"), "--server", address)
        assert registered.returncode == 0, registered.stderr
    result = jitdyn("demo", "--model", "swing:1", "--seconds", "1s", "--data", str(data), cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    # No actuators: the server's choice is PASSIVE, and the swing falls as it did here.
    assert re.search(r": swing v1 \(1 dof\), passive \(.+\), dt 50 ms, 20 ticks", result.stdout), (
        result.stdout
    )
    counts = summary_counts(result.stdout)
    assert counts["ticks"] >= 20 and counts["predicted"] + counts["measured"] >= 20, result.stdout
    assert re.search(r"predicted ticks after the first frame: \|q error\| vs truth median", result.stdout)
