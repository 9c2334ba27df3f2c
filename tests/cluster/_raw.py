"""A session over the raw generated stubs, for tests of what the server does on resumption,
fencing and draining (the SDK's own resumption is tested with the SDK)."""

from __future__ import annotations

import queue
import uuid
from collections.abc import Iterator
from importlib import resources

import grpc
import numpy as np
import sqlalchemy as sa

from jitdyn.v1 import common_pb2, dynamics_pb2, dynamics_pb2_grpc, model_registry_pb2

PENDULUM = (resources.files("jitdyn.models") / "pendulum_2.xml").read_text()
DT = 0.05


def open_message(mjcf: str, *, clock: int = common_pb2.CLOCK_LOCKSTEP) -> dynamics_pb2.OpenSession:
    """A 2-link pendulum, inline (every replica can then load it)."""
    return dynamics_pb2.OpenSession(
        inline_model=model_registry_pb2.RegisterModelRequest(name="pendulum_2_inline", mjcf=mjcf),
        dt=DT,
        clock=clock,
        outputs=[common_pb2.OUTPUT_INVERSE_DYNAMICS],
    )


def new_model() -> str:
    """The pendulum's MJCF with a comment of its own: content no replica has seen."""
    return f"<!-- {uuid.uuid4()} -->\n{PENDULUM}"


def frame(k: int) -> dynamics_pb2.Frame:
    return dynamics_pb2.Frame(
        seq=k, t=k * DT, qpos=[0.3 * np.cos(0.2 * k), 0.1 * np.sin(0.3 * k)], qvel=[0.0, 0.0]
    )


class RawSession:
    """One StreamSession: `send` requests, `next` responses."""

    def __init__(self, address: str, open_: dynamics_pb2.OpenSession, *, api_key: str | None = None) -> None:
        self.channel = grpc.insecure_channel(address)
        self._requests: queue.Queue[dynamics_pb2.StreamSessionRequest | None] = queue.Queue()
        stub = dynamics_pb2_grpc.DynamicsServiceStub(self.channel)
        metadata = [("authorization", f"Bearer {api_key}")] if api_key else None
        self._responses: Iterator[dynamics_pb2.StreamSessionResponse] = stub.StreamSession(
            iter(self._requests.get, None), metadata=metadata
        )
        self._requests.put(dynamics_pb2.StreamSessionRequest(open=open_))
        first = self.next()
        assert first.WhichOneof("payload") == "opened", first
        self.opened = first.opened
        self.moves: list[dynamics_pb2.Moving] = []  # `moving` notices, which this client ignores

    def next(self) -> dynamics_pb2.StreamSessionResponse:
        return next(self._responses)

    def send(self, k: int) -> dynamics_pb2.Result:
        """Frame `k`, answered (LOCKSTEP)."""
        self._requests.put(dynamics_pb2.StreamSessionRequest(frame=frame(k)))
        response = self.next()
        while response.WhichOneof("payload") == "moving":
            self.moves.append(response.moving)
            response = self.next()
        assert response.WhichOneof("payload") == "result", response
        return response.result

    def close(self) -> dynamics_pb2.SessionClosed:
        self._requests.put(dynamics_pb2.StreamSessionRequest(close=dynamics_pb2.CloseSession()))
        response = self.next()
        while response.WhichOneof("payload") == "moving":
            self.moves.append(response.moving)
            response = self.next()
        assert response.WhichOneof("payload") == "closed", response
        self._requests.put(None)
        return response.closed

    def drop(self) -> None:
        """End the stream without a close, as a client whose connection broke."""
        self._requests.put(None)
        self.channel.close()


def resume_message(
    mjcf: str, opened: dynamics_pb2.SessionOpened, token: str | None = None
) -> dynamics_pb2.OpenSession:
    message = open_message(mjcf, clock=common_pb2.CLOCK_LOCKSTEP)
    message.resume.session_id = opened.session_id
    message.resume.token = opened.resume_token if token is None else token
    return message


def session_row(index_url: str, session_id: str) -> dict[str, object] | None:
    """The session's row in the shared index, straight from PostgreSQL."""
    engine = sa.create_engine(index_url)
    try:
        with engine.connect() as conn:
            row = (
                conn.execute(
                    sa.text("SELECT status, location, ticks FROM sessions WHERE session_id = :id"),
                    {"id": session_id},
                )
                .mappings()
                .one_or_none()
            )
            return None if row is None else dict(row)
    finally:
        engine.dispose()
