"""ModelRegistryService over real gRPC (a grpc.aio server on port 0): messages, statuses, tenants."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import grpc
import pytest

from jitdyn.registry import BUILTIN_NAMES, ModelRegistry
from jitdyn.v1 import common_pb2, model_registry_pb2

PENDULUM = """<mujoco>
  <compiler angle="radian"/>
  <worldbody>
    <body><joint name="swing" axis="0 1 0" range="-1 1"/><geom type="capsule" fromto="0 0 0 0 0 -1" size="0.05"/></body>
  </worldbody>
  <actuator><motor name="torque" joint="swing" ctrlrange="-2 2"/></actuator>
</mujoco>"""


def register(stub: Any, **fields: Any) -> model_registry_pb2.RegisterModelResponse:
    fields.setdefault("mjcf", PENDULUM)
    return stub.RegisterModel(model_registry_pb2.RegisterModelRequest(**fields), timeout=60)


def status_of(call: Callable[[], Any]) -> tuple[grpc.StatusCode, str]:
    with pytest.raises(grpc.RpcError) as error:
        call()
    return error.value.code(), error.value.details()


def test_register_get_and_list_over_grpc(registry_stub: Any) -> None:
    metadata = model_registry_pb2.ModelMetadata(
        description="A pendulum.",
        tags=["service-test"],
        defaults=[
            model_registry_pb2.ScenarioDefaults(
                scenario=common_pb2.SCENARIO_EXTERNAL,
                estimator=common_pb2.EstimatorSettings(preset=common_pb2.PRESET_THESIS, q_var=50.0),
            )
        ],
    )
    response = register(registry_stub, name="service-pendulum", metadata=metadata)
    assert response.created
    model = response.model
    assert model.id.startswith("sha256:") and model.version == 1 and not model.builtin
    assert (model.dimensions.nq, model.dimensions.nv, model.dimensions.nu, model.dimensions.nbody) == (
        1,
        1,
        1,
        2,
    )
    (joint,) = model.joints
    assert (joint.name, joint.type, joint.limited, joint.range_lower, joint.range_upper) == (
        "swing",
        model_registry_pb2.JOINT_TYPE_HINGE,
        True,
        -1.0,
        1.0,
    )
    (actuator,) = model.actuators
    assert (actuator.name, actuator.target, actuator.ctrl_limited, actuator.ctrl_lower) == (
        "torque",
        "swing",
        True,
        -2.0,
    )
    assert model.metadata == metadata
    assert model.timestep == 0.002
    assert model.created_at.seconds > 0

    again = register(registry_stub, name="service-pendulum", metadata=metadata)
    assert not again.created and again.model == model
    by_id = registry_stub.GetModel(model_registry_pb2.GetModelRequest(model_id=model.id), timeout=30).model
    by_name = registry_stub.GetModel(
        model_registry_pb2.GetModelRequest(name="service-pendulum"), timeout=30
    ).model
    assert by_id == model == by_name
    listed = registry_stub.ListModels(model_registry_pb2.ListModelsRequest(tag="service-test"), timeout=30)
    assert [m.id for m in listed.models] == [model.id] and listed.next_page_token == ""


def test_builtins_are_served(registry_stub: Any) -> None:
    names = []
    token = ""
    while True:
        page = registry_stub.ListModels(
            model_registry_pb2.ListModelsRequest(tag="builtin", page_size=3, page_token=token), timeout=30
        )
        names += [m.name for m in page.models]
        assert all(m.builtin for m in page.models)
        token = page.next_page_token
        if not token:
            break
    assert names == sorted(BUILTIN_NAMES)


def test_tenants_are_kept_apart(
    registry_stub: Any, as_tenant: Callable[[str], list[tuple[str, str]]]
) -> None:
    mjcf = PENDULUM.replace("-1 1", "-0.5 0.5")
    request = model_registry_pb2.RegisterModelRequest(name="private", mjcf=mjcf)
    mine = registry_stub.RegisterModel(request, metadata=as_tenant("acme"), timeout=60).model
    code, details = status_of(
        lambda: registry_stub.GetModel(
            model_registry_pb2.GetModelRequest(model_id=mine.id), metadata=as_tenant("other"), timeout=30
        )
    )
    assert (code, details) == (grpc.StatusCode.NOT_FOUND, f"no model has id '{mine.id}'")
    found = registry_stub.GetModel(
        model_registry_pb2.GetModelRequest(name="private"), metadata=as_tenant("acme"), timeout=30
    )
    assert found.model == mine


@pytest.mark.parametrize(
    ("request_fields", "code", "details"),
    [
        (
            {"name": "bad name"},
            grpc.StatusCode.INVALID_ARGUMENT,
            "name must be 1-64 characters of [A-Za-z0-9_.-] starting with a letter, got 'bad name'",
        ),
        (
            {"name": "broken", "mjcf": "<mujoco><worldbody><geom/></worldbody>"},
            grpc.StatusCode.INVALID_ARGUMENT,
            "the MJCF is not well-formed XML: no element found: line 1, column 38",
        ),
        (
            {"name": "broken", "mjcf": '<mujoco><worldbody><geom type="sphere"/></worldbody></mujoco>'},
            grpc.StatusCode.INVALID_ARGUMENT,
            "MuJoCo could not compile the model: Error: size 0 must be positive in geom\nElement name '', id 0, line 1",
        ),
        (
            {"name": "leak", "mjcf": '<mujoco><include file="/etc/hostname"/></mujoco>'},
            grpc.StatusCode.INVALID_ARGUMENT,
            (
                "include (line 1) attribute file refers to file '/etc/hostname', which is an absolute path; "
                "files must be assets, named by relative paths"
            ),
        ),
        (
            {
                "name": "leak",
                "mjcf": '<mujoco><include file="scene.xml"/></mujoco>',
                "assets": {"other.xml": b""},
            },
            grpc.StatusCode.INVALID_ARGUMENT,
            (
                "include (line 1) attribute file refers to file 'scene.xml', which is not among the request's "
                "assets (assets: 'other.xml')"
            ),
        ),
        (
            {
                "name": "dup",
                "metadata": model_registry_pb2.ModelMetadata(
                    defaults=[
                        model_registry_pb2.ScenarioDefaults(scenario=common_pb2.SCENARIO_PASSIVE),
                        model_registry_pb2.ScenarioDefaults(scenario=common_pb2.SCENARIO_PASSIVE),
                    ]
                ),
            },
            grpc.StatusCode.INVALID_ARGUMENT,
            "metadata.defaults has more than one entry for scenario PASSIVE",
        ),
    ],
)
def test_register_errors_carry_their_status(
    registry_stub: Any, request_fields: dict[str, Any], code: grpc.StatusCode, details: str
) -> None:
    assert status_of(lambda: register(registry_stub, **request_fields)) == (code, details)


def test_oversized_mjcf_is_resource_exhausted(registry_stub: Any, served_registry: ModelRegistry) -> None:
    limit = served_registry.limits.max_mjcf_bytes
    mjcf = PENDULUM + "<!--" + "x" * limit + "-->"
    assert status_of(lambda: register(registry_stub, name="huge", mjcf=mjcf)) == (
        grpc.StatusCode.RESOURCE_EXHAUSTED,
        f"the MJCF is {len(mjcf)} bytes, over the limit of {limit} bytes (registry setting max_mjcf_bytes)",
    )


@pytest.mark.parametrize(
    ("get", "code", "details"),
    [
        (
            model_registry_pb2.GetModelRequest(),
            grpc.StatusCode.INVALID_ARGUMENT,
            "GetModelRequest: give model_id, or name (and version); got neither",
        ),
        (
            model_registry_pb2.GetModelRequest(model_id="sha256:" + "0" * 64, name="biped"),
            grpc.StatusCode.INVALID_ARGUMENT,
            "GetModelRequest: give model_id, or name (and version), not both; got model_id "
            "'sha256:" + "0" * 64 + "', name 'biped', version 0",
        ),
        (
            model_registry_pb2.GetModelRequest(name="biped", version=7),
            grpc.StatusCode.NOT_FOUND,
            "model 'biped' has no version 7 (versions: 1)",
        ),
        (
            model_registry_pb2.GetModelRequest(model_id="nope"),
            grpc.StatusCode.INVALID_ARGUMENT,
            "model_id must be 'sha256:' followed by 64 lowercase hex digits, got 'nope'",
        ),
    ],
)
def test_get_model_errors(
    registry_stub: Any, get: model_registry_pb2.GetModelRequest, code: grpc.StatusCode, details: str
) -> None:
    assert status_of(lambda: registry_stub.GetModel(get, timeout=30)) == (code, details)


def test_list_models_page_sizes_and_tokens(registry_stub: Any) -> None:
    default = registry_stub.ListModels(model_registry_pb2.ListModelsRequest(), timeout=30)
    assert 4 <= len(default.models) <= 50
    assert status_of(
        lambda: registry_stub.ListModels(model_registry_pb2.ListModelsRequest(page_size=1001), timeout=30)
    ) == (grpc.StatusCode.INVALID_ARGUMENT, "page_size must be at most 1000 (0: 50), got 1001")
    code, details = status_of(
        lambda: registry_stub.ListModels(
            model_registry_pb2.ListModelsRequest(page_token="garbage"), timeout=30
        )
    )
    assert code == grpc.StatusCode.INVALID_ARGUMENT
    assert details == "page_token 'garbage' is not a next_page_token of this listing (same filters)"
