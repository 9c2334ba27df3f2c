"""The cases of the registry and of opening a session: rules of model_registry.proto and of
OpenSession and SessionOpened in dynamics.proto, checked over the wire; each case's summary says
which.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Final

import grpc

from jitdyn.compliance.models import MODELS, MOTOR, PENDULUM, TIMESTEP
from jitdyn.compliance.suite import DT, Context, case, check, frame, scenario_name
from jitdyn.compliance.wire import CaseFailed, content_id
from jitdyn.v1 import common_pb2, dynamics_pb2, model_registry_pb2

__all__: list[str] = []

Code = grpc.StatusCode
# The default model size limit of RegisterModelRequest.mjcf (8 MiB) and a margin over it.
_OVERSIZED_MJCF_BYTES: Final = 8 * 1024 * 1024 + 4096


# -- the registry -------------------------------------------------------------------------------


@case(
    "register.content_id",
    "a model's id is the SHA-256 the contract defines; registering it again creates nothing",
)
def _(ctx: Context) -> str:
    model = ctx.model(PENDULUM)
    expected = content_id(MODELS[PENDULUM], {})
    check(model.id == expected, f"Model.id is {model.id}, the contract's hash is {expected}")
    dims = model.dimensions
    check(
        (dims.nq, dims.nv, dims.nu) == (1, 1, 0),
        f"expected nq, nv, nu 1, 1, 0, got {dims.nq}, {dims.nv}, {dims.nu}",
    )
    check(
        [(j.name, j.type) for j in model.joints] == [("hinge", model_registry_pb2.JOINT_TYPE_HINGE)],
        f"expected one hinge named 'hinge', got {[j.name for j in model.joints]}",
    )
    check(abs(model.timestep - TIMESTEP) < 1e-12, f"expected timestep {TIMESTEP}, got {model.timestep}")
    again = ctx.wire.call(
        ctx.wire.registry.RegisterModel,
        model_registry_pb2.RegisterModelRequest(name=PENDULUM, mjcf=MODELS[PENDULUM]),
        timeout=120.0,
    )
    check(
        not again.created and again.model.id == model.id,
        "registering identical content again created a model",
    )
    return f"{model.id[:15]}..."


@case("register.invalid", "bad MJCF, a file that is not an asset and a bad name are INVALID_ARGUMENT")
def _(ctx: Context) -> str:
    requests = {
        "MJCF that does not parse": model_registry_pb2.RegisterModelRequest(
            name="compliance_broken", mjcf="<mujoco><worldbody><body>"
        ),
        "a mesh not among the assets": model_registry_pb2.RegisterModelRequest(
            name="compliance_mesh",
            mjcf='<mujoco><asset><mesh file="arm.stl"/></asset><worldbody><geom type="mesh" mesh="arm"/>'
            "</worldbody></mujoco>",
        ),
        "a name starting with a digit": model_registry_pb2.RegisterModelRequest(
            name="1compliance", mjcf=MODELS[PENDULUM]
        ),
    }
    for what, request in requests.items():
        ended = ctx.wire.status_of(ctx.wire.registry.RegisterModel, request, timeout=120.0)
        try:
            ctx.status(ended, Code.INVALID_ARGUMENT)
        except CaseFailed as failure:
            raise CaseFailed(f"{what}: {failure}") from None
    return f"{len(requests)} requests refused"


@case("limits.message_size", "a model over the size limit (default 8 MiB) is RESOURCE_EXHAUSTED")
def _(ctx: Context) -> str:
    padding = "<!--" + "x" * (_OVERSIZED_MJCF_BYTES - len(MODELS[PENDULUM]) - 7) + "-->"
    mjcf = MODELS[PENDULUM].replace("<worldbody>", padding + "<worldbody>", 1)
    request = model_registry_pb2.RegisterModelRequest(name="compliance_oversized", mjcf=mjcf)
    ended = ctx.wire.status_of(ctx.wire.registry.RegisterModel, request, timeout=120.0)
    ctx.status(ended, Code.RESOURCE_EXHAUSTED)
    return f"{len(mjcf.encode()) / 2**20:.2f} MiB refused"


@case("models.get", "GetModel by id and by name; neither is INVALID_ARGUMENT; paging is checked")
def _(ctx: Context) -> str:
    model = ctx.model(PENDULUM)
    registry = ctx.wire.registry
    by_id = ctx.wire.call(registry.GetModel, model_registry_pb2.GetModelRequest(model_id=model.id)).model
    check(by_id.id == model.id, f"GetModel(model_id) answered {by_id.id}")
    by_name = ctx.wire.call(registry.GetModel, model_registry_pb2.GetModelRequest(name=model.name)).model
    check(by_name.name == model.name, f"GetModel(name={model.name}) answered {by_name.name}")
    ctx.status(
        ctx.wire.status_of(registry.GetModel, model_registry_pb2.GetModelRequest()), Code.INVALID_ARGUMENT
    )
    for request in (
        model_registry_pb2.ListModelsRequest(page_size=1001),
        model_registry_pb2.ListModelsRequest(page_token="not a token"),
    ):
        ctx.status(ctx.wire.status_of(registry.ListModels, request), Code.INVALID_ARGUMENT)
    ctx.model(MOTOR)
    first = ctx.wire.call(registry.ListModels, model_registry_pb2.ListModelsRequest(page_size=1))
    check(len(first.models) == 1 and first.next_page_token != "", "a page of 1 of 2+ models has no next page")
    second = ctx.wire.call(
        registry.ListModels,
        model_registry_pb2.ListModelsRequest(page_size=1, page_token=first.next_page_token),
    )
    check(
        len(second.models) == 1 and second.models[0].id != first.models[0].id,
        "the second page repeats the first",
    )
    return "by id, by name, 2 pages"


@case("models.unknown", "an unknown model is NOT_FOUND: by name or id, in GetModel and in a session's open")
def _(ctx: Context) -> str:
    registry = ctx.wire.registry
    unknown_id = "sha256:" + "0" * 64
    for request in (
        model_registry_pb2.GetModelRequest(model_id=unknown_id),
        model_registry_pb2.GetModelRequest(name="compliance_no_such_model"),
    ):
        ctx.status(ctx.wire.status_of(registry.GetModel, request), Code.NOT_FOUND)
    ctx.refused_open(Code.NOT_FOUND, model_name="compliance_no_such_model", dt=DT)
    ctx.refused_open(Code.NOT_FOUND, model_id=unknown_id, dt=DT)
    return "GetModel and open, by name and by id"


# -- opening a session --------------------------------------------------------------------------


@case("open.lockstep", "open answers `opened` with every setting in force; close answers `closed`, then OK")
def _(ctx: Context) -> str:
    model = ctx.model(PENDULUM)
    with ctx.wire.stream() as stream:
        opened = ctx.open(stream, model_id=model.id, dt=DT)
        check(bool(opened.session_id), "opened.session_id is empty")
        check(opened.model.id == model.id, f"opened.model.id is {opened.model.id}, asked {model.id}")
        check(
            scenario_name(opened.scenario) == "PASSIVE",
            f"a model without actuators opened {scenario_name(opened.scenario)}",
        )
        check(bool(opened.scenario_reason), "opened.scenario_reason is empty")
        check(
            opened.estimator.estimator != common_pb2.ESTIMATOR_UNSPECIFIED,
            "opened.estimator.estimator is unset",
        )
        check(opened.estimator.preset != common_pb2.PRESET_UNSPECIFIED, "opened.estimator.preset is unset")
        check(
            opened.estimator_choice != dynamics_pb2.ESTIMATOR_CHOICE_UNSPECIFIED
            and bool(opened.estimator_reason),
            "opened.estimator_choice or estimator_reason is unset",
        )
        check(
            opened.state_dimension == 2, f"PASSIVE on nv 1: state dimension 2, got {opened.state_dimension}"
        )
        check(
            list(opened.measured) == [common_pb2.CHANNEL_QPOS, common_pb2.CHANNEL_QVEL],
            f"default measured channels are qpos and qvel, got {list(opened.measured)}",
        )
        check(
            list(opened.outputs) == [common_pb2.OUTPUT_INVERSE_DYNAMICS],
            f"default outputs are inverse dynamics, got {list(opened.outputs)}",
        )
        check(
            abs(opened.dt - DT) < 1e-12 and opened.steps_per_tick == 1,
            f"dt {opened.dt}, steps {opened.steps_per_tick}",
        )
        check(opened.history == 50, f"the default history is 50 ticks, got {opened.history}")
        summary = ctx.close(stream)
    check(summary.ticks == 0, f"a session without frames closed with {summary.ticks} ticks")
    return f"session {opened.session_id[:8]}"


@case(
    "open.model_choices",
    "a model opens by name (newest or a version) and inline; no scenario on actuators is DRIVEN",
)
def _(ctx: Context) -> str:
    model = ctx.model(PENDULUM)
    motor = ctx.model(MOTOR)
    for fields in (
        {"model_name": model.name},
        {"model_name": model.name, "model_version": model.version},
        {"inline_model": model_registry_pb2.RegisterModelRequest(name=PENDULUM, mjcf=MODELS[PENDULUM])},
    ):
        with ctx.wire.stream() as stream:
            opened = ctx.open(stream, dt=DT, **fields)
            check(opened.model.id == model.id, f"open {list(fields)} opened {opened.model.id}")
            ctx.close(stream)
    with ctx.wire.stream() as stream:
        opened = ctx.open(stream, model_id=motor.id, dt=DT)
        got = scenario_name(opened.scenario)
        check(got == "DRIVEN", f"a model with an actuator, no scenario asked: expected DRIVEN, got {got}")
        check(bool(opened.scenario_reason), "opened.scenario_reason is empty")
        ctx.close(stream)
    return "by name, version, inline; DRIVEN"


_BAD_OPENS: Final[dict[str, Callable[[str, str], dynamics_pb2.OpenSession]]] = {
    "dt 0": lambda m, _: dynamics_pb2.OpenSession(model_id=m, dt=0.0),
    "dt -0.01": lambda m, _: dynamics_pb2.OpenSession(model_id=m, dt=-0.01),
    "dt 11 s": lambda m, _: dynamics_pb2.OpenSession(model_id=m, dt=11.0),
    "dt not a multiple of the timestep": lambda m, _: dynamics_pb2.OpenSession(model_id=m, dt=0.015),
    "grace of 10 dt": lambda m, _: dynamics_pb2.OpenSession(model_id=m, dt=DT, grace=10 * DT),
    "history 10001": lambda m, _: dynamics_pb2.OpenSession(model_id=m, dt=DT, history=10001),
    "model_version with model_id": lambda m, _: dynamics_pb2.OpenSession(model_id=m, model_version=1, dt=DT),
    "measured without qpos": lambda m, _: dynamics_pb2.OpenSession(
        model_id=m, dt=DT, measured=[common_pb2.CHANNEL_QVEL]
    ),
    "measured CHANNEL_UNSPECIFIED": lambda m, _: dynamics_pb2.OpenSession(
        model_id=m, dt=DT, measured=[common_pb2.CHANNEL_QPOS, common_pb2.CHANNEL_UNSPECIFIED]
    ),
    "outputs OUTPUT_UNSPECIFIED": lambda m, _: dynamics_pb2.OpenSession(
        model_id=m, dt=DT, outputs=[common_pb2.OUTPUT_UNSPECIFIED]
    ),
    "CONTROLLED without ctrl": lambda _, motor: dynamics_pb2.OpenSession(
        model_id=motor,
        dt=DT,
        scenario=common_pb2.SCENARIO_CONTROLLED,
        measured=[common_pb2.CHANNEL_QPOS, common_pb2.CHANNEL_QVEL],
    ),
    "WRONG_MODEL_DRIVEN in CONTROLLED": lambda _, motor: dynamics_pb2.OpenSession(
        model_id=motor,
        dt=DT,
        scenario=common_pb2.SCENARIO_CONTROLLED,
        estimator=common_pb2.EstimatorSettings(wrong_model=common_pb2.WRONG_MODEL_DRIVEN),
    ),
    "alpha 0": lambda m, _: dynamics_pb2.OpenSession(
        model_id=m, dt=DT, estimator=common_pb2.EstimatorSettings(alpha=0.0)
    ),
    "a subject attribute off the list": lambda m, _: dynamics_pb2.OpenSession(
        model_id=m, dt=DT, subject=dynamics_pb2.Subject(id="s1", attributes={"name": "Ada"})
    ),
    "a subject id of 257 characters": lambda m, _: dynamics_pb2.OpenSession(
        model_id=m, dt=DT, subject=dynamics_pb2.Subject(id="x" * 257)
    ),
    "sex 'female' (F, M or X)": lambda m, _: dynamics_pb2.OpenSession(
        model_id=m, dt=DT, subject=dynamics_pb2.Subject(id="s1", attributes={"sex": "female"})
    ),
}


@case("open.invalid", "every open the contract refuses ends the stream INVALID_ARGUMENT, with a message")
def _(ctx: Context) -> str:
    model, motor = ctx.model(PENDULUM).id, ctx.model(MOTOR).id
    for what, build in _BAD_OPENS.items():
        with ctx.wire.stream() as stream:
            stream.send(open=build(model, motor))
            ended = stream.expect_end(timeout=60.0)
        try:
            ctx.status(ended, Code.INVALID_ARGUMENT)
        except CaseFailed as failure:
            raise CaseFailed(f"{what}: {failure}") from None
        check(bool(ended.details), f"{what}: INVALID_ARGUMENT without a message")
    return f"{len(_BAD_OPENS)} opens refused"


@case("open.order", "a message before `open` is FAILED_PRECONDITION; a second `open` is INVALID_ARGUMENT")
def _(ctx: Context) -> str:
    with ctx.wire.stream() as stream:
        stream.send(frame=frame(0))
        ctx.status(stream.expect_end(), Code.FAILED_PRECONDITION)
    with ctx.wire.stream() as stream:
        ctx.open(stream, model_id=ctx.model(PENDULUM).id, dt=DT)
        stream.send(open=dynamics_pb2.OpenSession(model_id=ctx.model(PENDULUM).id, dt=DT))
        ctx.status(stream.expect_end(), Code.INVALID_ARGUMENT)
    return "frame first; open twice"


@case(
    "open.resume_unknown",
    "resuming with a forged token is refused (PERMISSION_DENIED, NOT_FOUND, or FAILED_PRECONDITION without a shared index)",
)
def _(ctx: Context) -> str:
    resume = dynamics_pb2.Resume(session_id="00000000-0000-4000-8000-000000000000", token="forged")
    with ctx.wire.stream() as stream:
        stream.send(open=dynamics_pb2.OpenSession(model_id=ctx.model(PENDULUM).id, dt=DT, resume=resume))
        # Which one depends on the server: with a shared index or without, and what it reads first.
        got = ctx.status(
            stream.expect_end(), Code.PERMISSION_DENIED, Code.NOT_FOUND, Code.FAILED_PRECONDITION
        )
    return got.name
