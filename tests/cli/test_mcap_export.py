"""`jitdyn sessions export ID --format mcap`, as a user runs it, on a session a real server stored
(a REALTIME demo over an emulated network: PREDICTED, CORRECTED and lost frames), read back with
the mcap package's own reader."""

from __future__ import annotations

import datetime
import json
import math
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from _cli import jitdyn
from mcap.reader import make_reader

TOPICS = {
    "/jitdyn/joint_states": "jitdyn.JointStates",
    "/jitdyn/forces": "jitdyn.Forces",
    "/jitdyn/frames": "jitdyn.Frames",
    "/jitdyn/source": "jitdyn.Source",
    "/jitdyn/lateness": "jitdyn.Lateness",
    "/jitdyn/rejections": "jitdyn.Rejection",
    "/tf": "foxglove.FrameTransforms",
}


def ok(result: subprocess.CompletedProcess[str]) -> str:
    assert result.returncode == 0, result.stdout + result.stderr
    return result.stdout


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str, dict[str, Any]]:
    """A demo session of pendulum_2 stored by an in-process server: its data folder, id and `show`."""
    work = tmp_path_factory.mktemp("work")
    data = work / "data"
    ok(jitdyn("demo", "--seconds", "2", "--model", "pendulum_2", "--data", str(data), cwd=work))
    listed = ok(jitdyn("sessions", "list", "--data", str(data))).split()
    session_id = next(
        word for word in listed if re.fullmatch(r"[0-9a-f]{8}(-[0-9a-f]{4}){3}-[0-9a-f]{12}", word)
    )
    shown = ok(jitdyn("sessions", "show", session_id, "--data", str(data)))
    details = json.loads(shown[shown.index("{") :])
    details["listed_start"] = " ".join(listed[listed.index(session_id) + 1 : listed.index(session_id) + 3])
    return data, session_id, details


@pytest.fixture(scope="module")
def exported(session: tuple[Path, str, dict[str, Any]], tmp_path_factory: pytest.TempPathFactory) -> Path:
    data, session_id, _ = session
    out = tmp_path_factory.mktemp("out") / "walk.mcap"
    result = jitdyn(
        "sessions", "export", session_id[:8], "--format", "mcap", "--out", str(out), "--data", str(data)
    )
    assert ok(result).strip() == f"exported {session_id} as mcap to {out}"
    assert result.stderr.startswith("messages by channel: /jitdyn/joint_states "), result.stderr
    return out


def read(path: Path) -> tuple[Any, dict[str, list[tuple[int, int, dict[str, Any]]]], dict[str, str]]:
    """The summary, every message by topic as (log time, publish time, JSON), and the session's metadata."""
    by_topic: dict[str, list[tuple[int, int, dict[str, Any]]]] = {}
    with path.open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            assert (schema.encoding, channel.message_encoding) == ("jsonschema", "json")
            assert schema.name == TOPICS[channel.topic]
            json.loads(schema.data)  # the schema is JSON Schema text
            by_topic.setdefault(channel.topic, []).append(
                (message.log_time, message.publish_time, json.loads(message.data))
            )
        metadata = {record.name: record.metadata for record in reader.iter_metadata()}
    return summary, by_topic, metadata["jitdyn.session"]


def test_every_channel_has_a_message_a_tick_at_the_ticks_time(
    session: tuple[Path, str, dict[str, Any]], exported: Path
) -> None:
    _, session_id, shown = session
    summary, by_topic, metadata = read(exported)
    counts = shown["summary"]
    assert {channel.topic for channel in summary.channels.values()} == set(TOPICS)
    ticks = counts["ticks"]
    assert ticks >= 30
    for topic in ("/jitdyn/joint_states", "/jitdyn/forces", "/jitdyn/source", "/jitdyn/lateness", "/tf"):
        assert len(by_topic[topic]) == ticks, topic
    # A frame a tick it came for, late ones included; the emulated network lost the rest.
    assert len(by_topic["/jitdyn/frames"]) == counts["frames"] - counts["rejected"] < ticks
    assert len(by_topic.get("/jitdyn/rejections", [])) == counts["rejected"]
    # The answer when due, and whether a late frame corrected it: the summary counts both.
    sources = [message["source"] for _, _, message in by_topic["/jitdyn/source"]]
    assert (sources.count("MEASURED"), sources.count("PREDICTED")) == (
        counts["measured"],
        counts["predicted"],
    )
    corrected = sum(message["corrected"] for _, _, message in by_topic["/jitdyn/source"])
    assert corrected == counts["corrected"] > 0

    assert metadata["session_id"] == session_id and metadata["model"] == "pendulum_2 v1"
    # The file's time is the session's: its first tick at the start the index holds.
    started = datetime.datetime.fromisoformat(metadata["started_at"])
    assert f"{started:%Y-%m-%d %H:%M:%S}" == shown["listed_start"]
    dt_ns = round(shown["dt"] * 1e9)
    times = [log for log, _, _ in by_topic["/tf"]]
    first = times[0]
    assert first == round(started.timestamp() * 1e6) * 1000
    assert [t - first for t in times] == [k * dt_ns for k in range(ticks)]
    for topic, messages in by_topic.items():
        for log, publish, message in messages:
            stamp = message["transforms"][0]["timestamp"] if topic == "/tf" else message["timestamp"]
            assert log == publish == stamp["sec"] * 10**9 + stamp["nsec"], topic
            assert (log - first) % dt_ns == 0, topic  # on a tick's time


def test_the_frames_are_the_model_bodies_at_the_answered_angles(exported: Path) -> None:
    _, by_topic, _ = read(exported)
    states = by_topic["/jitdyn/joint_states"]
    assert len(states) == len(by_topic["/tf"])
    for (_, _, state), (_, _, tf) in zip(states, by_topic["/tf"], strict=True):
        assert state["qpos"]["name"] == ["hinge_1", "hinge_2"]
        transforms = tf["transforms"]
        assert [(t["parent_frame_id"], t["child_frame_id"]) for t in transforms] == [
            ("world", "rod_1"),
            ("rod_1", "rod_2"),
        ]
        # pendulum_2's hinges turn about y: each body's rotation in its parent is its joint's angle.
        for transform, q in zip(transforms, state["qpos"]["value"], strict=True):
            rotation = transform["rotation"]
            assert rotation["x"] == pytest.approx(0.0, abs=1e-12)
            assert rotation["z"] == pytest.approx(0.0, abs=1e-12)
            angle = 2 * math.atan2(rotation["y"], rotation["w"])
            assert math.remainder(angle - q, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)
        assert transforms[0]["translation"] == {"x": 0.0, "y": 0.0, "z": 2.5}
        assert transforms[1]["translation"] == pytest.approx({"x": 0.0, "y": 0.0, "z": -1.0})


def test_without_the_lab_extra_it_says_which_to_install(
    session: tuple[Path, str, dict[str, Any]], tmp_path: Path
) -> None:
    data, session_id, _ = session
    result = jitdyn(
        "sessions", "export", session_id, "--format", "mcap", "--data", str(data),
        cwd=tmp_path, preamble="sys.modules['mcap'] = None",
    )  # fmt: skip
    assert result.returncode == 1
    assert "Traceback" not in result.stderr
    assert "needs mcap (MCAP files), which is not installed: pip install 'jitdyn[lab]'" in result.stderr
    assert list(tmp_path.iterdir()) == []


def test_the_preview_draws_the_file_from_its_channels(exported: Path, tmp_path: Path) -> None:
    script = Path(__file__).resolve().parents[2] / "scripts" / "mcap_preview.py"
    out = tmp_path / "preview.png"
    drawn = subprocess.run(
        [sys.executable, str(script), str(exported), "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert drawn.returncode == 0, drawn.stderr
    assert drawn.stdout.strip() == f"drew {exported} to {out}"
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_rejections_and_corrections_of_a_lockstep_session(client: Any, server: Any, tmp_path: Path) -> None:
    from jitdyn.client import FrameData, Rejection, SessionOptions, TickResult

    def frame(seq: int, q: float) -> FrameData:
        return FrameData(seq=seq, t=seq * 0.05, qpos=[q, -q], qvel=[0.0, 0.0])

    with client.open_session(SessionOptions(model_name="pendulum_2", dt=0.05, history=2)) as s:
        assert isinstance(s.send_frame(frame(0, 0.1)), TickResult)
        s.skip(1)
        late = s.send_frame(frame(1, 0.11))
        assert isinstance(late, TickResult) and late.source == "CORRECTED"
        bad = s.send_frame(FrameData(seq=2, t=0.1, qpos=[math.nan, 0.2], qvel=[0.0, 0.0]))
        assert isinstance(bad, Rejection)
        assert isinstance(s.send_frame(frame(2, 0.12)), TickResult)
        for seq in (3, 4, 5):
            s.skip(seq)
        too_old = s.send_frame(frame(3, 0.13))  # stored with its values, never used
        assert isinstance(too_old, Rejection) and too_old.reason == "TOO_OLD"
        session_id = s.opened.session_id
    out = tmp_path / "s.mcap"
    data = str(server.services.data_root)
    ok(jitdyn("sessions", "export", session_id, "--format", "mcap", "--out", str(out), "--data", data))
    _, by_topic, _ = read(out)
    assert [(m["seq"], m["reason"]) for _, _, m in by_topic["/jitdyn/rejections"]] == [
        (2, "NOT_FINITE"),
        (3, "TOO_OLD"),
    ]
    assert [(m["seq"], m["source"], m["corrected"]) for _, _, m in by_topic["/jitdyn/source"]] == [
        (0, "MEASURED", False),
        (1, "PREDICTED", True),
        (2, "MEASURED", False),
        (3, "PREDICTED", False),
        (4, "PREDICTED", False),
        (5, "PREDICTED", False),
    ]
    # The latest answer of tick 1 is its correction, at its frame's angles.
    states = by_topic["/jitdyn/joint_states"]
    assert [m["source"] for _, _, m in states] == ["MEASURED", "CORRECTED", "MEASURED", *["PREDICTED"] * 3]
    assert states[1][2]["qpos"]["value"] == [0.11, -0.11]
    # The frames the ticks used, once each: not the rejected ones.
    used = [(m["seq"], m["qpos"]["value"]) for _, _, m in by_topic["/jitdyn/frames"]]
    assert used == [(0, [0.1, -0.1]), (1, [0.11, -0.11]), (2, [0.12, -0.12])]
