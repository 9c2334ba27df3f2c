"""When an admitted session's clock starts (server/transport/start_gate.py): at once on a quiet
process; after the opens under way and the refusals of a burst, one at a time; never later than
the hold."""

from __future__ import annotations

import asyncio
import itertools
import time

from jitdyn.server.transport.start_gate import StartGate


def test_a_quiet_process_starts_a_session_at_once() -> None:
    async def main() -> float:
        return await StartGate().wait()

    assert asyncio.run(main()) == 0.0


def test_sessions_start_after_the_opens_under_way_one_at_a_time_in_order() -> None:
    async def main() -> tuple[list[tuple[int, float]], float]:
        gate = StartGate(spacing=0.005)
        started: list[tuple[int, float]] = []

        async def session(k: int) -> None:
            await gate.wait()
            started.append((k, time.monotonic()))

        with gate.opening():
            tasks = [asyncio.ensure_future(session(k)) for k in range(4)]
            await asyncio.sleep(0.1)
            assert started == []  # held while another opens
            opened = time.monotonic()
        await asyncio.gather(*tasks)
        return started, opened

    started, opened = asyncio.run(main())
    assert [k for k, _ in started] == [0, 1, 2, 3]
    assert started[0][1] >= opened
    gaps = [b - a for (_, a), (_, b) in itertools.pairwise(started)]
    assert min(gaps) >= 0.005


def test_refusals_hold_the_start_until_they_are_quiet_or_the_hold_has_passed() -> None:
    async def main() -> tuple[float, float]:
        gate = StartGate(hold=0.5, quiet=0.1)
        gate.refused()
        after_quiet = await gate.wait()

        async def refusing() -> None:  # a burst that does not end
            while True:
                gate.refused()
                await asyncio.sleep(0.02)

        burst = asyncio.ensure_future(refusing())
        await asyncio.sleep(0.01)
        held = await gate.wait()
        burst.cancel()
        return after_quiet, held

    after_quiet, held = asyncio.run(main())
    assert 0.09 <= after_quiet < 0.3
    assert 0.5 <= held < 0.7


def test_a_session_that_left_while_held_does_not_hold_the_next() -> None:
    async def main() -> float:
        gate = StartGate(spacing=0.001)
        with gate.opening():
            left = asyncio.ensure_future(gate.wait())
            waiting = asyncio.ensure_future(gate.wait())
            await asyncio.sleep(0.03)
            left.cancel()
        began = time.monotonic()
        await waiting
        return time.monotonic() - began

    assert asyncio.run(main()) < 0.1
