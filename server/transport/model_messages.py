"""Conversions between the registry's types and the jitdyn.v1 model messages.

    model_message(info) -> jitdyn.v1.Model
    metadata_from_message(message) -> registry.ModelMetadata     # validated

Estimator defaults travel as `ScenarioDefaults` messages and live in the registry as dicts keyed
by scenario, one entry per row of estimator_settings.SETTINGS that is set, enum settings as their
vocabulary members: {"PASSIVE": {"preset": Preset.THESIS, "alpha": 0.001}}.
"""

from __future__ import annotations

from typing import Any

from google.protobuf import timestamp_pb2

from jitdyn.errors import InvalidArgument
from jitdyn.registry import ModelInfo, ModelMetadata
from jitdyn.registry.info import check_metadata
from jitdyn.roles import joint_roles
from jitdyn.server.runtime.choice import CostTable
from jitdyn.settings_message import settings_from_message, settings_message
from jitdyn.v1 import common_pb2, model_registry_pb2
from jitdyn.vocabulary import EstimatorKind, JointType, Scenario, SigmaScheme, from_proto, parse, to_proto

__all__ = [
    "cost_messages",
    "metadata_from_message",
    "metadata_message",
    "model_message",
]


def metadata_from_message(message: model_registry_pb2.ModelMetadata) -> ModelMetadata:
    """The registry's ModelMetadata of a message, validated (registry.info.check_metadata).

    Raises:
      InvalidArgument: an unset or unknown scenario, two entries for one scenario, or a field that
        breaks the registry's rules.
    """
    defaults: dict[str, dict[str, Any]] = {}
    for i, entry in enumerate(message.defaults):
        argument = f"metadata.defaults[{i}]"
        scenario = from_proto(Scenario, entry.scenario, argument=f"{argument}.scenario")
        if scenario is None:
            raise InvalidArgument(f"{argument}.scenario must be set (PASSIVE, CONTROLLED or EXTERNAL)")
        if scenario in defaults:
            raise InvalidArgument(f"metadata.defaults has more than one entry for scenario {scenario}")
        defaults[scenario.value] = settings_from_message(entry.estimator, argument=f"{argument}.estimator")
    return check_metadata(
        ModelMetadata(description=message.description, tags=tuple(message.tags), defaults=defaults)
    )


def metadata_message(metadata: ModelMetadata) -> model_registry_pb2.ModelMetadata:
    """The message of the registry's ModelMetadata."""
    return model_registry_pb2.ModelMetadata(
        description=metadata.description,
        tags=list(metadata.tags),
        defaults=[
            model_registry_pb2.ScenarioDefaults(
                scenario=common_pb2.Scenario.ValueType(
                    to_proto(parse(Scenario, scenario, argument="metadata.defaults.scenario"))
                ),
                estimator=settings_message(settings),
            )
            for scenario, settings in metadata.defaults.items()
        ],
    )


def _estimator(name: str) -> common_pb2.Estimator.ValueType:
    return common_pb2.Estimator.ValueType(to_proto(EstimatorKind[name]) if name else 0)


def _sigma(name: str) -> common_pb2.SigmaPoints.ValueType:
    return common_pb2.SigmaPoints.ValueType(to_proto(SigmaScheme[name]) if name else 0)


def cost_messages(
    table: CostTable,
) -> tuple[list[model_registry_pb2.EstimatorCost], list[model_registry_pb2.EstimatorChoiceAtRate]]:
    """A model's stored costs, and the choice they make at a few rates, as messages."""
    costs = [
        model_registry_pb2.EstimatorCost(
            scenario=common_pb2.Scenario.ValueType(to_proto(Scenario[cost.scenario])),
            estimator=_estimator(cost.estimator),
            sigma_points=_sigma(cost.sigma_points),
            steps=list(cost.steps),
            seconds=list(cost.seconds),
            max_rate=table.max_rate(cost),
        )
        for cost in table.costs
    ]
    choices = []
    for scenario in Scenario:
        if not table.of(scenario):
            continue
        for rate in table.rates():
            chosen = table.pick(scenario, 1.0 / rate)
            choices.append(
                model_registry_pb2.EstimatorChoiceAtRate(
                    scenario=common_pb2.Scenario.ValueType(to_proto(scenario)),
                    rate=rate,
                    estimator=_estimator(chosen.estimator if chosen else ""),
                    sigma_points=_sigma(chosen.sigma_points if chosen else ""),
                )
            )
    return costs, choices


def model_message(info: ModelInfo, costs: CostTable | None = None) -> model_registry_pb2.Model:
    """The jitdyn.v1.Model of a registered model, with its stored estimator costs when given."""
    estimator_costs, estimator_choices = cost_messages(costs) if costs is not None else ([], [])
    created_at = timestamp_pb2.Timestamp()
    created_at.FromDatetime(info.created_at)
    roles = {role.joint: role for role in joint_roles(info.joints, info.tags)}
    return model_registry_pb2.Model(
        id=info.id,
        name=info.name,
        version=info.version,
        dimensions=model_registry_pb2.Dimensions(
            nq=info.nq, nv=info.nv, nu=info.nu, na=info.na, nsensor=info.nsensor, nbody=info.nbody
        ),
        joints=[
            model_registry_pb2.Joint(
                name=joint.name,
                type=model_registry_pb2.JointType.ValueType(to_proto(JointType(joint.type))),
                limited=joint.limited,
                range_lower=joint.lower,
                range_upper=joint.upper,
                qpos_address=joint.qpos_address,
                dof_address=joint.dof_address,
                role=roles[joint.name].role if joint.name in roles else "",
                role_source=roles[joint.name].source if joint.name in roles else "",
            )
            for joint in info.joints
        ],
        actuators=[
            model_registry_pb2.Actuator(
                name=actuator.name,
                target=actuator.target,
                ctrl_limited=actuator.ctrl_limited,
                ctrl_lower=actuator.lower,
                ctrl_upper=actuator.upper,
            )
            for actuator in info.actuators
        ],
        metadata=metadata_message(info.metadata),
        created_at=created_at,
        timestep=info.timestep,
        builtin=info.builtin,
        estimator_costs=estimator_costs,
        estimator_choices=estimator_choices,
    )
