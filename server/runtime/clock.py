"""The REALTIME clock: placing client time on the server clock from NTP-style `sync` exchanges.

Each probe i carries the client's send time t1; the server stamps its arrival t2 and the answer's
departure t3. A later probe reports t4, the client's receive time of answer i, and the exchange is
complete: offset = ((t2 - t1) + (t3 - t4)) / 2, round trip = (t4 - t1) - (t3 - t2). As NTP's clock
filter does, the offset is taken from the exchange with the smallest round trip among the recent
ones: its error is bounded by half that round trip.

Server time is seconds since the session opened (time.monotonic based); client time is seconds since
the client's session start.
"""

from __future__ import annotations

import time
from collections import OrderedDict, deque
from dataclasses import dataclass

__all__ = ["ClockSync", "MonotonicClock", "SyncSample"]


class MonotonicClock:
    """Seconds since construction, from time.monotonic."""

    def __init__(self) -> None:
        self._start = time.monotonic()

    @property
    def start(self) -> float:
        """The time.monotonic() value that is server time 0."""
        return self._start

    def now(self) -> float:
        return time.monotonic() - self._start

    def restart(self, *, elapsed: float = 0.0) -> None:
        """Make now server time `elapsed` (the session's clock starts as `opened` leaves; a resumed
        session's, at the time it has run since it first opened)."""
        self._start = time.monotonic() - elapsed

    def to_monotonic(self, server_time: float) -> float:
        return self._start + server_time


@dataclass(frozen=True, slots=True)
class SyncSample:
    """One completed exchange: offset (server - client) and round trip, seconds."""

    offset: float
    round_trip: float


class ClockSync:
    """Estimates the offset of the server clock from the client clock, and the round trip.

    Before any probe the offset is `initial_offset` (0: the client started its clock when it sent
    `open`, which arrived at server time 0); after probes but before a completed exchange, the
    smallest one-way t2 - t1 (an upper bound, by the uplink's transit).
    """

    def __init__(self, *, window: int = 8, pending_limit: int = 64, initial_offset: float = 0.0) -> None:
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        self._samples: deque[SyncSample] = deque(maxlen=window)
        self._pending: OrderedDict[int, tuple[float, float, float]] = OrderedDict()
        self._pending_limit = pending_limit
        self._offset = initial_offset
        self._one_way = float("inf")  # the smallest t2 - t1 seen before any exchange is complete
        self._round_trip = 0.0

    @property
    def offset(self) -> float:
        """Server clock minus client clock (seconds)."""
        return self._offset

    @property
    def round_trip(self) -> float:
        """Round trip of the best recent exchange (seconds); 0 when none is complete."""
        return self._round_trip

    def to_server(self, client_time: float) -> float:
        """A client time on the server clock."""
        return client_time + self._offset

    def on_probe(
        self,
        *,
        probe_id: int,
        client_send_time: float,
        server_receive_time: float,
        server_send_time: float,
        previous_id: int | None = None,
        previous_receive_time: float | None = None,
    ) -> SyncSample | None:
        """Record probe `probe_id` (t1, t2, t3); complete `previous_id` with its t4 if given.

        Returns the completed sample, if any. Unknown or implausible previous exchanges (t4 before
        t1, a negative round trip) are ignored: a careless client cannot move the clock by them.
        """
        sample = None
        if previous_id is not None and previous_receive_time is not None:
            stamps = self._pending.pop(previous_id, None)
            if stamps is not None:
                t1, t2, t3 = stamps
                t4 = previous_receive_time
                round_trip = (t4 - t1) - (t3 - t2)
                if t4 >= t1 and round_trip >= 0.0:
                    sample = SyncSample(offset=((t2 - t1) + (t3 - t4)) / 2.0, round_trip=round_trip)
                    self._samples.append(sample)
                    best = min(self._samples, key=lambda s: s.round_trip)
                    self._offset, self._round_trip = best.offset, best.round_trip
        if not self._samples:
            # Until an exchange is complete (the next probe brings its t4), the smallest one-way
            # estimate t2 - t1: late by the uplink's transit, where 0 would be early by opened's
            # transit and more (docs/decisions/0004-clock-offset-before-the-first-exchange.md).
            one_way = server_receive_time - client_send_time
            self._one_way = min(self._one_way, one_way)
            self._offset = self._one_way
        self._pending[probe_id] = (client_send_time, server_receive_time, server_send_time)
        while len(self._pending) > self._pending_limit:
            self._pending.popitem(last=False)
        return sample
