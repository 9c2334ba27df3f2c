"""Helpers of the hostile-client suite (tests/hostile): abusive clients over real gRPC against a real `jitdyn serve` process.

Each test starts its own server (`serve(...)`, extra flags as arguments) on a loopback port 0, so
that what one abuse leaves behind (slots, threads, descriptors, memory) is measured on a process
nobody else touched. `Served.resources()` reads the server's threads, descriptors and RSS from /proc.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import grpc

from jitdyn.v1 import (
    common_pb2,
    dynamics_pb2,
    dynamics_pb2_grpc,
    model_registry_pb2,
    model_registry_pb2_grpc,
    session_pb2,
    session_pb2_grpc,
)

Request = dynamics_pb2.StreamSessionRequest


@dataclass(frozen=True)
class Resources:
    threads: int
    fds: int
    data_fds: int  # descriptors of files under the data folder but the index
    rss_mb: float
    hwm_mb: float


class Served:
    """`jitdyn serve` in a child process; its output goes to a file (a pipe could fill up)."""

    def __init__(self, data: Path, env: dict[str, str], args: list[str], *, output: Path) -> None:
        self.data = data
        self.output = output
        self._out = output.open("w")
        self.process = subprocess.Popen(
            [sys.executable, "-m", "jitdyn.cli", "serve", "--address", "127.0.0.1:0", "--data", str(data)]
            + ["--workers", "1", "--processes", "1", *args],
            stdout=self._out,
            stderr=subprocess.STDOUT,
            env=env,
        )
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            match = re.search(r"listening on (127\.0\.0\.1:\d+)", self.text())
            if match:
                self.address = match.group(1)
                self.channel = grpc.insecure_channel(self.address)
                self.dynamics = dynamics_pb2_grpc.DynamicsServiceStub(self.channel)
                self.registry = model_registry_pb2_grpc.ModelRegistryServiceStub(self.channel)
                self.sessions = session_pb2_grpc.SessionServiceStub(self.channel)
                return
            if self.process.poll() is not None:
                raise RuntimeError("the server exited early:\n" + self.text())
            time.sleep(0.05)
        raise RuntimeError("the server did not say where it listens:\n" + self.text())

    @property
    def pid(self) -> int:
        return self.process.pid

    def text(self) -> str:
        return self.output.read_text()

    def alive(self) -> bool:
        return self.process.poll() is None

    def resources(self) -> Resources:
        status = Path(f"/proc/{self.pid}/status").read_text()

        def field(name: str) -> int:
            match = re.search(rf"^{name}:\s+(\d+)", status, re.MULTILINE)
            assert match is not None
            return int(match.group(1))

        targets = []
        for fd in os.listdir(f"/proc/{self.pid}/fd"):
            try:
                targets.append(os.readlink(f"/proc/{self.pid}/fd/{fd}"))
            except FileNotFoundError:
                continue  # closed meanwhile
        data = str(self.data.resolve())
        return Resources(
            threads=field("Threads"),
            fds=len(targets),
            data_fds=sum(t.startswith(data) and "/index.sqlite" not in t for t in targets),
            rss_mb=field("VmRSS") / 1024,
            hwm_mb=field("VmHWM") / 1024,
        )

    def kill(self) -> None:
        self.channel.close()
        self.process.kill()
        self.process.wait(timeout=30)
        self._out.close()

    def stop(self) -> str:
        self.channel.close()
        if self.alive():
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self._out.close()
        return self.text()


def open_request(
    *,
    model: str = "pendulum_1",
    dt: float = 0.025,
    clock: str = "LOCKSTEP",
    history: int = 0,
    attributes: dict[str, str] | None = None,
    subject: str = "",
    estimator: str = "",
) -> Request:
    return Request(
        open=dynamics_pb2.OpenSession(
            model_name=model,
            dt=dt,
            clock=common_pb2.Clock.Value(f"CLOCK_{clock}"),
            history=history,
            subject=dynamics_pb2.Subject(id=subject, attributes=attributes or {}),
            estimator=common_pb2.EstimatorSettings(
                estimator=common_pb2.Estimator.Value(f"ESTIMATOR_{estimator}") if estimator else 0
            ),
        )
    )


def frame(seq: int, nq: int = 1, *, dt: float = 0.025) -> Request:
    return Request(frame=dynamics_pb2.Frame(seq=seq, t=seq * dt, qpos=[0.1] * nq, qvel=[0.0] * nq))


def close() -> Request:
    return Request(close=dynamics_pb2.CloseSession())


def settle(check: Callable[[], bool], *, timeout: float = 20.0) -> bool:
    """Poll `check` until it holds or `timeout` seconds pass; whether it held."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if check():
            return True
        time.sleep(0.1)
    return check()


def honest_session(
    served: Served, *, ticks: int = 3, nq: int = 1, **options: object
) -> dynamics_pb2.SessionClosed:
    """A well-behaved LOCKSTEP session: open, `ticks` frames, close; its summary."""
    requests = [open_request(**options), *(frame(k, nq) for k in range(ticks)), close()]  # type: ignore[arg-type]
    responses = list(served.dynamics.StreamSession(iter(requests), timeout=60))
    assert responses[0].WhichOneof("payload") == "opened"
    assert [r.WhichOneof("payload") for r in responses[1:-1]] == ["result"] * ticks
    return responses[-1].closed


def stored(served: Served, status: str) -> list[session_pb2.Session]:
    """The sessions of the default tenant with `status` (OPEN, COMPLETE, ABANDONED, ...)."""
    found: list[session_pb2.Session] = []
    token = ""
    while True:
        page = served.sessions.ListSessions(
            session_pb2.ListSessionsRequest(
                page_size=1000,
                page_token=token,
                status=session_pb2.SessionStatus.Value(f"SESSION_STATUS_{status}"),
            ),
            timeout=30,
        )
        found.extend(page.sessions)
        token = page.next_page_token
        if not token:
            return found


def logs(served: Served) -> list[str]:
    folder = served.data / "logs"
    return sorted(os.listdir(folder)) if folder.is_dir() else []


def chain(ndof: int, *, timestep: float = 0.005) -> str:
    """An MJCF chain of `ndof` hinged capsules, each the child of the one before."""
    body = ""
    for i in reversed(range(ndof)):
        body = (
            f'<body name="b{i}" pos="0 0 -0.1"><joint name="j{i}" type="hinge" axis="0 1 0" damping="0.1"/>'
            f'<geom type="capsule" size="0.02" fromto="0 0 0 0 0 -0.1" mass="0.1"/>{body}</body>'
        )
    return f'<mujoco><option timestep="{timestep}"/><worldbody>{body}</worldbody></mujoco>'


def hfield(rows: int) -> str:
    """A tiny MJCF that asks for a `rows` x `rows` height field (4 bytes a point once compiled)."""
    return f'<mujoco><asset><hfield name="h" nrow="{rows}" ncol="{rows}" size="1 1 1 1"/></asset></mujoco>'


def register(served: Served, name: str, mjcf: str) -> model_registry_pb2.RegisterModelResponse:
    return served.registry.RegisterModel(  # type: ignore[no-any-return]
        model_registry_pb2.RegisterModelRequest(name=name, mjcf=mjcf), timeout=120
    )
