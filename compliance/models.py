"""The suite's own models, registered through the contract's RegisterModel: it assumes nothing of
a server's built-ins. Both are a 1 m, 1 kg rod on one hinge, timestep 10 ms (nq = nv = 1)."""

from __future__ import annotations

from typing import Final

__all__ = ["MODELS", "MOTOR", "PENDULUM", "TIMESTEP"]

TIMESTEP: Final = 0.01
_ROD: Final = (
    '<body name="rod"><joint name="hinge" type="hinge" axis="0 1 0"/>'
    '<geom type="capsule" fromto="0 0 0 0 0 -1" size="0.05" mass="1"/></body>'
)
# No actuator: a session that names no scenario is PASSIVE.
PENDULUM: Final = "compliance_pendulum"
# One motor on the hinge: a session that names no scenario is DRIVEN.
MOTOR: Final = "compliance_motor"
MODELS: Final = {
    PENDULUM: f'<mujoco model="{PENDULUM}"><option timestep="{TIMESTEP}"/><worldbody>{_ROD}</worldbody></mujoco>',
    MOTOR: (
        f'<mujoco model="{MOTOR}"><option timestep="{TIMESTEP}"/><worldbody>{_ROD}</worldbody>'
        '<actuator><motor name="motor" joint="hinge"/></actuator></mujoco>'
    ),
}
