"""The gRPC health check HAProxy sends as raw bytes: deploy/haproxy/haproxy.cfg carries exactly
what deploy/haproxy/grpc_health_frames.py builds, and the h2 project's own parsers (hyperframe,
hpack) read those bytes as a well-formed grpc.health.v1.Health/Check of jitdyn's session service,
so renaming the service or the check's framing cannot leave the balancer's check stale."""

from __future__ import annotations

import importlib.util
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from _tls import Authority
from grpc_health.v1 import health_pb2
from hpack import Decoder
from hyperframe.frame import DataFrame, Frame, HeadersFrame, SettingsFrame

from jitdyn.v1 import dynamics_pb2

REPO = Path(__file__).resolve().parents[2]
HAPROXY_TEMPLATE = REPO / "deploy" / "haproxy" / "haproxy.cfg"
SESSION_SERVICE = dynamics_pb2.DESCRIPTOR.services_by_name["DynamicsService"].full_name


def _generator() -> object:
    path = REPO / "deploy" / "haproxy" / "grpc_health_frames.py"
    spec = importlib.util.spec_from_file_location("grpc_health_frames", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def _config_check_lines() -> list[str]:
    lines = [line.strip() for line in HAPROXY_TEMPLATE.read_text().splitlines()]
    return [line for line in lines if line.startswith("tcp-check ")]


def _parse(data: bytes) -> list[Frame]:
    frames = []
    while data:
        frame, length = Frame.parse_frame_header(memoryview(data[:9]))
        frame.parse_body(memoryview(data[9 : 9 + length]))
        frames.append(frame)
        data = data[9 + length :]
    return frames


def test_haproxy_cfg_sends_the_bytes_the_generator_builds() -> None:
    generator = _generator()
    generated = [line for line in generator.config_lines() if not line.startswith("#")]  # type: ignore[attr-defined]
    assert _config_check_lines() == generated


def test_the_bytes_are_a_health_check_of_the_session_service() -> None:
    sent = b"".join(
        bytes.fromhex(line.split()[-1])
        for line in _config_check_lines()
        if line.startswith("tcp-check send-binary")
    )
    preface = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n"
    assert sent.startswith(preface)
    settings, headers, data = _parse(sent[len(preface) :])

    assert isinstance(settings, SettingsFrame) and settings.settings == {} and settings.stream_id == 0
    assert isinstance(headers, HeadersFrame) and headers.stream_id == 1 and "END_HEADERS" in headers.flags
    assert Decoder().decode(headers.data) == [
        (":method", "POST"),
        (":scheme", "http"),
        (":path", "/grpc.health.v1.Health/Check"),
        (":authority", "jitdyn"),
        ("content-type", "application/grpc"),
        ("te", "trailers"),
    ]
    assert isinstance(data, DataFrame) and data.stream_id == 1 and "END_STREAM" in data.flags
    message = health_pb2.HealthCheckRequest(service=SESSION_SERVICE).SerializeToString()
    assert data.data == b"\x00" + len(message).to_bytes(4, "big") + message

    expected = [line for line in _config_check_lines() if line.startswith("tcp-check expect binary")]
    assert len(expected) == 1
    (answer,) = _parse(bytes.fromhex(expected[0].split()[-1]))
    serving = health_pb2.HealthCheckResponse(
        status=health_pb2.HealthCheckResponse.SERVING
    ).SerializeToString()
    assert isinstance(answer, DataFrame) and answer.stream_id == 1
    assert answer.data == b"\x00" + len(serving).to_bytes(4, "big") + serving


def test_haproxy_accepts_the_rendered_config(tmp_path: Path) -> None:
    haproxy = shutil.which("haproxy")
    if haproxy is None:
        pytest.skip("haproxy is not installed (apt-get install -y haproxy)")
    template = HAPROXY_TEMPLATE.read_text()
    assert set(re.findall(r"\$\{(\w+)\}", template)) == {
        "JITDYN_LB_BIND",
        "JITDYN_LB_CERT",
        "JITDYN_LB_STATS_SOCKET",
        "JITDYN_LB_SERVERS",
    }
    edge = Authority.make(tmp_path / "pki").issue("edge", hosts=["jitdyn.example.org"])
    config = tmp_path / "haproxy.cfg"
    config.write_text(
        template.replace("${JITDYN_LB_BIND}", "127.0.0.1:50051")
        .replace("${JITDYN_LB_CERT}", str(edge.pem))
        .replace("${JITDYN_LB_STATS_SOCKET}", str(tmp_path / "sock"))
        .replace("${JITDYN_LB_SERVERS}", "    server r1 127.0.0.2:50051\n    server r2 127.0.0.3:50051")
    )
    check = subprocess.run([haproxy, "-c", "-f", str(config)], check=False, capture_output=True, text=True)
    assert check.returncode == 0, check.stdout + check.stderr
    assert "Configuration file is valid" in check.stdout + check.stderr
