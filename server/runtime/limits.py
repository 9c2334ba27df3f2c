"""Limits on what one session may cost the server, checked at open and while it runs; each has a
`jitdyn serve` flag, which the refusal names.

    limits = StreamLimits(max_history_bytes=64 << 20, idle_timeout=60.0)
    limits.check_history(
        history=500, snapshot_bytes=snapshot_bytes(estimator.snapshot()), state_dimension=n
    )
    cost = tick_cost(model, nsigma=nsigma, steps_per_tick=steps, state_dimension=n)
    limits.check_tick_cost(cost, dt=0.002, state_dimension=n, nsigma=nsigma, steps=steps)

What is measured to check them, `snapshot_bytes` and `tick_cost`, is in `costs`: this module
imports nothing heavy, so that the command line parses its flags without loading MuJoCo.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from jitdyn.errors import InvalidArgument, ResourceExhausted
from jitdyn.settings import DEFAULTS

__all__ = ["DEFAULT_STREAM_LIMITS", "IdleTimeout", "LateTimeout", "StreamLimits"]


class IdleTimeout(ResourceExhausted):
    """A session sent nothing (no frame, no sync, no skip) for longer than the idle timeout."""


class LateTimeout(ResourceExhausted):
    """A REALTIME session told that its answers may go late stayed among those its server process
    could not serve on time for longer than the late timeout."""


@dataclass(frozen=True, kw_only=True)
class StreamLimits:
    """Limits on one session's memory, clock and time.

    Attributes:
      max_history_bytes: memory the late-frame history may hold (ticks x the estimator's state
        size), in bytes (--max-history-bytes).
      max_clock_offset: how far (s) a REALTIME client's clock may be placed from the session's by
        `sync` (--max-clock-offset); both start as `opened` is sent, so an honest offset is about
        half a round trip.
      idle_timeout: seconds a session may go with no request at all (--idle-timeout).
      max_tick_share: the largest share of dt a REALTIME tick's estimated cost may take
        (--max-tick-share).
      late_timeout: seconds a REALTIME session told in band that its answers may go late (its
        process is past what it serves on time and it is among the last admitted) may stay so
        before it is ended, stored, so that the sessions admitted before it are on time again
        (--late-timeout). Long enough that a passing overload (a collection, a compaction, a burst
        of opens) ends no one; the session admitted first is never ended.
    """

    # The defaults are those of `jitdyn serve`'s settings (jitdyn.settings).
    max_history_bytes: int = DEFAULTS.max_history_bytes
    max_clock_offset: float = DEFAULTS.max_clock_offset
    idle_timeout: float = DEFAULTS.idle_timeout
    max_tick_share: float = DEFAULTS.max_tick_share
    late_timeout: float = DEFAULTS.late_timeout

    def __post_init__(self) -> None:
        for name in (
            "max_history_bytes",
            "max_clock_offset",
            "idle_timeout",
            "max_tick_share",
            "late_timeout",
        ):
            value = getattr(self, name)
            if (
                isinstance(value, bool)
                or not isinstance(value, (int, float))
                or not (math.isfinite(value) and value > 0)
            ):
                raise InvalidArgument(f"StreamLimits.{name} must be a positive number, got {value!r}")

    def check_history(self, *, history: int, snapshot_bytes: int, state_dimension: int) -> None:
        """Refuse a history whose snapshots would hold more than max_history_bytes."""
        needed = history * snapshot_bytes
        if needed > self.max_history_bytes:
            fits = max(1, self.max_history_bytes // max(1, snapshot_bytes))
            raise ResourceExhausted(
                f"open.history {history} ticks at state dimension {state_dimension} would hold "
                f"{needed / 2**20:.1f} MiB; the limit per session is {self.max_history_bytes / 2**20:.1f} MiB "
                f"(--max-history-bytes): ask for at most {fits} ticks"
            )

    def check_clock_offset(self, offset: float) -> None:
        """Refuse a REALTIME client clock placed further than max_clock_offset from the session's."""
        if not abs(offset) <= self.max_clock_offset:
            raise InvalidArgument(
                f"sync: the client's clock is {offset:+.6g} s from the session's; the limit is "
                f"±{self.max_clock_offset:g} s (--max-clock-offset): start the session clock when "
                "`opened` arrives"
            )

    def idle(self) -> IdleTimeout:
        return IdleTimeout(
            f"the session sent no frame, sync or skip for {self.idle_timeout:g} s, the limit "
            f"(--idle-timeout); it was stored and its slot given back"
        )

    def late(self, told: float) -> LateTimeout:
        return LateTimeout(
            f"the session was ended: {told:.1f} s after it was told its answers may go late, this "
            f"server process still could not serve it on time (the limit, --late-timeout "
            f"{self.late_timeout:g} s); it was stored. Resume it on another server or at a lower rate"
        )

    def check_tick_cost(
        self, cost: float, *, dt: float, state_dimension: int, nsigma: int, steps: int
    ) -> None:
        """Refuse a REALTIME session whose estimated tick cost (s) does not fit its dt."""
        if cost > self.max_tick_share * dt:
            raise ResourceExhausted(
                f"a tick of this session would cost about {cost * 1e3:.1f} ms (state dimension "
                f"{state_dimension}, {nsigma} sigma points, {steps} physics steps each), over "
                f"{self.max_tick_share:g} of open.dt {dt * 1e3:g} ms (--max-tick-share): use a larger dt, "
                "fewer sigma points (estimator.sigma_points) or a smaller model"
            )


DEFAULT_STREAM_LIMITS = StreamLimits()
