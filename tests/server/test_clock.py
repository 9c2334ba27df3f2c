"""The REALTIME clock: NTP-style offset and round trip, and the horizon over real gRPC."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest

from jitdyn.client import FrameData, SessionOptions, SyncSample, TickResult
from jitdyn.server.runtime.clock import ClockSync


def _exchange(
    sync: ClockSync, probe: int, *, t1: float, offset: float, up: float, down: float, hold: float = 0.001
) -> float:
    """One probe answered; returns t4, the client's receive time of the answer."""
    t2 = t1 + up + offset
    t3 = t2 + hold
    sync.on_probe(probe_id=probe, client_send_time=t1, server_receive_time=t2, server_send_time=t3)
    return t3 - offset + down


def test_offset_and_round_trip_of_a_symmetric_exchange() -> None:
    sync = ClockSync()
    t4 = _exchange(sync, 1, t1=0.0, offset=0.25, up=0.01, down=0.01)
    # Nothing complete yet: the one-way estimate t2 - t1, late by the uplink (0.01 s).
    assert sync.offset == pytest.approx(0.26, abs=1e-12) and sync.round_trip == 0.0
    sync.on_probe(
        probe_id=2,
        client_send_time=t4 + 0.1,
        server_receive_time=9.0,
        server_send_time=9.0,
        previous_id=1,
        previous_receive_time=t4,
    )
    assert sync.offset == pytest.approx(0.25, abs=1e-12)
    assert sync.round_trip == pytest.approx(0.02, abs=1e-12)


def test_the_smallest_round_trip_wins_and_bounds_the_error() -> None:
    sync = ClockSync(window=8)
    previous: tuple[int, float] | None = None
    for probe, (up, down) in enumerate([(0.05, 0.001), (0.002, 0.002), (0.001, 0.09)], start=1):
        t1 = probe * 1.0
        kwargs = (
            {} if previous is None else {"previous_id": previous[0], "previous_receive_time": previous[1]}
        )
        t2 = t1 + up - 0.3
        sync.on_probe(
            probe_id=probe, client_send_time=t1, server_receive_time=t2, server_send_time=t2, **kwargs
        )
        previous = (probe, t2 + 0.3 + down)
    sync.on_probe(
        probe_id=99,
        client_send_time=10.0,
        server_receive_time=0.0,
        server_send_time=0.0,
        previous_id=previous[0],
        previous_receive_time=previous[1],
    )
    assert sync.round_trip == pytest.approx(0.004)
    assert sync.offset == pytest.approx(-0.3, abs=sync.round_trip / 2)


def test_implausible_reports_do_not_move_the_clock() -> None:
    sync = ClockSync()
    _exchange(sync, 1, t1=5.0, offset=0.0, up=0.01, down=0.01)
    sync.on_probe(
        probe_id=2,
        client_send_time=6.0,
        server_receive_time=6.0,
        server_send_time=6.0,
        previous_id=1,
        previous_receive_time=4.0,
    )  # answer received before the probe was sent
    sync.on_probe(
        probe_id=3,
        client_send_time=7.0,
        server_receive_time=7.0,
        server_send_time=7.0,
        previous_id=42,
        previous_receive_time=7.5,
    )  # a probe the server never saw
    assert (sync.offset, sync.round_trip) == (0.0, 0.0)


def test_sync_over_the_stream_and_the_half_round_trip_horizon(client: Any) -> None:
    options = SessionOptions(model_name="pendulum_1", dt=0.05, clock="REALTIME", horizon="HALF_ROUND_TRIP")
    with client.open_session(options) as session:
        answers: list[Any] = []
        for _ in range(4):
            session.sync()
            time.sleep(0.01)
            answers += session.poll()
        for k in range(10):
            time.sleep(max(0.0, k * 0.05 - session.now()))
            session.send(FrameData(seq=k, t=k * 0.05, qpos=[0.2 * np.cos(k * 0.05)], qvel=[0.0]))
        time.sleep(0.15)
        answers += session.poll()
        session.close()
    samples = [a for a in answers if isinstance(a, SyncSample)]
    results = [a for a in answers if isinstance(a, TickResult)]
    assert len(samples) >= 4  # ours, and the ones the session sends by itself
    assert samples[-1].server_round_trip > 0.0
    assert all(abs(s.offset) < 0.05 for s in samples)
    measured = [r for r in results if r.source == "MEASURED"]
    assert measured and all(
        r.horizon == pytest.approx(samples[-1].server_round_trip / 2, rel=0.5) for r in measured[1:]
    )
    assert all(r.t == pytest.approx(r.seq * 0.05 + r.horizon) for r in results)


def test_before_an_exchange_completes_the_offset_is_the_smallest_one_way_estimate() -> None:
    sync = ClockSync()
    assert sync.offset == 0.0  # no probe yet: the client's clock started with `open`
    t4 = _exchange(sync, 1, t1=0.0, offset=-0.003, up=0.004, down=0.001)
    assert sync.offset == pytest.approx(0.001)  # -0.003 + 0.004 of uplink
    _exchange(sync, 2, t1=0.5, offset=-0.003, up=0.0005, down=0.001)
    assert sync.offset == pytest.approx(-0.0025)  # the faster uplink bounds it closer
    _exchange(sync, 3, t1=0.6, offset=-0.003, up=0.002, down=0.001)
    assert sync.offset == pytest.approx(-0.0025)
    sync.on_probe(
        probe_id=4,
        client_send_time=1.0,
        server_receive_time=1.0,
        server_send_time=1.0,
        previous_id=1,
        previous_receive_time=t4,
    )
    # The first complete exchange replaces it: half its round-trip asymmetry, (0.004 - 0.001) / 2.
    assert sync.offset == pytest.approx(-0.003 + 0.0015)
