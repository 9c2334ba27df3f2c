"""The session runtime: ticks, frames, skips, late frames and the timewarp, free of gRPC.

One `SessionRuntime` per session. Every tick k gets one outcome: MEASURED when its frame is there,
PREDICTED when not. A frame that arrives after its tick was answered rolls the estimator back to its
state before that tick, applies the frame, replays the later ticks with the inputs they had
(timewarp, as in distributed simulation) and yields a CORRECTED outcome for that tick. Because the
replay uses the same inputs in the same order, the estimator ends exactly where a run in which the
frame came on time would be. A REALTIME session waits for frames that come late instead: the
estimator runs each tick once, in tick order, when its frame comes or its wait is over, and the
ticks it has not reached are answered by a glance ahead (docs/decisions/0007); a frame later than
its wait replays only its own tick at once, and the rest of the replay is caught up over the ticks
that follow (docs/decisions/0167).

Calls are synchronous and CPU-bound, one at a time: LOCKSTEP sessions run them in a worker thread,
REALTIME sessions on the event loop (their deadlines are its timers).
"""

from __future__ import annotations

import dataclasses
import enum
import time
from collections import OrderedDict, deque
from dataclasses import dataclass
from typing import Final

import mujoco
import numpy as np

from jitdyn.mujoco_log import WarningCounter
from jitdyn.server.estimation.dynamics import Dynamics, DynamicsResult
from jitdyn.server.estimation.interface import Estimate, Estimator, Measurement
from jitdyn.server.runtime.costs import snapshot_bytes
from jitdyn.server.runtime.frames import FrameIn, Rejection
from jitdyn.vocabulary import Scenario, Source

__all__ = ["Place", "SessionCounts", "SessionRuntime", "TickOutcome"]

_RESIZE_EVERY = 64  # ticks between two measures of the snapshots' size (it creeps as windows fill)
# A session that waits for late frames waits as many ticks as its frames came late lately (the most
# of the last _LATENESS_KEPT), and at most _MAX_WAIT.
_LATENESS_KEPT: Final = 64
_MAX_WAIT: Final = 8
# A stall (ticks skipped or shed) leaves at most `_stall_room()` ticks waiting for their frames, and
# the ticks past the wait are run at most _CATCH_UP a tick, so a stall's work is spread, not queued.
_CATCH_UP: Final = 2


class Place(enum.Enum):
    """Where a frame belongs among a session's ticks (`SessionRuntime.classify`)."""

    NEXT = enum.auto()  # the first tick not yet answered
    FUTURE = enum.auto()  # a tick after it
    LATE = enum.auto()  # a tick answered PREDICTED and still in the history: a timewarp applies it
    DUPLICATE = enum.auto()  # a tick that has its frame already
    TOO_OLD = enum.auto()  # a tick past the history


@dataclass(frozen=True, slots=True)
class TickOutcome:
    """The answer for one tick, before it becomes a message and a stored row."""

    seq: int
    t: float  # the tick's time on the client clock, plus the horizon (s)
    source: Source
    qpos: np.ndarray  # (nq,)
    qvel: np.ndarray  # (nv,)
    qacc: np.ndarray  # (nv,)
    dynamics: DynamicsResult
    estimate: Estimate | None  # None before the first frame
    frame: FrameIn | None
    late_ticks: int
    compute_us: int
    horizon: float
    late_compute: bool = False  # answered from what the runtime had, without running the estimator


@dataclass(slots=True)
class SessionCounts:
    """What happened so far; becomes the session summary."""

    ticks: int = 0
    frames: int = 0
    measured: int = 0
    predicted: int = 0
    corrected: int = 0
    rejected: int = 0
    late: int = 0
    late_compute: int = 0  # ticks answered without the estimator (overload)
    mujoco_warnings: int = 0  # warnings MuJoCo raised in this session's work
    skipped: int = 0  # ticks not answered at all: the server was behind (overload)
    compute_us_total: int = 0
    compute_us_max: int = 0
    results: int = 0
    qfrc_min: np.ndarray | None = None
    qfrc_max: np.ndarray | None = None

    def add_result(self, outcome: TickOutcome) -> None:
        self.results += 1
        self.compute_us_total += outcome.compute_us
        self.compute_us_max = max(self.compute_us_max, outcome.compute_us)
        qfrc = outcome.dynamics.qfrc_inverse
        if qfrc is not None:
            if self.qfrc_min is None or self.qfrc_max is None:
                self.qfrc_min, self.qfrc_max = qfrc.copy(), qfrc.copy()
            else:
                np.minimum(self.qfrc_min, qfrc, out=self.qfrc_min)
                np.maximum(self.qfrc_max, qfrc, out=self.qfrc_max)


@dataclass(slots=True)
class _Tick:
    """What the timewarp needs to redo a tick: the estimator before it and its inputs."""

    seq: int
    before: object | None  # estimator snapshot before this tick; None: not yet initialised
    frame: FrameIn | None
    ctrl: np.ndarray | None  # the control the prediction of this tick used (CONTROLLED)


class SessionRuntime:
    """Ticks of one session. `history` ticks are kept for late frames."""

    def __init__(
        self,
        *,
        model: mujoco.MjModel,
        estimator: Estimator,
        dynamics: Dynamics,
        dt: float,
        scenario: Scenario,
        history: int,
        max_history_bytes: int | None = None,
        first_tick: int = 0,
        wait_for_late: bool = False,
    ) -> None:
        self._model = model
        self._estimator = estimator
        self._dynamics = dynamics
        self._dt = dt
        self._controlled = scenario == Scenario.CONTROLLED
        self._history = history
        # The ticks kept: `history`, or fewer when their snapshots would pass max_history_bytes at
        # the size the newest has (the open checks the size the estimator starts with; it grows,
        # and a PASSIVE filter that turns DRIVEN holds 8x as much).
        self._max_history_bytes = max_history_bytes
        self._retained = history
        self._sized_for = -1  # the state dimension the retained count was last sized at
        self._ticks: OrderedDict[int, _Tick] = OrderedDict()
        self._initialised = False
        # A resumed session continues at `first_tick`, its estimator restarted from the next
        # frame, and the first estimate says so (`reinitialised`).
        self._next = first_tick
        self._restarted = first_tick > 0
        self.counts = SessionCounts()
        self._zero_ctrl = np.zeros(model.nu)
        self._qpos0 = model.qpos0.copy()
        self._zero_nv = np.zeros(model.nv)
        self._last: TickOutcome | None = None
        # Every call into MuJoCo for this session runs under `mujoco_log.counting(self.warnings)`
        # (the servicer does it), so its warnings are counted here.
        self.warnings = WarningCounter()
        # The first tick shed without a frame: from it on the estimator is behind, until a frame
        # re-initialises it or a late frame at or before it replays the ticks properly.
        self._stale_since: int | None = None
        # The first tick the estimator has not run. Ticks from it to `_next` were answered by a
        # glance ahead and wait for frames that may come late (docs/decisions/0007): the estimator
        # runs each once, in tick order, when its frame comes or it has waited `_wait` ticks, so a
        # late frame costs one tick of the filter instead of a replay of every tick since.
        self._frontier = first_tick
        self._waits = wait_for_late
        self._lateness: deque[int] = deque(maxlen=_LATENESS_KEPT)
        self._wait = 0
        # The last tick a late frame's replay left for the catch-up: a session that waits runs only
        # the late tick when its frame comes, and the ticks after it _CATCH_UP a tick more than the
        # clock asks, frame or not (docs/decisions/0167-spread-replays.md).
        self._owed = -1
        # s of the last `advance` that caught up a replay's ticks: replay work, not the tick's own.
        self.caught_up = 0.0

    @property
    def history(self) -> int:
        """The ticks kept for late frames now (at most the session's history)."""
        return self._retained

    @property
    def next_tick(self) -> int:
        """The first tick not yet answered."""
        return self._next

    @property
    def oldest_late_tick(self) -> int:
        """The oldest tick a late frame can still be applied to: the first in the history, which
        `skip` empties (then the next tick: no late frame replays across skipped ticks)."""
        return next(iter(self._ticks), self._next)

    def classify(self, seq: int) -> Place:
        """Where a frame for `seq` belongs."""
        if seq >= self._next:
            return Place.NEXT if seq == self._next else Place.FUTURE
        tick = self._ticks.get(seq)
        if tick is None:
            return Place.TOO_OLD
        return Place.DUPLICATE if tick.frame is not None else Place.LATE

    @property
    def model(self) -> mujoco.MjModel:
        return self._model

    def release(self) -> None:
        """Drop the history (its snapshots are most of a session's memory) once the session has
        ended, whatever still refers to the runtime (an exception's traceback, until the garbage
        collector finds the cycle it is part of)."""
        self._ticks.clear()

    def reject(self, rejection: Rejection) -> Rejection:
        self.counts.rejected += 1
        return rejection

    def advance(self, frame: FrameIn | None, *, horizon: float = 0.0) -> TickOutcome:
        """Answer the next tick, with its frame or without one."""
        if self._stale_since is not None:
            return self.shed(frame)
        started = time.perf_counter_ns()
        seq = self._next
        tick = _Tick(seq=seq, before=None, frame=frame, ctrl=self._control_for(seq, frame))
        self._ticks[seq] = tick
        self._next += 1
        self.counts.ticks += 1
        if frame is not None:
            self.counts.frames += 1
            self.counts.measured += 1
            self._note_lateness(0)
        else:
            self.counts.predicted += 1
        last = seq
        if frame is None and self._initialised:
            last = min(seq - self._wait, self._frontier + _CATCH_UP - 1)
        elif self._frontier <= self._owed:
            last = min(seq, self._frontier + _CATCH_UP)
        owed = max(0, min(last, self._owed) - self._frontier + 1)
        ran, run_started = max(1, last - self._frontier + 1), time.perf_counter_ns()
        estimate = self._run_through(last)
        self.caught_up = (time.perf_counter_ns() - run_started) * 1e-9 * owed / ran
        ahead = 0.0
        if self._frontier <= seq:
            ahead = (seq - self._frontier + 1) * self._dt
            estimate = self._estimator.glance(ahead)
        self._keep_history()
        outcome = self._outcome(tick, estimate, late_ticks=0, started=started, horizon=horizon, ahead=ahead)
        self.counts.add_result(outcome)
        self._last = outcome
        return outcome

    def shed(self, frame: FrameIn | None) -> TickOutcome:
        """Answer the next tick without running the estimator, for a server that cannot finish it by
        the deadline: from the frame when it came (the estimator re-initialised from it, a cheap
        reset), else the last answer repeated (the estimator is then a tick behind: the next frame
        re-initialises it). The tick stays in the history with the estimator's state before it, so
        a late frame for it or an earlier tick replays it properly and repairs the estimate.

        A session that waits for late frames keeps a shed tick without a frame waiting for it, as
        it keeps any tick answered before its frame, while fewer than `_stall_room()` wait: the
        estimator is not behind, only later."""
        started = time.perf_counter_ns()
        if frame is None and self._stale_since is None and self._next - self._frontier < self._stall_room():
            tick = self._add_waiting()
            self.counts.ticks += 1
            self.counts.predicted += 1
            self.counts.late_compute += 1
            outcome = dataclasses.replace(self._repeat_last(tick, started=started), late_compute=True)
            self.counts.add_result(outcome)
            self._last = outcome
            return outcome
        self._abandon_waiting()
        seq = self._next
        ctrl = self._control_for(seq, frame)
        tick = _Tick(seq=seq, before=self._snapshot(), frame=frame, ctrl=ctrl)
        estimate: Estimate | None = None
        if frame is not None:
            self._estimator.initialise(self._measurement(tick))
            self._initialised = True
            self._stale_since = None
            estimate = dataclasses.replace(self._estimator.extrapolate(0.0), reinitialised=True)
        elif self._initialised and self._stale_since is None:
            self._stale_since = seq
        self._ticks[seq] = tick
        self._size_history(tick)
        self._keep_history()
        self._next += 1
        self._frontier = self._next
        self.counts.ticks += 1
        self.counts.late_compute += 1
        if frame is not None:
            self.counts.frames += 1
            self.counts.measured += 1
            outcome = self._outcome(tick, estimate, late_ticks=0, started=started, horizon=0.0)
        else:
            self.counts.predicted += 1
            outcome = self._repeat_last(tick, started=started)
        outcome = dataclasses.replace(outcome, late_compute=True)
        self.counts.add_result(outcome)
        self._last = outcome
        return outcome

    def _size_history(self, newest: _Tick) -> None:
        """Re-size the ticks retained from the newest snapshot every _RESIZE_EVERY ticks and
        whenever the estimator's state dimension changes."""
        limit = self._max_history_bytes
        if limit is not None and newest.before is not None:
            dimension = self._estimator.state_dimension
            if dimension != self._sized_for or newest.seq % _RESIZE_EVERY == 0:
                self._sized_for = dimension
                size = max(1, snapshot_bytes(newest.before))
                self._retained = max(1, min(self._history, limit // size))

    def _keep_history(self) -> None:
        """Drop the ticks beyond what is retained (never one still waiting for its frame)."""
        while len(self._ticks) > max(self._retained, self._next - self._frontier):
            self._ticks.popitem(last=False)

    def _note_lateness(self, late_ticks: int) -> None:
        """A frame came `late_ticks` after its tick was answered: the wait follows the lateness."""
        if not self._waits:
            return
        self._lateness.append(late_ticks)
        self._wait = min(max(self._lateness), _MAX_WAIT, self._retained - 1)

    def _run_through(self, last: int, *, answer: int | None = None) -> Estimate | None:
        """Run the estimator through every tick from the frontier to `last`, in order; the estimate
        of tick `answer` (default `last`) when it ran, else None."""
        answer = last if answer is None else answer
        estimate: Estimate | None = None
        previous_ctrl = self._ctrl_before(self._frontier)
        for seq in range(self._frontier, last + 1):
            tick = self._ticks[seq]
            tick.before = self._snapshot()
            tick.ctrl = self._pick_ctrl(tick.frame, previous_ctrl)
            previous_ctrl = tick.ctrl
            ran = self._run_tick(tick, answered=seq == answer)
            if seq == answer:
                estimate = ran
            self._size_history(tick)
            self._frontier = seq + 1
        return estimate

    def _stall_room(self) -> int:
        """How many ticks may wait for their frames through a stall: twice the wait, at most
        _MAX_WAIT (and less than the history); none while frames come on time, so that a server
        behind sheds the ticks it skipped instead of running them later (an overloaded loop that
        deferred them fell further behind: benchmarks/RESULTS.md Round 8)."""
        if not (self._waits and self._initialised):
            return 0
        return min(2 * self._wait, _MAX_WAIT, self._retained - 1)

    def _add_waiting(self) -> _Tick:
        """The next tick, without a frame, left for the estimator to run when its wait ends."""
        seq = self._next
        tick = _Tick(seq=seq, before=None, frame=None, ctrl=self._control_for(seq, None))
        self._ticks[seq] = tick
        self._next += 1
        self._keep_history()
        return tick

    def _abandon_waiting(self) -> None:
        """Give the ticks waiting for frames the estimator as it is, as a shed tick gets it: the
        estimator is behind from the first of them, until a frame re-initialises it or a late
        frame at or before it runs the ticks properly."""
        if self._frontier >= self._next:
            return
        snapshot = self._snapshot()
        for seq in range(self._frontier, self._next):
            self._ticks[seq].before = snapshot
        if self._initialised and self._stale_since is None:
            self._stale_since = self._frontier
        self._frontier = self._next

    def skip(self, count: int) -> None:
        """Leave the next `count` ticks unanswered: a server far behind answers a tick by its
        deadline or not at all. The history goes (no late frame replays across the gap) and the
        estimator, now behind, restarts from the next frame. A session that waits for late frames
        keeps the ticks of a stall that leaves at most `_stall_room()` ticks waiting, waiting for
        their frames: a frame that comes for one of them (`classify` says LATE) is applied as a late frame."""
        if count <= 0:
            return
        if self._stale_since is None and self._next + count - self._frontier <= self._stall_room():
            for _ in range(count):
                self._add_waiting()
            self.counts.skipped += count
            return
        self._next += count
        self._frontier = self._next
        self.counts.skipped += count
        self._ticks.clear()
        if self._initialised and self._stale_since is None:
            self._stale_since = self._next

    def _repeat_last(self, tick: _Tick, *, started: int) -> TickOutcome:
        last = self._last
        if last is None or last.estimate is None and last.frame is None:
            return self._outcome(tick, None, late_ticks=0, started=started, horizon=0.0)
        return dataclasses.replace(
            last,
            seq=tick.seq,
            t=tick.seq * self._dt,
            source=Source.PREDICTED,
            frame=None,
            late_ticks=0,
            horizon=0.0,
            compute_us=int((time.perf_counter_ns() - started) // 1000),
        )

    def apply_late(self, frame: FrameIn) -> TickOutcome:
        """Apply a frame whose tick was answered PREDICTED; returns its CORRECTED outcome."""
        started = time.perf_counter_ns()
        target = self._ticks[frame.seq]
        if target.frame is not None:
            raise ValueError(f"tick {frame.seq} already has a frame")
        target.frame = frame
        self.note_late(frame.seq)
        corrected: Estimate | None
        if self._restarts_from(frame.seq):
            corrected = self._restart_at(target)
        elif frame.seq >= self._frontier:
            corrected = self._run_through(frame.seq)  # it was waiting: the ticks before it, then it
        else:
            # The timewarp: back to the state before it, and every tick the estimator ran since;
            # a session that waits runs the late tick now and leaves the rest to the catch-up.
            ran = self._frontier
            self._restore(target.before)
            self._frontier = frame.seq
            if self._waits:
                corrected = self._run_through(frame.seq)
                self._owed = max(self._owed, ran - 1)
            else:
                corrected = self._run_through(ran - 1, answer=frame.seq)
        if self._stale_since is not None and frame.seq <= self._stale_since:
            self._stale_since = None  # every skipped tick was just replayed properly
        # Ticks answered since this one was due, itself included: 1 = just missed its deadline.
        late_ticks = self._next - frame.seq
        self.counts.frames += 1
        self.counts.corrected += 1
        self.counts.late += 1
        outcome = self._outcome(target, corrected, late_ticks=late_ticks, started=started, horizon=0.0)
        self.counts.add_result(outcome)
        return outcome

    def note_late(self, seq: int) -> None:
        """A frame for `seq` came after its tick was answered (applied or not): a session that
        waits for late frames waits as long as they come late."""
        self._note_lateness(self._next - seq)

    def late_cost(self, seq: int) -> int:
        """Ticks of the estimator a late frame for `seq` costs: one when it restarts a behind
        estimator, those up to it when it was waiting, else the timewarp's replay of every tick
        run since it."""
        if self._restarts_from(seq):
            return 1
        return seq - self._frontier + 1 if seq >= self._frontier else self._frontier - seq

    def replay_cost(self, seq: int) -> int:
        """Ticks of the estimator a late frame for `seq` adds now to those every tick runs once:
        the timewarp's replay of the ticks run since it (only its own tick in a session that waits:
        the rest are caught up over the ticks that follow), none when its tick was waiting (the
        ticks up to it run now instead of later) or when it restarts a behind estimator."""
        if self._restarts_from(seq) or seq >= self._frontier:
            return 0
        return 1 if self._waits else self._frontier - seq

    def _restarts_from(self, seq: int) -> bool:
        """Whether a late frame for `seq` restarts the estimator: it is behind (a stall outlasted
        the wait) since a tick at or before `seq`, so the frame is the best state there is, and
        at most `_stall_room()` ticks after it wait to be run from it."""
        stale = self._stale_since
        return stale is not None and seq >= stale and self._next - seq <= self._stall_room()

    def _restart_at(self, tick: _Tick) -> Estimate:
        """Restart the estimator from a late frame at its tick: the ticks after it wait for the
        estimator as a late frame's ticks do (`advance` catches up _CATCH_UP a tick)."""
        self._estimator.initialise(self._measurement(tick))
        self._stale_since = None
        self._frontier = tick.seq + 1
        return dataclasses.replace(self._estimator.extrapolate(0.0), reinitialised=True)

    def extrapolated(self, seconds: float) -> Estimate | None:
        """The current estimate carried `seconds` ahead, without changing the estimator."""
        if not self._initialised or seconds <= 0.0:
            return None
        return self._estimator.extrapolate(seconds)

    # The timewarp's building blocks.

    def _snapshot(self) -> object | None:
        return self._estimator.snapshot() if self._initialised else None

    def _restore(self, snapshot: object | None) -> None:
        if snapshot is None:
            self._initialised = False
        else:
            self._estimator.restore(snapshot)
            self._initialised = True

    def _ctrl_before(self, seq: int) -> np.ndarray | None:
        previous = self._ticks.get(seq - 1)
        return previous.ctrl if previous is not None else None

    def _control_for(self, seq: int, frame: FrameIn | None) -> np.ndarray | None:
        return self._pick_ctrl(frame, self._ctrl_before(seq))

    def _pick_ctrl(self, frame: FrameIn | None, previous: np.ndarray | None) -> np.ndarray | None:
        # A tick without a frame holds the control of the tick before it.
        if not self._controlled:
            return frame.ctrl if frame is not None else previous
        if frame is not None and frame.ctrl is not None:
            return frame.ctrl
        return previous if previous is not None else self._zero_ctrl

    def _measurement(self, tick: _Tick) -> Measurement:
        frame = tick.frame
        if frame is None:
            raise ValueError("a measurement needs a frame")
        return Measurement(qpos=frame.qpos, qvel=frame.qvel, qacc=frame.qacc, ctrl=frame.ctrl)

    def _run_tick(self, tick: _Tick, *, answered: bool = True) -> Estimate | None:
        """Advance the estimator through one tick; None while it has no frame to start from, or
        when a tick without a frame is not `answered` (its answer was given already)."""
        if tick.frame is None:
            if not self._initialised:
                return None
            ctrl = tick.ctrl if self._controlled else None
            if not answered:
                self._estimator.advance(ctrl=ctrl)
                return None
            return self._estimator.predict(ctrl=ctrl)
        measurement = self._measurement(tick)
        if not self._initialised:
            self._estimator.initialise(measurement)
            self._initialised = True
            if self._restarted:
                self._restarted = False
                return dataclasses.replace(self._estimator.extrapolate(0.0), reinitialised=True)
            return self._estimator.extrapolate(0.0)
        return self._estimator.step(ctrl=tick.ctrl if self._controlled else None, m=measurement)

    def _frame_qacc(self, tick: _Tick, estimate: Estimate | None) -> np.ndarray:
        """qacc of a measured tick: the frame's, else the backward difference of qvel, else the estimate's."""
        frame = tick.frame
        if frame is None:
            raise ValueError("a measured tick needs a frame")
        if frame.qacc is not None:
            return frame.qacc
        previous = self._ticks.get(tick.seq - 1)
        if (
            frame.qvel is not None
            and previous is not None
            and previous.frame is not None
            and previous.frame.qvel is not None
        ):
            return np.asarray((frame.qvel - previous.frame.qvel) / self._dt)
        if estimate is not None:
            return estimate.qacc
        qvel = frame.qvel if frame.qvel is not None else self._zero_nv
        return self._dynamics.forward_acceleration(qpos=frame.qpos, qvel=qvel, ctrl=tick.ctrl)

    def _outcome(
        self,
        tick: _Tick,
        estimate: Estimate | None,
        *,
        late_ticks: int,
        started: int,
        horizon: float,
        ahead: float = 0.0,
    ) -> TickOutcome:
        frame = tick.frame
        if frame is not None:
            qpos = frame.qpos
            qvel = (
                frame.qvel
                if frame.qvel is not None
                else (estimate.qvel if estimate is not None else self._zero_nv)
            )
            qacc = self._frame_qacc(tick, estimate)
            source = Source.CORRECTED if late_ticks else Source.MEASURED
            horizon = 0.0 if late_ticks else horizon
        elif estimate is not None:
            qpos, qvel, qacc = estimate.qpos, estimate.qvel, estimate.qacc
            source = Source.PREDICTED
        else:
            qpos, qvel, qacc = self._qpos0, self._zero_nv, self._zero_nv
            source = Source.PREDICTED
        if horizon > 0.0 and self._initialised:
            # `ahead`: the tick is that far past the estimator (it waits for a late frame).
            further = (
                self._estimator.extrapolate(horizon)
                if ahead == 0.0
                else self._estimator.glance(ahead + horizon)
            )
            qpos, qvel, qacc = further.qpos, further.qvel, further.qacc
        else:
            horizon = 0.0
        dynamics = self._dynamics.compute(qpos=qpos, qvel=qvel, qacc=qacc, ctrl=tick.ctrl)
        compute_us = (time.perf_counter_ns() - started) // 1000
        return TickOutcome(
            seq=tick.seq,
            t=tick.seq * self._dt + horizon,
            source=source,
            qpos=qpos,
            qvel=qvel,
            qacc=qacc,
            dynamics=dynamics,
            estimate=estimate,
            frame=frame,
            late_ticks=late_ticks,
            compute_us=int(compute_us),
            horizon=horizon,
        )
