"""A session's metrics counted per window (server/transport/tally.py): a flushed tally is the
same series as the same values observed one by one, bucket by bucket, on real prometheus-client
metrics."""

from __future__ import annotations

import math

import numpy as np
from prometheus_client import CollectorRegistry, Counter, Histogram

from jitdyn.server.transport.tally import CounterTally, HistogramTally

BUCKETS = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.1)


def _samples(registry: CollectorRegistry) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    return {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in registry.collect()
        for s in family.samples
        if not s.name.endswith("_created")
    }


def test_a_flushed_histogram_tally_is_the_values_observed_one_by_one() -> None:
    rng = np.random.default_rng(7)
    # Values on the bounds themselves (observe() puts them in that bucket), between, past the
    # last, zero and NaN (in no bucket, in the sum).
    values = [*BUCKETS, 0.0, 0.2, 7.0, math.nan, *rng.exponential(0.003, 500).tolist()]
    one_by_one, tallied = CollectorRegistry(), CollectorRegistry()
    direct = Histogram("lateness", "", ["model"], buckets=BUCKETS, registry=one_by_one).labels("arm")
    tally = HistogramTally(
        Histogram("lateness", "", ["model"], buckets=BUCKETS, registry=tallied).labels("arm")
    )
    for k, value in enumerate(values):
        direct.observe(value)
        tally.observe(value)
        if k % 97 == 0:
            tally.flush()
    before = _samples(tallied)
    tally.flush()
    tally.flush()  # nothing new: nothing added
    expected, got = _samples(one_by_one), _samples(tallied)
    assert got.keys() == expected.keys()
    for key, value in expected.items():
        if key[0] == "lateness_sum":  # NaN in the sum: NaN on both sides
            assert math.isnan(value) and math.isnan(got[key])
        else:
            assert got[key] == value, key
    assert before != got  # the last flush added the values since the one before


def test_a_counter_tally_adds_its_count_when_flushed() -> None:
    registry = CollectorRegistry()
    counter = Counter("ticks", "", ["source"], registry=registry)
    tally = CounterTally(counter.labels("MEASURED"))
    for _ in range(41):
        tally.inc()
    assert registry.get_sample_value("ticks_total", {"source": "MEASURED"}) == 0.0
    tally.flush()
    tally.inc()
    tally.flush()
    tally.flush()
    assert registry.get_sample_value("ticks_total", {"source": "MEASURED"}) == 42.0
