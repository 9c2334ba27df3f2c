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

import queue
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from types import TracebackType
from typing import Self, TypeVar

import grpc

from jitdyn.client._models import (
    FrameData,
    ModelRef,
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
from jitdyn.client._transport import CHANNEL_OPTIONS, END, End, auth_metadata, status_error
from jitdyn.errors import FailedPrecondition, NoAnswer, error_for_status
from jitdyn.lifecycle import Closeable
from jitdyn.v1 import (
    dynamics_pb2,
    dynamics_pb2_grpc,
    model_registry_pb2,
    model_registry_pb2_grpc,
    session_pb2,
    session_pb2_grpc,
)
from jitdyn.vocabulary import Clock

__all__ = ["Client", "Session"]

_Request = TypeVar("_Request")
_Response = TypeVar("_Response")


class Session:
    """One open session. Use as a context manager; `close()` is safe to call twice.

    LOCKSTEP: `send_frame` and `skip` return the server's one answer. REALTIME: `send` queues a frame
    without waiting, and `results()` or `poll()` give answers as they arrive, among them the
    `SyncSample`s of the clock probes the session sends by itself (at open, then every
    `sync_interval` seconds with the frames).
    """

    def __init__(
        self,
        stub: dynamics_pb2_grpc.DynamicsServiceStub,
        options: SessionOptions,
        *,
        timeout: float | None,
        metadata: Sequence[tuple[str, str]],
        checksum: bool,
        sync_interval: float = 0.5,
        on_end: Callable[[], None] | None = None,
    ) -> None:
        self._on_end = on_end  # called once the stream has ended: the client closes its connection
        self._requests: queue.Queue[dynamics_pb2.StreamSessionRequest | End] = queue.Queue()
        self._responses: queue.Queue[
            tuple[float, dynamics_pb2.StreamSessionResponse] | grpc.RpcError | End
        ] = queue.Queue()
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
        open_request = dynamics_pb2.StreamSessionRequest(open=options.to_message())
        self._requests.put(open_request)
        self._call = stub.StreamSession(self._request_iterator(), metadata=tuple(metadata))
        self._reader = threading.Thread(target=self._read, name="jitdyn-session-reader", daemon=True)
        self._reader.start()
        first = self._get(self._timeout)
        if first is None:
            raise FailedPrecondition("the session stream has ended")
        opened = opened_from_response(first[1])
        # The session clock starts when `opened` arrived (the reader's time of it, not the time
        # this thread got to it): the server's starts as it sends it, so the two differ by one
        # transit until `sync` exchanges measure the offset.
        self._clock_start = first[0]
        self.opened = opened
        if self._realtime:
            self.sync()

    # Plumbing.

    def _request_iterator(self) -> Iterator[dynamics_pb2.StreamSessionRequest]:
        while True:
            item = self._requests.get()
            if item is END:
                return
            yield item

    def _read(self) -> None:
        try:
            for response in self._call:
                received_at = time.monotonic()
                if response.HasField("sync"):
                    # t4 of this exchange, reported by the next probe however late the caller reads it.
                    self._last_probe = (response.sync.id, received_at - self._clock_start)
                self._responses.put((received_at, response))
        except grpc.RpcError as error:
            self._responses.put(error)
        finally:
            self._responses.put(END)
            if self._on_end is not None:
                self._on_end()

    def _next_response(self, timeout: float | None) -> dynamics_pb2.StreamSessionResponse:
        item = self._get(timeout)
        if item is None:
            raise FailedPrecondition("the session stream has ended")
        return item[1]

    def _get(self, timeout: float | None) -> tuple[float, dynamics_pb2.StreamSessionResponse] | None:
        try:
            item = self._responses.get(timeout=timeout)
        except queue.Empty:
            raise NoAnswer(f"no answer from the server within {timeout} s") from None
        if item is END:
            self._responses.put(END)
            return None
        if isinstance(item, grpc.RpcError):
            self._responses.put(END)
            raise status_error(item)
        return item

    def _convert(
        self, item: tuple[float, dynamics_pb2.StreamSessionResponse]
    ) -> TickResult | Rejection | SyncSample | Summary:
        received_at, response = item
        answer = session_answer(response, received_at=received_at, clock_start=self._clock_start)
        if isinstance(answer, Summary):
            self.summary = answer
        return answer

    def _send(self, request: dynamics_pb2.StreamSessionRequest) -> None:
        if self._closed:
            raise FailedPrecondition("the session is closed")
        self._requests.put(request)

    @property
    def clock_start(self) -> float:
        """The time.monotonic() value that is 0 on the session clock."""
        return self._clock_start

    def now(self) -> float:
        """The client's session clock: seconds since `opened` arrived. REALTIME frames are due at
        `seq * dt` on this clock."""
        return time.monotonic() - self._clock_start

    # LOCKSTEP.

    def send_frame(self, frame: FrameData) -> TickResult | Rejection:
        """Send one frame and wait for its answer (LOCKSTEP)."""
        self.send(frame)
        return self._answer()

    def skip(self, seq: int) -> TickResult | Rejection:
        """Tell the server tick `seq` had no frame; returns the PREDICTED result (LOCKSTEP)."""
        self._send(dynamics_pb2.StreamSessionRequest(skip=dynamics_pb2.Skip(seq=seq)))
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
        if self._realtime and self.now() - self._last_sync_sent >= self._sync_interval:
            self.sync()
        self._send(dynamics_pb2.StreamSessionRequest(frame=frame.to_message(checksum=self._checksum)))

    def results(self, *, timeout: float | None = None) -> Iterator[TickResult | Rejection | SyncSample]:
        """Answers as they arrive, until the session is closed or `timeout` passes with none."""
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
        """Every answer that has arrived, without waiting."""
        answers: list[TickResult | Rejection | SyncSample] = []
        while True:
            try:
                item = self._responses.get_nowait()
            except queue.Empty:
                return answers
            if item is END or isinstance(item, grpc.RpcError):
                self._responses.put(item)
                if isinstance(item, grpc.RpcError):
                    self._responses.get_nowait()
                    raise status_error(item)
                return answers
            answer = self._convert(item)
            if not isinstance(answer, Summary):
                answers.append(answer)

    def sync(self) -> None:
        """Send a clock probe; its answer comes back among the results (a `SyncSample`)."""
        self._probe_id += 1
        self._last_sync_sent = self.now()
        self._send(sync_request(self._probe_id, self._last_sync_sent, self._last_probe))

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
                raise FailedPrecondition("the session stream ended without a summary")
            self._convert(item)
        self._reader.join(timeout=5)
        return self.summary

    def cancel(self) -> None:
        """Drop the stream without closing (the server stores the session as ABANDONED)."""
        self._closed = True
        self._call.cancel()
        self._requests.put(END)

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is None:
            self.close()
        elif not self._closed:
            self.cancel()


class Client(Closeable):
    """A connection to a jitdyn server. Keyword-only options beyond the address."""

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
        options = CHANNEL_OPTIONS if shared else (*CHANNEL_OPTIONS, ("grpc.use_local_subchannel_pool", 1))
        if self._root_certificates is not None:
            return grpc.secure_channel(
                self._address, grpc.ssl_channel_credentials(self._root_certificates), options=options
            )
        return grpc.insecure_channel(self._address, options=options)

    def open_session(self, options: SessionOptions) -> Session:
        """Open a session; raises the server's error (InvalidArgument, NotFound, ...) if it refuses."""
        stub, ended = self._dynamics, None
        if self._connection_per_session:
            channel = self._new_channel(shared=False)
            with self._lock:
                self._session_channels.add(channel)
            stub = dynamics_pb2_grpc.DynamicsServiceStub(channel)

            def ended() -> None:
                with self._lock:
                    if channel not in self._session_channels:
                        return
                    self._session_channels.discard(channel)
                channel.close()

        try:
            return Session(
                stub,
                options,
                timeout=self._timeout,
                metadata=self._metadata,
                checksum=self._checksum,
                on_end=ended,
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
