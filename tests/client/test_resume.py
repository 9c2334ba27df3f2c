"""The resume bookkeeping both transports share, against hand-built messages: what is kept until
durable, which answers are handed out once, how many ticks a resume missed, each attempt's verdict."""

from __future__ import annotations

import grpc
import pytest

from jitdyn.client import ResumePolicy
from jitdyn.client._resume import Refused, ResumeLedger, resume_outcome
from jitdyn.client._transport import END
from jitdyn.errors import ResumeBufferFull, SessionLost
from jitdyn.settings import Settings
from jitdyn.storage.commit import SHARED_OUTAGE_LIMIT
from jitdyn.v1 import dynamics_pb2


def frame(seq: int) -> dynamics_pb2.StreamSessionRequest:
    return dynamics_pb2.StreamSessionRequest(frame=dynamics_pb2.Frame(seq=seq))


def result(seq: int, *, durable: int | None = None, corrected: bool = False) -> dynamics_pb2.Result:
    message = dynamics_pb2.Result(
        seq=seq, source=dynamics_pb2.SOURCE_CORRECTED if corrected else dynamics_pb2.SOURCE_MEASURED
    )
    if durable is not None:
        message.durable_seq = durable
    return message


def ledger(policy: ResumePolicy | None = None, token: str = "t0k3n") -> ResumeLedger:
    kept = ResumeLedger(policy or ResumePolicy(), dynamics_pb2.OpenSession(dt=0.05))
    kept.opened(dynamics_pb2.SessionOpened(session_id="s1", resume_token=token))
    return kept


def test_frames_are_kept_until_durable_and_resent_from_the_servers_resume_point() -> None:
    kept = ledger()
    for seq in range(6):
        kept.keep(seq, frame(seq))
    assert all(kept.fresh(result(seq)) for seq in range(3))
    assert kept.fresh(result(3, durable=1)) and len(kept) == 4  # frames 2-5
    request = kept.resume_request()
    assert (request.open.dt, request.open.resume.session_id, request.open.resume.token) == (
        0.05,
        "s1",
        "t0k3n",
    )
    opened = dynamics_pb2.SessionOpened(resume_from_seq=3, resume_reason="ticks 0-2 are stored")
    resent = kept.resumed(opened, cause="UNAVAILABLE: gone", attempts=2, started=0.0)
    assert [r.frame.seq for r in resent] == [3, 4, 5]
    assert kept.resumptions[0].from_seq == 3 and kept.resumptions[0].attempts == 2
    # The answer to re-sent frame 3 was handed out already; 4 and 5 were not; CORRECTED always is.
    assert not kept.fresh(result(3))
    assert kept.fresh(result(4)) and kept.fresh(result(5)) and kept.fresh(result(2, corrected=True))
    assert kept.missed == 0


def test_ticks_that_passed_during_a_resume_are_counted_missed() -> None:
    kept = ledger()
    assert kept.fresh(result(0))
    kept.resumed(
        dynamics_pb2.SessionOpened(resume_from_seq=1), cause="moving: drain", attempts=1, started=0.0
    )
    assert kept.fresh(result(4)) and kept.missed == 3
    assert kept.fresh(result(5)) and kept.missed == 3


def test_the_buffer_is_bounded_and_nothing_is_kept_without_a_token_or_after_cancel() -> None:
    kept = ledger(ResumePolicy(max_unacknowledged=2))
    kept.keep(0, frame(0))
    kept.keep(1, frame(1))
    with pytest.raises(ResumeBufferFull, match=r"2 frames are not yet durable .* frame 2 was not sent"):
        kept.keep(2, frame(2))
    assert len(kept) == 2
    tokenless = ledger(token="")
    tokenless.keep(0, frame(0))
    assert len(tokenless) == 0 and not tokenless.resumable(grpc.StatusCode.UNAVAILABLE)
    cancelled = ledger()
    cancelled.stop()
    assert not cancelled.resumable(grpc.StatusCode.CANCELLED)
    assert str(cancelled.moving(dynamics_pb2.Moving(reason="drain"))).endswith(
        "(drain) and resumption is off"
    )
    assert ledger().moving(dynamics_pb2.Moving(reason="drain")) is None
    lost = ledger().lost("UNAVAILABLE: gone", "NOT_FOUND: no such session")
    assert isinstance(lost, SessionLost) and lost.attempts == ResumePolicy().attempts


def test_the_resume_budget_outlasts_the_longest_outage_the_server_holds_rows_through() -> None:
    policy = ResumePolicy()
    waited = sum(policy.backoff(attempt) for attempt in range(policy.attempts))
    assert waited > SHARED_OUTAGE_LIMIT, waited


def test_a_resume_token_outlasts_the_resume_budget_and_the_longest_outage() -> None:
    """A stream renews its client's token every half of --resume-token-ttl: when it breaks, the
    token it left is good for at least that half, which covers every attempt of the SDK's budget
    after the longest outage a replica answers through."""
    policy = ResumePolicy()
    waited = sum(policy.backoff(attempt) for attempt in range(policy.attempts))
    assert Settings().resume_token_ttl / 2 > waited + SHARED_OUTAGE_LIMIT


def test_the_newest_token_is_the_one_a_resume_presents() -> None:
    kept = ledger(token="first")
    kept.resumed(
        dynamics_pb2.SessionOpened(resume_from_seq=0, resume_token="second"),
        cause="UNAVAILABLE: gone",
        attempts=1,
        started=0.0,
    )
    assert kept.resume_request().open.resume.token == "second"
    renewal = result(0)
    renewal.resume_token = "third"
    assert kept.fresh(renewal)
    assert kept.resume_request().open.resume.token == "third"
    # A stream a move has left renews nothing; a result without a renewal keeps the token.
    stale = result(1)
    stale.resume_token = "left-behind"
    kept.fresh(stale, current=False)
    kept.fresh(result(2))
    assert kept.resume_request().open.resume.token == "third"


class _Status(grpc.RpcError):
    def __init__(self, code: grpc.StatusCode) -> None:
        self._code = code

    def code(self) -> grpc.StatusCode:
        return self._code

    def details(self) -> str:
        return "why"


@pytest.mark.parametrize(
    ("first", "expected"),
    [
        (None, Refused("no `opened` within 10.0 s", retry=True)),
        (END, Refused("the stream ended before `opened`", retry=True)),
        (_Status(grpc.StatusCode.UNAVAILABLE), Refused("UNAVAILABLE: why", retry=True)),
        (_Status(grpc.StatusCode.FAILED_PRECONDITION), Refused("FAILED_PRECONDITION: why", retry=True)),
        (_Status(grpc.StatusCode.PERMISSION_DENIED), Refused("PERMISSION_DENIED: why", retry=False)),
    ],
)
def test_each_attempts_verdict(first: object, expected: Refused) -> None:
    assert resume_outcome(first, open_timeout=10.0) == expected  # type: ignore[arg-type]


def test_an_attempt_that_opened_gives_its_opened() -> None:
    response = dynamics_pb2.StreamSessionResponse(opened=dynamics_pb2.SessionOpened(resume_from_seq=7))
    outcome = resume_outcome((0.0, response), open_timeout=10.0)
    assert isinstance(outcome, dynamics_pb2.SessionOpened) and outcome.resume_from_seq == 7
