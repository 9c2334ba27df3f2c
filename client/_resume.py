"""What a session keeps so that it can resume, shared by the sync and the async transports: the
frames no `durable_seq` covers yet, the ticks answered, the resumes made; and the messages and
verdicts of a resume. No I/O here: each transport runs its own attempts, with these as its steps."""

from __future__ import annotations

import collections
import dataclasses
import logging
import time
from dataclasses import dataclass

import grpc

from jitdyn.client._models import ResumePolicy, Resumption, Summary
from jitdyn.client._transport import RESUMABLE_CODES, End
from jitdyn.errors import ResumeBufferFull, SessionLost, Unavailable
from jitdyn.v1 import dynamics_pb2

__all__ = ["Refused", "ResumeLedger", "resume_outcome"]

_log = logging.getLogger("jitdyn.client")

# What a stream gave first: an answer with its receive time, the status it ended with, its end, or
# None when nothing came in time.
_First = tuple[float, dynamics_pb2.StreamSessionResponse] | grpc.RpcError | End | None


@dataclass(frozen=True)
class Refused:
    """Why one resume attempt did not open the session, and whether another attempt may."""

    reason: str
    retry: bool


def resume_outcome(first: _First, *, open_timeout: float) -> dynamics_pb2.SessionOpened | Refused:
    """The `opened` a resume attempt's stream answered with, or why it did not."""
    if first is None:
        return Refused(f"no `opened` within {open_timeout} s", retry=True)
    if isinstance(first, grpc.RpcError):
        code = first.code()
        # The old owner may still hold the lease for a moment (FAILED_PRECONDITION).
        retry = code in RESUMABLE_CODES or code == grpc.StatusCode.FAILED_PRECONDITION
        return Refused(f"{code.name}: {first.details()}", retry=retry)
    if isinstance(first, End) or first[1].WhichOneof("payload") != "opened":
        return Refused("the stream ended before `opened`", retry=True)
    return first[1].opened


class ResumeLedger:
    """The resume state of one session. `keep` each frame and skip as it is sent, pass each result
    through `fresh` as it is read; when the stream breaks, open again with `resume_request()`, and
    once `resume_outcome` is an `opened`, `resumed` says what to re-send."""

    def __init__(self, policy: ResumePolicy, open_message: dynamics_pb2.OpenSession) -> None:
        self.policy = policy
        self._open_message = open_message
        self.session_id = ""
        self._token = ""
        self._stopped = False
        # Frames and skips sent that no `durable_seq` covers yet, oldest first: what a resume re-sends.
        self._unacknowledged: collections.deque[tuple[int, dynamics_pb2.StreamSessionRequest]] = (
            collections.deque()
        )
        self._durable = -1
        self._delivered = -1  # the highest tick answered to the caller (not counting CORRECTED)
        self._after_resume = False  # the next fresh answer tells how many ticks the resume missed
        self.resumptions: list[Resumption] = []
        self.missed = 0
        self.overloaded: str | None = None  # the server's latest warning that answers may go late

    def warned(self, message: dynamics_pb2.Overloaded) -> None:
        """The server's in-band warning that this session's answers may go late: kept and logged,
        once per warning (the server repeats it every few seconds while it holds)."""
        self.overloaded = message.reason
        _log.warning("session %s: the server warns: %s", self.session_id, message.reason)

    def opened(self, opened: dynamics_pb2.SessionOpened) -> None:
        """The session's first `opened`: its id, and the token a resume presents."""
        self.session_id = opened.session_id
        self._token = opened.resume_token

    def renewed(self, token: str) -> None:
        """A newer resume token from the server (a resume's `opened`, or a result's renewal): the
        one the next resume presents, since the server refuses an older one once it has been
        passed (expired, or stale). Never logged."""
        if token:
            self._token = token

    def stop(self) -> None:
        """The caller cancelled the session: it is never resumed."""
        self._stopped = True

    @property
    def active(self) -> bool:
        """Whether a broken stream is resumed (the policy allows it, the server gave a token)."""
        return self.policy.enabled and bool(self._token) and not self._stopped

    def resumable(self, code: grpc.StatusCode) -> bool:
        """Whether a stream that ended with `code` is resumed."""
        return self.active and code in RESUMABLE_CODES

    def __len__(self) -> int:
        return len(self._unacknowledged)

    def keep(self, seq: int, request: dynamics_pb2.StreamSessionRequest) -> None:
        """Keep frame or skip `seq` until a `durable_seq` covers it; raises ResumeBufferFull, and
        keeps nothing, when the policy's `max_unacknowledged` are kept already."""
        if not self.active:
            return
        if len(self._unacknowledged) >= self.policy.max_unacknowledged:
            raise ResumeBufferFull(
                f"session {self.session_id}: {len(self._unacknowledged)} frames are not "
                f"yet durable (the newest durable_seq is {self._durable}), the most the client "
                f"keeps for a resume (max_unacknowledged); frame {seq} was not sent"
            )
        self._unacknowledged.append((seq, request))

    def acknowledge(self, durable_seq: int) -> None:
        """Frames up to `durable_seq` are stored off the server's host: no resume needs them again."""
        self._durable = max(self._durable, durable_seq)
        while self._unacknowledged and self._unacknowledged[0][0] <= self._durable:
            self._unacknowledged.popleft()

    def fresh(self, result: dynamics_pb2.Result, *, current: bool = True) -> bool:
        """Bookkeeping of a result; False for the answer to a re-sent frame the caller already had.
        `current`: it came on the session's current stream (one a move has left renews no token)."""
        if result.HasField("durable_seq"):
            self.acknowledge(result.durable_seq)
        if current:
            self.renewed(result.resume_token)
        if result.source == dynamics_pb2.SOURCE_CORRECTED:
            return True
        if result.seq <= self._delivered:
            return False
        if self._after_resume:
            self._after_resume = False
            self.missed += result.seq - self._delivered - 1
        self._delivered = result.seq
        return True

    def moving(self, moving: dynamics_pb2.Moving) -> Unavailable | None:
        """The server's notice that it is moving the session: None when it resumes elsewhere, else
        the error the session ends with."""
        if moving.HasField("durable_seq"):
            self.acknowledge(moving.durable_seq)
        if self.active:
            return None
        return Unavailable(
            f"session {self.session_id}: the server is moving it elsewhere "
            f"({moving.reason}) and resumption is off"
        )

    def resume_request(self) -> dynamics_pb2.StreamSessionRequest:
        """The `open` that continues this session on whichever replica takes it."""
        message = dynamics_pb2.OpenSession()
        message.CopyFrom(self._open_message)
        message.resume.session_id = self.session_id
        message.resume.token = self._token
        return dynamics_pb2.StreamSessionRequest(open=message)

    def refused(self, attempt: int, refused: Refused) -> None:
        _log.info("session %s: resume attempt %d: %s", self.session_id, attempt + 1, refused.reason)

    def resumed(
        self, opened: dynamics_pb2.SessionOpened, *, cause: str, attempts: int, started: float
    ) -> list[dynamics_pb2.StreamSessionRequest]:
        """A resume opened the session again (`started` is its time.monotonic()): the frames and
        skips to re-send on the new stream, in order."""
        from_seq = opened.resume_from_seq if opened.HasField("resume_from_seq") else 0
        self.acknowledge(from_seq - 1)
        self.renewed(opened.resume_token)
        self._after_resume = True
        self.resumptions.append(
            Resumption(
                session_id=self.session_id,
                from_seq=from_seq,
                cause=cause,
                reason=opened.resume_reason,
                attempts=attempts,
                took=time.monotonic() - started,
            )
        )
        return [request for _, request in self._unacknowledged]

    def lost(self, cause: str, last: str) -> SessionLost:
        """The error of a session every resume attempt failed for."""
        return SessionLost(
            f"session {self.session_id} could not be resumed after its stream broke ({cause}); "
            f"{self.policy.attempts} attempts, the last: {last}",
            session_id=self.session_id,
            attempts=self.policy.attempts,
        )

    def summarised(self, summary: Summary) -> Summary:
        """`summary` with what the resumes took (`resumes`, `missed`)."""
        return dataclasses.replace(summary, resumes=len(self.resumptions), missed=self.missed)
