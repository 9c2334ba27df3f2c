"""Conversions between the registry's types and the jitdyn.v1 model messages."""

from __future__ import annotations

import datetime

import pytest

from jitdyn.errors import InvalidArgument
from jitdyn.registry import ActuatorInfo, JointInfo, ModelInfo
from jitdyn.server.transport.model_messages import metadata_from_message, model_message
from jitdyn.v1 import common_pb2, model_registry_pb2


def scenario_defaults(scenario: int, **settings: object) -> model_registry_pb2.ScenarioDefaults:
    return model_registry_pb2.ScenarioDefaults(
        scenario=scenario, estimator=common_pb2.EstimatorSettings(**settings)
    )


def test_metadata_defaults_become_dicts_of_enum_names() -> None:
    message = model_registry_pb2.ModelMetadata(
        description="d",
        tags=["a", "b"],
        defaults=[
            scenario_defaults(
                common_pb2.SCENARIO_CONTROLLED,
                estimator=common_pb2.ESTIMATOR_UKF,
                sigma_points=common_pb2.SIGMA_POINTS_SIMPLEX,
                alpha=0.001,
                kappa=0.0,
            ),
            scenario_defaults(common_pb2.SCENARIO_PASSIVE),
        ],
    )
    metadata = metadata_from_message(message)
    assert metadata.description == "d" and metadata.tags == ("a", "b")
    # kappa = 0 is set (field presence), unset fields are absent.
    assert metadata.defaults == {
        "CONTROLLED": {"estimator": "UKF", "sigma_points": "SIMPLEX", "alpha": 0.001, "kappa": 0.0},
        "PASSIVE": {},
    }


@pytest.mark.parametrize(
    ("defaults", "message"),
    [
        (
            [scenario_defaults(0)],
            "metadata.defaults[0].scenario must be set (PASSIVE, CONTROLLED or EXTERNAL)",
        ),
        (
            [scenario_defaults(9)],
            "metadata.defaults[0].scenario must be one of SCENARIO_PASSIVE, SCENARIO_CONTROLLED, SCENARIO_EXTERNAL, SCENARIO_DRIVEN, got the undefined value 9",
        ),
        (
            [scenario_defaults(1), scenario_defaults(2), scenario_defaults(1)],
            "metadata.defaults has more than one entry for scenario PASSIVE",
        ),
        (
            [scenario_defaults(1, preset=7)],
            "metadata.defaults[0].estimator.preset must be one of PRESET_JITDYN, PRESET_THESIS, got the undefined value 7",
        ),
        ([scenario_defaults(1, p0=-1.0)], "metadata.defaults.PASSIVE.p0 must be > 0, got -1"),
    ],
)
def test_bad_metadata_messages_are_invalid_argument(
    defaults: list[model_registry_pb2.ScenarioDefaults], message: str
) -> None:
    with pytest.raises(InvalidArgument) as error:
        metadata_from_message(model_registry_pb2.ModelMetadata(defaults=defaults))
    assert str(error.value) == message


def test_model_message_carries_every_field() -> None:
    info = ModelInfo(
        id="sha256:" + "ab" * 32,
        name="arm",
        version=3,
        tenant="t",
        builtin=True,
        nq=7,
        nv=6,
        nu=1,
        na=1,
        nsensor=3,
        nbody=2,
        timestep=0.004,
        joints=(
            JointInfo(
                name="root", type="free", limited=False, lower=0.0, upper=0.0, qpos_address=0, dof_address=0
            ),
        ),
        actuators=(ActuatorInfo(name="m", target="tendon0", ctrl_limited=True, lower=0.0, upper=1.0),),
        description="d",
        tags=("x",),
        defaults={"EXTERNAL": {"preset": "THESIS", "q_var": 50.0}},
        created_at=datetime.datetime(2026, 1, 2, 3, 4, 5, 600000, tzinfo=datetime.UTC),
    )
    message = model_message(info)
    assert (message.id, message.name, message.version, message.builtin, message.timestep) == (
        info.id,
        "arm",
        3,
        True,
        0.004,
    )
    assert message.dimensions == model_registry_pb2.Dimensions(nq=7, nv=6, nu=1, na=1, nsensor=3, nbody=2)
    assert message.joints[0].type == model_registry_pb2.JOINT_TYPE_FREE
    assert message.actuators[0] == model_registry_pb2.Actuator(
        name="m", target="tendon0", ctrl_limited=True, ctrl_lower=0.0, ctrl_upper=1.0
    )
    assert message.created_at.ToDatetime(tzinfo=datetime.UTC) == info.created_at
    assert metadata_from_message(message.metadata) == info.metadata
