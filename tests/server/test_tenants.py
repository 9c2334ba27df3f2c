"""API keys map callers to tenants: no key, no service; a tenant never sees another's sessions or
models; the health service stays open."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

from jitdyn.client import Client, FrameData, SessionOptions
from jitdyn.errors import InvalidArgument, NotFound, Unauthenticated
from jitdyn.server.transport.app import ServerConfig, create_server
from jitdyn.server.transport.background import BackgroundServer

KEY_A = "a" * 24
KEY_B = "b" * 24
SLIDER = '<mujoco><worldbody><body><joint name="x" type="slide"/><geom size=".1" mass="1"/></body></worldbody></mujoco>'


@pytest.fixture(scope="module")
def keyed_server(
    tmp_path_factory: pytest.TempPathFactory, make_config: Callable[..., Any]
) -> Iterator[BackgroundServer]:
    keys = tmp_path_factory.mktemp("keys") / "api-keys"
    keys.write_text(f"# key tenant\n{KEY_A} lab-a\n{KEY_B} lab-b\n")
    keys.chmod(0o600)
    with BackgroundServer(make_config(tmp_path_factory.mktemp("data"), api_keys=keys)) as running:
        yield running


def test_no_key_is_unauthenticated_but_health_answers(keyed_server: BackgroundServer) -> None:
    with Client(keyed_server.address) as anonymous:
        with pytest.raises(Unauthenticated, match="needs an API key"):
            list(anonymous.list_models())
        with pytest.raises(Unauthenticated):
            anonymous.open_session(SessionOptions(model_name="pendulum_1", dt=0.05))
    with Client(keyed_server.address, api_key="x" * 24) as wrong, pytest.raises(Unauthenticated):
        list(wrong.list_models())
    with grpc.insecure_channel(keyed_server.address) as channel:
        status = health_pb2_grpc.HealthStub(channel).Check(
            health_pb2.HealthCheckRequest(service="jitdyn.v1.DynamicsService")
        )
    assert status.status == health_pb2.HealthCheckResponse.SERVING


def test_tenants_see_only_their_own_sessions_and_models(keyed_server: BackgroundServer) -> None:
    with Client(keyed_server.address, api_key=KEY_A) as a, Client(keyed_server.address, api_key=KEY_B) as b:
        model, _ = a.register_model(name="slider", mjcf=SLIDER)
        with a.open_session(SessionOptions(model_name="pendulum_1", dt=0.05)) as session:
            session.send_frame(FrameData(seq=0, t=0.0, qpos=[0.1], qvel=[0.0]))
            session_id = session.opened.session_id
        assert [s.session_id for s in a.list_sessions()] == [session_id]
        assert a.get_session(session_id).status != 0
        assert list(b.list_sessions()) == []
        with pytest.raises(NotFound):
            b.get_session(session_id)
        with pytest.raises(NotFound):
            b.get_model(model_id=model.id)
        assert "slider" not in {m.name for m in b.list_models()}
        assert "pendulum_1" in {m.name for m in b.list_models()}  # built-ins are everyone's


def test_a_public_bind_needs_tls_and_keys(tmp_path: Path) -> None:
    config = ServerConfig(address="0.0.0.0:0", data_root=tmp_path, environ={"JITDYN_SECRET": "ab" * 32})
    import asyncio

    with pytest.raises(InvalidArgument, match="not a loopback address"):
        asyncio.run(create_server(config))
