"""The event loop's precise wake-ups (server/runtime/alarm.py): never early, in order, cancellable."""

from __future__ import annotations

import asyncio
import os
import time

import pytest

from jitdyn.server.runtime.alarm import Alarm

pytestmark = pytest.mark.skipif(not os.path.exists("/proc/self/fd"), reason="Linux timerfd")


def test_sleepers_wake_in_order_and_never_early() -> None:
    async def main() -> list[tuple[float, float]]:
        alarm = Alarm.of(asyncio.get_running_loop())
        assert alarm.precise
        start = time.monotonic()
        woken: list[tuple[float, float]] = []

        async def sleeper(when: float) -> None:
            await alarm.sleep_until(when)
            woken.append((when, time.monotonic()))

        # Pushed out of order: each new earliest re-arms the timer.
        dues = [start + 0.001 * k for k in (30, 5, 20, 1, 12, 12, 40, 3)]
        await asyncio.gather(*(sleeper(when) for when in dues))
        return woken

    woken = asyncio.run(main())
    assert [when for when, _ in woken] == sorted(when for when, _ in woken)
    assert all(at >= when for when, at in woken)
    assert all(at - when < 0.5 for when, at in woken)  # woken at all (not at some later event)


def test_a_cancelled_sleeper_leaves_the_others_on_time() -> None:
    async def main() -> float:
        alarm = Alarm.of(asyncio.get_running_loop())
        early = asyncio.create_task(alarm.sleep_until(time.monotonic() + 0.005))
        await asyncio.sleep(0)
        early.cancel()
        due = time.monotonic() + 0.02
        await alarm.sleep_until(due)
        with pytest.raises(asyncio.CancelledError):
            await early
        return time.monotonic() - due

    assert 0.0 <= asyncio.run(main()) < 0.5


def test_a_time_already_past_returns_at_once() -> None:
    async def main() -> None:
        alarm = Alarm.of(asyncio.get_running_loop())
        await asyncio.wait_for(alarm.sleep_until(time.monotonic() - 1.0), timeout=1.0)

    asyncio.run(main())


def test_close_cancels_sleepers_and_releases_the_timer() -> None:
    before = len(os.listdir("/proc/self/fd"))

    async def main() -> None:
        loop = asyncio.get_running_loop()
        alarm = Alarm.of(loop)
        assert Alarm.of(loop) is alarm  # one per loop
        sleeping = asyncio.create_task(alarm.sleep_until(time.monotonic() + 60))
        await asyncio.sleep(0)
        alarm.close()
        with pytest.raises(asyncio.CancelledError):
            await sleeping
        assert Alarm.of(loop) is not alarm

    asyncio.run(main())
    import gc

    gc.collect()  # the second alarm's timer goes with its loop
    assert len(os.listdir("/proc/self/fd")) <= before


def test_a_moved_wakeup_wakes_at_its_new_time_and_not_before() -> None:
    async def main() -> tuple[float, float, float]:
        alarm = Alarm.of(asyncio.get_running_loop())
        wakeup = alarm.wakeup()
        start = time.monotonic()
        sleeping = asyncio.create_task(wakeup.until(start + 0.01))
        await asyncio.sleep(0)
        assert wakeup.when == start + 0.01
        wakeup.move(start + 0.06)  # later: the first time passes without waking it
        await asyncio.sleep(0.03)
        assert not sleeping.done()
        later = time.monotonic() + 0.01
        wakeup.move(later)  # earlier than 0.06 again
        await sleeping
        woke = time.monotonic()
        assert wakeup.when is None
        return start, later, woke

    start, later, woke = asyncio.run(main())
    assert woke >= later
    assert woke - start < 0.06  # the move earlier took effect


def test_moving_a_wakeup_into_the_past_wakes_it_at_once_and_leaves_others_on_time() -> None:
    async def main() -> tuple[float, float]:
        alarm = Alarm.of(asyncio.get_running_loop())
        wakeup = alarm.wakeup()
        other_due = time.monotonic() + 0.02
        other = asyncio.create_task(alarm.sleep_until(other_due))
        sleeping = asyncio.create_task(wakeup.until(time.monotonic() + 60))
        await asyncio.sleep(0)
        moved = time.monotonic()
        wakeup.move(moved - 1.0)
        await asyncio.wait_for(sleeping, timeout=1.0)
        woke = time.monotonic() - moved
        await other
        return woke, time.monotonic() - other_due

    woke, other_late = asyncio.run(main())
    assert woke < 0.5
    assert 0.0 <= other_late < 0.5


def test_a_cancelled_wakeup_can_sleep_again_and_has_one_sleeper_at_a_time() -> None:
    async def main() -> None:
        alarm = Alarm.of(asyncio.get_running_loop())
        wakeup = alarm.wakeup()
        sleeping = asyncio.create_task(wakeup.until(time.monotonic() + 60))
        await asyncio.sleep(0)
        with pytest.raises(RuntimeError, match="sleeper already"):
            await wakeup.until(time.monotonic() + 1)
        sleeping.cancel()
        with pytest.raises(asyncio.CancelledError):
            await sleeping
        assert wakeup.when is None
        wakeup.move(time.monotonic())  # nobody sleeps: nothing happens
        due = time.monotonic() + 0.01
        await wakeup.until(due)
        assert time.monotonic() >= due

    asyncio.run(main())
