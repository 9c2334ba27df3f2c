"""The `jitdyn` command line, run as a user runs it: a separate process against a real server."""

from __future__ import annotations

import os
import re
import secrets
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

MJCF = """<mujoco model="arm">
  <compiler meshdir="meshes"/>
  <asset><mesh name="box" file="box.obj"/></asset>
  <include file="parts.xml"/>
  <worldbody><body><joint name="elbow" type="hinge" axis="0 1 0"/><geom type="mesh" mesh="box" mass="1"/></body></worldbody>
</mujoco>
"""
OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"


def jitdyn(*args: str, cwd: Path | None = None, check: bool = True) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, JITDYN_SECRET=secrets.token_hex(32))
    result = subprocess.run(
        [sys.executable, "-m", "jitdyn.cli", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=env,
        timeout=300,
        check=False,
    )
    if check:
        assert result.returncode == 0, result.stdout + result.stderr
    return result


@pytest.fixture()
def arm(tmp_path: Path) -> Path:
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "box.obj").write_text(OBJ)
    (tmp_path / "meshes" / "unrelated.txt").write_text("not sent")
    (tmp_path / "parts.xml").write_text("<mujoco><default/></mujoco>")
    (tmp_path / "arm.xml").write_text(MJCF)
    return tmp_path / "arm.xml"


def test_models_register_list_show(server: Any, arm: Path) -> None:
    first = jitdyn("models", "--server", server.address, "register", str(arm), "--tag", "lab")
    assert "registering 'arm': 2 assets" in first.stderr
    assert first.stdout.startswith("registered: sha256:")
    again = jitdyn("models", "--server", server.address, "register", str(arm))
    assert again.stdout.startswith("already registered (identical content)")
    listing = jitdyn("models", "--server", server.address, "list", "--tag", "lab").stdout
    assert re.search(r"sha256:[0-9a-f]{64}  arm v1  nq=1 nv=1 nu=0", listing), listing
    shown = jitdyn("models", "--server", server.address, "show", "arm:1").stdout
    assert '"name": "elbow"' in shown and '"type": "JOINT_TYPE_HINGE"' in shown


def test_models_register_refuses_a_file_outside_the_asset_folder(server: Any, tmp_path: Path) -> None:
    evil = tmp_path / "evil.xml"
    evil.write_text('<mujoco><asset><hfield name="h" file="../../etc/hostname"/></asset></mujoco>')
    result = jitdyn("models", "--server", server.address, "register", str(evil), check=False)
    assert result.returncode == 1
    assert (
        "InvalidArgument: hfield 'h' (line 1) attribute file refers to file '../../etc/hostname'"
        in result.stderr
    )


def test_unknown_model_is_a_clear_error(server: Any) -> None:
    result = jitdyn("models", "--server", server.address, "show", "no_such_model", check=False)
    assert result.returncode == 1 and "NotFound" in result.stderr and "no_such_model" in result.stderr


def test_demo_against_a_running_server(server: Any) -> None:
    out = jitdyn(
        "demo", "--server", server.address, "--seconds", "1.5", "--model", "pendulum_2", "--latency", "20ms"
    ).stdout
    assert "answers received for 30 of the 30 ticks" in out, out
    # No --estimator: the server's choice, by the model's cost, said in the session's line.
    assert re.search(r"^session \S+: pendulum_2 .*, estimator UKF \(chosen by cost", out, re.MULTILINE), out
    assert re.search(
        r"stored: frames/model=pendulum_2/date=\d{4}-\d\d-\d\d/[0-9a-f-]{36}\.parquet "
        rf"\(in the data folder of the server at {re.escape(server.address)}\)",
        out,
    ), out


def test_demo_starts_its_own_server_and_stores_locally(tmp_path: Path) -> None:
    out = jitdyn("demo", "--seconds", "1", "--data", str(tmp_path / "data")).stdout
    assert "starting a local jitdyn server" in out
    stored = re.search(r"stored: (\S+\.parquet)", out)
    assert stored and Path(stored.group(1)).is_absolute() and Path(stored.group(1)).is_file(), out
    listing = jitdyn("sessions", "--data", str(tmp_path / "data"), "list").stdout
    assert "COMPLETE" in listing and "pendulum_3" in listing


@pytest.mark.parametrize(
    "command", [[], ["serve"], ["models"], ["demo"], ["sessions"], ["sessions", "query"]]
)
def test_every_command_explains_itself(command: list[str]) -> None:
    assert "usage: jitdyn" in jitdyn(*command, "--help").stdout


def test_bad_flags_say_what_was_expected() -> None:
    result = jitdyn("demo", "--latency", "fast", check=False)
    assert result.returncode == 2
    assert (
        "argument --latency: expected a duration with a unit, like 35ms or 0.5s, got 'fast'" in result.stderr
    )
    result = jitdyn("sessions", "--data", "/nonexistent/jitdyn", "list", check=False)
    assert result.returncode == 1 and "no jitdyn data in /nonexistent/jitdyn" in result.stderr


@pytest.mark.parametrize(
    ("root", "message"),
    [
        (
            "gs://bucket/p",
            (
                "jitdyn serve: InvalidArgument: --data-root scheme 'gs' is not supported; use "
                "s3://bucket/prefix, file:///path or a path, got 'gs://bucket/p'\n"
            ),
        ),
        (
            "s3://",
            "jitdyn serve: InvalidArgument: --data-root 's3://' names no bucket; write s3://BUCKET/PREFIX\n",
        ),
    ],
)
def test_serve_refuses_a_bad_data_root_before_touching_the_data_folder(
    tmp_path: Path, root: str, message: str
) -> None:
    result = jitdyn(
        "serve", "--address", "127.0.0.1:0", "--processes", "1", "--data", str(tmp_path / "data"),
        "--data-root", root, check=False,
    )  # fmt: skip
    assert (result.returncode, result.stderr) == (1, message)
    assert not (tmp_path / "data").exists()


def test_serve_names_an_unreachable_data_root_and_why(tmp_path: Path) -> None:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]  # nobody listens there once the socket is closed
    result = subprocess.run(
        [sys.executable, "-m", "jitdyn.cli", "serve", "--address", "127.0.0.1:0", "--processes", "2",
         "--data", str(tmp_path / "data"), "--data-root", "s3://bucket/prefix"],
        capture_output=True, text=True, timeout=120, check=False,
        env=dict(os.environ, JITDYN_SECRET=secrets.token_hex(32), AWS_ENDPOINT_URL=f"http://127.0.0.1:{port}",
                 AWS_REGION="us-east-1", AWS_ACCESS_KEY_ID="testing", AWS_SECRET_ACCESS_KEY="testing"),
    )  # fmt: skip
    assert result.returncode == 1
    assert result.stderr.startswith(
        "jitdyn serve: Unavailable: the data root s3://bucket/prefix cannot be reached: "
    ), result.stderr
    assert result.stderr.count("\n") == 1 and "Traceback" not in result.stderr
    assert not (tmp_path / "data").exists()


LEG = """<mujoco model="leg_roles">
  <worldbody><body><joint name="hip_flexion_r" type="hinge" axis="0 -1 0"/><geom size="0.1" mass="1"/>
    <body pos="0 0 -0.4"><joint name="knee_angle_r" type="hinge" axis="0 1 0" range="-120 5"/><geom size="0.1" mass="1"/>
      <body pos="0 0 -0.4"><joint name="toe" type="hinge" axis="0 1 0"/><geom size="0.1" mass="1"/></body>
    </body></body></worldbody>
</mujoco>
"""


def test_models_show_prints_the_joint_roles_it_inferred_or_was_told(server: Any, tmp_path: Path) -> None:
    """Roles inferred from names say so (and the knee's sign from its range); a role tag says it
    instead; a tag naming no joint is refused at registration in one line."""
    leg = tmp_path / "leg_roles.xml"
    leg.write_text(LEG)
    jitdyn("models", "--server", server.address, "register", str(leg))
    shown = jitdyn("models", "--server", server.address, "show", "leg_roles:1").stdout
    assert '"role": "hip_flexion_r",\n      "role_source": "inferred from its name"' in shown, shown
    assert (
        '"role": "knee_extension_r",\n      "role_source": "inferred from its name, its sign from its range"'
        in shown
    )
    assert '"name": "toe"' in shown and '"role": "",' in shown
    leg = tmp_path / "leg_declared.xml"
    leg.write_text(LEG.replace("leg_roles", "leg_declared"))
    tag = "role.ankle_dorsiflexion_r.toe"
    jitdyn("models", "--server", server.address, "register", str(leg), "--tag", tag)
    declared = jitdyn("models", "--server", server.address, "show", "leg_declared:1").stdout
    assert '"role": "ankle_dorsiflexion_r",\n      "role_source": "declared"' in declared, declared
    assert '"role": "hip_flexion_r"' not in declared  # declared roles replace the inferred ones
    leg = tmp_path / "leg_wrong.xml"
    leg.write_text(LEG.replace("leg_roles", "leg_wrong"))
    wrong = jitdyn(
        "models",
        "--server",
        server.address,
        "register",
        str(leg),
        "--tag",
        "role.knee_flexion_r.shin",
        check=False,
    )
    assert wrong.returncode == 1
    assert "InvalidArgument: tag 'role.knee_flexion_r.shin': the model has no joint 'shin'" in wrong.stderr
    assert "Traceback" not in wrong.stderr
