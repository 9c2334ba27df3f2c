"""MyoSuite's big models end to end, as a user runs them: `jitdyn models
register --myo NAME` of myolegs_osl, myoHand and myolegs against a real server, `jitdyn demo --model
NAME` of each to completion (LOCKSTEP, said so: their REALTIME tick does not fit their dt), and
`sessions plot` and `sessions render` of each one's session. Short demos, few ticks: the legs' UKF
tick takes half a second here. They run in CI (about 45 s); listing every model myo-sim offers
compiles each of them (20 s) and runs with the slow tests."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from _cli import jitdyn

pytest.importorskip("myo_sim")

# name typed, name registered, nv, demo length (5 ticks of 10 model timesteps each). No UKF of
# theirs fits the tick, so the server's choice by cost is the linearised filter where its stored
# cost fits (decision 0210), else dead reckoning, and the demo runs REALTIME unless the machine is
# too busy for it (then LOCKSTEP, with the preset's UKF).
MODELS = [
    ("myolegs_osl", "myolegs_osl", 29, "50ms"),
    ("myoHand", "myohand", 23, "100ms"),
    ("myolegs", "myolegs", 34, "100ms"),
]


def ok(result: subprocess.CompletedProcess[str]) -> subprocess.CompletedProcess[str]:
    assert result.returncode == 0, result.stdout + result.stderr
    assert "Traceback" not in result.stderr, result.stderr
    return result


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """XDG_CACHE_HOME of the commands: the list of myo-sim models is found once, in this module."""
    return {"XDG_CACHE_HOME": str(tmp_path_factory.mktemp("cache"))}


@pytest.fixture(scope="module")
def demos(server: Any) -> dict[str, str]:
    """The session id of each model's demo, filled in by test_a_big_myosuite_model_registers_and_demos."""
    return {}


@pytest.mark.parametrize(("typed", "name", "nv", "seconds"), MODELS)
def test_a_big_myosuite_model_registers_and_demos(
    server: Any, demos: dict[str, str], typed: str, name: str, nv: int, seconds: str
) -> None:
    registered = ok(jitdyn("models", "register", "--myo", typed, "--server", server.address))
    assert re.search(rf"^registered: sha256:[0-9a-f]{{64}}  {name} v1  nq=\d+ nv={nv} ", registered.stdout), (
        registered.stdout
    )
    demo = ok(jitdyn("demo", "--model", name, "--seconds", seconds, "--server", server.address))
    # Refused REALTIME (a busy machine), it says why and runs LOCKSTEP with the preset's UKF.
    refused = re.search(
        r"^the server refused a REALTIME session \(.+\); running it LOCKSTEP", demo.stdout, re.MULTILINE
    )
    clock = ", LOCKSTEP" if refused else ""
    estimator = "UKF" if refused else "CONSTANT_VELOCITY \\(chosen by cost"
    session = re.search(
        rf"^session (\S+): {name} v1 \({nv} dof\), driven \(.+\), dt \d+ ms, 5 ticks{clock}, estimator {estimator}",
        demo.stdout,
        re.MULTILINE,
    )
    assert session, demo.stdout
    assert re.search(r"answers received for 5 of the 5 ticks", demo.stdout), demo.stdout
    assert re.search(r"ticks +\d+ +measured +\d+ +predicted +\d+", demo.stdout), demo.stdout
    demos[name] = session.group(1)


def test_a_demo_asked_for_realtime_is_refused_in_one_line(server: Any) -> None:
    ok(jitdyn("models", "register", "--myo", "myolegs_osl", "--server", server.address))
    # The UKF asked for by name: no tick of 10 model timesteps fits its cost.
    result = jitdyn(
        "demo",
        "--model",
        "myolegs_osl",
        "--clock",
        "realtime",
        "--estimator",
        "ukf",
        "--server",
        server.address,
    )
    assert result.returncode == 1, result.stdout + result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("jitdyn demo: ResourceExhausted: "), result.stderr


@pytest.mark.parametrize("name", [name for _, name, *_ in MODELS])
def test_each_models_session_plots_and_renders(
    server: Any, demos: dict[str, str], tmp_path: Path, name: str
) -> None:
    if name not in demos:
        pytest.skip(f"the {name} demo did not run")
    session, data = demos[name], str(server.services.data_root)
    plotted = ok(jitdyn("sessions", "plot", session, "--data", data, cwd=tmp_path))
    assert plotted.stdout == f"plotted {session} to {session}.png\n"
    assert (tmp_path / f"{session}.png").stat().st_size > 50_000
    out = tmp_path / "frame.png"
    rendered = ok(
        jitdyn(
            "sessions",
            "render",
            session,
            "--data",
            data,
            "--out",
            str(out),
            "--frame",
            "40ms",
            env={"MUJOCO_GL": "osmesa"},
        )
    )
    assert re.search(rf"{name} v1, DRIVEN (LOCKSTEP|REALTIME), COMPLETE, ticks \d+", rendered.stderr), (
        rendered.stderr
    )
    PIL = pytest.importorskip("PIL.Image")
    with PIL.open(out) as image:
        pixels = np.asarray(image.convert("RGB"), dtype=np.float64)
    # The model and the MyoSuite scene's meshes and textures, not a blank frame.
    assert pixels.std() > 20, pixels.std()


@pytest.mark.slow
def test_myo_list_needs_no_server_and_an_unknown_name_gets_the_names(cache: dict[str, str]) -> None:
    listed = ok(jitdyn("models", "register", "--myo", "list", env=cache))
    names = [line.split()[0] for line in listed.stdout.splitlines()]
    assert {"myoelbow", "myohand", "myolegs", "myolegs_osl"} <= set(names), listed.stdout
    assert re.search(
        r"^myohand +nq=23 nv=23 nu=39 na=39 \(also hand, myohand_r\)$", listed.stdout, re.MULTILINE
    )
    unknown = jitdyn("models", "register", "--myo", "myoknee", "--server", "127.0.0.1:1", env=cache)
    assert unknown.returncode == 2, unknown.stdout + unknown.stderr
    expected = (
        f"jitdyn models register: --myo: no myo-sim model is named 'myoknee'; models that compile: "
        f"{', '.join(names)} (`jitdyn models register --myo list` shows them with their other names)"
    )
    assert unknown.stderr.strip().splitlines() == [expected]
    help_text = ok(jitdyn("models", "register", "--help")).stdout
    assert "--myo list" in " ".join(help_text.split())
