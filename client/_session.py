"""What the sync `Session` and the async `AsyncSession` share: a session's state and every step of it
that needs no I/O (the session clock, clock probes, answers turned into values, the resume
ledger's counts). Each transport subclasses `SessionCore` and adds its own reads and writes."""

from __future__ import annotations

import collections
import time
from collections.abc import Callable, Sequence
from typing import NotRequired, TypedDict

from jitdyn.client._models import (
    FrameData,
    Opened,
    Rejection,
    ResumePolicy,
    Resumption,
    SessionOptions,
    Summary,
    SyncSample,
    TickResult,
    opened_from_response,
    session_answer,
    sync_request,
)
from jitdyn.client._resume import ResumeLedger
from jitdyn.v1 import dynamics_pb2
from jitdyn.vocabulary import Clock

__all__ = ["Received", "SessionArguments", "SessionCore"]

# An answer with the client's time.monotonic() of its arrival.
Received = tuple[float, dynamics_pb2.StreamSessionResponse]


class SessionArguments(TypedDict):
    """What a transport's session passes on to `SessionCore` (see its arguments)."""

    timeout: float | None
    metadata: Sequence[tuple[str, str]]
    checksum: bool
    sync_interval: NotRequired[float]
    on_end: NotRequired[Callable[[], None] | None]
    resume: NotRequired[ResumePolicy | None]


class SessionCore:
    """A session's state, its clock and its views, with no stream: the transports add the I/O."""

    opened: Opened

    def __init__(
        self,
        options: SessionOptions,
        *,
        timeout: float | None,
        metadata: Sequence[tuple[str, str]],
        checksum: bool,
        sync_interval: float = 0.5,
        on_end: Callable[[], None] | None = None,
        resume: ResumePolicy | None = None,
    ) -> None:
        """`timeout`: how long a read waits (None: for ever); `metadata`: the stream's call
        metadata; `checksum`: whether frames carry CRC32C; `sync_interval`: seconds between the
        REALTIME clock probes; `on_end`: called once when the session ends; `resume`: its policy."""
        self._on_end = on_end  # called once the session has ended: the client closes its connection
        self._metadata = tuple(metadata)
        self._timeout = timeout
        self._checksum = checksum
        self._clock_start = time.monotonic()
        self._last_probe: tuple[int, float] | None = None
        self._probe_id = 0
        self._realtime = options.clock == Clock.REALTIME
        self._sync_interval = sync_interval
        self._last_sync_sent = -float("inf")
        self._closed = False
        self._finished = False
        self.summary: Summary | None = None
        # Answers that arrived while `close` waited for the summary (the server answers the ticks
        # still pending as it closes): kept for `poll` and `results`, not dropped.
        self._unread: collections.deque[TickResult | Rejection | SyncSample] = collections.deque()
        self._open_message = options.to_message()
        self._ledger = ResumeLedger(resume if resume is not None else ResumePolicy(), self._open_message)

    def _opened(self, first: Received) -> None:
        """The stream's first answer, `opened`, arrived at `first[0]`: the session clock starts
        then (the server's starts as it sends it, so the two differ by one transit until `sync`
        exchanges measure the offset). Raises the contract's error when it is not `opened`."""
        opened = opened_from_response(first[1])
        self._clock_start = first[0]
        self.opened = opened
        self._ledger.opened(first[1].opened)

    def _pong(self, received_at: float, response: dynamics_pb2.StreamSessionResponse) -> None:
        """Note t4 of a clock probe's exchange, which the next probe reports however late the
        caller reads the answer."""
        if response.HasField("sync"):
            self._last_probe = (response.sync.id, received_at - self._clock_start)

    def _sync_due(self) -> bool:
        """In REALTIME, a clock probe goes along with the frames every `sync_interval` seconds."""
        return self._realtime and self.now() - self._last_sync_sent >= self._sync_interval

    def _probe(self) -> dynamics_pb2.StreamSessionRequest:
        """The next clock probe, its send time now: write it at once."""
        self._probe_id += 1
        self._last_sync_sent = self.now()
        return sync_request(self._probe_id, self._last_sync_sent, self._last_probe)

    def _frame_request(self, frame: FrameData) -> dynamics_pb2.StreamSessionRequest:
        return dynamics_pb2.StreamSessionRequest(frame=frame.to_message(checksum=self._checksum))

    def _finish(self) -> None:
        """The session is over (closed, cancelled, or failed for good): its connection may go."""
        if self._finished:
            return
        self._finished = True
        if self._on_end is not None:
            self._on_end()

    def _convert(self, item: Received) -> TickResult | Rejection | SyncSample | Summary:
        received_at, response = item
        answer = session_answer(response, received_at=received_at, clock_start=self._clock_start)
        if isinstance(answer, Summary):
            answer = self._ledger.summarised(answer)
            self.summary = answer
        return answer

    def _read_while_closing(self, item: Received) -> None:
        """An item `close` read while it waited for the summary: the summary, or an answer kept."""
        answer = self._convert(item)
        if not isinstance(answer, Summary):
            self._unread.append(answer)

    def _take_unread(self) -> list[TickResult | Rejection | SyncSample]:
        answers = list(self._unread)
        self._unread.clear()
        return answers

    @property
    def clock_start(self) -> float:
        """The time.monotonic() value that is 0 on the session clock."""
        return self._clock_start

    @property
    def unacknowledged(self) -> int:
        """Frames sent that no result's durable_seq covers yet (kept for a resume)."""
        return len(self._ledger)

    @property
    def resumptions(self) -> list[Resumption]:
        """Every resume so far, oldest first."""
        return self._ledger.resumptions

    @property
    def missed(self) -> int:
        """Ticks no answer came for across the resumes (REALTIME ticks that passed meanwhile)."""
        return self._ledger.missed

    @property
    def overloaded(self) -> str | None:
        """The server's latest in-band warning that this session's answers may go late (it is past
        what it serves on time, and this session was among the last admitted), or None. The
        session goes on; resuming it elsewhere or lowering its rate is the caller's choice."""
        return self._ledger.overloaded

    def now(self) -> float:
        """The client's session clock: seconds since `opened` arrived. REALTIME frames are due at
        `seq * dt` on this clock."""
        return time.monotonic() - self._clock_start
