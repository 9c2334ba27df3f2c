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
import time
from collections.abc import AsyncIterator, Callable, Mapping, Sequence
from types import TracebackType
from typing import TYPE_CHECKING, Self, TypeAlias, TypeVar

import grpc

from jitdyn.client._models import (
    FrameData,
    ModelRef,
    Opened,
    Rejection,
    SessionOptions,
    Summary,
    SyncSample,
    TickResult,
    opened_from_response,
    register_request,
    session_answer,
    sync_request,
)
from jitdyn.client._transport import (
    CHANNEL_OPTIONS,
    END,
    End,
    auth_metadata,
    explain_open_error,
    status_error,
)
from jitdyn.errors import FailedPrecondition, JitdynError, NoAnswer, error_for_status
from jitdyn.v1 import (
    dynamics_pb2,
    dynamics_pb2_grpc,
    model_registry_pb2,
    model_registry_pb2_grpc,
    session_pb2,
    session_pb2_grpc,
)
from jitdyn.vocabulary import Clock

if TYPE_CHECKING:
    # The async stubs exist for type checkers only; at run time the sync stub class builds them.
    from jitdyn.v1.dynamics_pb2_grpc import DynamicsServiceAsyncStub

__all__ = ["AsyncClient", "AsyncSession"]

_Request = TypeVar("_Request")
_Response = TypeVar("_Response")
_Received: TypeAlias = tuple[float, dynamics_pb2.StreamSessionResponse]


class AsyncSession:
    """One open session, from `await AsyncClient.open_session(...)`. Use as an async context
    manager; `close()` is safe to call twice.

    LOCKSTEP: `send_frame` and `skip` return the server's one answer. REALTIME: `send` writes a frame
    without waiting for its answer, and `async for answer in session.results()` gives answers as
    they arrive, among them the `SyncSample`s of the clock probes the session sends by itself (at
    open, then every `sync_interval` seconds with the frames).
    """

    opened: Opened

    def __init__(
        self,
        stub: DynamicsServiceAsyncStub,
        options: SessionOptions,
        *,
        timeout: float | None,
        metadata: Sequence[tuple[str, str]],
        checksum: bool,
        sync_interval: float = 0.5,
        on_end: Callable[[], None] | None = None,
    ) -> None:
        self._on_end = on_end  # called once the stream has ended: the client closes its connection
        self._open_request = dynamics_pb2.StreamSessionRequest(open=options.to_message())
        self._responses: asyncio.Queue[_Received | grpc.RpcError | End] = asyncio.Queue()
        self._write_lock = asyncio.Lock()
        self._close_lock = asyncio.Lock()
        self._timeout = timeout
        self._checksum = checksum
        self._clock_start = time.monotonic()
        self._last_probe: tuple[int, float] | None = None
        self._probe_id = 0
        self._realtime = options.clock == Clock.REALTIME
        self._sync_interval = sync_interval
        self._last_sync_sent = -float("inf")
        self._closed = False
        self.summary: Summary | None = None
        self._call = stub.StreamSession(metadata=tuple(metadata))
        # Reads as responses arrive, not as the caller asks: a pong's receive time is its arrival.
        self._reader = asyncio.create_task(self._read(), name="jitdyn-session-reader")

    async def _open(self) -> None:
        try:
            await self._write_now(self._open_request)
            try:
                first = await self._get(self._timeout)
            except JitdynError as error:
                raise explain_open_error(error) from None
            if first is None:
                raise FailedPrecondition("the session stream has ended")
            opened = opened_from_response(first[1])
        except BaseException:
            self.cancel()
            await self._reader_done()
            raise
        # The session clock starts when `opened` arrived (the reader's time of it): the server's
        # starts as it sends it, so the two differ by one transit until `sync` exchanges measure
        # the offset.
        self._clock_start = first[0]
        self.opened = opened
        if self._realtime:
            await self.sync()

    # Plumbing.

    async def _read(self) -> None:
        try:
            async for response in self._call:
                received_at = time.monotonic()
                if response.HasField("sync"):
                    # t4 of this exchange, reported by the next probe however late the caller reads it.
                    self._last_probe = (response.sync.id, received_at - self._clock_start)
                self._responses.put_nowait((received_at, response))
        except grpc.RpcError as error:
            self._responses.put_nowait(error)
        finally:
            self._responses.put_nowait(END)
            if self._on_end is not None:
                self._on_end()

    async def _reader_done(self, timeout: float = 5.0) -> None:
        await asyncio.wait({self._reader}, timeout=timeout)
        if self._reader.done() and not self._reader.cancelled():
            self._reader.exception()  # retrieved, so asyncio does not log it; the queue carries errors

    async def _wait(self, timeout: float | None) -> _Received | None:
        """The next response; None once the stream has ended. Raises TimeoutError after `timeout`."""
        item = await asyncio.wait_for(self._responses.get(), timeout)
        if item is END:
            self._responses.put_nowait(END)
            return None
        if isinstance(item, grpc.RpcError):
            self._responses.put_nowait(END)
            raise status_error(item)
        return item

    async def _get(self, timeout: float | None) -> _Received | None:
        try:
            return await self._wait(timeout)
        except TimeoutError:
            raise NoAnswer(f"no answer from the server within {timeout} s") from None

    async def _next_response(self, timeout: float | None) -> dynamics_pb2.StreamSessionResponse:
        item = await self._get(timeout)
        if item is None:
            raise FailedPrecondition("the session stream has ended")
        return item[1]

    def _convert(self, item: _Received) -> TickResult | Rejection | SyncSample | Summary:
        received_at, response = item
        answer = session_answer(response, received_at=received_at, clock_start=self._clock_start)
        if isinstance(answer, Summary):
            self.summary = answer
        return answer

    async def _send(self, request: dynamics_pb2.StreamSessionRequest) -> None:
        if self._closed:
            raise FailedPrecondition("the session is closed")
        await self._write_now(request)

    async def _write_now(self, request: dynamics_pb2.StreamSessionRequest | None) -> None:
        """Write `request`, or end the requests (half-close) for None; one write at a time, as
        grpc.aio allows."""
        async with self._write_lock:
            try:
                if request is None:
                    await self._call.done_writing()
                else:
                    await self._call.write(request)
            except grpc.RpcError as error:
                raise status_error(error) from None
            except asyncio.InvalidStateError:
                # The stream has already ended: say how, as a read would.
                code = await self._call.code()
                if code == grpc.StatusCode.OK:
                    raise FailedPrecondition("the session stream has ended") from None
                raise error_for_status(code, await self._call.details()) from None

    @property
    def clock_start(self) -> float:
        """The time.monotonic() value that is 0 on the session clock."""
        return self._clock_start

    def now(self) -> float:
        """The client's session clock: seconds since `opened` arrived. REALTIME frames are due at
        `seq * dt` on this clock."""
        return time.monotonic() - self._clock_start

    # LOCKSTEP.

    async def send_frame(self, frame: FrameData) -> TickResult | Rejection:
        """Send one frame and wait for its answer (LOCKSTEP)."""
        await self.send(frame)
        return await self._answer()

    async def skip(self, seq: int) -> TickResult | Rejection:
        """Tell the server tick `seq` had no frame; returns the PREDICTED result (LOCKSTEP)."""
        await self._send(dynamics_pb2.StreamSessionRequest(skip=dynamics_pb2.Skip(seq=seq)))
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
        if self._realtime and self.now() - self._last_sync_sent >= self._sync_interval:
            await self.sync()
        await self._send(dynamics_pb2.StreamSessionRequest(frame=frame.to_message(checksum=self._checksum)))

    async def results(
        self, *, timeout: float | None = None
    ) -> AsyncIterator[TickResult | Rejection | SyncSample]:
        """Answers as they arrive, until the session is closed or `timeout` passes with none."""
        while True:
            try:
                item = await self._wait(timeout)
            except TimeoutError:
                return
            if item is None:
                return
            answer = self._convert(item)
            if isinstance(answer, Summary):
                return
            yield answer

    def poll(self) -> list[TickResult | Rejection | SyncSample]:
        """Every answer that has arrived, without waiting."""
        answers: list[TickResult | Rejection | SyncSample] = []
        while not self._responses.empty():
            item = self._responses.get_nowait()
            if item is END or isinstance(item, grpc.RpcError):
                self._responses.put_nowait(END)
                if isinstance(item, grpc.RpcError):
                    raise status_error(item)
                return answers
            answer = self._convert(item)
            if not isinstance(answer, Summary):
                answers.append(answer)
        return answers

    async def sync(self) -> None:
        """Send a clock probe; its answer comes back among the results (a `SyncSample`)."""
        self._probe_id += 1
        self._last_sync_sent = self.now()
        await self._send(sync_request(self._probe_id, self._last_sync_sent, self._last_probe))

    # Ending.

    async def close(self) -> Summary:
        """Close the session; returns its summary (where it is stored, counts)."""
        async with self._close_lock:  # a second close waits for the first one's summary
            if self.summary is not None:
                return self.summary
            if self._closed:
                raise FailedPrecondition("the session ended without a summary")
            self._closed = True
            await self._write_now(dynamics_pb2.StreamSessionRequest(close=dynamics_pb2.CloseSession()))
            await self._write_now(None)
            while self.summary is None:
                item = await self._get(self._timeout)
                if item is None:
                    # results() in another task may have read the summary just before the end.
                    if self.summary is None:
                        raise FailedPrecondition("the session stream ended without a summary")
                    break
                self._convert(item)
            await self._reader_done()
            return self.summary

    def cancel(self) -> None:
        """Drop the stream without closing (the server stores the session as ABANDONED)."""
        self._closed = True
        self._call.cancel()

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


class AsyncClient:
    """A connection to a jitdyn server over grpc.aio. Keyword-only options beyond the address."""

    def __init__(
        self,
        address: str = "127.0.0.1:50051",
        *,
        timeout: float | None = 60.0,
        api_key: str | None = None,
        root_certificates: bytes | None = None,
        checksum: bool = True,
        connection_per_session: bool = True,
    ) -> None:
        self._address = address
        self._root_certificates = root_certificates
        self._channel = self._new_channel(shared=True)
        # See Client: each session on its own connection, so that `jitdyn serve --processes N`
        # spreads them over its processes.
        self._connection_per_session = connection_per_session
        self._session_channels: set[grpc.aio.Channel] = set()
        self._closing: set[asyncio.Task[None]] = set()
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
        options = CHANNEL_OPTIONS if shared else (*CHANNEL_OPTIONS, ("grpc.use_local_subchannel_pool", 1))
        if self._root_certificates is not None:
            return grpc.aio.secure_channel(
                self._address, grpc.ssl_channel_credentials(self._root_certificates), options=options
            )
        return grpc.aio.insecure_channel(self._address, options=options)

    async def open_session(self, options: SessionOptions) -> AsyncSession:
        """Open a session; raises the server's error (InvalidArgument, NotFound, ...) if it refuses."""
        if not self._connection_per_session:
            session = AsyncSession(
                self._dynamics,
                options,
                timeout=self._timeout,
                metadata=self._metadata,
                checksum=self._checksum,
            )
            await session._open()
            return session
        channel = self._new_channel(shared=False)
        self._session_channels.add(channel)

        def ended() -> None:
            if channel in self._session_channels:
                self._session_channels.discard(channel)
                task = asyncio.ensure_future(channel.close())
                self._closing.add(task)
                task.add_done_callback(self._closing.discard)

        session = AsyncSession(
            dynamics_pb2_grpc.DynamicsServiceStub(channel),
            options,
            timeout=self._timeout,
            metadata=self._metadata,
            checksum=self._checksum,
            on_end=ended,
        )
        await session._open()
        return session

    async def close(self) -> None:
        """Close the connections (open sessions end with them); safe to call twice."""
        if not self._closed:
            self._closed = True
            channels, self._session_channels = self._session_channels, set()
            await asyncio.gather(self._channel.close(), *(c.close() for c in channels), *self._closing)

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.close()
