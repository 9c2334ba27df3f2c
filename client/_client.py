"""The sync transport of jitdyn's SDK: `Client` (the connection) and `Session` (one open stream).

    from jitdyn.client import Client, SessionOptions, FrameData

    with Client("127.0.0.1:50051") as c:
        with c.open_session(SessionOptions(model_name="pendulum_1", dt=0.05)) as s:
            r = s.send_frame(FrameData(seq=0, t=0.0, qpos=[0.3], qvel=[0.0]))
            r.qfrc_inverse          # numpy array, (nv,)
            s.skip(1).source        # Source.PREDICTED
            summary = s.close()

Every call raises a `jitdyn.errors` exception for the status the server ends it with; a wait that
outlasts the client's timeout raises NoAnswer. Frames carry the contract's CRC32C checksum unless
told otherwise.
"""

from __future__ import annotations

import collections
import logging
import os
import queue
import threading
import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Self, TypeVar, Unpack

import grpc

from jitdyn.client._models import (
    FrameData,
    ModelRef,
    Rejection,
    ResumePolicy,
    SessionOptions,
    Summary,
    SyncSample,
    TickResult,
    register_request,
)
from jitdyn.client._resume import Refused, resume_outcome
from jitdyn.client._session import SessionArguments, SessionCore
from jitdyn.client._transport import (
    END,
    End,
    auth_metadata,
    channel_options,
    explain_open_error,
    status_error,
    unbatched,
)
from jitdyn.client._transport import root_certificates as root_certificates_of
from jitdyn.errors import FailedPrecondition, JitdynError, NoAnswer, error_for_status
from jitdyn.lifecycle import Closeable
from jitdyn.v1 import (
    dynamics_pb2,
    dynamics_pb2_grpc,
    model_registry_pb2,
    model_registry_pb2_grpc,
    session_pb2,
    session_pb2_grpc,
)

__all__ = ["Client", "Session"]

_log = logging.getLogger("jitdyn.client")


_Request = TypeVar("_Request")
_Response = TypeVar("_Response")


class Session(SessionCore):
    """One open session. Use as a context manager; `close()` is safe to call twice.

    LOCKSTEP: `send_frame` and `skip` return the server's one answer. REALTIME: `send` queues a frame
    without waiting, and `results()` or `poll()` give answers as they arrive, among them the
    `SyncSample`s of the clock probes the session sends by itself (at open, then every
    `sync_interval` seconds with the frames).

    Resumption (`ResumePolicy`): a session whose server gave it a resume token keeps every frame no
    result's `durable_seq` covers yet. When its stream breaks (UNAVAILABLE; CANCELLED, which is what
    a balancer's RST_STREAM(CANCEL) of a dead replica's stream arrives as; or the server's `moving`
    notice) it opens again through the same target with the token, re-sends the frames from the
    new stream's `resume_from_seq`, and goes on: the caller sees no error, and answers it already
    had are not handed out twice. `resumptions` lists every resume; `missed` counts the ticks no
    answer came for across them. All of it runs in the caller's thread, as it reads answers.
    """

    def __init__(
        self,
        stub: dynamics_pb2_grpc.DynamicsServiceStub,
        options: SessionOptions,
        *,
        connections: _Connections | None = None,
        **arguments: Unpack[SessionArguments],
    ) -> None:
        super().__init__(options, **arguments)
        self._connections = connections  # a new connection for each resume attempt (None: the same one)
        self._stub = stub
        # Every stream's answers, tagged with the stream's generation: a resumed session ignores
        # what an earlier stream left behind.
        self._responses: queue.Queue[tuple[int, _Item]] = queue.Queue()
        self._generation = 0
        self._requests: queue.Queue[dynamics_pb2.StreamSessionRequest | End] = queue.Queue()
        self._call: grpc.Call | None = None
        self._reader: threading.Thread | None = None
        # Answers of the stream before a move (or of one that stayed), handed out before the
        # current stream's (see `_move`).
        self._left: collections.deque[_Item] = collections.deque()
        self._generations = 0  # the newest stream's, a tried one's too
        self._trial: _Trial | None = None  # a move being tried
        self._start_stream(dynamics_pb2.StreamSessionRequest(open=self._open_message))
        try:
            first = self._get(self._timeout)
        except JitdynError as error:
            raise explain_open_error(error) from None
        if first is None:
            self._finish()
            raise FailedPrecondition("the session stream has ended")
        # The reader's time of `opened`, not the time this thread got to it.
        self._opened(first)
        if self._realtime:
            self.sync()

    # Plumbing.

    def _start_stream(self, open_request: dynamics_pb2.StreamSessionRequest) -> None:
        """A new stream that begins with `open_request`, and a reader thread of its own."""
        self._generation, self._requests, self._call, self._reader = self._new_stream(open_request)

    def _new_stream(self, open_request: dynamics_pb2.StreamSessionRequest) -> _Stream:
        """A stream that begins with `open_request`, read by a thread of its own under a new
        generation; not yet the session's current one."""
        self._generations += 1
        requests: queue.Queue[dynamics_pb2.StreamSessionRequest | End] = queue.Queue()
        requests.put(open_request)
        call = self._stub.StreamSession(_iterate(requests), metadata=self._metadata)
        reader = threading.Thread(
            target=self._read, args=(call, self._generations), name="jitdyn-session-reader", daemon=True
        )
        reader.start()
        return self._generations, requests, call, reader

    def _end_stream(self) -> None:
        """Let go of the current stream (it broke, or its server said `moving`)."""
        self._requests.put(END)
        if self._call is not None:
            self._call.cancel()

    def _read(self, call: Iterator[dynamics_pb2.StreamSessionResponse], generation: int) -> None:
        try:
            for message in call:
                received_at = time.monotonic()
                for response in unbatched(message):
                    self._pong(received_at, response)
                    self._responses.put((generation, (received_at, response)))
        except grpc.RpcError as error:
            self._responses.put((generation, error))
        finally:
            self._responses.put((generation, END))

    def _next_response(self, timeout: float | None) -> dynamics_pb2.StreamSessionResponse:
        item = self._get(timeout)
        if item is None:
            raise FailedPrecondition("the session stream has ended")
        return item[1]

    def _raw(self, timeout: float | None) -> _Item:
        """The current stream's next item, with none of the resume logic."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            try:
                generation, item = self._responses.get(timeout=remaining)
            except queue.Empty:
                raise NoAnswer(f"no answer from the server within {timeout} s") from None
            if generation == self._generation:
                return item
            if self._trial is not None and generation == self._trial.stream[0]:
                self._settle(self._trial, item)

    def _get(self, timeout: float | None) -> tuple[float, dynamics_pb2.StreamSessionResponse] | None:
        while True:
            item = self._left.popleft() if self._left else self._raw(timeout)
            if item is END:
                self._responses.put((self._generation, END))
                return None
            if isinstance(item, grpc.RpcError):
                if self._trial is not None and self._moved_meanwhile(self._trial):
                    continue  # the stream broke because the move took the session: go on there
                if self._ledger.resumable(item.code()):
                    self._resume(f"{item.code().name}: {item.details()}")
                    continue
                self._responses.put((self._generation, END))
                self._finish()
                raise status_error(item)
            response = item[1]
            kind = response.WhichOneof("payload")
            if kind == "overloaded":
                self._ledger.warned(response.overloaded)
                continue
            if kind == "moving":
                error = self._ledger.moving(response.moving)
                if error is None:
                    self._move(f"moving: {response.moving.reason}")
                    continue
                self._responses.put((self._generation, END))
                self._finish()
                raise error
            if kind == "result" and not self._ledger.fresh(response.result):
                continue
            return item

    def _move(self, cause: str) -> None:
        """Open the session elsewhere while this stream still answers (make before break): the
        tried stream's first answer is read as it comes, among this one's (`_raw`). Moved once
        another replica has taken it; when none takes it now (the index is down for all of them
        too), this stream goes on, and the server says `moving` again later."""
        if self._trial is not None:
            return  # one try at a time
        previous = self._stub
        if self._connections is not None:
            self._stub = self._connections.trial()
        generation, requests, call, reader = self._new_stream(self._ledger.resume_request())
        self._trial = _Trial(
            stream=(generation, requests, call, reader), cause=cause, started=time.monotonic(), stub=previous
        )

    def _settle(self, trial: _Trial, first: _Item) -> None:
        """The tried stream's first answer: move to it, or let it go."""
        self._trial = None
        generation, requests, call, reader = trial.stream
        outcome = resume_outcome(first, open_timeout=self._ledger.policy.open_timeout)
        if isinstance(outcome, Refused):
            self._ledger.refused(0, outcome)
            self._drop_trial(trial)
            return
        self._end_stream()
        if self._connections is not None:
            self._connections.adopt(moved=True)
        self._generation, self._requests, self._call, self._reader = generation, requests, call, reader
        self._after_resume(
            self._ledger.resumed(outcome, cause=trial.cause, attempts=1, started=trial.started)
        )

    def _after_resume(self, resent: Iterable[dynamics_pb2.StreamSessionRequest]) -> None:
        """On the new stream: the requests the server has not acknowledged, again; the close when
        the session was closed meanwhile; a sync on a REALTIME session, whose clock starts anew."""
        for request in resent:
            self._requests.put(request)
        if self._closed:
            self._requests.put(dynamics_pb2.StreamSessionRequest(close=dynamics_pb2.CloseSession()))
            self._requests.put(END)
        if self._realtime and not self._closed:
            self.sync()

    def _moved_meanwhile(self, trial: _Trial) -> bool:
        """The current stream broke while a move was being tried (it may be why: the move took the
        session from it): wait for the try's first answer, and say whether it moved."""
        deadline = time.monotonic() + self._ledger.policy.open_timeout
        while self._trial is trial:
            try:
                tag, item = self._responses.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                self._drop_trial(trial)
                return False
            if tag == trial.stream[0]:
                self._settle(trial, item)
        return self._generation == trial.stream[0]

    def _drop_trial(self, trial: _Trial) -> None:
        self._trial = None
        _, requests, call, _ = trial.stream
        requests.put(END)
        call.cancel()
        self._stub = trial.stub
        if self._connections is not None:
            self._connections.adopt(moved=False)

    def _resume(self, cause: str) -> None:
        """Open the session again through the same target, re-send what is not durable, go on."""
        policy = self._ledger.policy
        started = time.monotonic()
        if self._trial is not None:
            self._drop_trial(self._trial)
        self._end_stream()
        last = cause
        for attempt in range(policy.attempts):
            time.sleep(policy.backoff(attempt))
            if self._connections is not None:
                self._stub = self._connections.reconnect()
            self._start_stream(self._ledger.resume_request())
            try:
                first: _Item | None = self._raw(policy.open_timeout)
            except NoAnswer:
                first = None
            outcome = resume_outcome(first, open_timeout=policy.open_timeout)
            if isinstance(outcome, Refused):
                self._ledger.refused(attempt, outcome)
                last = outcome.reason
                self._end_stream()
                if outcome.retry:
                    continue
                break
            self._after_resume(
                self._ledger.resumed(outcome, cause=cause, attempts=attempt + 1, started=started)
            )
            return
        self._responses.put((self._generation, END))
        self._finish()
        raise self._ledger.lost(cause, last)

    def _send(self, request: dynamics_pb2.StreamSessionRequest, seq: int | None = None) -> None:
        if self._closed:
            raise FailedPrecondition("the session is closed")
        if seq is not None:
            self._ledger.keep(seq, request)
        self._requests.put(request)

    # LOCKSTEP.

    def send_frame(self, frame: FrameData) -> TickResult | Rejection:
        """Send one frame and wait for its answer (LOCKSTEP)."""
        self.send(frame)
        return self._answer()

    def skip(self, seq: int) -> TickResult | Rejection:
        """Tell the server tick `seq` had no frame; returns the PREDICTED result (LOCKSTEP)."""
        self._send(dynamics_pb2.StreamSessionRequest(skip=dynamics_pb2.Skip(seq=seq)), seq)
        return self._answer()

    def _answer(self) -> TickResult | Rejection:
        while True:
            item = self._get(self._timeout)
            if item is None:
                raise FailedPrecondition("the session stream ended before the answer")
            answer = self._convert(item)
            if isinstance(answer, (TickResult, Rejection)):
                return answer

    # REALTIME (and LOCKSTEP, for callers that pipeline).

    def send(self, frame: FrameData) -> None:
        """Queue a frame without waiting for its answer. In REALTIME a clock probe goes along every
        `sync_interval` seconds, so the server keeps client time on its clock."""
        if self._sync_due():
            self.sync()
        self._send(self._frame_request(frame), frame.seq)

    def results(self, *, timeout: float | None = None) -> Iterator[TickResult | Rejection | SyncSample]:
        """Answers as they arrive, until the session is closed or `timeout` passes with none
        (after `close`: those that arrived while it waited for the summary)."""
        yield from self._take_unread()
        while True:
            try:
                item = self._get(timeout)
            except NoAnswer:
                return
            if item is None:
                return
            answer = self._convert(item)
            if isinstance(answer, Summary):
                return
            yield answer

    def poll(self) -> list[TickResult | Rejection | SyncSample]:
        """Every answer that has arrived, without waiting (after `close`: those that arrived while
        it waited for the summary)."""
        answers = self._take_unread()
        while True:
            try:
                item = self._get(0)
            except NoAnswer:
                return answers
            if item is None:
                return answers
            answer = self._convert(item)
            if not isinstance(answer, Summary):
                answers.append(answer)

    def sync(self) -> None:
        """Send a clock probe; its answer comes back among the results (a `SyncSample`)."""
        self._send(self._probe())

    # Ending.

    def close(self) -> Summary:
        """Close the session; returns its summary (where it is stored, counts)."""
        if self._closed:
            if self.summary is None:
                raise FailedPrecondition("the session ended without a summary")
            return self.summary
        self._requests.put(dynamics_pb2.StreamSessionRequest(close=dynamics_pb2.CloseSession()))
        self._closed = True
        self._requests.put(END)
        while self.summary is None:
            item = self._get(self._timeout)
            if item is None:
                self._finish()
                raise FailedPrecondition("the session stream ended without a summary")
            self._read_while_closing(item)
        if self._reader is not None:
            self._reader.join(timeout=5)
        self._finish()
        return self.summary

    def cancel(self) -> None:
        """Drop the stream without closing (the server stores the session as ABANDONED, or as
        RECOVERED when it was resumable and nobody resumes it)."""
        self._closed = True
        self._ledger.stop()
        if self._call is not None:
            self._call.cancel()
        self._requests.put(END)
        self._finish()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is None:
            self.close()
        elif not self._closed:
            self.cancel()


def _iterate(
    requests: queue.Queue[dynamics_pb2.StreamSessionRequest | End],
) -> Iterator[dynamics_pb2.StreamSessionRequest]:
    while True:
        item = requests.get()
        if item is END:
            return
        yield item


_Item = tuple[float, dynamics_pb2.StreamSessionResponse] | grpc.RpcError | End
# A stream: its generation, its requests, its call, its reader.
_Stream = tuple[int, "queue.Queue[dynamics_pb2.StreamSessionRequest | End]", grpc.Call, threading.Thread]


@dataclass(frozen=True)
class _Trial:
    """A move being tried: its stream, why, since when, and the stub of the stream it would leave."""

    stream: _Stream
    cause: str
    started: float
    stub: dynamics_pb2_grpc.DynamicsServiceStub


class _Connections:
    """The connections of one session when each has its own: the current stream's, and one a move
    is tried on (make before break). A resume takes a new connection: a balancer keeps a
    connection's streams on the backend it first chose (HAProxy's connection reuse), which is the
    replica that died, is draining, or cannot hold the session."""

    def __init__(self, client: Client) -> None:
        self._client = client
        self._current: grpc.Channel | None = None
        self._trial: grpc.Channel | None = None

    def _open(self) -> grpc.Channel:
        channel = self._client._new_channel(shared=False)
        with self._client._lock:
            self._client._session_channels.add(channel)
        return channel

    def _drop(self, channel: grpc.Channel | None) -> None:
        if channel is None:
            return
        with self._client._lock:
            if channel not in self._client._session_channels:
                return
            self._client._session_channels.discard(channel)
        channel.close()

    def first(self) -> dynamics_pb2_grpc.DynamicsServiceStub:
        self._current = self._open()
        return dynamics_pb2_grpc.DynamicsServiceStub(self._current)

    def reconnect(self) -> dynamics_pb2_grpc.DynamicsServiceStub:
        """The current connection closed, a new one current (break before make)."""
        self.close()
        return self.first()

    def trial(self) -> dynamics_pb2_grpc.DynamicsServiceStub:
        """A new connection beside the current one, for a move."""
        self._drop(self._trial)
        self._trial = self._open()
        return dynamics_pb2_grpc.DynamicsServiceStub(self._trial)

    def adopt(self, moved: bool) -> None:
        """The move worked (the tried connection is the current one now), or did not (it goes)."""
        if moved:
            self._drop(self._current)
            self._current, self._trial = self._trial, None
        else:
            self._drop(self._trial)
            self._trial = None

    def close(self) -> None:
        self._drop(self._trial)
        self._drop(self._current)
        self._trial = self._current = None


class Client(Closeable):
    """A connection to a jitdyn server. Keyword-only options beyond the address."""

    def __init__(
        self,
        address: str = "127.0.0.1:50051",
        *,
        timeout: float | None = 60.0,
        api_key: str | None = None,
        root_certificates: bytes | None = None,
        ca_file: str | os.PathLike[str] | None = None,
        checksum: bool = True,
        connection_per_session: bool = True,
        channel_options: Sequence[tuple[str, Any]] = (),
        resume: ResumePolicy | bool = True,
    ) -> None:
        """`channel_options` are gRPC channel arguments added to the SDK's own (e.g.
        `[("grpc.lb_policy_name", "round_robin")]` with `address="ipv4:10.0.0.1:50051,10.0.0.2:50051"`).
        `resume`: how sessions resume by themselves when their stream breaks (`ResumePolicy`);
        False turns it off. TLS: `ca_file`, a PEM file of the CA that signed the server's (or its
        balancer's) certificate, or the same as bytes in `root_certificates`; neither: plaintext."""
        self._address = address
        self._channel_options = tuple(channel_options)
        self._resume = resume if isinstance(resume, ResumePolicy) else ResumePolicy(enabled=resume)
        # TLS when given roots to trust: the server's (or its balancer's) CA, as bytes or a PEM file.
        self._root_certificates = root_certificates_of(root_certificates, ca_file)
        self._channel = self._new_channel(shared=True)
        # Each session on its own connection (its own HTTP/2 connection, not a stream of the
        # client's): `jitdyn serve --processes N` is N processes on one port, and the kernel spreads
        # connections, not streams, over them, so sessions sharing one connection share one process
        # and one core. False: every session on the client's one connection.
        self._connection_per_session = connection_per_session
        self._session_channels: set[grpc.Channel] = set()
        self._lock = threading.Lock()
        self._metadata = auth_metadata(api_key)
        self._timeout = timeout
        self._checksum = checksum
        self._registry = model_registry_pb2_grpc.ModelRegistryServiceStub(self._channel)
        self._dynamics = dynamics_pb2_grpc.DynamicsServiceStub(self._channel)
        self._sessions = session_pb2_grpc.SessionServiceStub(self._channel)

    def wait_ready(self, timeout: float = 10.0) -> None:
        """Block until the server answers, or raise Unavailable."""
        try:
            grpc.channel_ready_future(self._channel).result(timeout=timeout)
        except grpc.FutureTimeoutError:
            raise error_for_status(
                grpc.StatusCode.UNAVAILABLE, f"no jitdyn server answered within {timeout} s"
            ) from None

    def _unary(
        self, method: grpc.UnaryUnaryMultiCallable[_Request, _Response], request: _Request
    ) -> _Response:
        try:
            return method(request, timeout=self._timeout, metadata=self._metadata)
        except grpc.RpcError as error:
            raise status_error(error) from None

    def register_model(
        self,
        *,
        name: str,
        mjcf: str,
        assets: Mapping[str, bytes] | None = None,
        description: str = "",
        tags: Sequence[str] = (),
    ) -> tuple[ModelRef, bool]:
        """Register a model; returns it and whether it was new."""
        request = register_request(name=name, mjcf=mjcf, assets=assets, description=description, tags=tags)
        response = self._unary(self._registry.RegisterModel, request)
        return ModelRef.from_message(response.model), response.created

    def get_model(self, *, model_id: str = "", name: str = "", version: int = 0) -> ModelRef:
        return ModelRef.from_message(
            self._unary(
                self._registry.GetModel,
                model_registry_pb2.GetModelRequest(model_id=model_id, name=name, version=version),
            ).model
        )

    def get_model_message(
        self, *, model_id: str = "", name: str = "", version: int = 0
    ) -> model_registry_pb2.Model:
        """The full `Model` message (joints with ranges, actuators, metadata)."""
        return self._unary(
            self._registry.GetModel,
            model_registry_pb2.GetModelRequest(model_id=model_id, name=name, version=version),
        ).model

    def list_models(self, *, name: str = "", tag: str = "", page_size: int = 0) -> Iterator[ModelRef]:
        """Every model matching the filters, page after page."""
        token = ""
        while True:
            page = self._unary(
                self._registry.ListModels,
                model_registry_pb2.ListModelsRequest(
                    page_size=page_size, page_token=token, name=name, tag=tag
                ),
            )
            for model in page.models:
                yield ModelRef.from_message(model)
            token = page.next_page_token
            if not token:
                return

    def list_sessions(
        self, request: session_pb2.ListSessionsRequest | None = None
    ) -> Iterator[session_pb2.Session]:
        """Every stored session matching the request's filters, newest first."""
        page_request = session_pb2.ListSessionsRequest()
        if request is not None:
            page_request.CopyFrom(request)
        while True:
            page = self._unary(self._sessions.ListSessions, page_request)
            yield from page.sessions
            if not page.next_page_token:
                return
            page_request.page_token = page.next_page_token

    def get_session(self, session_id: str) -> session_pb2.Session:
        return self._unary(
            self._sessions.GetSession, session_pb2.GetSessionRequest(session_id=session_id)
        ).session

    def _new_channel(self, *, shared: bool) -> grpc.Channel:
        # gRPC shares one connection between channels of the same target and arguments unless a
        # channel asks for its own subchannel pool.
        base = channel_options(self._channel_options)
        options = base if shared else (*base, ("grpc.use_local_subchannel_pool", 1))
        if self._root_certificates is not None:
            return grpc.secure_channel(
                self._address, grpc.ssl_channel_credentials(self._root_certificates), options=options
            )
        return grpc.insecure_channel(self._address, options=options)

    def open_session(self, options: SessionOptions) -> Session:
        """Open a session; raises the server's error (InvalidArgument, NotFound, ...) if it refuses."""
        stub, connections = self._dynamics, None
        if self._connection_per_session:
            connections = _Connections(self)
            stub = connections.first()
        try:
            return Session(
                stub,
                options,
                timeout=self._timeout,
                metadata=self._metadata,
                checksum=self._checksum,
                on_end=connections.close if connections is not None else None,
                resume=self._resume,
                connections=connections,
            )
        except grpc.RpcError as error:
            raise status_error(error) from None

    def close(self) -> None:
        """Close the connections (open sessions end with them); safe to call twice."""
        with self._lock:
            channels, self._session_channels = self._session_channels, set()
        for channel in channels:
            channel.close()
        self._channel.close()
