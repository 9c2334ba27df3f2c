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
from _cli import jitdyn, listed, one_line_error, serving

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
@pytest.mark.slow  # 3-8 s of demos and servers
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


@pytest.mark.slow  # 3-8 s of demos and servers
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
    listing = listed(jitdyn("sessions", "list", "--limit", "500", "--data", str(data)).stdout)
    (row,) = [row for row in listing if row["id"] == ids[0]]
    assert (row["model"], row["scenario"], row["clock"]) == ("pendulum_1 v1", "PASSIVE", "LOCKSTEP"), row


@pytest.mark.slow  # 3-8 s of demos and servers
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


@pytest.mark.slow  # 3-8 s of demos and servers
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
    from jitdyn.settings import LIMITS, settings_for

    help_text = " ".join(jitdyn("serve", "--help").stdout.split())
    limits = [s for s in settings_for("serve") if s.group == LIMITS]
    assert len(limits) == 11 and f"{LIMITS}:" in help_text
    for limit in limits:
        assert f"{limit.flag} {limit.metavar} " in help_text, limit.flag
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
        "role": "",  # a pendulum's hinge is no hip, knee or ankle
        "role_source": "",
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
    page = " ".join((ROOT / "docs" / "data.md").read_text(encoding="utf-8").split())
    assert "`late` counts the ticks whose frame came after the tick was answered" in page


@pytest.mark.slow  # 3-8 s of demos and servers
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


def manual_blocks(page: str) -> list[tuple[str, str]]:
    """The fenced blocks (language, code) of the manual's `page` before its first section, in order."""
    text = (ROOT / "docs" / page).read_text(encoding="utf-8")
    end = text.find("\n## ")
    return re.findall(r"```(\w+)\n(.*?)```", text[: end if end >= 0 else None], re.DOTALL)


def test_the_first_sdk_example_falls_as_mujoco_does(server: Any, tmp_path: Path) -> None:
    import mujoco

    from jitdyn.registry import builtin_model_path

    blocks = manual_blocks("sdk.md")
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
    page = " ".join((ROOT / "docs" / "sdk.md").read_text(encoding="utf-8").split())
    assert f"({', '.join(f'{t:.3f}' for t in truth[:4])} and {truth[4]:.3f} rad)" in page, truth


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


@pytest.mark.slow  # 3-8 s of demos and servers
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


@pytest.mark.slow  # 3-8 s of demos and servers
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


@pytest.mark.slow  # 3-8 s of demos and servers
def test_demo_of_a_model_whose_mjcf_is_not_here_says_why(server: Any, tmp_path: Path) -> None:
    (tmp_path / "swing.xml").write_text(SWING, encoding="utf-8")
    registered = jitdyn("models", "register", str(tmp_path / "swing.xml"), "--server", server.address)
    assert registered.returncode == 0, registered.stderr
    result = jitdyn("demo", "--model", "swing", "--server", server.address)
    assert one_line_error(result, 1) == (
        f"jitdyn demo: FailedPrecondition: swing v1 is registered at {server.address}, but the demo simulates "
        "its truth here and has no copy of its MJCF: give the file it was registered from (--mjcf FILE, "
        "with --asset-dir for its assets), or run the demo on the data folder that holds it (--data DIR)"
    )
    unknown = jitdyn("demo", "--model", "no_such_model:2", "--server", server.address)
    assert one_line_error(unknown, 1).startswith("jitdyn demo: NotFound: ")


@pytest.mark.slow  # 3-8 s of demos and servers
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


# -- the demo's summary: forces in the units of each dof, over the answers the store holds ------------


@pytest.mark.slow  # 3-8 s of demos and servers
def test_the_demos_force_ranges_are_the_stored_ones_in_each_dofs_unit(server: Any) -> None:
    out = jitdyn(
        "demo", "--model", "biped", "--seconds", "1s", "--clock", "realtime", "--server", server.address
    )
    assert out.returncode == 0, out.stderr
    session_id = re.search(r"^session (\S+):", out.stdout, re.MULTILINE)
    ranges = re.search(
        r"^qfrc_inverse range per dof over .*?\((\d+) of them corrections, as stored\): (.*)$",
        out.stdout,
        re.MULTILINE,
    )
    assert session_id and ranges, out.stdout
    assert int(ranges.group(1)) > 0, "no tick was corrected: the test proves nothing"
    printed = re.findall(r"\[([-+\d.]+), ([-+\d.]+)\] (N m|N)(?:,|$)", ranges.group(2))
    # root_x, root_z (slides: N), then each leg's hip (hinge: N m) and absorber (slide: N).
    assert [unit for *_, unit in printed] == ["N", "N", "N m", "N", "N m", "N"], ranges.group(2)
    bounds = ", ".join(f"min(qfrc_inverse[{i}]) lo{i}, max(qfrc_inverse[{i}]) hi{i}" for i in range(1, 7))
    sql = (
        f"SELECT {bounds} FROM frames WHERE session_id = '{session_id.group(1)}' AND kind = 'result' "
        "AND seq < 100"
    )
    stored = jitdyn("sessions", "query", sql, "--format", "json", "--data", str(server.services.data_root))
    assert stored.returncode == 0, stored.stderr
    row = json.loads(stored.stdout)
    for i, (lo, hi, _) in enumerate(printed, start=1):
        assert (float(lo), float(hi)) == (round(row[f"lo{i}"], 2), round(row[f"hi{i}"], 2)), (i, printed, row)


# -- files that are not UTF-8 MJCF, a missing mesh ----------------------------------------------------


def test_a_file_that_is_not_text_is_one_line(server: Any, tmp_path: Path) -> None:
    png = tmp_path / "arm.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)))
    result = jitdyn("models", "register", str(png), "--server", server.address)
    assert one_line_error(result, 1) == (
        f"jitdyn models register: InvalidArgument: {str(png)!r} is not UTF-8 text (byte 0x89 at offset 0), "
        "and no XML declaration names its encoding: an MJCF file is XML text"
    )


def test_an_mjcf_in_the_encoding_its_declaration_names_registers(server: Any, tmp_path: Path) -> None:
    latin = tmp_path / "bras.xml"
    latin.write_bytes(
        '<?xml version="1.0" encoding="ISO-8859-1"?>\n<!-- le bras gauche, épaule fixe -->\n'
        '<mujoco model="bras"><worldbody><body><joint name="coude" type="hinge"/>'
        '<geom size=".1" mass="1"/></body></worldbody></mujoco>\n'.encode("iso-8859-1")
    )
    result = jitdyn("models", "register", str(latin), "--server", server.address)
    assert result.returncode == 0, result.stderr
    assert re.match(r"registered: sha256:\w+  bras v1  nq=1 ", result.stdout), result.stdout


def test_a_missing_mesh_says_where_it_looked_and_names_asset_dir(server: Any, tmp_path: Path) -> None:
    arm = tmp_path / "arm.xml"
    arm.write_text(
        '<mujoco><asset><mesh name="upper" file="meshes/upper.stl"/></asset>\n<worldbody><body>'
        '<joint type="hinge"/><geom type="mesh" mesh="upper"/></body></worldbody></mujoco>',
        encoding="utf-8",
    )
    result = jitdyn("models", "register", str(arm), "--server", server.address)
    assert one_line_error(result, 1) == (
        f"jitdyn models register: InvalidArgument: mesh 'upper' (line 1) names the file 'meshes/upper.stl', "
        f"which is not in the MJCF's folder {str(tmp_path)!r} (looked for "
        f"{str(tmp_path / 'meshes/upper.stl')!r}); give the folder that holds the model's files with "
        "--asset-dir DIR"
    )


# -- the demo of a model registered from a file, against a server; its start pose ---------------------

# An elbow whose range starts at its rest pose, as myoelbow's: a start moved below it is outside.
ELBOW = """<mujoco model="elbow">
  <compiler angle="radian"/>
  <worldbody><body pos="0 0 1"><joint name="elbow" type="hinge" axis="0 1 0" range="0 2.27" damping="0.5"/>
    <geom type="capsule" size=".03" fromto="0 0 0 .3 0 0" mass="1"/></body></worldbody>
</mujoco>
"""


@pytest.mark.slow  # 3-8 s of demos and servers
def test_the_demo_runs_a_model_the_server_holds_inside_its_range(server: Any, tmp_path: Path) -> None:
    mjcf = tmp_path / "elbow.xml"
    mjcf.write_text(ELBOW, encoding="utf-8")
    registered = jitdyn("models", "register", str(mjcf), "--server", server.address)
    assert registered.returncode == 0, registered.stderr
    demo = [
        "demo",
        "--model",
        "elbow",
        "--seconds",
        "0.3s",
        "--clock",
        "lockstep",
        "--server",
        server.address,
    ]
    data = str(server.services.data_root)
    sessions = []
    for extra in (["--mjcf", str(mjcf)], ["--data", data]):
        result = jitdyn(*demo, *extra, cwd=tmp_path)
        assert result.returncode == 0, result.stderr
        sessions.append(re.search(r"^session (\S+):", result.stdout, re.MULTILINE).group(1))  # type: ignore[union-attr]
    ids = ", ".join(f"'{s}'" for s in sessions)
    sql = f"SELECT frame_qpos[1] AS q FROM frames WHERE session_id IN ({ids}) AND seq = 0"
    starts = jitdyn("sessions", "query", sql, "--format", "json", "--data", data)
    assert starts.returncode == 0, starts.stderr
    for line in starts.stdout.splitlines():
        assert 0.0 <= json.loads(line)["q"] <= 2.27, starts.stdout
    other = tmp_path / "other.xml"
    other.write_text(ELBOW.replace('damping="0.5"', 'damping="0.6"'), encoding="utf-8")
    wrong = jitdyn(*demo, "--mjcf", str(other), cwd=tmp_path)
    assert "is not the content registered as elbow v1: its id is sha256:" in one_line_error(wrong, 1)


# -- one casing everywhere, help that explains --------------------------------------------------------


@pytest.mark.slow  # 3-8 s of demos and servers
def test_the_demo_takes_its_words_in_any_case(server: Any) -> None:
    for scenario, estimator, clock in (
        ("PASSIVE", "ukf", "LockStep"),
        ("passive", "Constant_Velocity", "lockstep"),
    ):
        result = jitdyn(
            "demo", "--seconds", "0.2s", "--model", "pendulum_1", "--server", server.address,
            "--scenario", scenario, "--estimator", estimator, "--clock", clock,
        )  # fmt: skip
        assert result.returncode == 0, result.stderr
        assert f"passive, dt 50 ms, 4 ticks, LOCKSTEP, estimator {estimator.upper()}" in result.stdout
    bad = jitdyn("demo", "--scenario", "hovering")
    assert one_line_error(bad, 2) == (
        "jitdyn demo: error: argument --scenario: expected one of passive, controlled, external, driven "
        "(in any case), got 'hovering'"
    )


def test_every_demo_option_has_help() -> None:
    import argparse

    from jitdyn.cli.main import build_parser

    parser = build_parser()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    demo = commands.choices["demo"]
    silent = [a.option_strings[0] for a in demo._actions if a.option_strings and not a.help]
    assert silent == [], silent


# -- the version, options before the action, the sessions table, render by prefix ---------------------


def test_the_version_is_the_installed_packages() -> None:
    from importlib.metadata import version

    result = jitdyn("--version")
    assert (result.returncode, result.stdout) == (0, f"jitdyn {version('jitdyn')}\n"), result.stderr


@pytest.mark.slow  # 3-8 s of demos and servers
def test_an_actions_options_go_before_it_too(sessions_data: tuple[Path, list[str]]) -> None:
    data, _ = sessions_data
    after = jitdyn("sessions", "list", "--limit", "2", "--status", "complete", "--data", str(data))
    assert after.returncode == 0 and len(listed(after.stdout)) == 2, after.stdout + after.stderr
    for args in (
        ["--limit", "2", "--status", "COMPLETE", "list"],
        ["--limit=2", "--data", str(data), "--status", "Complete", "list"],
        ["-v", "--limit", "2", "list", "--status", "complete"],
    ):
        before = jitdyn("sessions", *args, "--data", str(data))
        assert (before.returncode, before.stdout) == (0, after.stdout), before.stderr


@pytest.mark.slow  # 3-8 s of demos and servers
def test_sessions_list_has_a_header_and_takes_a_version(server: Any, tmp_path: Path) -> None:
    from jitdyn.client import Client, FrameData, SessionOptions

    long_name = "a_model_with_a_name_longer_than_the_column_was"
    mjcf = tmp_path / f"{long_name}.xml"
    with Client(server.address, timeout=30) as client:
        for damping in (0.21, 0.22):  # two versions of one name
            mjcf.write_text(ELBOW.replace('damping="0.5"', f'damping="{damping}"'), encoding="utf-8")
            assert jitdyn("models", "register", str(mjcf), "--server", server.address).returncode == 0
            with client.open_session(
                SessionOptions(model_name=long_name, dt=0.05, clock="LOCKSTEP")
            ) as session:
                session.send_frame(FrameData(seq=0, t=0.0, qpos=[0.3], qvel=[0.0]))
    data = str(server.services.data_root)
    table = jitdyn("sessions", "list", "--data", data).stdout
    header, _, *rows = table.splitlines()
    assert header.split() == [
        "id", "started", "status", "model", "scenario", "clock", "ticks", "measured", "predicted", "corrected",
        "rejected", "late",
    ]  # fmt: skip
    # Every column starts where its header does, however long a model's name.
    for name in ("status", "scenario", "clock"):
        column = header.index(name)
        assert all(row[column - 2 : column] == "  " and row[column] != " " for row in rows[:3]), (name, table)
    assert {len(row) for row in rows} == {len(header)}, table  # the counts right-aligned under theirs
    for reference, versions in ((f"{long_name}:2", ["v2"]), (long_name, ["v2", "v1"])):
        shown = listed(jitdyn("sessions", "list", "--model", reference, "--data", data).stdout)
        assert [row["model"].split()[-1] for row in shown] == versions, shown
    none = jitdyn("sessions", "list", "--model", f"{long_name}:3", "--data", data)
    assert none.returncode == 0 and none.stdout == "", none.stdout
    assert none.stderr.startswith("no sessions match; the stored sessions are of "), none.stderr
    assert f"{long_name} v1, {long_name} v2" in none.stderr


def test_render_takes_an_id_prefix(sessions_data: tuple[Path, list[str]], tmp_path: Path) -> None:
    data, ids = sessions_data
    out = tmp_path / "frame.png"
    result = jitdyn("sessions", "render", ids[0][:8], "--out", str(out), "--data", str(data))
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == f"rendered {ids[0]} to {out}"
    assert out.stat().st_size > 0


# -- the registry: unknown names list the known ones; a new version keeps its tags --------------------


def test_an_unknown_model_lists_the_models_there_are(server: Any) -> None:
    result = jitdyn("models", "show", "pendulum_4", "--server", server.address)
    message = one_line_error(result, 1)
    assert message.startswith(
        "jitdyn models show: NotFound: no model is named 'pendulum_4'; the registered models are "
    ), message
    assert "biped, " in message and "pendulum_1, pendulum_2, pendulum_3" in message


def test_a_new_version_keeps_the_tags_of_the_last(server: Any, tmp_path: Path) -> None:
    mjcf = tmp_path / "tagged_arm.xml"
    tags: list[str] = []
    for damping, given in ((0.31, ["--tag", "lab", "--tag", "arm"]), (0.32, []), (0.33, ["--tag", "v3"])):
        mjcf.write_text(ELBOW.replace('damping="0.5"', f'damping="{damping}"'), encoding="utf-8")
        result = jitdyn("models", "register", str(mjcf), *given, "--server", server.address)
        assert result.returncode == 0, result.stderr
        tags.append(result.stdout.split("tags=")[1].strip())
    assert tags == ["lab,arm", "lab,arm", "v3"], tags


def test_experiments_help_gives_the_exit_codes_and_the_environment() -> None:
    help_text = jitdyn("experiments", "--help", preamble=BASE_INSTALL).stdout
    assert (
        "exit codes: 0 done (report.md written in --out), 1 an experiment or the server failed" in help_text
    )
    environment = help_text[help_text.index("environment:\n") :]
    for name in ("JITDYN_SERVER", "JITDYN_SECRET", "JITDYN_SECRET_FILE", "MUJOCO_GL"):
        assert name in environment, help_text


def test_the_readme_tells_a_first_sdk_session_what_it_needs(server: Any) -> None:
    import dataclasses

    from jitdyn.client import Client, FrameData, Opened, Rejection, SessionOptions

    page = (ROOT / "docs" / "sdk.md").read_text(encoding="utf-8")
    section = page[page.index("What else a first session needs to know:") : page.index("## Async")]
    said = " ".join(section.split())
    assert "`send_frame` and `skip` return a `TickResult` or a `Rejection`" in said
    assert '`model_name="arm"` opens the newest version of `arm`; `model_version=2` pins one' in said
    quoted = re.search(r'rejected BAD_SHAPE \("(.+?)"\)', said)
    assert quoted and 'measured=["QPOS", "QVEL", "QACC"]' in said, said
    named = re.findall(
        r"`(\w+)`", said[said.index("`s.opened` is") : said.index("The calls that change nothing")]
    )
    fields = {field.name for field in dataclasses.fields(Opened)}
    assert len(named) >= 8 and set(named) <= fields | {"s", "opened"}, set(named) - fields
    with Client(server.address, timeout=30) as client:
        options = SessionOptions(model_name="pendulum_1", scenario="PASSIVE", dt=0.05)
        with client.open_session(options) as session:
            answer = session.send_frame(FrameData(seq=0, t=0.0, qpos=[0.3], qvel=[0.0], qacc=[1.0]))
        assert isinstance(answer, Rejection) and answer.reason == "BAD_SHAPE", answer
        assert quoted.group(1) in answer.message, answer.message
        measured = dataclasses.replace(options, measured=["QPOS", "QVEL", "QACC"])
        with client.open_session(measured) as session:
            answer = session.send_frame(FrameData(seq=0, t=0.0, qpos=[0.3], qvel=[0.0], qacc=[1.0]))
        assert not isinstance(answer, Rejection), answer


# -- the frames' arrays named, their columns' units documented ----------------------------------------


def test_every_frames_column_is_explained_with_its_unit(sessions_data: tuple[Path, list[str]]) -> None:
    from jitdyn.storage.columns import FRAME_COLUMN_NOTES

    data, _ = sessions_data
    described = jitdyn("sessions", "query", "DESCRIBE frames", "--format", "json", "--data", str(data))
    assert described.returncode == 0, described.stderr
    columns = [json.loads(line)["column_name"] for line in described.stdout.splitlines()]
    assert columns == list(FRAME_COLUMN_NOTES), set(columns) ^ set(FRAME_COLUMN_NOTES)
    help_text = jitdyn("sessions", "query", "--help").stdout
    assert "  frame_delay          s: REALTIME, the frame's arrival after its tick's deadline" in help_text
    assert "(table `coordinates`:" in help_text


def test_coordinates_name_each_element_of_the_arrays_with_its_unit(server: Any) -> None:
    from jitdyn.client import Client, FrameData, SessionOptions

    options = SessionOptions(model_name="biped", scenario="PASSIVE", dt=0.01, clock="LOCKSTEP")
    with Client(server.address, timeout=30) as client, client.open_session(options) as session:
        session.send_frame(FrameData(seq=0, t=0.0, qpos=[0.0, 0.9, 0.3, 0.0, -0.3, 0.0], qvel=[0.0] * 6))
    sql = (
        "SELECT c.vector, c.i, c.name, c.unit, c.force_unit, f.frame_qpos[c.i] AS q FROM frames f "
        f"JOIN coordinates c USING (session_id) WHERE session_id = '{session.opened.session_id}' "
        "AND f.seq = 0 ORDER BY c.vector DESC, c.i"
    )
    result = jitdyn("sessions", "query", sql, "--format", "json", "--data", str(server.services.data_root))
    assert result.returncode == 0, result.stderr
    rows = [json.loads(line) for line in result.stdout.splitlines()]
    names = ["root_x", "root_z", "left_hip", "left_absorber", "right_hip", "right_absorber"]
    assert [(r["vector"], r["name"]) for r in rows] == [("qpos", n) for n in names] + [
        ("dof", n) for n in names
    ]
    assert [r["q"] for r in rows[:6]] == [0.0, 0.9, 0.3, 0.0, -0.3, 0.0]
    assert [(r["unit"], r["force_unit"]) for r in rows[6:]] == [
        ("m", "N"), ("m", "N"), ("rad", "N m"), ("m", "N"), ("rad", "N m"), ("m", "N"),
    ]  # fmt: skip


def test_the_readme_says_how_long_the_suite_takes() -> None:
    readme = " ".join((ROOT / "README.md").read_text(encoding="utf-8").split())
    assert "about 12 to 16 minutes on a 2-core machine" in readme
