"""client.netem: seeded delays, LOCKSTEP schedules (loss rate, order, lateness) and the delayed sender."""

from __future__ import annotations

import itertools
import math
import threading
import time

import numpy as np
import pytest

from jitdyn.experiments.netem import (
    DelayedSender,
    Distribution,
    NetworkProfile,
    gap_schedule,
    lockstep_schedule,
    sample_delays,
)


def test_same_seed_same_delays_other_seed_other_delays():
    profile = NetworkProfile(latency=0.03, jitter=0.01, loss=0.1)
    a = sample_delays(profile, 100, seed=7)
    np.testing.assert_array_equal(a, sample_delays(profile, 100, seed=7))
    assert not np.array_equal(a, sample_delays(profile, 100, seed=8))


@pytest.mark.parametrize("distribution", list(Distribution))
def test_delay_distributions_have_the_mean_asked_for_and_are_never_negative(distribution):
    profile = NetworkProfile(latency=0.03, jitter=0.005, distribution=distribution)
    d = sample_delays(profile, 20_000, seed=1)
    assert np.all(d >= 0)
    assert d.mean() == pytest.approx(0.03, abs=3e-4)


def test_loss_does_not_shift_the_latencies_of_frames_that_arrive():
    lossless = sample_delays(NetworkProfile(latency=0.03, jitter=0.01), 500, seed=3)
    lossy = sample_delays(NetworkProfile(latency=0.03, jitter=0.01, loss=0.3), 500, seed=3)
    kept = np.isfinite(lossy)
    np.testing.assert_array_equal(lossy[kept], lossless[kept])


def test_loss_rate_within_binomial_bounds():
    n, p = 10_000, 0.05
    schedule = lockstep_schedule(n, dt=0.05, profile=NetworkProfile(loss=p), seed=11)
    # 4.5 standard deviations of a binomial: a seeded test that is not on a knife's edge.
    assert abs(schedule.lost - n * p) < 4.5 * math.sqrt(n * p * (1 - p))
    assert schedule.on_time + schedule.lost == n


def _check_invariants(schedule):
    ticks = [d for d in schedule.deliveries if d.tick == d.seq and d.late_ticks == 0]
    # One tick message per tick, in order.
    assert [d.seq for d in ticks] == list(range(schedule.ticks))
    frames = [d.seq for d in schedule.deliveries if d.kind == "frame"]
    assert len(frames) == len(set(frames))  # every frame at most once
    position = {(d.kind, d.seq): i for i, d in enumerate(schedule.deliveries)}
    for d in schedule.deliveries:
        if d.kind == "frame" and d.late_ticks > 0:
            # A late frame comes after its tick's skip and after every earlier tick message.
            assert position[("skip", d.seq)] < position[("frame", d.seq)]
            assert d.tick == min(d.seq + d.late_ticks, schedule.ticks)
            if d.tick < schedule.ticks:
                assert position[("frame", d.seq)] < position.get(
                    ("frame", d.tick), position.get(("skip", d.tick))
                )
    # Ticks answered in order: the tick of every message never decreases.
    assert all(a.tick <= b.tick for a, b in zip(schedule.deliveries, schedule.deliveries[1:]))


def test_perfect_network_every_frame_in_time():
    schedule = lockstep_schedule(20, dt=0.05)
    assert [(d.kind, d.seq, d.tick) for d in schedule.deliveries] == [("frame", k, k) for k in range(20)]
    assert schedule.received_in_time().all()


def test_latency_under_grace_is_in_time_over_it_is_late_by_whole_ticks():
    profile = NetworkProfile(latency=0.035, distribution=Distribution.CONSTANT)
    assert lockstep_schedule(10, dt=0.05, profile=profile, grace=0.04).late == 0
    schedule = lockstep_schedule(10, dt=0.05, profile=profile, grace=0.0)
    _check_invariants(schedule)
    # ceil(35 ms / 50 ms) = 1: skip(k), then frame k just before tick k + 1.
    assert [(d.kind, d.seq) for d in schedule.deliveries[:5]] == [
        ("skip", 0),
        ("frame", 0),
        ("skip", 1),
        ("frame", 1),
        ("skip", 2),
    ]
    assert {d.late_ticks for d in schedule.deliveries if d.kind == "frame"} == {1}
    slow = lockstep_schedule(
        10, dt=0.05, profile=NetworkProfile(latency=0.12, distribution=Distribution.CONSTANT)
    )
    # ceil(120 / 50) = 3, but for the last frames, which come after the last tick
    assert {d.late_ticks for d in slow.deliveries if d.kind == "frame" and d.tick < 10} == {3}


def test_exactly_one_dt_late_is_one_tick_late():
    schedule = lockstep_schedule(
        3, dt=0.05, profile=NetworkProfile(latency=0.05, distribution=Distribution.CONSTANT)
    )
    assert [d.late_ticks for d in schedule.deliveries if d.kind == "frame"] == [1, 1, 1]


def test_frames_late_past_the_end_come_after_the_last_tick():
    schedule = lockstep_schedule(
        2, dt=0.05, profile=NetworkProfile(latency=1.0, distribution=Distribution.CONSTANT)
    )
    assert [(d.kind, d.seq, d.tick) for d in schedule.deliveries] == [
        ("skip", 0, 0),
        ("skip", 1, 1),
        ("frame", 0, 2),
        ("frame", 1, 2),
    ]


def test_jitter_and_reordering_keep_the_invariants_and_do_reorder():
    profile = NetworkProfile(latency=0.03, jitter=0.02, loss=0.05, reorder=0.2, reorder_delay=0.1)
    schedule = lockstep_schedule(2000, dt=0.05, profile=profile, seed=5)
    _check_invariants(schedule)
    late_order = [d.seq for d in schedule.deliveries if d.kind == "frame" and d.late_ticks > 0]
    assert any(a > b for a, b in itertools.pairwise(late_order))  # some frames overtaken
    assert schedule.on_time + schedule.late + schedule.lost == 2000


def test_gap_schedule_loses_whole_gaps_every_period():
    schedule = gap_schedule(12, dt=0.05, gap_ticks=2, period=5)
    np.testing.assert_array_equal(schedule.received_in_time(), [1, 1, 1, 1, 1, 0, 0, 1, 1, 1, 0, 0])
    assert schedule.late == 0 and schedule.lost == 4


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"latency": -1.0}, "latency must be a finite number of seconds >= 0, got -1.0"),
        ({"loss": 1.5}, r"loss must be a probability in \[0, 1\], got 1.5"),
        ({"reorder": 0.1}, "reorder_delay must be > 0 seconds when reorder > 0, got 0.0"),
    ],
)
def test_bad_profiles_are_refused_by_name(kwargs, message):
    with pytest.raises(ValueError, match=message):
        NetworkProfile(**kwargs)


def test_delayed_sender_sends_after_the_delay_and_drops_lost_items():
    sent: list[tuple[int, float]] = []
    lock = threading.Lock()
    start = time.monotonic()

    def send(item: int) -> None:
        with lock:
            sent.append((item, time.monotonic() - start))

    profile = NetworkProfile(latency=0.02, distribution=Distribution.CONSTANT)
    with DelayedSender(send, profile, seed=0) as net:
        for k in range(5):
            assert net.submit(k) == pytest.approx(0.02)
    assert [k for k, _ in sent] == [0, 1, 2, 3, 4]
    assert all(at >= 0.02 for _, at in sent)

    dropped: list[int] = []
    with DelayedSender(dropped.append, NetworkProfile(loss=1.0), seed=0) as net:
        assert net.submit(1) == math.inf
    assert dropped == []


def test_delayed_sender_is_seeded_and_reports_send_errors_at_close():
    a = DelayedSender(lambda _: None, NetworkProfile(latency=0.001, jitter=0.001), seed=4)
    b = DelayedSender(lambda _: None, NetworkProfile(latency=0.001, jitter=0.001), seed=4)
    assert [a.submit(k) for k in range(3)] == [b.submit(k) for k in range(3)]
    a.close()
    b.close()
    b.close()  # twice is fine

    def fail(_: int) -> None:
        raise OSError("link down")

    broken = DelayedSender(fail, NetworkProfile(), seed=0)
    broken.submit(1)
    with pytest.raises(RuntimeError, match="the send function failed"):
        broken.close()
