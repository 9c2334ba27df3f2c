"""The suite's frame: cases by name, the context they run in, and their outcomes.

    @case("frame.shape", "a channel of the wrong length is rejected BAD_SHAPE; the session goes on")
    def _(ctx: Context) -> str:
        ...
        return "what was seen, for the table"

A case raises CaseFailed when the server breaks the contract, Skipped when it cannot run here
(auth cases without an API key), and returns a note otherwise.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Final

import grpc

from jitdyn.compliance.models import MODELS, TIMESTEP
from jitdyn.compliance.wire import CaseFailed, Connection, Ended, Stream
from jitdyn.v1 import common_pb2, dynamics_pb2, model_registry_pb2

__all__ = [
    "CASES",
    "DT",
    "Case",
    "Context",
    "Outcome",
    "Skipped",
    "case",
    "check",
    "finite",
    "frame",
    "measured",
    "reason_name",
    "rejected_as",
    "result_of",
    "run_case",
    "scenario_name",
    "source_name",
]

# The frame period of the suite's sessions (s): one step of its models' timestep.
DT: Final = TIMESTEP


class Skipped(Exception):
    """The case cannot run against this target (say why)."""


@dataclass
class Context:
    """What the cases share: the connection, the models registered for them, the statuses seen."""

    wire: Connection
    other_key: str | None = None
    # s a REALTIME open refused for the server's load (RESOURCE_EXHAUSTED) is tried again.
    admission_wait: float = 30.0
    provoked: set[str] = field(default_factory=set)
    _models: dict[str, model_registry_pb2.Model] = field(default_factory=dict)

    def model(self, name: str) -> model_registry_pb2.Model:
        """One of the suite's own models (compliance/models.py), registered at first use."""
        if name not in self._models:
            mjcf = MODELS[name]
            response = self.wire.call(
                self.wire.registry.RegisterModel,
                model_registry_pb2.RegisterModelRequest(name=name, mjcf=mjcf),
                timeout=120.0,
            )
            self._models[name] = response.model
        return self._models[name]

    def status(self, ended: Ended, *expected: grpc.StatusCode) -> grpc.StatusCode:
        """The status, which must be one of `expected`; recorded as provoked."""
        self.provoked.add(ended.code.name)
        if ended.code not in expected:
            wanted = " or ".join(code.name for code in expected)
            raise CaseFailed(f"expected {wanted}, got {ended.code.name}: {ended.details}")
        return ended.code

    def open(self, stream: Stream, **fields: Any) -> dynamics_pb2.SessionOpened:
        stream.send(open=dynamics_pb2.OpenSession(**fields))
        opened: dynamics_pb2.SessionOpened = stream.expect("opened", timeout=60.0)
        return opened

    def refused_open(self, expected: grpc.StatusCode, **fields: Any) -> Ended:
        """Open with `fields`, which must end the stream with `expected`."""
        with self.wire.stream() as stream:
            stream.send(open=dynamics_pb2.OpenSession(**fields))
            ended = stream.expect_end(timeout=60.0)
        self.status(ended, expected)
        return ended

    def close(self, stream: Stream) -> dynamics_pb2.SessionSummary:
        """Close the session: `closed`, then the stream ends OK."""
        stream.send(close=dynamics_pb2.CloseSession())
        closed = stream.expect("closed", timeout=60.0)
        self.status(stream.expect_end(), grpc.StatusCode.OK)
        summary: dynamics_pb2.SessionSummary = closed.summary
        return summary


@dataclass(frozen=True)
class Case:
    name: str
    summary: str
    run: Callable[[Context], str]


@dataclass(frozen=True)
class Outcome:
    """How one case went: "pass", "fail" or "skip", how long it took, and what it saw."""

    name: str
    result: str
    seconds: float
    note: str


CASES: Final[dict[str, Case]] = {}


def case(name: str, summary: str) -> Callable[[Callable[[Context], str]], Callable[[Context], str]]:
    """Register a case under `name` (unique), in the order of definition."""

    def register(run: Callable[[Context], str]) -> Callable[[Context], str]:
        if name in CASES:
            raise ValueError(f"two cases named {name!r}")
        CASES[name] = Case(name, summary, run)
        return run

    return register


def run_case(ctx: Context, chosen: Case) -> Outcome:
    start = time.monotonic()
    try:
        note = chosen.run(ctx)
        result = "pass"
    except Skipped as why:
        note, result = str(why), "skip"
    except CaseFailed as failure:
        note, result = str(failure), "fail"
    except grpc.RpcError as error:  # a call the case expected to answer ended instead
        note, result = f"unexpected {error.code().name}: {error.details()}", "fail"
    return Outcome(chosen.name, result, time.monotonic() - start, " ".join(note.split()))


def check(condition: bool, failure: str) -> None:
    if not condition:
        raise CaseFailed(failure)


def finite(values: Iterable[float]) -> bool:
    return all(math.isfinite(v) for v in values)


def frame(seq: int, *, dt: float = TIMESTEP, q: float = 0.1, **channels: Any) -> dynamics_pb2.Frame:
    """A frame of the suite's one-hinge models at tick `seq`: qpos [q], qvel [0] unless given."""
    values: dict[str, Any] = {"qpos": [q], "qvel": [0.0], **channels}
    return dynamics_pb2.Frame(seq=seq, t=seq * dt, **values)


def source_name(value: dynamics_pb2.Source.ValueType) -> str:
    return dynamics_pb2.Source.Name(value).removeprefix("SOURCE_")


def reason_name(value: dynamics_pb2.RejectReason.ValueType) -> str:
    return dynamics_pb2.RejectReason.Name(value).removeprefix("REJECT_REASON_")


def scenario_name(value: common_pb2.Scenario.ValueType) -> str:
    return common_pb2.Scenario.Name(value).removeprefix("SCENARIO_")


def result_of(stream: Stream, seq: int) -> dynamics_pb2.Result:
    result: dynamics_pb2.Result = stream.expect("result")
    check(result.seq == seq, f"expected the result of tick {seq}, got tick {result.seq}")
    return result


def rejected_as(
    stream: Stream, seq: int, reason: str, *, passing: tuple[str, ...] = ()
) -> dynamics_pb2.Rejected:
    """The next answer, past any kinds `passing`: the rejection of tick `seq` for `reason`."""
    rejected: dynamics_pb2.Rejected = stream.expect("rejected", passing=passing)
    got = reason_name(rejected.reason)
    check(
        rejected.seq == seq and got == reason,
        f"expected tick {seq} rejected {reason}, got tick {rejected.seq} {got}",
    )
    check(bool(rejected.message), f"rejection {reason} of tick {seq} has no message")
    return rejected


def measured(stream: Stream, seq: int, q: float = 0.1) -> dynamics_pb2.Result:
    stream.send(frame=frame(seq, q=q))
    result = result_of(stream, seq)
    check(
        source_name(result.source) == "MEASURED",
        f"tick {seq}: expected MEASURED, got {source_name(result.source)}",
    )
    return result
