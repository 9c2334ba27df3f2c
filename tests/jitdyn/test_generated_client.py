"""A client generated from proto/ alone — no client/, no jitdyn package — registers a model and
runs a LOCKSTEP session against a real server, in its own process. This is what a user of another
language does."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]

# The foreign client: it knows only the generated code of package `contract` and the proto's
# comments (the checksum layout among them).
FOREIGN_CLIENT = r"""
import struct, sys
import google_crc32c, grpc
from contract.v1 import common_pb2, dynamics_pb2, dynamics_pb2_grpc, model_registry_pb2, model_registry_pb2_grpc

assert "jitdyn" not in sys.modules and "client" not in sys.modules
MJCF = '<mujoco model="slider"><worldbody><body name="cart"><joint name="x" type="slide" axis="1 0 0"/>' \
       '<geom type="box" size=".1 .1 .1" mass="2"/></body></worldbody></mujoco>'

def checksum(seq, t, channels):
    data = struct.pack("<Qd", seq, t)
    for values in channels:
        data += struct.pack("<I", len(values)) + struct.pack(f"<{len(values)}d", *values)
    return google_crc32c.value(data)

with grpc.insecure_channel(sys.argv[1]) as channel:
    model = model_registry_pb2_grpc.ModelRegistryServiceStub(channel).RegisterModel(
        model_registry_pb2.RegisterModelRequest(name="slider", mjcf=MJCF), timeout=30).model
    assert model.id.startswith("sha256:") and model.dimensions.nv == 1, model

    def requests():
        yield dynamics_pb2.StreamSessionRequest(open=dynamics_pb2.OpenSession(
            model_id=model.id, dt=0.01, clock=common_pb2.CLOCK_LOCKSTEP, scenario=common_pb2.SCENARIO_PASSIVE,
            measured=[common_pb2.CHANNEL_QPOS, common_pb2.CHANNEL_QVEL, common_pb2.CHANNEL_QACC]))
        for k in range(5):
            t, qpos, qvel, qacc = k * 0.01, [0.1 * k], [0.1], [3.0]
            yield dynamics_pb2.StreamSessionRequest(frame=dynamics_pb2.Frame(
                seq=k, t=t, qpos=qpos, qvel=qvel, qacc=qacc, checksum=checksum(k, t, [qpos, qvel, qacc, [], []])))
        yield dynamics_pb2.StreamSessionRequest(close=dynamics_pb2.CloseSession())

    responses = list(dynamics_pb2_grpc.DynamicsServiceStub(channel).StreamSession(requests(), timeout=60))
kinds = [r.WhichOneof("payload") for r in responses]
assert kinds == ["opened"] + ["result"] * 5 + ["closed"], kinds
for r in responses[1:6]:
    assert r.result.source == dynamics_pb2.SOURCE_MEASURED, r
    # A 2 kg cart on a frictionless slide accelerating at 3 m/s^2 needs 6 N.
    assert abs(r.result.qfrc_inverse[0] - 6.0) < 1e-9, r.result.qfrc_inverse
assert responses[-1].closed.summary.measured == 5
print("foreign client ok")
"""


def test_a_client_from_proto_alone_registers_and_runs_a_session(server: Any, tmp_path: Path) -> None:
    protos = tmp_path / "protos" / "contract" / "v1"
    protos.mkdir(parents=True)
    for source in (ROOT / "proto" / "jitdyn" / "v1").glob("*.proto"):
        # A foreign client files the protos under its own path; the imports follow it.
        protos.joinpath(source.name).write_text(
            source.read_text().replace('import "jitdyn/v1/', 'import "contract/v1/')
        )
    from grpc_tools import protoc

    include = Path(protoc.__file__).parent / "_proto"
    out = tmp_path / "generated"
    out.mkdir()
    generate = subprocess.run(
        [
            sys.executable,
            "-m",
            "grpc_tools.protoc",
            f"-I{tmp_path / 'protos'}",
            f"-I{include}",
            f"--python_out={out}",
            f"--grpc_python_out={out}",
            *[str(p.relative_to(tmp_path / "protos")) for p in protos.glob("*.proto")],
        ],
        capture_output=True,
        text=True,
        check=False,
    )
    assert generate.returncode == 0, generate.stderr
    for package in (out / "contract", out / "contract" / "v1"):
        (package / "__init__.py").write_text("")
    (out / "foreign_client.py").write_text(FOREIGN_CLIENT)
    run = subprocess.run(
        [sys.executable, str(out / "foreign_client.py"), server.address],
        capture_output=True,
        text=True,
        cwd=out,
        timeout=120,
        check=False,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    assert "foreign client ok" in run.stdout
