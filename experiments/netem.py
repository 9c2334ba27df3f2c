"""Network emulation for experiments: seeded latency, jitter, loss and reordering of frames.

LOCKSTEP (virtual time, deterministic): `lockstep_schedule` turns a stream of frames into the
messages the server sees, in order: at each tick the frame if it came in time, else a skip; a late
frame when it arrives (the server answers it CORRECTED); a lost frame never::

    schedule = lockstep_schedule(200, dt=0.05, profile=NetworkProfile(latency=0.035, jitter=0.01, loss=0.05), seed=1)
    for d in schedule.deliveries:      # Delivery(kind="frame" | "skip", seq, tick, late_ticks)
        ...

REALTIME (wall clock): `DelayedSender` calls a send function after each frame's sampled delay, from
one background thread.
"""

from __future__ import annotations

import heapq
import itertools
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum
from typing import Generic, Literal, TypeVar

import numpy as np

from jitdyn.lifecycle import Closeable

__all__ = [
    "PERFECT",
    "DelayedSender",
    "Delivery",
    "Distribution",
    "NetworkProfile",
    "Schedule",
    "gap_schedule",
    "lockstep_schedule",
    "sample_delays",
]

T = TypeVar("T")


class Distribution(Enum):
    """The shape of the one-way latency around its mean."""

    CONSTANT = "constant"  # every frame takes `latency`
    NORMAL = "normal"  # N(latency, jitter^2), cut at 0
    LOGNORMAL = "lognormal"  # mean `latency`, standard deviation `jitter`: the long right tail of real links
    UNIFORM = "uniform"  # U(latency - jitter, latency + jitter), cut at 0


@dataclass(frozen=True, slots=True)
class NetworkProfile:
    """A one-way link from client to server. Times in seconds, probabilities in [0, 1]."""

    latency: float = 0.0  # mean one-way delay
    jitter: float = 0.0  # spread of the delay (see Distribution)
    distribution: Distribution = Distribution.NORMAL
    loss: float = 0.0  # probability that a frame never arrives
    # Probability that a frame is held back by `reorder_delay` more, so later frames overtake it
    # (as netem's reorder does).
    reorder: float = 0.0
    reorder_delay: float = 0.0

    def __post_init__(self) -> None:
        for name in ("latency", "jitter", "reorder_delay"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number of seconds >= 0, got {value}")
        for name in ("loss", "reorder"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must be a probability in [0, 1], got {value}")
        if self.reorder > 0 and self.reorder_delay <= 0:
            raise ValueError(f"reorder_delay must be > 0 seconds when reorder > 0, got {self.reorder_delay}")
        if self.distribution is Distribution.LOGNORMAL and self.jitter > 0 and self.latency <= 0:
            raise ValueError(f"latency must be > 0 for a lognormal delay with jitter, got {self.latency}")


PERFECT = NetworkProfile()


def sample_delays(profile: NetworkProfile, n: int, *, seed: int) -> np.ndarray:
    """One-way delays of `n` frames in seconds, inf for a lost frame; (n,). Same seed, same delays.

    Every random draw is made for every frame whatever the outcome, so changing the loss rate does
    not shift the latencies of the frames that do arrive.
    """
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    rng = np.random.default_rng(seed)
    base = rng.standard_normal(n)
    uniform = rng.random(n)
    lost = rng.random(n) < profile.loss
    held = rng.random(n) < profile.reorder
    m, j = profile.latency, profile.jitter
    match profile.distribution:
        case Distribution.CONSTANT:
            delays = np.full(n, m)
        case Distribution.NORMAL:
            delays = m + j * base
        case Distribution.UNIFORM:
            delays = m + j * (2.0 * uniform - 1.0)
        case Distribution.LOGNORMAL:
            if j == 0:
                delays = np.full(n, m)
            else:
                # Parameters of the underlying normal that give the delay mean m and deviation j.
                sigma2 = math.log1p((j / m) ** 2)
                delays = np.exp(math.log(m) - sigma2 / 2 + math.sqrt(sigma2) * base)
    delays = np.maximum(delays, 0.0) + np.where(held, profile.reorder_delay, 0.0)
    return np.where(lost, np.inf, delays)


@dataclass(frozen=True, slots=True)
class Delivery:
    """One message the server sees: tick `seq`'s frame, or a skip of tick `seq`.

    `tick` is the tick the server is about to answer when the message comes: a frame in time has
    tick == seq; a late frame comes just before tick `tick` (tick - seq = late_ticks >= 1), or after
    the last tick when tick == the schedule's length.
    """

    kind: Literal["frame", "skip"]
    seq: int
    tick: int
    late_ticks: int = 0


@dataclass(frozen=True, slots=True)
class Schedule:
    """The messages of a LOCKSTEP session in the order the server sees them."""

    ticks: int
    dt: float
    deliveries: tuple[Delivery, ...]
    delays: np.ndarray = field(repr=False)  # (ticks,) the sampled one-way delays; inf when lost

    @property
    def on_time(self) -> int:
        return sum(1 for d in self.deliveries if d.kind == "frame" and d.late_ticks == 0)

    @property
    def late(self) -> int:
        return sum(1 for d in self.deliveries if d.kind == "frame" and d.late_ticks > 0)

    @property
    def lost(self) -> int:
        return int(np.isinf(self.delays).sum())

    def received_in_time(self) -> np.ndarray:
        """(ticks,) bool: which ticks had their frame when they were answered."""
        out = np.zeros(self.ticks, dtype=bool)
        for d in self.deliveries:
            if d.kind == "frame" and d.late_ticks == 0:
                out[d.seq] = True
        return out


def lockstep_schedule(
    ticks: int,
    *,
    dt: float,
    profile: NetworkProfile = PERFECT,
    seed: int = 0,
    grace: float = 0.0,
) -> Schedule:
    """The messages a LOCKSTEP server sees when frame k, sent at k dt, takes its sampled delay d_k.

    Tick k is answered at its deadline k dt + grace. Frame k is in time when d_k <= grace; otherwise
    the server gets skip(k), then frame k before the first tick whose deadline is at or after its
    arrival (ceil((d_k - grace) / dt) ticks late); frames arriving between two deadlines come in
    order of arrival. A lost frame leaves a skip only. With grace = 0 every frame with any latency is
    late, so the server dead-reckons every tick and corrects it a tick or more later.
    """
    if ticks < 0:
        raise ValueError(f"ticks must be >= 0, got {ticks}")
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a finite number of seconds > 0, got {dt}")
    if not (math.isfinite(grace) and 0 <= grace):
        raise ValueError(f"grace must be a finite number of seconds >= 0, got {grace}")
    delays = sample_delays(profile, ticks, seed=seed)
    return _schedule(ticks, dt, delays, grace)


def gap_schedule(ticks: int, *, dt: float, gap_ticks: int, period: int, first: int | None = None) -> Schedule:
    """Deterministic gaps: frames in time except `gap_ticks` lost in a row every `period` ticks.

    The first gap starts at tick `first` (default: `period`, so the filter settles first). Meant
    for measuring the error of dead reckoning against the gap's length.
    """
    if gap_ticks < 1 or period <= gap_ticks:
        raise ValueError(f"need 1 <= gap_ticks < period, got gap_ticks={gap_ticks}, period={period}")
    start = period if first is None else first
    if start < 1:
        raise ValueError(f"first must be >= 1 (tick 0 carries the initial state), got {start}")
    delays = np.zeros(ticks)
    for k in range(ticks):
        if k >= start and (k - start) % period < gap_ticks:
            delays[k] = np.inf
    return _schedule(ticks, dt, delays, 0.0)


def _schedule(ticks: int, dt: float, delays: np.ndarray, grace: float) -> Schedule:
    # Late frames keyed by the tick they come before, then by arrival time (then seq for ties).
    late: list[tuple[int, float, int]] = []
    for k in range(ticks):
        d = float(delays[k])
        if math.isinf(d) or d <= grace:
            continue
        # Tolerance: a delay of exactly one dt past the grace is one tick late, not two.
        lateness = max(1, math.ceil((d - grace) / dt - 1e-9))
        late.append((min(k + lateness, ticks), k * dt + d, k))
    late.sort()
    deliveries: list[Delivery] = []
    pending = iter(late)
    upcoming = next(pending, None)
    for j in range(ticks + 1):
        while upcoming is not None and upcoming[0] == j:
            deliveries.append(Delivery("frame", upcoming[2], j, j - upcoming[2]))
            upcoming = next(pending, None)
        if j == ticks:
            break
        in_time = math.isfinite(delays[j]) and delays[j] <= grace
        deliveries.append(Delivery("frame" if in_time else "skip", j, j))
    return Schedule(ticks=ticks, dt=dt, deliveries=tuple(deliveries), delays=delays)


class DelayedSender(Closeable, Generic[T]):
    """Calls `send(item)` after each item's delay, from one background thread (REALTIME emulation).

    Delays come from `profile` with `seed`, in order of submission; lost items are never sent.
    `send` runs on the sender's thread, one item at a time, in order of due time. Use as a context
    manager; `close()` waits for the items still due (or drops them with `drain=False`) and is safe to
    call twice::

        with DelayedSender(session.send_frame_async, NetworkProfile(latency=0.03), seed=0) as net:
            net.submit(frame)
    """

    def __init__(
        self,
        send: Callable[[T], object],
        profile: NetworkProfile,
        *,
        seed: int,
        clock: Callable[[], float] = time.monotonic,
        chunk: int = 1024,
    ) -> None:
        self._send = send
        self._profile = profile
        self._seed = seed
        self._clock = clock
        self._chunk = chunk
        self._delays: np.ndarray = np.empty(0)
        self._drawn = 0
        self._submitted = 0
        self._heap: list[tuple[float, int, T]] = []
        self._order = itertools.count()
        self._cv = threading.Condition()
        self._closing = False
        self._drain = True
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="jitdyn-netem", daemon=True)
        self._thread.start()

    def next_delay(self) -> float:
        """The delay the next submitted item will get (inf: lost); the sequence is fixed by the seed."""
        if self._submitted >= self._delays.size:
            # Drawn in chunks of one seeded stream per chunk, so the sequence does not depend on
            # how many items a run submits.
            chunk = sample_delays(self._profile, self._chunk, seed=self._seed * 1_000_003 + self._drawn)
            self._delays = np.concatenate([self._delays, chunk])
            self._drawn += 1
        return float(self._delays[self._submitted])

    def submit(self, item: T) -> float:
        """Schedules `item`; returns its delay in seconds (inf when it is lost)."""
        with self._cv:
            if self._closing:
                raise RuntimeError("submit after close: the DelayedSender is closed")
            if self._error is not None:
                raise RuntimeError("the send function failed") from self._error
            delay = self.next_delay()
            self._submitted += 1
            if math.isfinite(delay):
                heapq.heappush(self._heap, (self._clock() + delay, next(self._order), item))
                self._cv.notify()
            return delay

    def close(self, *, drain: bool = True) -> None:
        """Stops the thread after sending what is due (drain) or at once; re-raises a send error."""
        with self._cv:
            if not self._closing:
                self._closing = True
                self._drain = drain
                self._cv.notify()
        self._thread.join()
        if self._error is not None:
            error, self._error = self._error, None
            raise RuntimeError("the send function failed") from error

    def _run(self) -> None:
        while True:
            with self._cv:
                while True:
                    if self._closing and (not self._drain or not self._heap):
                        return
                    if self._heap:
                        wait = self._heap[0][0] - self._clock()
                        if wait <= 0:
                            _, _, item = heapq.heappop(self._heap)
                            break
                        self._cv.wait(wait)
                    else:
                        self._cv.wait()
            try:
                self._send(item)
            except BaseException as error:  # noqa: BLE001 - handed to the caller at close()
                with self._cv:
                    self._error = error
                    self._closing = True
                    self._drain = False
                return
