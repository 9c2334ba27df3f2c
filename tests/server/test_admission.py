"""Admission by measured cost, on the class itself (the server-level test is test_capacity.py)."""

from __future__ import annotations

import re
import time

import pytest

from jitdyn.errors import ResourceExhausted
from jitdyn.server.runtime.admission import TRANSPORT_COST, Admission


def _beat_for(admission: Admission, seconds: float) -> None:
    """The loop's watch, beating every 5 ms (stalls.BEAT) for `seconds`, as a server's loop would."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        admission.observe_loop_lag(0.0)
        time.sleep(0.005)


def test_a_session_that_cannot_fit_alone_is_refused_by_an_idle_process_saying_what_rate_fits() -> None:
    """Its filter alone fits (0.9 ms of a 2 ms tick), but not with the CPU a tick costs around it:
    an idle process used to take it on its filter alone, and answered it late."""
    admission = Admission(budget=0.75, count_process_cpu=False)
    cost = 0.9e-3 + TRANSPORT_COST
    with pytest.raises(ResourceExhausted) as refused:
        admission.admit(cost_per_tick=cost, dt=2e-3, what="myoelbow at 500 Hz", filter_seconds=0.9e-3)
    assert str(refused.value) == (
        f"a session of myoelbow at 500 Hz is estimated at {1e6 * cost:.0f} us of this server's CPU per "
        f"tick: its filter 900 us and {1e6 * TRANSPORT_COST:.0f} us around it (the frame's read, the "
        "result's dynamics and message, the write, the record, the event loop; the starting guess, "
        f"until this process has measured its own ticks), {100 * cost / 2e-3:.0f} % of a core against "
        "the tick budget of 75 % (--tick-budget 0.75) on its own: its answers could not be on time. "
        f"At most {0.75 / cost:.0f} Hz fits here. Try again later, on another server, or at a lower rate"
    )
    assert admission.refused == 1 and admission.sessions == 0
    # At the rate it names, it is admitted; a second is refused on the first one's estimate.
    dt = cost / 0.75
    ticket = admission.admit(cost_per_tick=cost, dt=dt * 1.01, what="myoelbow", filter_seconds=0.9e-3)
    with pytest.raises(ResourceExhausted, match=rf"estimated at {1e6 * cost:.0f} us per tick"):
        admission.admit(cost_per_tick=cost, dt=dt * 1.01, what="myoelbow", filter_seconds=0.9e-3)
    ticket.release()
    assert admission.sessions == 0


def test_a_rehearsal_is_wanted_only_where_the_overhead_decides_and_can_be_measured() -> None:
    admission = Admission(budget=0.75, count_machine_cpu=False)
    guess = admission.overhead
    # myoElbow at 500 Hz: fits with half the overhead figure, not with REHEARSE_SPAN times it.
    assert admission.wants_rehearsal(filter_seconds=0.3e-3, dt=2e-3)
    # pendulum_3 at 20 Hz fits whatever the overhead; at 5 kHz nothing around the filter fits.
    assert not admission.wants_rehearsal(filter_seconds=0.23e-3, dt=0.05)
    assert not admission.wants_rehearsal(filter_seconds=0.05e-3, dt=guess / 4)
    # A process serving a session, or one that does not count its own CPU, cannot measure it.
    ticket = admission.admit(cost_per_tick=2.5e-3, dt=0.05, what="pendulum_3 at 20 Hz")
    assert not admission.wants_rehearsal(filter_seconds=0.3e-3, dt=2e-3)
    ticket.release()
    assert not Admission(budget=0.75, count_process_cpu=False).wants_rehearsal(filter_seconds=0.3e-3, dt=2e-3)


def test_a_filter_that_alone_exceeds_the_budget_is_refused_even_on_an_idle_process() -> None:
    admission = Admission(budget=0.75, count_process_cpu=False)
    with pytest.raises(
        ResourceExhausted,
        match=rf"myohand at 500 Hz is estimated at {1e6 * (2.2e-3 + TRANSPORT_COST):.0f} us",
    ):
        admission.admit(
            cost_per_tick=2.2e-3 + TRANSPORT_COST, dt=2e-3, what="myohand at 500 Hz", filter_seconds=2.2e-3
        )
    assert admission.sessions == 0


def test_sessions_are_admitted_until_their_estimates_fill_the_budget() -> None:
    admission = Admission(budget=0.5, count_process_cpu=False)
    tickets = []
    with pytest.raises(ResourceExhausted):
        for _ in range(100):
            tickets.append(admission.admit(cost_per_tick=2.5e-3, dt=0.05, what="pendulum_3 at 20 Hz"))
    assert len(tickets) == 10  # 10 x 2.5 ms / 50 ms = 0.5 of a core


def test_a_resumed_session_is_admitted_over_the_budget_and_counts_against_new_ones(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A session moving here from a lost or draining replica was admitted by the fleet: refusing it
    would lose it. It is taken whatever the load, logged, and new sessions are refused after it."""
    admission = Admission(budget=0.5, count_process_cpu=False)
    full = [admission.admit(cost_per_tick=2.5e-3, dt=0.05, what="pendulum_3 at 20 Hz") for _ in range(10)]
    with pytest.raises(ResourceExhausted):
        admission.admit(cost_per_tick=2.5e-3, dt=0.05, what="pendulum_3 at 20 Hz")
    moved = admission.admit(cost_per_tick=2.5e-3, dt=0.05, what="pendulum_3 at 20 Hz", resumed=True)
    assert admission.sessions == 11
    assert "a resumed session of pendulum_3 at 20 Hz is admitted over the tick budget" in caplog.text
    full[0].release()
    with pytest.raises(ResourceExhausted):  # the moved session holds the freed place
        admission.admit(cost_per_tick=2.5e-3, dt=0.05, what="pendulum_3 at 20 Hz")
    moved.release()
    admission.admit(cost_per_tick=2.5e-3, dt=0.05, what="pendulum_3 at 20 Hz")


def test_a_machine_that_others_keep_busy_refuses_the_sessions_it_cannot_carry() -> None:
    import os
    import subprocess
    import sys
    import time

    hogs = [
        subprocess.Popen([sys.executable, "-c", "while True: pass"])
        for _ in range(len(os.sched_getaffinity(0)))
    ]
    try:
        time.sleep(0.3)  # the hogs running
        machine = Admission(budget=0.75)
        alone = Admission(budget=0.75, count_machine_cpu=False)
        # Even the first session of an idle process is refused: before any window has ended, a
        # short look at the machine finds no core free.
        with pytest.raises(ResourceExhausted, match=r"^this machine has 0\.\d\d of its \d+ cores free"):
            machine.admit(cost_per_tick=2.5e-3, dt=0.05, what="pendulum_3 at 20 Hz", filter_seconds=0.5e-3)
        assert machine.machine_free is not None and machine.machine_free < 0.2
        time.sleep(2.2)  # a window of the machine's CPU, all of it taken by the hogs
        with pytest.raises(ResourceExhausted, match=r"^this machine has 0\.\d\d of its \d+ cores free"):
            machine.admit(cost_per_tick=2.5e-3, dt=0.05, what="pendulum_3 at 20 Hz")
        assert machine.machine_free is not None and machine.machine_free < 0.2
        # The process budget alone would have taken both: the machine's CPU is what refused them.
        for _ in range(2):
            alone.admit(cost_per_tick=2.5e-3, dt=0.05, what="pendulum_3 at 20 Hz")
        assert alone.sessions == 2 and machine.sessions == 0
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()


def test_the_machine_s_cpu_is_read_over_the_last_window_not_since_the_last_admission(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A server idle for a while, then beside hogs that take every core: its loop's beats close
    each window on time, so the next session is refused for the hogs, not admitted on the
    idle time before them."""
    import os
    import subprocess
    import sys

    from jitdyn.server.runtime import admission as module

    monkeypatch.setattr(module, "_CPU_WINDOW", 0.5)
    window = module._CPU_WINDOW
    admission = Admission(budget=0.75)

    _beat_for(admission, 2 * window + 0.2)  # idle
    hogs = [
        subprocess.Popen([sys.executable, "-c", "while True: pass"])
        for _ in range(len(os.sched_getaffinity(0)))
    ]
    try:
        _beat_for(admission, 2 * window + 0.3)  # a whole window with the hogs in it
        with pytest.raises(ResourceExhausted, match=r"^this machine has 0\.\d\d of its \d+ cores free"):
            admission.admit(cost_per_tick=2.5e-3, dt=0.05, what="pendulum_3 at 20 Hz", filter_seconds=0.5e-3)
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()


def test_during_a_burst_of_opens_the_machine_is_read_over_the_latest_quarter_second() -> None:
    """Hogs started after a whole idle window: before the next window ends, one open is admitted
    on the window's figure (a quarter second alone is too short to judge by), but during a burst of
    opens the machine's idle CPU over the latest quarter second refuses it (the window still saw
    two cores free: the surplus of 400 opens came in the same way, while admitted ones opened)."""
    import os
    import subprocess
    import sys

    admission = Admission(budget=0.75)
    price = {"cost_per_tick": 2.5e-3, "dt": 0.05, "what": "pendulum_3 at 20 Hz", "filter_seconds": 0.5e-3}

    _beat_for(admission, 2.2)  # a whole window, idle
    assert admission.machine_free is not None and admission.machine_free > 0.5
    hogs = [
        subprocess.Popen([sys.executable, "-c", "while True: pass"])
        for _ in range(len(os.sched_getaffinity(0)))
    ]
    try:
        _beat_for(admission, 0.6)
        admission.observe_open()
        admission.admit(**price).release()
        for _ in range(20):
            admission.observe_open()
        with pytest.raises(ResourceExhausted, match=r"^this machine has 0\.\d\d of its \d+ cores free"):
            admission.admit(**price)
        assert admission.machine_free > 0.5  # the last window's figure, which alone would have admitted
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()


def test_starting_up_is_not_taken_for_load(monkeypatch: pytest.MonkeyPatch) -> None:
    import time

    from jitdyn.server.runtime import admission as module

    monkeypatch.setattr(module, "_CPU_WINDOW", 0.3)

    def start_up() -> Admission:
        # A budget of 0.4: a start that got a fifth of a core (a loaded machine) is still load.
        admission = Admission(budget=0.4, count_machine_cpu=False)
        until = time.process_time() + 0.4  # imports, the registry, migrations: a busy start
        while time.process_time() < until:
            pass
        return admission

    def admit(admission: Admission) -> None:
        admission.admit(
            cost_per_tick=0.7e-3 + TRANSPORT_COST, dt=5e-3, what="myoelbow at 200 Hz", filter_seconds=0.7e-3
        )

    with pytest.raises(ResourceExhausted, match=r"this server process is at \d+ % of a core"):
        admit(start_up())
    served = start_up()
    served.start_window()  # the server calls it once it serves
    admit(served)
    assert served.sessions == 1


def test_the_gil_changes_hands_as_often_as_the_tightest_open_grace_needs() -> None:
    import sys

    from jitdyn.server.runtime.switch_interval import SWITCH_DEFAULT, SWITCH_SHARE, SwitchInterval

    switch = SwitchInterval()  # the process's, shared by every admission of it
    first = Admission(count_process_cpu=False, switch=switch)
    second = Admission(count_process_cpu=False, switch=switch)
    slow = first.admit(cost_per_tick=1e-3, dt=0.05, what="pendulum_3 at 20 Hz", grace=0.025)
    assert sys.getswitchinterval() == pytest.approx(SWITCH_DEFAULT)  # 5 ms of a 25 ms grace
    fast = second.admit(cost_per_tick=1e-3, dt=5e-3, what="biped at 200 Hz", grace=2.5e-3)
    assert sys.getswitchinterval() == pytest.approx(SWITCH_SHARE * 2.5e-3)
    slow.release()  # another admission's session ending leaves the tight one's interval
    assert sys.getswitchinterval() == pytest.approx(SWITCH_SHARE * 2.5e-3)
    fast.release()
    fast.release()  # twice is safe
    assert sys.getswitchinterval() == pytest.approx(SWITCH_DEFAULT)


def test_an_admission_without_a_switch_leaves_the_gil_alone() -> None:
    import sys

    from jitdyn.server.runtime.switch_interval import SWITCH_DEFAULT

    ticket = Admission(count_process_cpu=False).admit(
        cost_per_tick=1e-3, dt=5e-3, what="biped at 200 Hz", grace=2.5e-3
    )
    assert sys.getswitchinterval() == pytest.approx(SWITCH_DEFAULT)
    ticket.release()


def test_a_process_whose_answers_go_late_refuses_new_sessions_and_warns_its_newest(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Admission learns from what it observes: when more than 1 % of a window's answers went more
    than 5 ms past their deadlines, the budget's estimate notwithstanding, no session is admitted,
    and the sessions admitted last are told, so that they can move before they go late."""
    import time

    from jitdyn.server.runtime import admission as module

    monkeypatch.setattr(module, "_CPU_WINDOW", 0.2)
    admission = Admission(budget=0.75, count_process_cpu=False)
    first, second, third = (
        admission.admit(cost_per_tick=2.5e-3, dt=0.05, what="pendulum_3 at 20 Hz") for _ in range(3)
    )
    # A window of answers on time: nothing to say, room for more.
    for _ in range(100):
        admission.observe_lateness(0.001)
    time.sleep(0.25)
    assert [admission.unaffordable(t) for t in (first, second, third)] == [None, None, None]
    assert admission.late_share == 0.0
    # A window with 3 answers in 100 more than 5 ms late: the process is past what it serves.
    for k in range(100):
        admission.observe_lateness(0.012 if k % 33 == 0 else 0.0)
    time.sleep(0.25)
    warned = [admission.unaffordable(t) for t in (first, second, third)]
    assert warned[:2] == [None, None]
    assert warned[2] is not None and re.fullmatch(
        r"this server process is past what it serves on time \(0 % of a core against its tick budget of "
        r"75 %; it answered 4\.0 % of its ticks more than 5 ms past their deadlines in the last 0\.2 s\) and "
        r"this session is among the last admitted: its answers may go late\. Resume it on another server "
        r"or lower its rate",
        warned[2],
    ), warned[2]
    with pytest.raises(
        ResourceExhausted, match=r"^this server process answered 4\.0 % of its ticks more than 5 ms"
    ):
        admission.admit(cost_per_tick=2.5e-3, dt=0.05, what="pendulum_3 at 20 Hz")
    # Too few answers in a window are no evidence; on time again, admission opens.
    for _ in range(10):
        admission.observe_lateness(0.05)
    time.sleep(0.25)
    assert admission.unaffordable(third) is None
    admission.admit(cost_per_tick=2.5e-3, dt=0.05, what="pendulum_3 at 20 Hz")


def test_a_loop_that_runs_its_deadlines_late_admits_no_one(monkeypatch: pytest.MonkeyPatch) -> None:
    """The loop's lag is evidence before any answer is late: a window in which what fell due on the
    loop ran more than 5 ms late for more than 1 % of the time admits no one and tells the session
    admitted last; lags under 5 ms, however many, are not counted."""
    import time

    from jitdyn.server.runtime import admission as module

    monkeypatch.setattr(module, "_CPU_WINDOW", 0.2)
    admission = Admission(budget=0.75, count_process_cpu=False)
    first, second = (
        admission.admit(cost_per_tick=2.5e-3, dt=0.05, what="pendulum_3 at 20 Hz") for _ in range(2)
    )
    for _ in range(40):
        admission.observe_loop_lag(0.0049)
    time.sleep(0.25)
    assert [admission.unaffordable(t) for t in (first, second)] == [None, None]
    assert admission.lag_share == 0.0
    # One stall of 45 ms: 40 ms of the window's 0.25 s more than 5 ms late, 16 %.
    admission.observe_loop_lag(0.045)
    time.sleep(0.25)
    assert admission.unaffordable(first) is None
    warning = admission.unaffordable(second)
    assert warning is not None and re.fullmatch(
        r"this server process is past what it serves on time \(0 % of a core against its tick budget of "
        r"75 %; it ran its deadlines more than 5 ms late for 1\d\.\d % of the last 0\.2 s\) and this session "
        r"is among the last admitted: its answers may go late\. Resume it on another server or lower its "
        r"rate",
        warning,
    ), warning
    with pytest.raises(
        ResourceExhausted,
        match=r"^this server process ran its deadlines more than 5 ms late for 1\d\.\d % of the last 0\.2 s \(at ",
    ):
        admission.admit(cost_per_tick=2.5e-3, dt=0.05, what="pendulum_3 at 20 Hz")
    # A window without a stall: admission opens again.
    time.sleep(0.25)
    assert admission.unaffordable(second) is None
    admission.admit(cost_per_tick=2.5e-3, dt=0.05, what="pendulum_3 at 20 Hz")


def test_a_lagging_loop_tells_but_only_late_answers_or_cpu_past_the_budget_end_a_session(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The loop's lag tells the last admitted session (above) but is not what ends it: at 56-63 % of
    a core, loop lags of 5-20 ms ended sessions whose answers were all on time. Their answers late,
    or the process past its budget, are."""
    from jitdyn.server.runtime import admission as module

    monkeypatch.setattr(module, "_CPU_WINDOW", 0.2)
    admission = Admission(budget=0.75, count_process_cpu=False)
    _first, second = (
        admission.admit(cost_per_tick=2.5e-3, dt=0.05, what="pendulum_3 at 20 Hz") for _ in range(2)
    )
    admission.observe_loop_lag(0.045)
    for _ in range(40):
        second.answered(0.0)  # every answer on time
    time.sleep(0.25)
    admission.observe_loop_lag(0.0)
    assert admission.lag_share > 0.1 and admission.late_share == 0.0
    assert admission.unaffordable(second) is not None  # told
    assert not admission.answers_short()  # not to be ended
    for lateness in [0.0] * 30 + [0.02] * 10:  # a quarter of the answers 20 ms late
        second.answered(lateness)
    time.sleep(0.25)
    admission.observe_loop_lag(0.0)
    assert admission.late_share == pytest.approx(0.25)
    assert admission.answers_short()
    # A window on time, then a process whose CPU passes its budget.
    time.sleep(0.25)
    admission.observe_loop_lag(0.0)
    assert not admission.answers_short()
    busy = Admission(budget=0.01)
    busy.start_window()
    end = time.process_time() + 0.1
    while time.process_time() < end:
        pass
    time.sleep(max(0.0, module._CPU_WINDOW - 0.1))
    assert busy.answers_short()


def test_a_loop_that_lags_with_no_session_admitted_is_late_for_no_one(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Clients starting up beside an idle server lag its loop; their opens are judged by the
    machine's idle CPU, not refused for a lateness no session saw."""
    import time

    from jitdyn.server.runtime import admission as module

    monkeypatch.setattr(module, "_CPU_WINDOW", 0.2)
    admission = Admission(budget=0.75, count_process_cpu=False)
    admission.observe_loop_lag(0.045)  # 40 ms of a 0.25 s window more than 5 ms late, 16 %
    time.sleep(0.25)
    admission.observe_loop_lag(0.0)
    assert admission.lag_share == 0.0
    first = admission.admit(cost_per_tick=2.5e-3, dt=0.05, what="pendulum_3 at 20 Hz")
    admission.admit(cost_per_tick=2.5e-3, dt=0.05, what="pendulum_3 at 20 Hz")
    # With a session admitted, the same lag is late for it.
    admission.observe_loop_lag(0.045)
    time.sleep(0.25)
    admission.observe_loop_lag(0.0)
    assert admission.lag_share > 0.1
    assert admission.unaffordable(first) is None  # the first admitted is never the one told


def test_the_door_refuses_only_what_admit_would(monkeypatch: pytest.MonkeyPatch) -> None:
    """Admission.full, asked before a session is priced: a process whose last sessions went late
    but that has none now may still take one (their lateness is late for no one now), so the door
    lets it through;
    with a session open, the same lateness closes the door, in admit's words."""
    import time

    from jitdyn.server.runtime import admission as module

    monkeypatch.setattr(module, "_CPU_WINDOW", 0.2)
    admission = Admission(budget=0.75, count_process_cpu=False)
    ticket = admission.admit(cost_per_tick=2.5e-3, dt=0.05, what="pendulum_3 at 20 Hz")
    for _ in range(30):
        admission.observe_lateness(0.02)  # every answer of the window 20 ms late
    time.sleep(0.25)
    message = admission.full("pendulum_3 at 20 Hz")
    assert message is not None and re.fullmatch(
        r"this server process answered 100\.0 % of its ticks more than 5 ms past their deadlines in the "
        r"last 0\.2 s \(at \d+ % of a core, tick budget 75 %\): the CPU its sessions get is short, so a "
        r"session of pendulum_3 at 20 Hz is not admitted\. Try again later, on another server, or at a "
        r"lower rate",
        message,
    ), message
    ticket.release()
    assert admission.full("pendulum_3 at 20 Hz") is None
    admission.admit(cost_per_tick=2.5e-3, dt=0.05, what="pendulum_3 at 20 Hz", filter_seconds=0.5e-3)


def test_a_refusal_asked_from_a_price_is_admit_s_own_and_admits_nothing() -> None:
    admission = Admission(budget=0.5, count_process_cpu=False)
    price = {"cost_per_tick": 10e-3, "filter_seconds": 1e-3, "dt": 0.05, "what": "pendulum_3 at 20 Hz"}
    assert admission.refusal(**price) is None  # the first would be taken
    assert admission.sessions == 0
    tickets = [admission.admit(**price) for _ in range(2)]  # 0.2 + 0.2 of the 0.5
    reason = admission.refusal(**price)
    assert reason is not None and admission.sessions == 2
    with pytest.raises(ResourceExhausted) as refused:
        admission.admit(**price)
    assert str(refused.value) == reason
    tickets[0].release()
    assert admission.refusal(**price) is None


def test_late_frames_wait_while_their_replays_keep_the_process_late(monkeypatch: pytest.MonkeyPatch) -> None:
    """A late frame's replay is refused only when the process went late in the last window and
    replays took more than a tenth of it: late answers alone, or replays on time, do not stop them."""
    import time

    from jitdyn.server.runtime import admission as module

    monkeypatch.setattr(module, "_CPU_WINDOW", 0.2)
    admission = Admission(budget=0.75, count_process_cpu=False)

    def window(*, late: bool, replaying: float) -> str | None:
        for _ in range(30):
            admission.observe_lateness(0.02 if late else 0.0)
        admission.observe_replay(replaying)
        time.sleep(0.25)
        admission.observe_loop_lag(0.0)  # the beat that closes the window
        return admission.replays_behind()

    assert window(late=True, replaying=0.01) is None  # late, but replays took 4 % of it
    assert window(late=False, replaying=0.1) is None  # replays took 40 %, all answers on time
    reason = window(late=True, replaying=0.1)
    assert reason is not None and re.fullmatch(
        r"answered 100\.0 % of its ticks more than 5 ms past their deadlines in the last 0\.2 s, and "
        r"replaying late frames took \d\d % of that time",
        reason,
    ), reason
    assert window(late=False, replaying=0.0) is None  # caught up: replays again


def test_a_replay_is_priced_at_what_the_sessions_replays_cost_in_cpu() -> None:
    """Before its first replay a session's replayed tick is priced at its compute per tick; then at
    the CPU its replays took per tick replayed (a fading mean), whatever the wall clock said: a
    process stopped mid-replay does not price every later replay out of reach. The wall time is
    the process's time in replays."""
    from jitdyn.server.runtime.admission import Ticket

    admission = Admission(budget=1.0, count_machine_cpu=False, count_process_cpu=False)
    ticket = Ticket(admission, dt=0.02, cost_per_tick=0.003, compute_per_tick=0.0012)
    assert ticket.replay_price == pytest.approx(0.0012)
    ticket.observe_replay(0.5, cpu=0.006, ticks=12)  # stopped for most of half a second
    assert ticket.replay_price == pytest.approx(0.0005)
    ticket.observe_replay(0.006, cpu=0.012, ticks=12)
    assert ticket.replay_price == pytest.approx(0.0005 + 0.05 * (0.001 - 0.0005))
    ticket.observe_replay(0.001, cpu=0.001, ticks=0)  # nothing replayed: the price stands
    assert ticket.replay_price == pytest.approx(0.0005 + 0.05 * (0.001 - 0.0005))


def test_a_replay_may_take_the_loops_idle_share_of_the_shortest_grace() -> None:
    """A late frame's replay runs on the loop ahead of every session's next tick: it may take what
    the process's load leaves idle of the shortest grace among its sessions, and anything on a
    process with no session."""
    import math

    admission = Admission(budget=1.0, count_machine_cpu=False, count_process_cpu=False)
    assert admission.replay_room() == math.inf
    arm = admission.admit(cost_per_tick=0.004, dt=0.02, what="arm at 50 Hz", grace=0.010)
    assert admission.replay_room() == pytest.approx(0.010 * (1 - 0.2))
    pendulum = admission.admit(cost_per_tick=0.003, dt=0.05, what="pendulum at 20 Hz")  # grace dt / 2
    assert admission.replay_room() == pytest.approx(0.010 * (1 - 0.2 - 0.06))
    arm.release()
    assert admission.replay_room() == pytest.approx(0.025 * (1 - 0.06))
    busy = [admission.admit(cost_per_tick=0.01, dt=0.05, what="x", resumed=True) for _ in range(6)]
    assert admission.replay_room() == 0.0  # past a whole core: no room at all
    for ticket in [pendulum, *busy]:
        ticket.release()


def test_before_its_first_replay_a_session_prices_one_at_its_ticks_cpu() -> None:
    """Until a session has replayed, a replayed tick is priced at the thread CPU of its ticks once
    they tell it, not at their wall time, which a busy machine stretches."""
    from jitdyn.server.runtime.admission import Ticket

    admission = Admission(budget=1.0, count_machine_cpu=False, count_process_cpu=False)
    ticket = Ticket(admission, dt=0.02, cost_per_tick=0.003, compute_per_tick=0.0012)
    ticket.observe(0.0023)  # no CPU told: the compute stands
    assert ticket.replay_price == pytest.approx(ticket.compute_per_tick)
    ticket.observe(0.0023, cpu=0.0006)  # preempted for most of the tick
    assert ticket.replay_price == pytest.approx(0.0006)
    ticket.observe(0.0023, cpu=0.0008)
    assert ticket.replay_price == pytest.approx(0.0006 + 0.05 * (0.0008 - 0.0006))
    ticket.observe_replay(0.01, cpu=0.002, ticks=4)
    assert ticket.replay_price == pytest.approx(0.0005)  # its own replays, once measured


def test_tickets_count_their_answers_and_the_window_adds_them_up(monkeypatch: pytest.MonkeyPatch) -> None:
    """Each session counts its own answers on its ticket, without the process's lock; the process
    adds up what its tickets counted when a window ends, a released ticket's last answers with them,
    and what was counted before the process started its first window not at all."""
    import time

    from jitdyn.server.runtime import admission as module

    monkeypatch.setattr(module, "_CPU_WINDOW", 0.2)
    admission = Admission(budget=0.75, count_process_cpu=False)
    first, second = (
        admission.admit(cost_per_tick=2.5e-3, dt=0.05, what="pendulum_3 at 20 Hz") for _ in range(2)
    )
    for _ in range(30):
        first.answered(0.02)  # before the window starts: not the window's
    admission.start_window()
    for k in range(60):
        first.answered(0.0)
        second.answered(0.012 if k % 20 == 0 else 0.001)  # 3 late in 120
    second.release()  # its answers still count in this window
    time.sleep(0.25)
    admission.measured_load()  # the window ends
    assert admission.late_share == pytest.approx(3 / 120)
    for _ in range(60):
        first.answered(0.0)
    time.sleep(0.25)
    admission.measured_load()
    assert admission.late_share == 0.0


def _burn(seconds: float) -> None:
    """Spend `seconds` of this thread's CPU."""
    until = time.thread_time() + seconds
    while time.thread_time() < until:
        pass


def test_a_session_is_priced_at_the_process_s_cpu_per_tick_not_its_ticks_wall_time(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Each tick: 0.3 ms of its own CPU, 1 ms of wall time (other threads held the GIL and the
    core), 0.3 ms of the process's CPU around it. Priced by wall time, a session cost 1.4 ms a
    tick against 0.6 ms of CPU; and an open, priced at its 0.15 ms filter cycle plus the overhead
    around the tick's wall time, cost less than the ticks it would add."""
    from jitdyn.server.runtime import admission as module

    monkeypatch.setattr(module, "_CPU_WINDOW", 0.5)
    admission = Admission(budget=0.75, count_machine_cpu=False)
    cycle = 0.15e-3
    ticket = admission.admit(
        cost_per_tick=cycle + TRANSPORT_COST, dt=0.05, what="pendulum_3", filter_seconds=cycle
    )
    admission.start_window()

    def tick() -> None:
        wall, cpu = time.perf_counter(), time.thread_time()
        _burn(0.3e-3)
        time.sleep(0.7e-3)
        ticket.observe(time.perf_counter() - wall, cpu=time.thread_time() - cpu)
        _burn(0.3e-3)

    # Before the process has measured a window the price it was admitted at stands.
    for _ in range(20):
        tick()
    assert ticket.cost_per_tick == cycle + TRANSPORT_COST
    used, ticks = time.process_time(), 0
    while not admission.overhead_measured:
        tick()
        ticks += 1
        admission.measured_load()
    per_tick = (time.process_time() - used) / ticks  # what a tick cost this process
    for _ in range(100):  # the ticket's price follows its ticks
        tick()
    assert ticket.cost_per_tick == pytest.approx(per_tick, rel=0.25)
    assert cycle + admission.overhead == pytest.approx(per_tick, rel=0.25)
    ticket.release()


def test_a_window_whose_ticks_went_unanswered_does_not_price_a_tick(monkeypatch: pytest.MonkeyPatch) -> None:
    """A loop busy refusing a burst of opens skips its sessions' ticks: the window's CPU, divided
    among the few ticks it counted, priced each at 13 ms. Such a window does not measure them; one
    that counted its sessions' ticks does."""
    from jitdyn.server.runtime import admission as module

    monkeypatch.setattr(module, "_CPU_WINDOW", 0.3)
    admission = Admission(budget=0.75, count_machine_cpu=False)
    ticket = admission.admit(cost_per_tick=0.3e-3, dt=1e-3, what="a 1 kHz session", filter_seconds=0.1e-3)
    admission.start_window()

    def window(ticks: int) -> None:
        started = time.monotonic()
        for _ in range(ticks):
            _burn(10e-6)
            ticket.observe(10e-6, cpu=10e-6)
        time.sleep(max(0.0, started + 0.35 - time.monotonic()))
        admission.measured_load()

    window(60)  # of about 350 due
    assert not admission.overhead_measured and admission.overhead == TRANSPORT_COST
    window(2000)
    assert admission.overhead_measured and admission.around_ticks is not None
    ticket.release()
