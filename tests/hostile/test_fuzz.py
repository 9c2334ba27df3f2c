"""Finding-independent fuzzing (must-have 5): random and mutated frames, opens and registrations
against one live `jitdyn serve`. Every answer is a result, a rejected frame or a documented status;
the server stays up; an honest REALTIME session running alongside stays on time."""

from __future__ import annotations

import statistics
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import grpc
import pytest
from _hostile import Request, Served, close, open_request
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from jitdyn.v1 import common_pb2, dynamics_pb2, model_registry_pb2

FUZZ = settings(
    max_examples=100,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
    derandomize=True,
)
# What an open, a registration or a session may end with (the contract's statuses).
DOCUMENTED = {
    grpc.StatusCode.INVALID_ARGUMENT,
    grpc.StatusCode.NOT_FOUND,
    grpc.StatusCode.FAILED_PRECONDITION,
    grpc.StatusCode.RESOURCE_EXHAUSTED,
    grpc.StatusCode.ALREADY_EXISTS,
}
PENDULUM = Path(__file__).resolve().parents[2].joinpath("models", "pendulum_1.xml").read_text()

floats = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 1e-300, 1e300, 0.025, 0.05]),
)
vectors = st.lists(floats, max_size=4)


class Honest:
    """A REALTIME pendulum session sending a frame every dt on its clock, for as long as it runs:
    the latency from each frame to its result, and how its ticks were answered."""

    def __init__(self, served: Served, *, dt: float = 0.025) -> None:
        self.dt = dt
        self.latencies: list[float] = []
        self.server_latencies: list[float] = []  # frame arrival to result sent, server clock
        self.sources: list[int] = []
        self.seqs: list[int] = []
        self.late_compute = 0
        self.started = time.monotonic()  # the session clock's 0: when `opened` arrived
        self._answered: tuple[int, float] | None = None  # the last probe answered, and when
        self._stop = threading.Event()
        self._sent: dict[int, float] = {}
        self._opened = threading.Event()
        self._call = served.dynamics.StreamSession(self._requests(), timeout=600)
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        assert self._opened.wait(30)

    def _requests(self) -> Iterator[Request]:
        opening = open_request(clock="REALTIME", dt=self.dt)
        # PASSIVE named: what is judged is the server's fairness beside the fuzzing, not the price
        # of the default DRIVEN filter's forecast combination (benchmarks/RESULTS.md), which shed
        # 95 of 393 ticks of this session in one full-suite run on a quiet machine.
        opening.open.scenario = common_pb2.Scenario.Value("SCENARIO_PASSIVE")
        yield opening
        self._opened.wait(30)
        seq = probe = 0
        while not self._stop.is_set():
            due = self.started + seq * self.dt
            time.sleep(max(0.0, due - time.monotonic()))
            if seq % 10 == 0:
                # As a real client (and the SDK) does: the clock starts as `opened` arrives, so it
                # lags the server's by however long this busy process took to read it; the sync
                # exchanges let the server measure that. Without them, frames of one full-suite
                # run all came after their deadline (none on time).
                ping = dynamics_pb2.SyncPing(id=probe, client_send_time=time.monotonic() - self.started)
                if self._answered is not None:
                    ping.previous_id, ping.previous_receive_time = self._answered
                probe += 1
                yield Request(sync=ping)
            self._sent[seq] = time.monotonic()
            yield Request(frame=dynamics_pb2.Frame(seq=seq, t=seq * self.dt, qpos=[0.1], qvel=[0.0]))
            seq += 1
        yield close()

    def _read(self) -> None:
        for response in self._call:
            received = time.monotonic()
            kind = response.WhichOneof("payload")
            if kind == "opened":
                self.started = received
                self._opened.set()
            elif kind == "sync":
                self._answered = (response.sync.id, received - self.started)
            elif kind == "result":
                result = response.result
                sent = self._sent.get(result.seq)
                if sent is not None and result.frame_received:
                    self.latencies.append(received - sent)
                    self.server_latencies.append(result.receive_to_send_us / 1e6)
                self.sources.append(result.source)
                if result.source != dynamics_pb2.Source.Value("SOURCE_CORRECTED"):
                    self.seqs.append(result.seq)
                self.late_compute += result.late_compute

    def finish(self, *, at_least: float = 5.0) -> None:
        """Stop sending once the session has run `at_least` seconds (enough ticks to judge)."""
        time.sleep(max(0.0, self.started + at_least - time.monotonic()))
        self._stop.set()
        self._reader.join(30)


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    import os
    import secrets

    env = dict(os.environ, JITDYN_SECRET=secrets.token_hex(32))
    env.pop("JITDYN_INDEX_URL", None)
    folder = tmp_path_factory.mktemp("fuzz")
    served = Served(folder / "data", env, ["--idle-timeout", "20"], output=folder / "server.out")
    try:
        honest = Honest(served)
        yield served
        honest.finish()
        assert served.alive()
    finally:
        served.stop()
    measured = sum(s == dynamics_pb2.Source.Value("SOURCE_MEASURED") for s in honest.sources)
    ticks = len(honest.seqs)
    assert honest.latencies, f"no frame of the honest session was on time: {ticks} ticks, {measured} measured"
    print(
        f"\nhonest REALTIME session beside the fuzzing: {ticks} ticks, {measured} measured, "
        f"late_compute {honest.late_compute}, frame->result median "
        f"{statistics.median(honest.latencies) * 1e3:.2f} ms, max {max(honest.latencies) * 1e3:.1f} ms"
    )
    # On time: the ticks answered (PREDICTED when this client's own frame was late: it shares a
    # process and its GIL with the fuzzing), hardly any answered late from the last estimate, and
    # answers within a dt of their frame.
    assert ticks > 100
    # In order, once each; a tick the server reached more than a tick late may go unanswered (a
    # REALTIME tick is answered by its deadline or not at all), but hardly any.
    assert honest.seqs == sorted(set(honest.seqs))
    assert ticks >= 0.97 * (honest.seqs[-1] + 1)
    # Shed ticks (answered by their deadline from the last estimate) are the server's overload
    # answer, not a lockout. Full-suite runs shed 12-24 % of them while this client started its
    # clock late and sent no sync: its frames came just before their deadline, leaving the filter
    # no time. With sync exchanges, it sheds 1-3 %, alone or in the suite, and 5 % (14 of 277) in a
    # suite run beside another developer's experiments; a lockout sheds them all.
    assert honest.late_compute <= 0.10 * ticks
    assert statistics.median(honest.latencies) < honest.dt / 2
    # This client shares its process (and GIL) with the fuzzer, so its own reading lags on a loaded
    # machine: the tail is judged on the server's clock (frame arrival to result sent).
    server = sorted(honest.server_latencies)
    assert server[int(0.95 * len(server))] < honest.dt


def _stream(served: Served, requests: list[Request]) -> tuple[list[str], grpc.RpcError | None]:
    kinds: list[str] = []
    try:
        for response in served.dynamics.StreamSession(iter(requests), timeout=60):
            kinds.append(response.WhichOneof("payload"))
    except grpc.RpcError as error:
        return kinds, error
    return kinds, None


frames = st.builds(
    lambda seq, t, qpos, qvel, qacc, checksum: Request(
        frame=dynamics_pb2.Frame(seq=seq, t=t, qpos=qpos, qvel=qvel, qacc=qacc, checksum=checksum)
        if checksum is not None
        else dynamics_pb2.Frame(seq=seq, t=t, qpos=qpos, qvel=qvel, qacc=qacc)
    ),
    st.one_of(st.integers(0, 5), st.integers(0, 2**64 - 1)),
    floats,
    vectors,
    vectors,
    vectors,
    st.none() | st.integers(0, 2**32 - 1),
)
others = st.one_of(
    st.builds(lambda seq: Request(skip=dynamics_pb2.Skip(seq=seq)), st.integers(0, 2**64 - 1)),
    st.builds(
        lambda i, t: Request(sync=dynamics_pb2.SyncPing(id=i, client_send_time=t)),
        st.integers(0, 2**64 - 1),
        floats,
    ),
)


@FUZZ
@given(st.lists(st.one_of(frames, frames, others), min_size=1, max_size=8))
def test_random_frames_are_answered_or_rejected(live: Served, requests: list[Request]) -> None:
    kinds, error = _stream(live, [open_request(dt=0.025), *requests, close()])
    if error is not None:
        # Only a non-finite sync time ends a session; a frame never does.
        assert error.code() == grpc.StatusCode.INVALID_ARGUMENT, error
        assert "sync.client_send_time must be finite" in (error.details() or "")
        return
    assert kinds[0] == "opened" and kinds[-1] == "closed"
    assert set(kinds[1:-1]) <= {"result", "rejected", "sync"}


opens = st.builds(
    lambda model, dt, clock, scenario, history, grace, subject, attributes, measured: Request(
        open=dynamics_pb2.OpenSession(
            model_name=model,
            dt=dt,
            clock=clock,
            scenario=scenario,
            history=history,
            grace=grace,
            subject=dynamics_pb2.Subject(id=subject, attributes=attributes),
            measured=measured,
        )
    ),
    st.sampled_from(["pendulum_1", "pendulum_3", "biped", "", "nope"]) | st.text(max_size=20),
    floats,
    st.integers(0, 5),
    st.integers(0, 6),
    st.integers(0, 2**32 - 1),
    floats,
    st.text(max_size=300),
    st.dictionaries(
        st.sampled_from(["sex", "age", "limb", "height_m", "x"]) | st.text(max_size=8),
        st.text(max_size=40),
        max_size=3,
    ),
    st.lists(st.integers(0, 6), max_size=4),
)


@FUZZ
@given(opens)
def test_random_opens_are_opened_or_refused_with_a_documented_status(live: Served, request: Request) -> None:
    kinds, error = _stream(live, [request, close()])
    if error is not None:
        assert error.code() in DOCUMENTED, (error.code(), error.details())
        return
    assert kinds[0] == "opened" and kinds[-1] == "closed"


def _mutate(text: str, data: st.DataObject) -> str:
    for _ in range(data.draw(st.integers(1, 4))):
        at = data.draw(st.integers(0, len(text)))
        action = data.draw(st.sampled_from(["insert", "delete", "duplicate"]))
        if action == "insert":
            text = (
                text[:at]
                + data.draw(
                    st.sampled_from(
                        ["<", ">", '"', "<body>", "</body>", "nan", "1e308", "&x;", "<include file='a'/>"]
                    )
                    | st.text(max_size=5)
                )
                + text[at:]
            )
        elif action == "delete":
            text = text[:at] + text[at + data.draw(st.integers(1, 40)) :]
        else:
            text = text[:at] + text[max(0, at - 60) : at] + text[at:]
    return text


@FUZZ
@given(st.data())
def test_mutated_registrations_are_registered_or_refused(live: Served, data: st.DataObject) -> None:
    mjcf = _mutate(PENDULUM, data)
    name = data.draw(st.sampled_from(["fuzzed", "pendulum_1", ""]) | st.text(max_size=12))
    try:
        answer = live.registry.RegisterModel(
            model_registry_pb2.RegisterModelRequest(name=name, mjcf=mjcf), timeout=60
        )
    except grpc.RpcError as error:
        assert error.code() in DOCUMENTED, (error.code(), error.details())
        return
    assert answer.model.id.startswith("sha256:")
