"""A session's per-tick metrics counted in plain numbers on its own thread, and added to the
process's Prometheus metrics once a window (FLUSH_EVERY) and when the session ends: a tick then
costs a few additions instead of a Prometheus call (and its lock, or its memory-mapped file with
--processes) per metric (docs/decisions/0196-metrics-and-admission-per-window.md).

    ticks = CounterTally(metrics().ticks.labels(process, model, "MEASURED"))
    lateness = HistogramTally(metrics().lateness.labels(process, model))
    ticks.inc(); lateness.observe(0.002)      # on the tick's path
    ticks.flush(); lateness.flush()           # once a window: the same counts, bucket by bucket
"""

from __future__ import annotations

import math
from bisect import bisect_left
from typing import Final

from prometheus_client import Counter, Histogram

__all__ = ["FLUSH_EVERY", "CounterTally", "HistogramTally"]

# s between two flushes of a session's tallies: well under a scrape interval (Prometheus' default
# is 15 s), so a scrape sees every tick but those of the last quarter second of open sessions.
FLUSH_EVERY: Final = 0.25


class CounterTally:
    """Increments of one labelled Prometheus counter, added to it by flush()."""

    def __init__(self, counter: Counter) -> None:
        self._counter = counter
        self.count = 0

    def inc(self) -> None:
        self.count += 1

    def flush(self) -> None:
        if self.count:
            count, self.count = self.count, 0
            self._counter.inc(count)


class HistogramTally:
    """Observations of one labelled Prometheus histogram, counted by bucket as its observe()
    counts them (the first bucket whose upper bound is at least the value), added by flush()."""

    def __init__(self, histogram: Histogram) -> None:
        self._histogram = histogram
        # prometheus-client keeps a histogram's bounds and its per-bucket values in these; it has
        # no public call that adds many observations at once (tests/server/test_tally.py holds a
        # flushed tally equal to the same values observed one by one).
        self._bounds: list[float] = list(histogram._upper_bounds)
        self._counts = [0] * len(self._bounds)
        self._sum = 0.0
        self._pending = False

    def observe(self, value: float) -> None:
        self._sum += value
        if not math.isnan(value):  # NaN is in no bucket, as in observe()
            self._counts[bisect_left(self._bounds, value)] += 1
        self._pending = True

    def flush(self) -> None:
        if not self._pending:
            return
        histogram = self._histogram
        counts, total = self._counts, self._sum
        self._counts, self._sum, self._pending = [0] * len(self._bounds), 0.0, False
        histogram._sum.inc(total)
        for bucket, count in zip(histogram._buckets, counts, strict=True):
            if count:
                bucket.inc(count)
