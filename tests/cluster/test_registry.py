"""One registry: a model registered through one replica opens on every replica sharing the index,
includes and meshes too, though each replica has its own data folder (the content comes from the
index's model_blobs table and is cached in the opening replica's folder); built-in models too."""

from __future__ import annotations

import uuid

import numpy as np
import pytest
from _cluster import Replica

from jitdyn.client import Client, FrameData, SessionOptions, TickResult

pytestmark = pytest.mark.postgres

# A tetrahedron, as OBJ text.
MESH = b"v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 0 0.1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
ARM = """<mujoco model="arm">
  <compiler meshdir="meshes"/>
  <include file="parts/arm.xml"/>
</mujoco>"""
PART = """<mujoco>
  <asset><mesh name="hand" file="hand.obj"/></asset>
  <worldbody>
    <body name="upper">
      <joint name="shoulder" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.03" mass="1"/>
      <body name="lower" pos="0 0 -0.3">
        <joint name="elbow" type="hinge" axis="0 1 0"/>
        <geom type="mesh" mesh="hand" mass="0.5"/>
      </body>
    </body>
  </worldbody>
</mujoco>"""


def run_lockstep(address: str, options: SessionOptions, ticks: int = 10) -> None:
    """A LOCKSTEP session at `address` that answers every frame and closes with them all."""
    with Client(address) as client, client.open_session(options) as session:
        for k in range(ticks):
            frame = FrameData(seq=k, t=k * options.dt, qpos=[0.2 * np.sin(0.3 * k), 0.1], qvel=[0.0, 0.0])
            assert isinstance(session.send_frame(frame), TickResult)
        summary = session.close()
    assert summary.frames == ticks, summary


def cached(replica: Replica, model_id: str) -> bool:
    return (replica.data / "models" / f"{model_id.split(':', 1)[1]}.zip").exists()


def test_a_model_with_an_include_and_a_mesh_opens_on_every_replica(replicas: list[Replica]) -> None:
    # A fresh comment: content none of the run's replicas has seen, whatever ran before.
    mjcf = ARM.replace("<mujoco", f"<!-- {uuid.uuid4()} -->\n<mujoco", 1)
    with Client(replicas[0].address) as client:
        model, created = client.register_model(
            name="cluster_arm", mjcf=mjcf, assets={"parts/arm.xml": PART.encode(), "meshes/hand.obj": MESH}
        )
    assert created
    assert cached(replicas[0], model.id)
    for replica in replicas[1:]:
        assert not cached(replica, model.id)
        run_lockstep(replica.address, SessionOptions(model_id=model.id, dt=0.02, clock="LOCKSTEP"))
        assert cached(replica, model.id)


def test_a_builtin_opens_on_every_replica(replicas: list[Replica]) -> None:
    for replica in replicas:
        run_lockstep(replica.address, SessionOptions(model_name="pendulum_2", dt=0.05, clock="LOCKSTEP"))
