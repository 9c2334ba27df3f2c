"""The suite's side of the wire: a channel with its credentials, a session stream read with time
limits, and the contract's two hashes recomputed from proto/'s words (the frame checksum and the
model's content id), so that a server is checked against the contract, not against jitdyn's code.

    with Connection(Target("127.0.0.1:50051", api_key=None)) as wire:
        with wire.stream() as stream:
            stream.send(open=v1.OpenSession(model_id=model_id, dt=0.01))
            opened = stream.expect("opened")
"""

from __future__ import annotations

import hashlib
import queue
import struct
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final, Self

import google_crc32c
import grpc

from jitdyn.v1 import dynamics_pb2 as v1
from jitdyn.v1 import dynamics_pb2_grpc, model_registry_pb2_grpc, session_pb2_grpc

__all__ = [
    "CHANNELS",
    "CaseFailed",
    "Connection",
    "Ended",
    "Stream",
    "Target",
    "content_id",
    "frame_checksum",
]

# The order of a frame's channels in its checksummed bytes (Frame.checksum).
CHANNELS: Final = ("qpos", "qvel", "qacc", "ctrl", "sensordata")
# Large enough for the oversized-model case's request.
_MAX_MESSAGE_BYTES: Final = 64 * 1024 * 1024
_END: Final = object()


class CaseFailed(AssertionError):
    """The server broke the contract: what was expected and what arrived."""


@dataclass(frozen=True)
class Target:
    """The server under test and how to reach it."""

    address: str
    api_key: str | None = None
    ca_file: Path | None = None

    def metadata(self, key: str | None = "") -> tuple[tuple[str, str], ...]:
        """The call metadata: `authorization: Bearer KEY` with the target's key ("" default) or `key`."""
        chosen = self.api_key if key == "" else key
        return (("authorization", f"Bearer {chosen}"),) if chosen else ()


@dataclass(frozen=True)
class Ended:
    """How a stream ended: its status code and details."""

    code: grpc.StatusCode
    details: str


def frame_checksum(seq: int, t: float, channels: Mapping[str, Sequence[float]]) -> int:
    """CRC32C of Frame.checksum's canonical bytes: seq u64, t f64, then per channel in CHANNELS
    order its length u32 and its values f64, all little-endian."""
    parts = [struct.pack("<Qd", seq, t)]
    for name in CHANNELS:
        values = list(channels.get(name, ()))
        parts.append(struct.pack(f"<I{len(values)}d", len(values), *values))
    return int(google_crc32c.value(b"".join(parts)))


def content_id(mjcf: str, assets: Mapping[str, bytes]) -> str:
    """Model.id: "sha256:" and the hex SHA-256 of len(mjcf) mjcf n, then per asset in order of its
    UTF-8 name bytes len(name) name len(data) data, every integer a u64 big-endian."""
    digest = hashlib.sha256()

    def field(data: bytes) -> None:
        digest.update(struct.pack(">Q", len(data)))
        digest.update(data)

    field(mjcf.encode("utf-8"))
    digest.update(struct.pack(">Q", len(assets)))
    for name in sorted(assets, key=lambda n: n.encode("utf-8")):
        field(name.encode("utf-8"))
        field(assets[name])
    return f"sha256:{digest.hexdigest()}"


class Stream:
    """One StreamSession call: requests put on a queue, answers read by a thread, so that every
    read has a time limit and a stream that ends is told apart from one that is silent."""

    def __init__(
        self, stub: dynamics_pb2_grpc.DynamicsServiceStub, *, metadata: Any, deadline: float
    ) -> None:
        self._requests: queue.Queue[object] = queue.Queue()
        self._answers: queue.Queue[v1.StreamSessionResponse | Ended] = queue.Queue()
        self._call = stub.StreamSession(self._outgoing(), metadata=metadata, timeout=deadline)
        self.ended: Ended | None = None
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _outgoing(self) -> Iterator[v1.StreamSessionRequest]:
        while (request := self._requests.get()) is not _END:
            assert isinstance(request, v1.StreamSessionRequest)  # only send() puts requests
            yield request

    def _read(self) -> None:
        try:
            for answer in self._call:
                self._answers.put(answer)
        except grpc.RpcError as error:
            self._answers.put(Ended(error.code(), error.details() or ""))
            return
        self._answers.put(Ended(grpc.StatusCode.OK, ""))

    def send(self, **payload: Any) -> None:
        """One request: send(frame=v1.Frame(...)), send(close=v1.CloseSession()), ..."""
        self._requests.put(v1.StreamSessionRequest(**payload))

    def poll(self, timeout: float) -> v1.StreamSessionResponse | Ended | None:
        """The next answer, how the stream ended, or None when nothing came within `timeout`;
        notices (moving, overloaded) are passed over."""
        if self.ended is not None:
            return self.ended
        deadline = time.monotonic() + timeout
        while True:
            try:
                answer = self._answers.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                return None
            if isinstance(answer, Ended):
                self.ended = answer
                return answer
            if answer.WhichOneof("payload") not in ("moving", "overloaded"):
                return answer

    def receive(self, timeout: float = 10.0) -> v1.StreamSessionResponse | Ended:
        """As `poll`, but nothing within `timeout` is a failure."""
        answer = self.poll(timeout)
        if answer is None:
            raise CaseFailed(f"no answer within {timeout:g} s")
        return answer

    def expect(self, kind: str, timeout: float = 10.0, *, passing: tuple[str, ...] = ()) -> Any:
        """The next answer, which must be a `kind` ("opened", "result", ...), past any of the kinds
        `passing` (REALTIME results that come meanwhile); its payload."""
        while True:
            answer = self.receive(timeout)
            if isinstance(answer, Ended):
                raise CaseFailed(f"expected {kind}, the stream ended {answer.code.name}: {answer.details}")
            got = answer.WhichOneof("payload")
            if got != kind and got in passing:
                continue
            if got != kind:
                raise CaseFailed(f"expected {kind}, got {got}: {_short(getattr(answer, str(got)))}")
            return getattr(answer, kind)

    def expect_end(self, timeout: float = 10.0) -> Ended:
        """How the stream ends; any answer before the end is a failure."""
        answer = self.receive(timeout)
        if not isinstance(answer, Ended):
            raise CaseFailed(f"expected the stream to end, got {answer.WhichOneof('payload')}")
        return answer

    def half_close(self) -> None:
        self._requests.put(_END)

    def cancel(self) -> None:
        self._call.cancel()

    def close(self) -> None:
        """End the call (a half-close, then a cancel) and its reader; safe twice."""
        self.half_close()
        self._call.cancel()
        self._reader.join(timeout=5.0)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _short(message: Any) -> str:
    text = " ".join(str(message).split())
    return text if len(text) <= 160 else text[:157] + "..."


class Connection:
    """A channel to the target and its three services' stubs."""

    def __init__(self, target: Target) -> None:
        self.target = target
        options = [
            ("grpc.max_send_message_length", _MAX_MESSAGE_BYTES),
            ("grpc.max_receive_message_length", _MAX_MESSAGE_BYTES),
        ]
        if target.ca_file is not None:
            credentials = grpc.ssl_channel_credentials(root_certificates=target.ca_file.read_bytes())
            self.channel = grpc.secure_channel(target.address, credentials, options=options)
        else:
            self.channel = grpc.insecure_channel(target.address, options=options)
        self.registry = model_registry_pb2_grpc.ModelRegistryServiceStub(self.channel)
        self.dynamics = dynamics_pb2_grpc.DynamicsServiceStub(self.channel)
        self.sessions = session_pb2_grpc.SessionServiceStub(self.channel)

    def ready(self, timeout: float) -> None:
        """Wait for the channel to connect; CaseFailed naming the address when it does not."""
        try:
            grpc.channel_ready_future(self.channel).result(timeout=timeout)
        except grpc.FutureTimeoutError:
            raise CaseFailed(
                f"no gRPC server answers at {self.target.address} within {timeout:g} s"
            ) from None

    def stream(self, *, key: str | None = "", deadline: float = 60.0) -> Stream:
        return Stream(self.dynamics, metadata=self.target.metadata(key), deadline=deadline)

    def call(self, method: Any, request: Any, *, key: str | None = "", timeout: float = 30.0) -> Any:
        """A unary call with the target's credentials (or `key`, None: none)."""
        return method(request, metadata=self.target.metadata(key), timeout=timeout)

    def status_of(self, method: Any, request: Any, *, key: str | None = "", timeout: float = 30.0) -> Ended:
        """The status a unary call ends with (OK when it answers)."""
        try:
            self.call(method, request, key=key, timeout=timeout)
        except grpc.RpcError as error:
            return Ended(error.code(), error.details() or "")
        return Ended(grpc.StatusCode.OK, "")

    def close(self) -> None:
        self.channel.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
