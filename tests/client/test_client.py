"""The sync SDK: its values parse the vocabulary once and convert to messages; a wait that outlasts
the timeout is the typed NoAnswer, which `results()` takes as the end of what has arrived."""

from __future__ import annotations

import time
from typing import Any

import pytest

from jitdyn.client import Client, FrameData, SessionOptions, TickResult
from jitdyn.errors import InvalidArgument, JitdynError, NoAnswer
from jitdyn.v1 import common_pb2, dynamics_pb2
from jitdyn.vocabulary import Channel, Clock, Horizon, Output, Preset, Scenario, SigmaScheme, Source


def test_options_take_members_or_their_text_and_hold_members() -> None:
    options = SessionOptions(
        model_name="pendulum_1",
        scenario="passive",
        clock="CLOCK_REALTIME",
        measured=("qpos", Channel.QVEL),
        outputs=("INVERSE_DYNAMICS",),
        horizon=Horizon.HALF_ROUND_TRIP,
        estimator={"preset": "THESIS", "sigma_points": SigmaScheme.SIMPLEX, "alpha": 1},
    )
    assert options.scenario is Scenario.PASSIVE and options.clock is Clock.REALTIME
    assert options.measured == (Channel.QPOS, Channel.QVEL)
    assert options.outputs == (Output.INVERSE_DYNAMICS,)
    assert options.estimator == {"preset": Preset.THESIS, "sigma_points": SigmaScheme.SIMPLEX, "alpha": 1.0}
    message = options.to_message()
    assert (message.scenario, message.clock, message.horizon) == (
        common_pb2.SCENARIO_PASSIVE,
        common_pb2.CLOCK_REALTIME,
        dynamics_pb2.HORIZON_HALF_ROUND_TRIP,
    )
    assert list(message.measured) == [common_pb2.CHANNEL_QPOS, common_pb2.CHANNEL_QVEL]
    assert message.estimator == common_pb2.EstimatorSettings(
        preset=common_pb2.PRESET_THESIS, sigma_points=common_pb2.SIGMA_POINTS_SIMPLEX, alpha=1.0
    )
    assert (
        SessionOptions(model_name="m", scenario="").to_message().scenario == common_pb2.SCENARIO_UNSPECIFIED
    )


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"clock": "SOMETIMES"}, "clock must be one of REALTIME, LOCKSTEP, got 'SOMETIMES'"),
        ({"measured": ("qpos", "qjerk")}, "measured must be one of QPOS, QVEL, QACC, CTRL, got 'qjerk'"),
        ({"estimator": {"gamma": 1.0}}, "estimator has unknown setting 'gamma'; expected one of estimator,"),
        ({"estimator": {"preset": "FAST"}}, "estimator.preset must be one of JITDYN, THESIS, got 'FAST'"),
        ({"estimator": {"alpha": "big"}}, "estimator.alpha must be a number, got 'big'"),
    ],
)
def test_a_bad_word_or_setting_is_refused_on_creation(options: dict[str, Any], message: str) -> None:
    with pytest.raises(InvalidArgument) as caught:
        SessionOptions(model_name="pendulum_1", **options)
    assert str(caught.value).startswith(message)


def test_ranges_are_left_to_the_server() -> None:
    # The server judges ranges against the same table and names the field in full.
    assert SessionOptions(model_name="m", estimator={"alpha": -1.0}).estimator == {"alpha": -1.0}


def test_no_answer_is_a_typed_timeout() -> None:
    assert issubclass(NoAnswer, JitdynError) and issubclass(NoAnswer, TimeoutError)


def test_results_end_with_no_answer_and_reading_goes_on(server: Any) -> None:
    with (
        Client(server.address, timeout=0.2) as client,
        client.open_session(SessionOptions(model_name="pendulum_1", dt=0.05)) as session,
    ):
        session.send(FrameData(seq=0, t=0.0, qpos=[0.3], qvel=[0.0]))
        answers = list(session.results(timeout=1.0))
        assert [(a.seq, a.source) for a in answers if isinstance(a, TickResult)] == [(0, Source.MEASURED)]
        started = time.monotonic()
        with pytest.raises(NoAnswer, match=r"^no answer from the server within 0.2 s$"):
            session._answer()  # nothing was sent, so nothing comes
        assert time.monotonic() - started >= 0.2
        assert isinstance(session.skip(1), TickResult)


def test_answers_that_arrive_while_close_waits_are_kept(server: Any) -> None:
    """REALTIME frames sent ahead of their ticks, then close: the server answers the pending ticks
    as it closes, before the summary; those answers are read by `poll` after `close`."""
    options = SessionOptions(model_name="pendulum_1", dt=0.05, clock="REALTIME")
    with Client(server.address, timeout=30) as client:
        session = client.open_session(options)
        for k in range(10):
            session.send(FrameData(seq=k, t=k * 0.05, qpos=[0.3], qvel=[0.0]))
        summary = session.close()
        answered = sorted({a.seq for a in session.poll() if isinstance(a, TickResult)})
    assert summary.frames == 10
    assert answered == list(range(10))
    assert session.poll() == []  # handed out once
