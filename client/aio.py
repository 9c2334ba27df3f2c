"""The asyncio client of jitdyn, over grpc.aio: the sync SDK's types, checksums and clock sync.

    from jitdyn.client import AsyncClient, SessionOptions, FrameData

    async with AsyncClient("127.0.0.1:50051") as c:
        async with await c.open_session(SessionOptions(model_name="pendulum_1", dt=0.05)) as s:
            r = await s.send_frame(FrameData(seq=0, t=0.0, qpos=[0.3], qvel=[0.0]))
            (await s.skip(1)).source      # Source.PREDICTED
            summary = await s.close()

Make the client inside a running event loop: a grpc.aio channel belongs to the loop it was made in.
Every call raises a `jitdyn.errors` exception for the status the server ends it with.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import time
import weakref
from collections.abc import AsyncIterator, Mapping, Sequence
from types import TracebackType
from typing import TYPE_CHECKING, Any, Self, TypeAlias, TypeVar, Unpack

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
from jitdyn.client._session import Received, SessionArguments, SessionCore
from jitdyn.client._transport import (
    END,
    RESUMABLE_CODES,
    End,
    auth_metadata,
    channel_options,
    explain_open_error,
    status_error,
    unbatched,
)
from jitdyn.client._transport import root_certificates as root_certificates_of
from jitdyn.errors import FailedPrecondition, JitdynError, NoAnswer, error_for_status
from jitdyn.v1 import (
    dynamics_pb2,
    dynamics_pb2_grpc,
    model_registry_pb2,
    model_registry_pb2_grpc,
    session_pb2,
    session_pb2_grpc,
)

if TYPE_CHECKING:
    # The async stubs exist for type checkers only; at run time the sync stub class builds them.
    from jitdyn.v1.dynamics_pb2_grpc import DynamicsServiceAsyncStub

__all__ = ["AsyncClient", "AsyncSession"]

_Request = TypeVar("_Request")
_Response = TypeVar("_Response")
_Received: TypeAlias = Received
_First: TypeAlias = _Received | grpc.RpcError | End | None
_Call: TypeAlias = (
    "grpc.aio.StreamStreamCall[dynamics_pb2.StreamSessionRequest, dynamics_pb2.StreamSessionResponse]"
)


class AsyncSession(SessionCore):
    """One open session, from `await AsyncClient.open_session(...)`. Use as an async context
    manager; `close()` is safe to call twice.

    LOCKSTEP: `send_frame` and `skip` return the server's one answer. REALTIME: `send` writes a frame
    without waiting for its answer, and `async for answer in session.results()` gives answers as
    they arrive, among them the `SyncSample`s of the clock probes the session sends by itself (at
    open, then every `sync_interval` seconds with the frames).

    Resumption is the sync `Session`'s (`ResumePolicy`, `resumptions`, `missed`, `unacknowledged`),
    run by the session's reader task: when the stream breaks it opens the session again and
    re-sends what is not durable while writes wait, so the caller sees no error and no answer twice.
    """

    _call: _Call  # the current stream, from `_open` on

    def __init__(
        self,
        stub: DynamicsServiceAsyncStub,
        options: SessionOptions,
        *,
        connections: _AsyncConnections | None = None,
        **arguments: Unpack[SessionArguments],
    ) -> None:
        super().__init__(options, **arguments)
        self._connections = connections  # a new connection for each resume attempt (None: the same one)
        self._trial: asyncio.Task[None] | None = None  # a move being tried (see `_try_move`)
        self._stub = stub
        self._open_request = dynamics_pb2.StreamSessionRequest(open=self._open_message)
        self._responses: asyncio.Queue[_Received | JitdynError | End] = asyncio.Queue()
        # Writes one at a time, as grpc.aio allows; a resume holds it until it has re-sent.
        self._write_lock = asyncio.Lock()
        self._close_lock = asyncio.Lock()
        self._close_sent = False  # `close` and the half-close are written: a resume writes them again
        self._write_refused = False  # a write on the current stream failed (see `_broken`)
        self._reader: asyncio.Task[None] | None = None

    async def _open(self) -> None:
        try:
            first = await self._open_stream(self._open_request, self._timeout)
            if first is None:
                raise NoAnswer(f"no answer from the server within {self._timeout} s")
            if isinstance(first, grpc.RpcError):
                raise explain_open_error(status_error(first))
            if first is END:
                raise FailedPrecondition("the session stream has ended")
            self._opened(first)
        except BaseException:
            self.cancel()
            raise
        # Reads as responses arrive, not as the caller asks: a pong's receive time is its arrival.
        self._reader = asyncio.create_task(self._run(), name="jitdyn-session-reader")
        if self._realtime:
            await self.sync()

    # Plumbing.

    async def _open_stream(self, request: dynamics_pb2.StreamSessionRequest, timeout: float | None) -> _First:
        """A new stream that begins with `request` (an open), and its first answer, read here before
        the reader takes the stream over; None when none came within `timeout`."""
        self._call = call = self._stub.StreamSession(metadata=self._metadata)
        first, self._write_refused = await _first_answer(call, request, timeout)
        return first

    async def _run(self) -> None:
        """The session's reader: every stream's answers into the queue, a resume between streams,
        and the session's end (its error, if any, then END)."""
        try:
            while True:
                call = self._call
                ended = await self._read(call)
                if isinstance(ended, grpc.RpcError) and self._trial is not None:
                    # It may have broken because the move being tried took the session from it.
                    with contextlib.suppress(Exception):
                        await asyncio.wait_for(asyncio.shield(self._trial), self._ledger.policy.open_timeout)
                if call is not self._call:
                    continue  # a move left that stream: read the one it moved to
                if ended is None:
                    return
                if isinstance(ended, grpc.RpcError):
                    cause = self._broken(ended)
                    if cause is None:
                        self._fail(status_error(ended))
                        return
                    self._call.cancel()  # a write waiting on the broken stream gives the lock up
                    async with self._write_lock:
                        resumed = await self._resume(cause)
                else:
                    error = self._ledger.moving(ended)
                    if error is not None:
                        self._fail(error)
                        return
                    if self._trial is None:
                        self._trial = asyncio.create_task(self._try_move(f"moving: {ended.reason}"))
                    continue  # this stream answers on meanwhile
                if not resumed:
                    return
        finally:
            self._responses.put_nowait(END)

    async def _read(self, call: _Call) -> grpc.RpcError | dynamics_pb2.Moving | None:
        """One stream's answers into the queue, until it ends (None), breaks, or says `moving`."""
        try:
            while True:
                message = await call.read()
                if not isinstance(message, dynamics_pb2.StreamSessionResponse):
                    return None  # grpc.aio.EOF
                received_at = time.monotonic()
                for response in unbatched(message):
                    self._pong(received_at, response)
                    kind = response.WhichOneof("payload")
                    if kind == "moving":
                        return response.moving
                    elif kind == "overloaded":
                        self._ledger.warned(response.overloaded)
                    elif kind != "result" or self._ledger.fresh(response.result, current=call is self._call):
                        self._responses.put_nowait((received_at, response))
        except grpc.RpcError as error:
            return error
        except asyncio.CancelledError:
            task = asyncio.current_task()
            if call is not self._call and task is not None and not task.cancelling():
                return None  # a move cancelled the stream it left, not this task
            raise

    async def _try_move(self, cause: str) -> None:
        """Open the session elsewhere while the current stream answers on (make before break):
        moved once another replica has taken it, re-sending what is not durable there; when none
        takes it now (the index is down for all of them too), the current stream goes on."""
        try:
            policy = self._ledger.policy
            started = time.monotonic()
            stub = self._connections.trial() if self._connections is not None else self._stub
            call: _Call = stub.StreamSession(metadata=self._metadata)
            first, refused_write = await _first_answer(
                call, self._ledger.resume_request(), policy.open_timeout
            )
            outcome = resume_outcome(first, open_timeout=policy.open_timeout)
            if isinstance(outcome, Refused):
                self._ledger.refused(0, outcome)
                call.cancel()
                if self._connections is not None:
                    self._connections.adopt(moved=False)
                return
            async with self._write_lock:
                left, self._call, self._stub, self._write_refused = self._call, call, stub, refused_write
                left.cancel()
                if self._connections is not None:
                    self._connections.adopt(moved=True)
                resumed = self._ledger.resumed(outcome, cause=cause, attempts=1, started=started)
                try:
                    await self._resend(resumed)
                except JitdynError as error:
                    self._fail(error)
        finally:
            self._trial = None

    def _fail(self, error: JitdynError) -> None:
        """The session is over with `error`: the caller's next read raises it."""
        self._responses.put_nowait(error)
        self._finish()

    async def _resume(self, cause: str) -> bool:
        """Open the session again through the same target, re-send what is not durable, go on;
        False when every attempt failed (the session is lost). The caller holds the write lock, so
        that nothing is written until the frames not durable are re-sent."""
        policy = self._ledger.policy
        started = time.monotonic()
        if self._trial is not None:
            self._trial.cancel()
        self._call.cancel()
        last = cause
        for attempt in range(policy.attempts):
            await asyncio.sleep(policy.backoff(attempt))
            if self._connections is not None:
                self._stub = self._connections.reconnect()
            first = await self._open_stream(self._ledger.resume_request(), policy.open_timeout)
            outcome = resume_outcome(first, open_timeout=policy.open_timeout)
            if isinstance(outcome, Refused):
                self._ledger.refused(attempt, outcome)
                last = outcome.reason
                self._call.cancel()
                if outcome.retry:
                    continue
                break
            resumed = self._ledger.resumed(outcome, cause=cause, attempts=attempt + 1, started=started)
            try:
                await self._resend(resumed)
            except JitdynError as error:  # the new stream ended in a way no resume mends
                self._fail(error)
                return False
            return True
        self._fail(self._ledger.lost(cause, last))
        return False

    async def _resend(self, requests: list[dynamics_pb2.StreamSessionRequest]) -> None:
        """After a resume: the frames not durable, then the close if the caller had closed, or a
        clock probe for the new server; the caller holds the write lock."""
        for request in requests:
            await self._write(request)
        if self._close_sent:
            await self._write(dynamics_pb2.StreamSessionRequest(close=dynamics_pb2.CloseSession()))
            await self._write(None)
        elif self._realtime and not self._closed:
            await self._write(self._probe())

    async def _reader_done(self, timeout: float = 5.0) -> None:
        if self._reader is None:
            return
        await asyncio.wait({self._reader}, timeout=timeout)
        if self._reader.done() and not self._reader.cancelled():
            self._reader.exception()  # retrieved, so asyncio does not log it; the queue carries errors

    async def _get(self, timeout: float | None) -> _Received | None:
        """The next answer; None once the session has ended. Raises the session's error, or
        NoAnswer after `timeout`."""
        try:
            item = await asyncio.wait_for(self._responses.get(), timeout)
        except TimeoutError:
            raise NoAnswer(f"no answer from the server within {timeout} s") from None
        if isinstance(item, JitdynError):
            self._responses.put_nowait(END)
            raise item
        if item is END:
            self._responses.put_nowait(END)
            return None
        return item

    async def _send(self, request: dynamics_pb2.StreamSessionRequest, seq: int | None = None) -> None:
        if self._closed:
            raise FailedPrecondition("the session is closed")
        async with self._write_lock:
            if seq is not None:
                self._ledger.keep(seq, request)
            await self._write(request)

    async def _write(self, request: dynamics_pb2.StreamSessionRequest | None) -> None:
        """Write `request` on the current stream, or end its requests (half-close) for None; the
        caller holds the write lock. On a stream broken in a way a resume mends this says nothing:
        the reader resumes and re-sends what the ledger keeps."""
        call = self._call
        try:
            if request is None:
                await call.done_writing()
            else:
                await call.write(request)
        except grpc.RpcError as error:
            # Core refused the write because the stream has ended, and grpc.aio put INTERNAL in
            # place of the status it ended with, which the reader may read (see `_broken`).
            self._write_refused = True
            if not self._resumable():
                raise status_error(error) from None
        except asyncio.InvalidStateError:
            # The stream has already ended: say how, as a read would.
            code = await call.code()
            if code == grpc.StatusCode.OK:
                raise FailedPrecondition("the session stream has ended") from None
            if not (self._resumable() and (code in RESUMABLE_CODES or self._write_refused)):
                raise error_for_status(code, await call.details()) from None

    def _resumable(self) -> bool:
        return not self._finished and self._ledger.active

    def _broken(self, error: grpc.RpcError) -> str | None:
        """Why a resume may mend the current stream, which ended with `error`; None if none may.
        After a write Core refused, INTERNAL stands for a status nobody saw: the resume's open
        finds out whether the session goes on."""
        if self._write_refused and error.code() == grpc.StatusCode.INTERNAL:
            return "the stream ended under a write (grpc.aio hides how)" if self._resumable() else None
        return f"{error.code().name}: {error.details()}" if self._ledger.resumable(error.code()) else None

    # LOCKSTEP.

    async def send_frame(self, frame: FrameData) -> TickResult | Rejection:
        """Send one frame and wait for its answer (LOCKSTEP)."""
        await self.send(frame)
        return await self._answer()

    async def skip(self, seq: int) -> TickResult | Rejection:
        """Tell the server tick `seq` had no frame; returns the PREDICTED result (LOCKSTEP)."""
        await self._send(dynamics_pb2.StreamSessionRequest(skip=dynamics_pb2.Skip(seq=seq)), seq)
        return await self._answer()

    async def _answer(self) -> TickResult | Rejection:
        while True:
            item = await self._get(self._timeout)
            if item is None:
                raise FailedPrecondition("the session stream ended before the answer")
            answer = self._convert(item)
            if isinstance(answer, (TickResult, Rejection)):
                return answer

    # REALTIME (and LOCKSTEP, for callers that pipeline).

    async def send(self, frame: FrameData) -> None:
        """Write a frame without waiting for its answer. In REALTIME a clock probe goes along every
        `sync_interval` seconds, so the server keeps client time on its clock."""
        if self._sync_due():
            await self.sync()
        await self._send(self._frame_request(frame), frame.seq)

    async def results(
        self, *, timeout: float | None = None
    ) -> AsyncIterator[TickResult | Rejection | SyncSample]:
        """Answers as they arrive, until the session is closed or `timeout` passes with none
        (after `close`: those that arrived while it waited for the summary)."""
        for kept in self._take_unread():
            yield kept
        while True:
            try:
                item = await self._get(timeout)
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
        while not self._responses.empty():
            item = self._responses.get_nowait()
            if item is END or isinstance(item, JitdynError):
                self._responses.put_nowait(END)
                if isinstance(item, JitdynError):
                    raise item
                return answers
            answer = self._convert(item)
            if not isinstance(answer, Summary):
                answers.append(answer)
        return answers

    async def sync(self) -> None:
        """Send a clock probe; its answer comes back among the results (a `SyncSample`)."""
        if self._closed:
            raise FailedPrecondition("the session is closed")
        async with self._write_lock:
            # Stamped once the write may go: a probe that waited for a resume to re-send, stamped
            # before, would tell the server a send time the wait earlier than it was.
            await self._write(self._probe())

    # Ending.

    async def close(self) -> Summary:
        """Close the session; returns its summary (where it is stored, counts)."""
        async with self._close_lock:  # a second close waits for the first one's summary
            if self.summary is not None:
                return self.summary
            if self._closed:
                raise FailedPrecondition("the session ended without a summary")
            self._closed = True
            async with self._write_lock:
                await self._write(dynamics_pb2.StreamSessionRequest(close=dynamics_pb2.CloseSession()))
                await self._write(None)
                self._close_sent = True
            while self.summary is None:
                item = await self._get(self._timeout)
                if item is None:
                    # results() in another task may have read the summary just before the end.
                    if self.summary is None:
                        self._finish()
                        raise FailedPrecondition("the session stream ended without a summary")
                    break
                self._read_while_closing(item)
            await self._reader_done()
            self._finish()
            return self.summary

    def cancel(self) -> None:
        """Drop the stream without closing (the server stores the session as ABANDONED, or as
        RECOVERED when it was resumable and nobody resumes it)."""
        self._closed = True
        self._ledger.stop()
        self._call.cancel()
        if self._reader is not None:
            self._reader.cancel()
        self._finish()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is None:
            await self.close()
        elif not self._closed:
            self.cancel()
            await self._reader_done()


async def _first_answer(
    call: _Call, request: dynamics_pb2.StreamSessionRequest, timeout: float | None
) -> tuple[_First, bool]:
    """Write `request` (an open) on `call` and read its first answer (None: none within `timeout`
    s); and whether the write was refused (see `AsyncSession._broken`)."""
    refused = False
    try:
        await call.write(request)  # a refusal shows in the read that follows
    except grpc.RpcError:
        refused = True
    except asyncio.InvalidStateError:
        pass
    try:
        response = await asyncio.wait_for(call.read(), timeout)
    except TimeoutError:
        return None, refused
    except grpc.RpcError as error:
        if refused and error.code() == grpc.StatusCode.INTERNAL:
            return END, refused  # the stream ended under the write, and grpc.aio hides how
        return error, refused
    if not isinstance(response, dynamics_pb2.StreamSessionResponse):
        return END, refused  # grpc.aio.EOF
    return (time.monotonic(), response), refused


class _AsyncConnections:
    """The connections of one session when each has its own: the current stream's, and one a move
    is tried on (make before break). See the sync client's `_Connections`."""

    def __init__(self, client: AsyncClient) -> None:
        self._client = client
        self._current: grpc.aio.Channel | None = None
        self._trial: grpc.aio.Channel | None = None

    def _open(self) -> grpc.aio.Channel:
        channel = self._client._new_channel(shared=False)
        self._client._session_channels.add(channel)
        return channel

    def _drop(self, channel: grpc.aio.Channel | None) -> None:
        if channel is None or channel not in self._client._session_channels:
            return
        self._client._session_channels.discard(channel)
        task = asyncio.ensure_future(channel.close())
        self._client._closing.add(task)
        task.add_done_callback(self._client._closing.discard)

    def first(self) -> DynamicsServiceAsyncStub:
        self._current = self._open()
        return dynamics_pb2_grpc.DynamicsServiceStub(self._current)

    def reconnect(self) -> DynamicsServiceAsyncStub:
        """The current connection closed, a new one current (break before make)."""
        self.close()
        return self.first()

    def trial(self) -> DynamicsServiceAsyncStub:
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


class AsyncClient:
    """A connection to a jitdyn server over grpc.aio. Keyword-only options beyond the address."""

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
        """`channel_options`: gRPC channel arguments added to the SDK's own, as `Client` takes them.
        `resume`: how sessions resume by themselves when their stream breaks (`ResumePolicy`);
        False turns it off. TLS: `ca_file`, a PEM file of the CA that signed the server's (or its
        balancer's) certificate, or the same as bytes in `root_certificates`; neither: plaintext."""
        self._address = address
        self._channel_options = tuple(channel_options)
        self._resume = resume if isinstance(resume, ResumePolicy) else ResumePolicy(enabled=resume)
        # TLS when given roots to trust: the server's (or its balancer's) CA, as bytes or a PEM file.
        self._root_certificates = root_certificates_of(root_certificates, ca_file)
        self._channel = self._new_channel(shared=True)
        # See Client: each session on its own connection, so that `jitdyn serve --processes N`
        # spreads them over its processes.
        self._connection_per_session = connection_per_session
        self._session_channels: set[grpc.aio.Channel] = set()
        self._closing: set[asyncio.Task[None]] = set()
        # Sessions end with the client, and are not resumed: their reader would reconnect.
        self._open_sessions: weakref.WeakSet[AsyncSession] = weakref.WeakSet()
        self._metadata = auth_metadata(api_key)
        self._timeout = timeout
        self._checksum = checksum
        self._closed = False
        self._registry = model_registry_pb2_grpc.ModelRegistryServiceStub(self._channel)
        self._dynamics = dynamics_pb2_grpc.DynamicsServiceStub(self._channel)
        self._sessions = session_pb2_grpc.SessionServiceStub(self._channel)

    async def wait_ready(self, timeout: float = 10.0) -> None:
        """Wait until the server answers, or raise Unavailable."""
        try:
            await asyncio.wait_for(self._channel.channel_ready(), timeout)
        except TimeoutError:
            raise error_for_status(
                grpc.StatusCode.UNAVAILABLE, f"no jitdyn server answered within {timeout} s"
            ) from None

    async def _unary(
        self, method: grpc.aio.UnaryUnaryMultiCallable[_Request, _Response], request: _Request
    ) -> _Response:
        try:
            return await method(request, timeout=self._timeout, metadata=self._metadata)
        except grpc.RpcError as error:
            raise status_error(error) from None

    async def register_model(
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
        response = await self._unary(self._registry.RegisterModel, request)
        return ModelRef.from_message(response.model), response.created

    async def get_model(self, *, model_id: str = "", name: str = "", version: int = 0) -> ModelRef:
        return ModelRef.from_message(
            await self.get_model_message(model_id=model_id, name=name, version=version)
        )

    async def get_model_message(
        self, *, model_id: str = "", name: str = "", version: int = 0
    ) -> model_registry_pb2.Model:
        """The full `Model` message (joints with ranges, actuators, metadata)."""
        request = model_registry_pb2.GetModelRequest(model_id=model_id, name=name, version=version)
        return (await self._unary(self._registry.GetModel, request)).model

    async def list_models(
        self, *, name: str = "", tag: str = "", page_size: int = 0
    ) -> AsyncIterator[ModelRef]:
        """Every model matching the filters, page after page."""
        token = ""
        while True:
            request = model_registry_pb2.ListModelsRequest(
                page_size=page_size, page_token=token, name=name, tag=tag
            )
            page = await self._unary(self._registry.ListModels, request)
            for model in page.models:
                yield ModelRef.from_message(model)
            token = page.next_page_token
            if not token:
                return

    async def list_sessions(
        self, request: session_pb2.ListSessionsRequest | None = None
    ) -> AsyncIterator[session_pb2.Session]:
        """Every stored session matching the request's filters, newest first."""
        page_request = session_pb2.ListSessionsRequest()
        if request is not None:
            page_request.CopyFrom(request)
        while True:
            page = await self._unary(self._sessions.ListSessions, page_request)
            for session in page.sessions:
                yield session
            if not page.next_page_token:
                return
            page_request.page_token = page.next_page_token

    async def get_session(self, session_id: str) -> session_pb2.Session:
        return (
            await self._unary(self._sessions.GetSession, session_pb2.GetSessionRequest(session_id=session_id))
        ).session

    def _new_channel(self, *, shared: bool) -> grpc.aio.Channel:
        # gRPC shares one connection between channels of the same target and arguments unless a
        # channel asks for its own subchannel pool.
        base = channel_options(self._channel_options)
        options = base if shared else (*base, ("grpc.use_local_subchannel_pool", 1))
        if self._root_certificates is not None:
            return grpc.aio.secure_channel(
                self._address, grpc.ssl_channel_credentials(self._root_certificates), options=options
            )
        return grpc.aio.insecure_channel(self._address, options=options)

    async def open_session(self, options: SessionOptions) -> AsyncSession:
        """Open a session; raises the server's error (InvalidArgument, NotFound, ...) if it refuses."""
        stub: DynamicsServiceAsyncStub = self._dynamics
        connections = None
        if self._connection_per_session:
            connections = _AsyncConnections(self)
            stub = connections.first()
        session = AsyncSession(
            stub,
            options,
            timeout=self._timeout,
            metadata=self._metadata,
            checksum=self._checksum,
            on_end=connections.close if connections is not None else None,
            resume=self._resume,
            connections=connections,
        )
        await session._open()
        self._open_sessions.add(session)
        return session

    async def close(self) -> None:
        """Close the connections (open sessions end with them); safe to call twice."""
        if not self._closed:
            self._closed = True
            for session in list(self._open_sessions):
                if not session._finished:
                    session.cancel()
            channels, self._session_channels = self._session_channels, set()
            await asyncio.gather(self._channel.close(), *(c.close() for c in channels), *self._closing)

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.close()
