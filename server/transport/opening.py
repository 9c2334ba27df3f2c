"""The `open` message into the runtime's `OpenRequest`, and an `OpenedSession` into `opened`.

The session is opened by the runtime (server/runtime/opening.py); these convert its words and
check only what is the message's own shape (which model field is set, no UNSPECIFIED in a list).
"""

from __future__ import annotations

from jitdyn.errors import InvalidArgument
from jitdyn.server.runtime.opening import OpenedSession
from jitdyn.server.runtime.plan import InlineModel, ModelChoice, OpenRequest, Resume
from jitdyn.server.transport.model_messages import metadata_from_message, model_message
from jitdyn.settings_message import settings_from_message, settings_message
from jitdyn.v1 import common_pb2, dynamics_pb2
from jitdyn.vocabulary import Channel, Clock, Horizon, Output, Scenario, from_proto, to_proto

__all__ = ["open_request", "opened_message"]


def open_request(message: dynamics_pb2.OpenSession, *, tenant: str) -> OpenRequest:
    """The request `message` makes, its words converted (InvalidArgument naming the field)."""
    model = _model_choice(message)
    measured = [from_proto(Channel, c, argument="open.measured") for c in message.measured]
    if None in measured:
        raise InvalidArgument("open.measured must not contain CHANNEL_UNSPECIFIED")
    outputs = [from_proto(Output, o, argument="open.outputs") for o in message.outputs]
    if None in outputs:
        raise InvalidArgument("open.outputs must not contain OUTPUT_UNSPECIFIED")
    return OpenRequest(
        tenant=tenant,
        model=model,
        scenario=from_proto(Scenario, message.scenario, argument="open.scenario"),
        clock=from_proto(Clock, message.clock, argument="open.clock"),
        dt=message.dt,
        measured=frozenset(c for c in measured if c is not None),
        outputs=frozenset(o for o in outputs if o is not None),
        horizon=from_proto(Horizon, message.horizon, argument="open.horizon"),
        grace=message.grace,
        history=message.history,
        estimator=settings_from_message(message.estimator, argument="open.estimator"),
        subject_id=message.subject.id,
        subject_attributes=dict(message.subject.attributes),
        resume=_resume(message),
    )


def _resume(message: dynamics_pb2.OpenSession) -> Resume | None:
    if not message.HasField("resume"):
        return None
    if not message.resume.session_id or not message.resume.token:
        raise InvalidArgument("open.resume needs session_id and token (those of the session's `opened`)")
    return Resume(session_id=message.resume.session_id, token=message.resume.token)


def _model_choice(message: dynamics_pb2.OpenSession) -> ModelChoice:
    which = message.WhichOneof("model")
    if which is None:
        raise InvalidArgument("open.model must be set: model_id, model_name or inline_model")
    if which != "model_name" and message.model_version:
        raise InvalidArgument(f"open.model_version must be 0 with open.{which}, got {message.model_version}")
    if which == "model_id":
        return ModelChoice(model_id=message.model_id)
    if which == "model_name":
        return ModelChoice(name=message.model_name, version=message.model_version)
    inline = message.inline_model
    return ModelChoice(
        inline=InlineModel(
            name=inline.name,
            mjcf=inline.mjcf,
            assets=dict(inline.assets),
            metadata=metadata_from_message(inline.metadata),
        )
    )


def opened_message(opened: OpenedSession) -> dynamics_pb2.SessionOpened:
    """What the client is told of its session as it opens."""
    plan = opened.plan
    return dynamics_pb2.SessionOpened(
        session_id=opened.session_id,
        model=model_message(opened.info, opened.costs),
        estimator=settings_message(opened.settings),
        state_dimension=opened.state_dimension,
        measured=[common_pb2.Channel.ValueType(to_proto(c)) for c in sorted(plan.measured)],
        outputs=[common_pb2.Output.ValueType(to_proto(o)) for o in sorted(plan.outputs)],
        grace=plan.grace,
        history=plan.history,
        subject_pseudonym=opened.pseudonym,
        dt=plan.dt,
        steps_per_tick=plan.steps_per_tick,
        scenario=common_pb2.Scenario.ValueType(to_proto(opened.scenario)),
        scenario_reason=opened.scenario_reason,
        noise_reason=opened.noise_reason,
        resume_token=opened.resume_token,
        resume_from_seq=opened.resume_from_seq,
        resume_reason=opened.resume_reason,
        estimator_choice=dynamics_pb2.EstimatorChoice.ValueType(to_proto(opened.estimator_choice)),
        estimator_reason=opened.estimator_reason,
    )
