"""`jitdyn lsl` in one process, as a lab's streams meet it: a pylsl outlet sends iSen's recorded
stepping (right hip and knee, radians at 100 Hz) as a wearable would, the bridge takes it into a
session of a real `jitdyn serve`, and pylsl inlets read the two streams it publishes. LSL's
discovery stays on this machine: LSLAPICFG names a config whose ResolveScope is `machine`."""

from __future__ import annotations

import io
import os
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
from _cli import jitdyn, one_line_error, stored_frames

from jitdyn.experiments.recorded import load_isen

RATE = 100.0  # Hz, iSen's


@pytest.fixture(scope="module")
def pylsl(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ModuleType]:
    """pylsl, its liblsl configured (at its first use) to resolve streams of this machine only."""
    config = tmp_path_factory.mktemp("lsl") / "lsl_api.cfg"
    config.write_text("[ports]\nIPv6 = disable\n\n[multicast]\nResolveScope = machine\n", encoding="utf-8")
    before = os.environ.get("LSLAPICFG")
    os.environ["LSLAPICFG"] = str(config)
    try:
        yield pytest.importorskip("pylsl")
    finally:
        if before is None:
            os.environ.pop("LSLAPICFG", None)
        else:
            os.environ["LSLAPICFG"] = before


def source_outlet(pylsl: ModuleType, name: str) -> Any:
    info = pylsl.StreamInfo(name, "Angles", 2, RATE, pylsl.cf_double64, f"{name}-source")
    info.set_channel_labels(["hip_flexion_r", "knee_flexion_r"])
    info.set_channel_units(["radians", "radians"])
    return pylsl.StreamOutlet(info)


def inlet_of(pylsl: ModuleType, name: str) -> tuple[Any, list[str]]:
    """An open inlet of the stream `name`, and its channel labels (asked while it is alive: an
    inlet asks a stream gone for its info for ever)."""
    found = pylsl.resolve_byprop("name", name, minimum=1, timeout=30.0)
    assert found, f"no stream {name!r}"
    inlet = pylsl.StreamInlet(found[0], max_buflen=60, recover=False)
    labels = inlet.info(timeout=10.0).get_channel_labels()
    inlet.open_stream(timeout=10.0)
    return inlet, labels


def read_while(
    thread: threading.Thread, answers: Any, lateness: Any, pylsl: ModuleType, got: tuple[list[Any], ...]
) -> None:
    """Every sample of the two inlets, with their stamps, into `got`, as they come, until the bridge
    ends (at most 90 s)."""
    deadline = time.monotonic() + 90
    while thread.is_alive() and time.monotonic() < deadline:
        pull(answers, lateness, got, pylsl, timeout=0.05)
    thread.join(timeout=1)
    pull(answers, lateness, got, pylsl, timeout=0.5)


def pull(
    answers: Any, lateness: Any, got: tuple[list[Any], ...], pylsl: ModuleType, *, timeout: float
) -> None:
    for inlet, (values, stamps) in ((answers, got[:2]), (lateness, got[2:])):
        try:
            chunk, times = inlet.pull_chunk(timeout=timeout, max_samples=10_000)
        except pylsl.util.LostError:  # the bridge's outlets are gone with its session
            continue
        values += chunk
        stamps += times


def test_a_stream_of_joint_angles_goes_into_a_session_and_its_answers_come_back_as_lsl(
    pylsl: ModuleType, leg_server: str, leg_data: Path
) -> None:
    from jitdyn.cli.lsl import LslSettings, run_lsl

    walk = load_isen("isen_gait")[:300, :2]
    suffix = uuid.uuid4().hex[:8]
    outlet = source_outlet(pylsl, f"leg-{suffix}")
    settings = LslSettings(
        stream=f"leg-{suffix}", model="cmj_leg", idle=3.0, wait=30.0, name=f"jitdyn-{suffix}"
    )
    out = io.StringIO()
    ran: dict[str, Any] = {}

    def bridge() -> None:
        try:
            ran["numbers"] = run_lsl(leg_server, settings, out=out, progress=False)
        except BaseException as error:  # noqa: BLE001 - handed to the test's thread
            ran["error"] = error

    thread = threading.Thread(target=bridge)
    thread.start()
    answers, answer_labels = inlet_of(pylsl, f"jitdyn-{suffix}")
    lateness, lateness_labels = inlet_of(pylsl, f"jitdyn-{suffix}-lateness")
    got: tuple[list[Any], ...] = ([], [], [], [])
    reader = threading.Thread(target=read_while, args=(thread, answers, lateness, pylsl, got))
    reader.start()
    assert outlet.wait_for_consumers(timeout=30.0)
    pushed = []
    start = pylsl.local_clock()
    for k, sample in enumerate(walk):  # stamped when taken, on the recording's clock, as a device does
        stamp = start + k / RATE
        time.sleep(max(0.0, stamp - pylsl.local_clock()))
        outlet.push_sample(list(sample), stamp)
        pushed.append(stamp)
    time.sleep(0.5)
    del outlet  # the device stops: its stream goes, and the session ends
    reader.join(timeout=90)
    received, stamps, late, late_stamps = got
    assert not thread.is_alive() and "error" not in ran, (out.getvalue(), ran.get("error"))
    stdout = out.getvalue()

    assert answer_labels == [
        *(f"qpos_{j}" for j in ("hip_flexion_r", "knee_flexion_r", "ankle_flexion_r")),
        *(f"qvel_{j}" for j in ("hip_flexion_r", "knee_flexion_r", "ankle_flexion_r")),
        *(f"qfrc_inverse_{j}" for j in ("hip_flexion_r", "knee_flexion_r", "ankle_flexion_r")),
        "source",
        "seq",
    ]
    assert lateness_labels == ["frame_delay", "answer_time"]
    assert (
        "joints: hip_flexion_r <- hip_flexion_r, knee_flexion_r <- knee_flexion_r; held at rest (no column): "
        "ankle_flexion_r; unused columns: none"
    ) in stdout
    assert "the stream was closed by its sender: the session ends" in stdout
    assert "stored session: " in stdout
    # dt: the stream's 10 ms, a whole multiple of the leg's 2 ms timestep; every sample a tick.
    assert ", dt 10 ms, ticks while the stream sends" in stdout
    seqs, frames = stored_frames(stdout, leg_data)
    assert len(seqs) >= 0.9 * len(walk), stdout
    # What the server got is what was pushed.
    sent = {tuple(np.round(row, 12)) for row in walk}
    assert all(tuple(np.round(row[:2], 12)) in sent for row in frames)
    # A sample's time, through time_correction() onto this clock and the session's, is its tick's:
    # the answer of tick k is stamped k dt after the session's zero, within half a tick (and the
    # clocks' offset, tens of microseconds in one process) of the stamp the sample was pushed with.
    dt = 1.0 / RATE
    zero = stamps[0] - received[0][-1] * dt
    for values, stamp in zip(received, stamps, strict=True):
        assert values[-2] in (1.0, 2.0, 3.0)  # MEASURED, PREDICTED, CORRECTED
        assert abs(stamp - (zero + values[-1] * dt)) < 1e-6
    index = {tuple(np.round(row, 12)): i for i, row in enumerate(walk)}
    for seq, row in zip(seqs, frames, strict=True):
        pushed_at = pushed[index[tuple(np.round(row[:2], 12))]]
        assert abs(zero + seq * dt - pushed_at) <= dt / 2 + 1e-3, (seq, pushed_at - zero)
    assert len(received) >= 0.9 * len(walk) and len(late) == len(late_stamps) >= 0.9 * len(walk)
    assert np.all(np.array(late)[:, 1] >= 0)  # the server's time to answer


def test_no_stream_of_that_name_is_said_in_one_line(pylsl: ModuleType, tmp_path: Path) -> None:
    config = os.environ["LSLAPICFG"]
    result = jitdyn(
        "lsl", "--name", "nobody-streams-this", "--model", "pendulum_3", "--wait", "1s", "--data", str(tmp_path),
        env={"LSLAPICFG": config},
    )  # fmt: skip
    assert one_line_error(result, 1) == (
        "jitdyn lsl: FailedPrecondition: no LSL stream of name 'nobody-streams-this' answered within 1 s (LSL "
        "looks as far as lsl_api.cfg's ResolveScope lets it: this machine, its link or its site)"
    )


def test_without_the_lab_extra_it_names_it_before_starting_a_server(tmp_path: Path) -> None:
    result = jitdyn(
        "lsl", "--name", "leg", "--model", "pendulum_3", "--data", str(tmp_path / "data"),
        preamble="sys.modules['pylsl'] = None  # not installed",
    )  # fmt: skip
    assert one_line_error(result, 1) == (
        "jitdyn lsl: needs pylsl (Lab Streaming Layer), which is not installed: pip install 'jitdyn[lab]'"
    )
    assert not (tmp_path / "data").exists()
