"""Admission by measured cost: a REALTIME session is admitted only when its ticks fit in what is left
of this process's tick budget (a fraction of one core: one process runs Python on one core).

    admission = Admission(budget=0.75)
    ticket = admission.admit(cost_per_tick=probe + TRANSPORT_COST, dt=0.05, what="pendulum_3 at 20 Hz")
    ...
    ticket.observe(seconds)          # each tick's measured cost refines the session's estimate
    ticket.answered(lateness)        # each REALTIME answer's lateness
    ticket.release()                 # when the session ends (safe twice)

A session's load is its cost per tick divided by dt: CPU seconds per second. A session must fit the
budget alone, whatever else runs; where the CPU around its filter decides that, the servicer
rehearses it first (docs/decisions/0214-a-tick-priced-whole.md). The process's load is
the larger of the sum over its sessions and its CPU actually used over the last seconds (which
also counts what no estimate sees: the gRPC transport of LOCKSTEP sessions, compaction, GC).
A tick is counted on its ticket, in plain numbers its session's thread alone writes; the process
adds up what its tickets counted once per window, when it reads the window's evidence
(docs/decisions/0196-metrics-and-admission-per-window.md).

A process's budget is only worth what the machine can give it: on a machine whose cores other
programs (or the server's other processes, or the clients beside it) keep busy, a session is also
refused when the CPU the machine left idle over the last window, or during a burst of opens over
its latest quarter second (a burst the window has not seen yet), less what was admitted since,
cannot carry it (Linux: /proc/stat; elsewhere the process budget alone; docs/decisions/0008).
What a client on this machine spent starting up before its first open is not load: it is added back
to the idle CPU of the figures it fell in (server/runtime/clients.py,
docs/decisions/0207-a-clients-start-up-is-not-load.md).
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from dataclasses import dataclass, field
from typing import Final

from jitdyn.errors import InvalidArgument, ResourceExhausted
from jitdyn.server.runtime.clients import ClientStart
from jitdyn.server.runtime.switch_interval import SwitchInterval

__all__ = ["DEFAULT_TICK_BUDGET", "TRANSPORT_COST", "Admission", "Ticket"]

_log = logging.getLogger(__name__)

DEFAULT_TICK_BUDGET: Final = 0.75  # of one core per process
# Server CPU per tick around the filter's cycle (receiving the frame, checking it, the forecast, the
# result's dynamics and message, sending it, recording it, the event loop): the starting guess,
# which each process then replaces with its own, learnt from its CPU and its ticks
# (docs/decisions/0005-admission-starting-guesses.md, 0223-a-session-priced-at-its-cpu.md).
TRANSPORT_COST: Final = 0.85e-3  # s
_EWMA: Final = 0.05  # weight of the newest tick in a session's cost
# A lone session's tick costs up to this many times the overhead figure (learnt among many
# sessions, or guessed) around its filter: where that decides whether it fits, it is rehearsed
# (docs/decisions/0214-a-tick-priced-whole.md).
REHEARSE_SPAN: Final = 2.5
# Cores of the machine kept free of new sessions: the slack that keeps ticks on time when the
# machine is nearly full (a tick late by a scheduling quantum is late).
MACHINE_HEADROOM: Final = 0.1
# An answer this far past its deadline is late, for admission; when more than LATE_SHARE of a
# window's answers are, the process admits no one and tells its newest sessions, in band.
LATE_ANSWER: Final = 5e-3  # s (docs/decisions/0008-admission-learns-from-lateness.md)
LATE_SHARE: Final = 0.01
# While the process is behind, late frames are not replayed if replaying them took more than this
# share of the last window (of one core): the replays are then what keeps it behind.
REPLAY_SHARE: Final = 0.1
_LATE_EVIDENCE: Final = 20  # answers a window needs before its share of late ones counts
# Of the ticks due in a window, the share its sessions must have counted for it to price a tick.
_ANSWERED_SHARE: Final = 0.9


def _machine_times() -> tuple[int, int] | None:
    """(busy, total) jiffies of every CPU since boot, from /proc/stat; None where there is none.
    Busy is every process's time, whatever its priority, the kernel's own and the hypervisor's steal."""
    try:
        with open("/proc/stat", "rb") as stat:
            fields = [int(v) for v in stat.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    if len(fields) < 4:
        return None
    # user nice system idle iowait irq softirq steal (guest time is inside user). Niced work
    # counts as busy: with the kernel's autogroup scheduling a niced program of another login
    # session still gets its session's share of the CPU.
    total = sum(fields[:8])
    free = fields[3] + (fields[4] if len(fields) > 4 else 0)
    return total - free, total


def _rate(hz: float) -> str:
    """A rate for a refusal: "412 Hz", "2.5 Hz"."""
    return f"{hz:.0f} Hz" if hz >= 10 else f"{hz:.2g} Hz"


def _usable_cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


# Every refusal ends so: what the client can do about it.
_TRY_ELSEWHERE: Final = "Try again later, on another server, or at a lower rate"

_CPU_WINDOW: Final = 2.0  # s over which the process's own CPU use is measured
# s: during a burst of opens the machine's idle CPU is also read over this much of the latest time:
# the last window did not see the burst (the surplus of 400 opens, refused while admitted ones
# open). Outside a burst the window stands alone, as it was measured for (a quarter second is a few
# ticks of each session: docs/decisions/0008).
_RECENT: Final = 0.25
_BURST: Final = 20  # REALTIME opens asked of the process within two _RECENT periods that make a burst
# s of the machine's CPU looked at before the first admission, when no window has ended yet
_FIRST_LOOK: Final = 0.1


@dataclass
class Ticket:
    """One admitted session's share of the budget."""

    admission: Admission
    dt: float
    cost_per_tick: float  # s, the current estimate
    grace: float | None = None  # s, how long the session waits for a frame past its tick time
    # s, the session's own estimator and dynamics per tick (wall time on the loop), without the
    # process's transport: what replaying a tick costs. Starts at the priced filter cycle.
    compute_per_tick: float = 0.0
    # s, one tick of a late frame's replay (the timewarp), measured from this session's own replays;
    # None before its first (see `replay_price`).
    replay_per_tick: float | None = None
    # s, the thread CPU of the session's own estimator and dynamics per tick: `compute_per_tick`
    # without the time the machine took the CPU away mid-tick; None before a tick tells it.
    cpu_per_tick: float | None = None
    # s, the filter cycle the session was priced at (predict + update, at open): what the process's
    # overhead figure is measured around, so that an open of its kind is priced at a tick's CPU.
    filter_seconds: float = 0.0
    released: bool = False
    admitted_at: float = field(default_factory=time.monotonic)
    # What the session's own thread counted since admission: ticks, their compute (s), REALTIME
    # answers and the late ones among them. Only ever grown, so that the process reads what is new
    # of them at the end of a window without a lock on the tick's path (Admission._collect).
    counted_ticks: int = 0
    counted_compute: float = 0.0
    counted_answers: int = 0
    counted_late: int = 0

    @property
    def load(self) -> float:
        return self.cost_per_tick / self.dt

    def observe(self, seconds: float, *, cpu: float | None = None) -> None:
        """One tick took `seconds` of the estimator and dynamics on the loop, `cpu` of them its
        thread's CPU. Its price follows the tick's CPU plus the process's CPU per tick beyond its
        ticks' own (the transport, the loop, recording); before the process has measured that, the
        price it was admitted at stands (a tick's wall time during a burst of opens is other
        threads' CPU too: docs/decisions/0223-a-session-priced-at-its-cpu.md)."""
        own = seconds if cpu is None else cpu
        self.counted_ticks += 1
        self.counted_compute += own
        around = self.admission.around_ticks
        if around is not None:
            self.cost_per_tick += _EWMA * (own + around - self.cost_per_tick)
        self.compute_per_tick += _EWMA * (seconds - self.compute_per_tick)
        if cpu is not None:
            previous = self.cpu_per_tick
            self.cpu_per_tick = cpu if previous is None else previous + _EWMA * (cpu - previous)

    @property
    def replay_price(self) -> float:
        """s, what a late frame's replay is priced at per tick replayed: what this session's own
        replays measured, and until it has replayed the CPU of its ticks (a tick answered on the
        loop costs more than its replay: the answer's dynamics and message), or their compute
        before a tick tells it. In CPU time, not wall time: on a busy machine the wall time of a
        2-link arm's tick was 2.3 ms, and its first late frames were priced out of reach, so no
        replay ever measured what one costs (benchmarks/late_arm.py)."""
        if self.replay_per_tick is not None:
            return self.replay_per_tick
        return self.compute_per_tick if self.cpu_per_tick is None else self.cpu_per_tick

    def observe_replay(self, seconds: float, *, cpu: float, ticks: int) -> None:
        """A late frame's replay of `ticks` ticks took `seconds` on the loop, `cpu` of them its
        thread's CPU: the process's share of time in replays, and the session's replay price (in
        CPU time: a process the machine stopped mid-replay would otherwise price every later
        replay out of reach)."""
        self.admission.observe_replay(seconds)
        if ticks > 0:
            measured = cpu / ticks
            previous = self.replay_per_tick
            self.replay_per_tick = measured if previous is None else previous + _EWMA * (measured - previous)

    def answered(self, lateness: float) -> None:
        """A REALTIME answer of this session went `lateness` s past its deadline (0 when on time)."""
        self.counted_answers += 1
        self.counted_late += lateness > LATE_ANSWER

    def release(self) -> None:
        self.admission._release(self)


@dataclass
class Admission:
    """The tick budget of one process. Thread-safe."""

    budget: float = DEFAULT_TICK_BUDGET
    # False when the process is not the server's alone (a server inside a client program).
    count_process_cpu: bool = True
    # False: ignore what the rest of the machine does (the process budget alone).
    count_machine_cpu: bool = True
    # The process's GIL switch interval, told of each admitted session's grace; None: left alone.
    switch: SwitchInterval | None = None
    _by_id: dict[int, Ticket] = field(default_factory=dict)
    # Each ticket's counts (ticks, compute, answers, late) when the process last added them up.
    _collected: dict[int, tuple[int, float, int, int]] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _cpu_mark: tuple[float, float] = field(default_factory=lambda: (time.monotonic(), time.process_time()))
    _cpu_load: float = 0.0
    refused: int = 0
    overhead: float = TRANSPORT_COST  # s per tick around the priced filter cycle, learnt from the CPU
    overhead_measured: bool = False  # the overhead is this process's own figure, not the starting guess
    # s per tick of the process's CPU beyond its ticks' own CPU (the overhead is beyond their
    # priced filter cycles); None until a window has measured it.
    around_ticks: float | None = None
    _window_ticks: int = 0
    _window_compute: float = 0.0  # s, the CPU of the window's ticks
    _window_cycles: float = 0.0  # s, the filter cycles their sessions were priced at, one a tick
    _window_aside: float = 0.0  # s of the window's CPU that was no tick's: opening and storing sessions
    _machine_mark: tuple[int, int] | None = field(default_factory=_machine_times)
    _machine_mark_at: float = field(default_factory=time.monotonic)
    machine_free: float | None = None  # cores the machine left idle over the last window
    _machine_span: tuple[float, float] = (0.0, 0.0)  # monotonic s the machine_free figure spans
    _recent_mark: tuple[float, tuple[int, int] | None] = field(
        default_factory=lambda: (time.monotonic(), _machine_times())
    )
    recent_free: float | None = None  # cores the machine left idle over the last _RECENT s
    _recent_span: tuple[float, float] = (0.0, 0.0)
    # Client processes on this machine that opened sessions lately, by pid: their start-up's CPU is
    # not load (observe_client).
    _clients: dict[int, ClientStart] = field(default_factory=dict)
    _opens: tuple[int, int] = (0, 0)  # REALTIME opens asked in the last _RECENT period, this one
    _looked: bool = False  # the first admission's look at the machine was taken
    _answers: int = 0
    _late_answers: int = 0
    late_share: float = 0.0  # of the answers of the last window more than LATE_ANSWER late
    _lag_late: float = 0.0  # s of the window the loop ran more than LATE_ANSWER late
    lag_share: float = 0.0  # of the last window's time the loop ran more than LATE_ANSWER late
    _replaying: float = 0.0  # s of the window the loop spent replaying late frames
    replay_share: float = 0.0  # of the last window's time spent replaying late frames
    _ended_late_at: float = -math.inf  # monotonic s: when a session was last ended for going late

    def __post_init__(self) -> None:
        if not 0.0 < self.budget <= 1.0:
            raise InvalidArgument(f"the tick budget must be in (0, 1] of a core, got {self.budget}")

    def start_window(self) -> None:
        """Measure the process's CPU from now: called once it serves, so that starting up (imports,
        the registry, migrations) is not taken for the load of sessions
        (docs/decisions/0005-admission-starting-guesses.md)."""
        with self._lock:
            self._cpu_mark = (time.monotonic(), time.process_time())
            self._cpu_load = 0.0
            self._collect()  # what was counted before is not the window's
            self._window_ticks, self._window_compute, self._window_cycles = 0, 0.0, 0.0
            self._window_aside = 0.0
            self._answers, self._late_answers = 0, 0
            self._machine_mark, self._machine_mark_at = _machine_times(), time.monotonic()
            self._recent_mark, self.recent_free = (time.monotonic(), self._machine_mark), None

    def measured_load(self) -> float:
        """This process's CPU use over about the last `_CPU_WINDOW` seconds, in cores."""
        with self._lock:
            return self._sample_cpu()

    def _sample_cpu(self) -> float:
        """This process's CPU use in cores (0 when not counted), once a window is over also its
        overhead per tick, the machine's idle CPU and the share of late answers."""
        wall, cpu = time.monotonic(), time.process_time()
        since, used = self._cpu_mark
        if wall - since >= _CPU_WINDOW:
            self._collect()
            if self.count_process_cpu:
                self._cpu_load = (cpu - used) / (wall - since)
                if self._measures_ticks(since=since, wall=wall, cpu=cpu - used):
                    # What a tick cost this process beyond its priced filter cycle (an open's price is
                    # its cycle plus this), and beyond the tick's own CPU (an admitted session's).
                    per_tick = max(0.0, cpu - used - self._window_aside) / self._window_ticks
                    around_cycle = per_tick - self._window_cycles / self._window_ticks
                    around_ticks = max(per_tick - self._window_compute / self._window_ticks, 0.0)
                    # The first measurement replaces the starting guess; later ones are smoothed.
                    weight = 0.5 if self.overhead_measured else 1.0
                    self.overhead += weight * (max(around_cycle, 100e-6) - self.overhead)
                    previous = self.around_ticks
                    self.around_ticks = (
                        around_ticks if previous is None else previous + 0.5 * (around_ticks - previous)
                    )
                    self.overhead_measured = True
                self._sample_machine()
            self._window_ticks, self._window_compute, self._window_cycles = 0, 0.0, 0.0
            self._window_aside = 0.0
            self._cpu_mark = (wall, cpu)
            enough = self._answers >= _LATE_EVIDENCE
            self.late_share = self._late_answers / self._answers if enough else 0.0
            self._answers, self._late_answers = 0, 0
            self.lag_share = self._lag_late / (wall - since)
            self._lag_late = 0.0
            self.replay_share = self._replaying / (wall - since)
            self._replaying = 0.0
        return self._cpu_load if self.count_process_cpu else 0.0

    def _measures_ticks(self, *, since: float, wall: float, cpu: float) -> bool:
        """Whether the window from `since` to `wall`, in which the process spent `cpu` s, measures
        what a tick costs: it counted 50 ticks or more, it was not mostly opening sessions, and its
        sessions' ticks were answered (a loop busy refusing a burst of opens at its door skipped
        them: 65 ticks counted of 29 sessions' 1160, the CPU of 170 refusals priced each at 13 ms;
        docs/decisions/0223-a-session-priced-at-its-cpu.md). Under the lock."""
        due = sum((wall - max(since, t.admitted_at)) / t.dt for t in self._by_id.values())
        return (
            self._window_ticks >= 50
            and self._window_aside <= 0.5 * cpu
            and self._window_ticks >= _ANSWERED_SHARE * due
        )

    def _first_look(self) -> None:
        """The machine's idle CPU over a short look, when no window has ended since the process
        began serving: else the opens of its first 2 s were admitted without it (a server started
        beside two CPU hogs admitted 28 sessions, all within its first window). Outside the lock,
        which the loop's beats take: it waits _FIRST_LOOK on the opening thread, once."""
        # A server inside a client program counts neither its process nor the machine (_sample_cpu).
        if not (self.count_machine_cpu and self.count_process_cpu) or self._looked:
            return
        self._looked = True  # once, even where /proc/stat is not there to read
        if self.machine_free is not None:
            return
        before, since = _machine_times(), time.monotonic()
        time.sleep(_FIRST_LOOK)
        after = _machine_times()
        if before is None or after is None or after[1] <= before[1]:
            return
        free = _usable_cpus() * max(0.0, 1.0 - (after[0] - before[0]) / (after[1] - before[1]))
        with self._lock:
            if self.machine_free is None:  # a window that ended meanwhile knows better
                self.machine_free, self._machine_span = free, (since, time.monotonic())

    def _sample_machine(self) -> None:
        if not self.count_machine_cpu:
            return
        now, at = _machine_times(), time.monotonic()
        if now is not None and self._machine_mark is not None and now[1] > self._machine_mark[1]:
            busy, total = now[0] - self._machine_mark[0], now[1] - self._machine_mark[1]
            self.machine_free = _usable_cpus() * max(0.0, 1.0 - busy / total)
            self._machine_span = (self._machine_mark_at, at)
        self._machine_mark, self._machine_mark_at = now, at

    def _collect(self) -> None:
        """Add what every ticket counted since the last collection to the window. Under the lock.
        A tick counted while this reads may be in one of its counts and not yet in another: it is
        the next window's, whole, then."""
        for key, ticket in self._by_id.items():
            self._collect_one(key, ticket)

    def _collect_one(self, key: int, ticket: Ticket) -> None:
        ticks, compute = ticket.counted_ticks, ticket.counted_compute
        answers, late = ticket.counted_answers, ticket.counted_late
        seen_ticks, seen_compute, seen_answers, seen_late = self._collected.get(key, (0, 0.0, 0, 0))
        self._window_ticks += ticks - seen_ticks
        self._window_compute += compute - seen_compute
        self._window_cycles += (ticks - seen_ticks) * ticket.filter_seconds
        self._answers += answers - seen_answers
        self._late_answers += late - seen_late
        self._collected[key] = (ticks, compute, answers, late)

    def observe_lateness(self, seconds: float) -> None:
        """A REALTIME answer went `seconds` past its deadline (0 when on time)."""
        with self._lock:
            self._answers += 1
            self._late_answers += seconds > LATE_ANSWER

    def observe_loop_lag(self, seconds: float) -> None:
        """Something due on the process's event loop ran `seconds` late (server/runtime/stalls.py):
        every deadline due in that moment was as late. Called at every beat of the loop, it also
        closes each window on time: the evidence an admission reads is then always of the last
        window, not of everything since the last admission (a server idle for a minute, then
        beside a CPU hog for two seconds, saw half a minute's idle CPU as free). A lag while no
        session is admitted is late for no one: the machine's idle CPU judges that moment
        (docs/decisions/0207-a-clients-start-up-is-not-load.md)."""
        with self._lock:
            if seconds > LATE_ANSWER and self._by_id:
                self._lag_late += seconds - LATE_ANSWER
            now = time.monotonic()
            if now - self._cpu_mark[0] >= _CPU_WINDOW:
                self._sample_cpu()
            if now - self._recent_mark[0] >= _RECENT:
                self._sample_recent(now)

    def _sample_recent(self, now: float) -> None:
        """The machine's idle CPU since the last recent mark. Under the lock."""
        if not self.count_machine_cpu:
            return
        times, (_, mark) = _machine_times(), self._recent_mark
        if times is not None and mark is not None and times[1] > mark[1]:
            busy, total = times[0] - mark[0], times[1] - mark[1]
            self.recent_free = _usable_cpus() * max(0.0, 1.0 - busy / total)
            self._recent_span = (self._recent_mark[0], now)
        self._recent_mark = (now, times)
        self._opens = (self._opens[1], 0)

    def observe_aside(self, cpu: float) -> None:
        """The process spent `cpu` s of a thread's CPU opening or storing a session: load, but no
        tick's (a burst of opens in the first window priced every tick after it at 887 us around
        its CPU against 680 a window later: docs/decisions/0223-a-session-priced-at-its-cpu.md)."""
        with self._lock:
            self._window_aside += cpu

    def observe_open(self) -> None:
        """A REALTIME open was asked of this process (at the door, before any decision)."""
        with self._lock:
            self._opens = (self._opens[0], self._opens[1] + 1)

    def observe_client(self, start: ClientStart) -> None:
        """A client process on this machine opened a session: the CPU it spent starting up, before
        its first open, is not load. Its first open counts; clients seen more than two windows ago
        are forgotten (no figure reaches back that far)."""
        with self._lock:
            now = time.monotonic()
            self._clients.setdefault(start.pid, start)
            for pid in [p for p, c in self._clients.items() if c.opened < now - 2 * _CPU_WINDOW]:
                del self._clients[pid]

    def machine_short(self) -> bool:
        """Whether the machine's idle CPU, as admission reads it now, is under a core (and so a
        client's start-up may be what refuses an open), or not read yet; otherwise looking for
        the client is not worth its few ms (server/runtime/clients.py)."""
        if not (self.count_machine_cpu and self.count_process_cpu):
            return False
        with self._lock:
            free = self._machine_left()
            return free is None or free < 1.0 + MACHINE_HEADROOM

    def _started_within(self, span: tuple[float, float]) -> float:
        """Cores of a figure over `span` that were clients starting up (observe_client). Under the
        lock."""
        since, until = span
        if until <= since or not self._clients:
            return 0.0
        return sum(c.within(since, until) for c in self._clients.values()) / (until - since)

    def observe_replay(self, seconds: float) -> None:
        """A late frame's replay (the timewarp) took `seconds` on the loop."""
        with self._lock:
            self._replaying += seconds

    def replays_behind(self) -> str | None:
        """Why late frames are not replayed now, or None: the process went late in the last window
        while replays took more than REPLAY_SHARE of it. Each session's replays fit its own half
        tick; a dozen sessions' together kept a process 53.8 % late for 10 s, its late answers
        making more frames late (benchmarks/RESULTS.md, Round 13)."""
        with self._lock:
            behind = self._behind()
            if behind is None or self.replay_share <= REPLAY_SHARE:
                return None
            return f"{behind}, and replaying late frames took {100 * self.replay_share:.0f} % of that time"

    def replay_room(self) -> float:
        """s of the event loop a late frame's replay may take now without making another session's
        next answer late: the loop's idle share (1 - this process's load) of the shortest grace of
        its sessions, the longest any of their next ticks can wait past its time
        (docs/decisions/0001-timewarp-budget.md)."""
        with self._lock:
            graces = [t.dt / 2 if t.grace is None else t.grace for t in self._by_id.values()]
            if not graces:
                return math.inf
            load = max(sum(t.load for t in self._by_id.values()), self._sample_cpu())
            return min(graces) * max(0.0, 1.0 - load)

    def _behind(self) -> str | None:
        """Why the process's answers are late now (its answers or its loop, over the last window),
        or None. Under the lock."""
        if self.late_share > LATE_SHARE:
            return (
                f"answered {100 * self.late_share:.1f} % of its ticks more than {1e3 * LATE_ANSWER:g} ms "
                f"past their deadlines in the last {_CPU_WINDOW:g} s"
            )
        if self.lag_share > LATE_SHARE:
            return (
                f"ran its deadlines more than {1e3 * LATE_ANSWER:g} ms late for {100 * self.lag_share:.1f} % "
                f"of the last {_CPU_WINDOW:g} s"
            )
        return None

    def unaffordable(self, ticket: Ticket) -> str | None:
        """Why `ticket`'s session cannot count on being answered on time here, or None. When the
        process's answers go late or its CPU passes its budget, the sessions admitted last, as many
        as carry the excess (at least one), are told, so that they can move before they go late."""
        with self._lock:
            measured = self._sample_cpu()
            behind = self._behind()
            need = measured - self.budget
            if behind is None and need <= 0:
                return None
            covered = 0.0
            for other in sorted(self._by_id.values(), key=lambda t: t.admitted_at, reverse=True):
                if covered > 0.0 and covered >= need:
                    return None
                if other is ticket:
                    return (
                        f"this server process is past what it serves on time ({100 * measured:.0f} % of "
                        f"a core against its tick budget of {100 * self.budget:.0f} %"
                        f"{'' if behind is None else '; it ' + behind}) and this session is among the "
                        "last admitted: its answers may go late. Resume it on another server or lower "
                        "its rate"
                    )
                covered += other.load
            return None

    def answers_short(self) -> bool:
        """Whether what the process promises went short in the last window: more than LATE_SHARE of
        its answers late, or its CPU past its budget. Its loop's lag alone is not: it refuses new
        sessions and tells the last admitted, but a session is ended only for this (at 56-63 % of a
        core, loop lags of 5-20 ms against graces of 25 ms ended 1-2 sessions of 60 whose answers
        were all on time; docs/decisions/0224-ended-for-late-answers-not-lag.md)."""
        with self._lock:
            return self.late_share > LATE_SHARE or self._sample_cpu() > self.budget

    def admitted_before(self, ticket: Ticket) -> int:
        """How many of the process's sessions were admitted before `ticket`'s: those that ending
        it would keep on time (none: ending it would help no one)."""
        with self._lock:
            return sum(other.admitted_at < ticket.admitted_at for other in self._by_id.values())

    def ended_late(self) -> None:
        """A session was ended for staying unaffordable (dynamics_service, --late-timeout)."""
        with self._lock:
            self._ended_late_at = time.monotonic()

    def late_evidence_from(self) -> float:
        """Monotonic s from which the process's lateness counts against its sessions: one window
        after it last ended one, whose late answers that window still holds (without this, ending
        the newest session made the next newest look unaffordable too)."""
        with self._lock:
            return self._ended_late_at + _CPU_WINDOW

    def load(self) -> float:
        """The process's load in cores: the larger of its sessions' estimates and its measured CPU."""
        with self._lock:
            return max(sum(t.load for t in self._by_id.values()), self._sample_cpu())

    @property
    def sessions(self) -> int:
        with self._lock:
            return len(self._by_id)

    def admit(
        self,
        *,
        cost_per_tick: float,
        dt: float,
        what: str,
        filter_seconds: float | None = None,
        grace: float | None = None,
        resumed: bool = False,
        priced_by: str | None = None,
    ) -> Ticket:
        """A ticket for a session costing `cost_per_tick` seconds every `dt`, or ResourceExhausted
        saying why (the measured load, the session's estimated cost, the setting that raises it).
        resumed: a session the fleet admitted before, moving here (its replica died or drains): it
        is admitted whatever the load, since refusing it would lose it; its cost counts from now,
        so that new sessions are refused until the load falls.
        filter_seconds: the part of the cost that is the session's own filter, measured (the rest is
        the process's overhead per tick); the refusal of a session that cannot fit alone says both.
        grace: the session's grace, for the process's switch interval while it is open.
        priced_by: where the price comes from when not the filter and this process's overhead (a
        rehearsal), for the refusal."""
        if filter_seconds is None:
            filter_seconds = cost_per_tick
        if not dt > 0:
            raise InvalidArgument(f"dt must be > 0, got {dt}")
        self._first_look()
        ticket = Ticket(
            self,
            dt=dt,
            cost_per_tick=cost_per_tick,
            compute_per_tick=filter_seconds,
            filter_seconds=filter_seconds,
            grace=grace,
        )
        with self._lock:
            if resumed:
                current = max(sum(t.load for t in self._by_id.values()), self._sample_cpu())
                if current + ticket.load > self.budget:
                    _log.warning(
                        "a resumed session of %s is admitted over the tick budget (%.0f %% of a core "
                        "with it, budget %.0f %%): it was admitted before and moved here",
                        what,
                        100 * (current + ticket.load),
                        100 * self.budget,
                    )
            else:
                self._check(ticket, filter_seconds=filter_seconds, what=what, priced_by=priced_by)
            self._by_id[id(ticket)] = ticket
        if grace is not None and self.switch is not None:
            self.switch.add(grace)
        return ticket

    def _check(self, ticket: Ticket, *, filter_seconds: float, what: str, priced_by: str | None) -> None:
        """ResourceExhausted, saying why, when a new session of `ticket` is not admitted now. Under
        the lock."""
        self._check_alone(ticket, filter_seconds=filter_seconds, what=what, priced_by=priced_by)
        current = max(sum(t.load for t in self._by_id.values()), self._sample_cpu())
        self._check_room(ticket, current=current, what=what)

    def _check_alone(
        self, ticket: Ticket, *, filter_seconds: float, what: str, priced_by: str | None
    ) -> None:
        """ResourceExhausted, saying why and what rate would fit, when `ticket`'s session does not
        fit the budget even alone: its filter and the server's CPU around it (the overhead) at its
        rate. Whatever else the process serves: an idle process used to take a session whose filter
        alone fitted, and a 500 Hz session whose tick cost the server 2 ms of CPU was answered
        MEASURED on a third of its ticks (docs/decisions/0214-a-tick-priced-whole.md). Under the
        lock."""
        if ticket.load <= self.budget:
            return
        self.refused += 1
        around = ticket.cost_per_tick - filter_seconds
        if priced_by is not None:
            source = priced_by
        elif self.overhead_measured:
            source = "measured on this process's own ticks"
        else:
            source = "the starting guess, until this process has measured its own ticks"
        fits = self.budget / ticket.cost_per_tick
        raise ResourceExhausted(
            f"a session of {what} is estimated at {1e6 * ticket.cost_per_tick:.0f} us of this server's "
            f"CPU per tick: its filter {1e6 * filter_seconds:.0f} us and {1e6 * around:.0f} us around it "
            f"(the frame's read, the result's dynamics and message, the write, the record, the event "
            f"loop; {source}), {100 * ticket.load:.0f} % of a core against the tick budget of "
            f"{100 * self.budget:.0f} % (--tick-budget {self.budget:g}) on its own: its answers could "
            f"not be on time. At most {_rate(fits)} fits here. {_TRY_ELSEWHERE}"
        )

    def wants_rehearsal(self, *, filter_seconds: float, dt: float) -> bool:
        """Whether a session whose filter takes `filter_seconds` every `dt` should be rehearsed
        before it is priced: whether it fits alone hangs on the CPU a tick costs around its filter
        (fits with half this process's overhead figure, not with REHEARSE_SPAN times it: a lone
        session's tick pays the wake-ups and writes that many sessions share), and this process can
        measure it (it counts its own CPU and serves no session now)."""
        with self._lock:
            if not self.count_process_cpu or self._by_id:
                return False
            fits = (filter_seconds + 0.5 * self.overhead) / dt <= self.budget
            return fits and (filter_seconds + REHEARSE_SPAN * self.overhead) / dt > self.budget

    def count_refusal(self) -> None:
        """A REALTIME open was refused by what its rehearsal measured (server/runtime/opening.py)."""
        with self._lock:
            self.refused += 1

    def rehearsed(self) -> None:
        """A rehearsal ran on this process (server/transport/rehearsal.py): its CPU is not the load
        of sessions, and no session counted its ticks. While no session is admitted the windows
        start again after it, as after the start-up, and the next admission looks at the machine
        afresh (the rehearsal's CPU was in the machine's last figures)."""
        if self.sessions == 0:
            self.start_window()
            with self._lock:
                self.machine_free, self.recent_free, self._looked = None, None, False

    def refusal(
        self,
        *,
        cost_per_tick: float,
        filter_seconds: float,
        dt: float,
        what: str,
        priced_by: str | None = None,
    ) -> str | None:
        """Why `admit` would refuse a new session of this price now, or None; nothing is admitted.
        For the door, which prices a request from an identical open a moment ago, without its
        model (a burst of 375 surplus opens, priced one by one, cost the server 3.4 ms of CPU each
        against 1.3 ms for gRPC's part: benchmarks/RESULTS.md, Round 13). None before the first
        admission's look at the machine, which `admit` takes and which waits."""
        if not self._looked and self.count_machine_cpu and self.count_process_cpu:
            return None
        ticket = Ticket(self, dt=dt, cost_per_tick=cost_per_tick, compute_per_tick=filter_seconds)
        with self._lock:
            try:
                self._check(ticket, filter_seconds=filter_seconds, what=what, priced_by=priced_by)
            except ResourceExhausted as error:
                return str(error)
        return None

    def full(self, what: str) -> str | None:
        """Why this process admits no new REALTIME session now, whatever its cost, or None (`what`:
        the session asked for, as "pendulum_3 at 20 Hz"): its
        answers or its loop go late, its load is at its budget, or the machine has no more than
        its headroom idle. Asked at the door, before the model is looked up and priced (three
        quarters of a refused open's Python was the lookup: benchmarks/RESULTS.md, Round 12); it
        refuses only what admit would."""
        with self._lock:
            current = max(sum(t.load for t in self._by_id.values()), self._sample_cpu())
            # A process with no session may still take one: only the machine can say no before its
            # price is known. Its lateness was its last sessions'.
            behind = self._behind() if self._by_id else None
            if behind is not None:
                return self._late_refusal(behind, current, what)
            if current >= self.budget and self._by_id:
                return (
                    f"this server process is at {100 * current:.0f} % of a core and its tick budget is "
                    f"{100 * self.budget:.0f} % (--tick-budget {self.budget:g}): no session fits, so a "
                    f"session of {what} is not admitted. {_TRY_ELSEWHERE}"
                )
            free = self._machine_left()
            if free is not None and free <= MACHINE_HEADROOM:
                return (
                    f"this machine has {max(0.0, free):.2f} of its {_usable_cpus()} cores free (other "
                    f"programs, this server's other processes or its clients use the rest) and "
                    f"{MACHINE_HEADROOM:g} of a core is kept free: no session fits, so a session of {what} "
                    f"is not admitted. {_TRY_ELSEWHERE}"
                )
            return None

    def _late_refusal(self, behind: str, current: float, what: str) -> str:
        """Why a session of `what` is refused while the process's answers or loop go late."""
        return (
            f"this server process {behind} (at {100 * current:.0f} % of a core, tick budget "
            f"{100 * self.budget:.0f} %): the CPU its sessions get is short, so a session of {what} "
            f"is not admitted. {_TRY_ELSEWHERE}"
        )

    def _machine_left(self) -> float | None:
        """Cores the machine left idle, less what was admitted since, in the last window or, during
        a burst of opens, in the last _RECENT s, whichever is fewer; None where the machine is not
        counted. Under the lock."""
        figures = [(self.machine_free, self._machine_span)]
        if sum(self._opens) >= _BURST:
            figures.append((self.recent_free, self._recent_span))
        cores = _usable_cpus()
        left = [
            min(cores, free + self._started_within(span))
            - sum(t.load for t in self._by_id.values() if t.admitted_at >= span[1])
            for free, span in figures
            if free is not None
        ]
        return min(left, default=None)

    def _check_room(self, ticket: Ticket, *, current: float, what: str) -> None:
        """ResourceExhausted, saying why, when `ticket` does not fit the process's budget or the
        machine's idle CPU, or while the process's answers go late (the lateness of an idle
        process was its last sessions', late for no one now). Under the lock."""
        behind = self._behind() if self._by_id else None
        if behind is not None:
            self.refused += 1
            raise ResourceExhausted(self._late_refusal(behind, current, what))
        if current + ticket.load > self.budget:
            self.refused += 1
            raise ResourceExhausted(
                f"this server process is at {100 * current:.0f} % of a core and its tick budget is "
                f"{100 * self.budget:.0f} % (--tick-budget {self.budget:g}); a session of {what} is "
                f"estimated at {1e6 * ticket.cost_per_tick:.0f} us per tick, {100 * ticket.load:.1f} % more. "
                f"{_TRY_ELSEWHERE}"
            )
        self._check_machine(ticket, load=ticket.load, what=what)

    def _check_machine(self, ticket: Ticket, *, load: float, what: str) -> None:
        """ResourceExhausted when `load` (cores) does not fit the CPU the machine left idle in the
        last window, less what was admitted since. Under the lock."""
        free = self._machine_left()
        if free is not None and load > free - MACHINE_HEADROOM:
            self.refused += 1
            raise ResourceExhausted(
                f"this machine has {max(0.0, free):.2f} of its {_usable_cpus()} cores free (other "
                f"programs, this server's other processes or its clients use the rest); a session "
                f"of {what} is estimated at {1e6 * load * ticket.dt:.0f} us per tick, "
                f"{load:.2f} of a core, and {MACHINE_HEADROOM:g} of a core is kept free. "
                f"{_TRY_ELSEWHERE}"
            )

    def _release(self, ticket: Ticket) -> None:
        with self._lock:
            if ticket.released:
                return
            ticket.released = True
            if self._by_id.pop(id(ticket), None) is not None:
                self._collect_one(id(ticket), ticket)  # its last ticks count in this window
            self._collected.pop(id(ticket), None)
        if ticket.grace is not None and self.switch is not None:
            self.switch.remove(ticket.grace)
