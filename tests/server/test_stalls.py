"""The event loop's watch (server/runtime/stalls.py): its lag measured, its stalls caught with the
code that caused them."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

from jitdyn.server.runtime.stalls import BEAT, LoopWatch, Stall


def _holds_the_loop(seconds: float) -> None:
    time.sleep(seconds)  # as a long computation on the loop would


def _watched(hold: Callable[[float], None]) -> tuple[list[float], list[Stall]]:
    """The lags and stalls a watch (stall: 50 ms) saw of a loop that `hold` kept for 0.2 s."""
    lags: list[float] = []
    stalls: list[Stall] = []

    async def main() -> None:
        watch = LoopWatch(asyncio.get_running_loop(), on_lag=lags.append, stall=0.05, report=stalls.append)
        watch.start()
        await asyncio.sleep(0.1)
        hold(0.2)
        await asyncio.sleep(0.1)
        watch.stop()

    asyncio.run(main())
    return lags, stalls


def test_a_stall_is_reported_with_the_code_that_held_the_loop() -> None:
    lags, stalls = _watched(_holds_the_loop)
    # Beats on an idle loop are on time; the stall is one beat 0.2 s late.
    assert len(lags) > 20
    assert sorted(lags)[len(lags) // 2] < 5 * BEAT
    assert 0.18 < max(lags) < 0.4
    assert len(stalls) == 1
    stall = stalls[0]
    assert 0.18 < stall.seconds < 0.4
    assert sum(stall.loop_stacks.values()) >= 5  # sampled while it lasted
    top = stall.loop_stacks.most_common(1)[0][0]
    assert "test_stalls.py" in top and top.rstrip().endswith("_holds_the_loop")
    text = stall.describe()
    assert text.startswith("the event loop stalled 2") and "_holds_the_loop" in text, text
    # The kernel's account: a loop asleep ran nothing and waited for no CPU.
    account = stall.account
    assert account is not None, "Linux's schedstat is on this kind of machine"
    assert 0.15 < account.wall < 0.45 and account.ran < 0.03 and account.waited_for_cpu < 0.05, account
    assert "for the GIL, a lock or I/O" in text


def _computes(seconds: float) -> None:
    end = time.thread_time() + seconds
    while time.thread_time() < end:
        pass


def test_a_stall_of_computation_is_accounted_as_the_loop_running_or_waiting_for_a_cpu() -> None:
    _, stalls = _watched(_computes)
    assert len(stalls) == 1 and stalls[0].account is not None
    account = stalls[0].account
    # 0.2 s of the thread's own CPU time, all inside the stall; on a busy machine some of the wall
    # is spent runnable, waiting for a CPU, which the kernel counts apart.
    assert 0.15 < account.ran < 0.3 and account.ran + account.waited_for_cpu > 0.8 * account.wall, account


def test_a_busy_loop_without_a_stall_reports_none() -> None:
    stalls: list[Stall] = []
    lags: list[float] = []

    async def main() -> None:
        watch = LoopWatch(asyncio.get_running_loop(), on_lag=lags.append, stall=0.05, report=stalls.append)
        watch.start()
        for _ in range(40):  # 20 ms pieces of work with the loop let go between them
            _holds_the_loop(0.02)
            await asyncio.sleep(0)
        watch.stop()

    asyncio.run(main())
    assert stalls == []
    assert lags and max(lags) < 0.05
