"""Failover across replicas: what a client sees when the replica holding its session is lost.

Three `jitdyn serve` replicas (127.0.0.31-33, one process each, their own folders, one fresh
PostgreSQL database as the shared index) behind HAProxy (deploy/haproxy), as tests/cluster starts
them. The sessions are the SDK's own (`jitdyn.client.Client`, resumption on by default), REALTIME,
pendulum_3 PASSIVE, one thread each sending its frames on the session clock.

    kills     one session at --rate Hz; --kills times: kill -9 the replica that holds it, time
              from the kill to the first fresh answer (the SDK resumed it on another replica),
              restart the killed one on its address. Prints p50 / p99 / max of that time and the
              ticks missed (REALTIME ticks whose time passed with no answer).
    rolling   --sessions sessions at --rate Hz; each replica in turn gets SIGTERM (it drains: its
              sessions are told to move), is waited for and started again. Prints sessions lost,
              acknowledged frames lost (a frame some answer's durable_seq covered whose values
              are not in the stored session), ticks never answered and answered late.

    python -m benchmarks.failover                          # both: 20 kills, then 30 sessions rolling
    python -m benchmarks.failover --part kills --kills 5

Needs PostgreSQL at 127.0.0.1:5432 (database `test` reachable, trust auth) and haproxy on PATH.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys
import tempfile
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import sqlalchemy as sa

from jitdyn.client import Client, FrameData, Session, SessionOptions, TickResult
from jitdyn.errors import JitdynError

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests" / "cluster"))

# The cluster's process helpers, shared with its tests.
from _cluster import Balancer, Replica, postgres_database, wait_for

HOSTS = ("127.0.0.31", "127.0.0.32", "127.0.0.33")
# A replica silent for a second is taken for dead; a session nobody resumes in 10 s is stored.
FAST = ["--lease-ttl=1s", "--resume-timeout=10s", "--verbose"]


@dataclass
class Run:
    """One session driven on its clock, and what its client saw."""

    session: Session
    dt: float
    stop: threading.Event = field(default_factory=threading.Event)
    answers: list[tuple[float, int]] = field(default_factory=list)  # (monotonic arrival, seq), fresh only
    acknowledged: int = -1
    send_lag: list[float] = field(default_factory=list)  # how late this client sent each frame (s)
    sent: int = 0
    error: BaseException | None = None
    thread: threading.Thread | None = None

    def drive(self) -> None:
        session = self.session
        k = 0
        try:
            while not self.stop.is_set():
                time.sleep(max(0.0, k * self.dt - session.now()))
                self.send_lag.append(session.now() - k * self.dt)
                q = 0.3 * np.sin(2 * np.pi * 0.5 * k * self.dt)
                session.send(FrameData(seq=k, t=k * self.dt, qpos=[q, -0.5 * q, 0.2 * q], qvel=[0.0] * 3))
                self.sent = k + 1
                k += 1
                self._take(session.poll())
        except BaseException as error:  # noqa: BLE001 (reported: a lost session is what is measured)
            self.error = error

    def _take(self, answers: Sequence[object]) -> None:
        for answer in answers:
            if isinstance(answer, TickResult):
                if answer.source != "CORRECTED":
                    self.answers.append((answer.received_at, answer.seq))

                if answer.durable_seq is not None:
                    self.acknowledged = max(self.acknowledged, answer.durable_seq)

    def after(self, killed_at: float, start: int) -> list[tuple[float, int]]:
        """Answers to frames sent after `killed_at` (monotonic), from answers[start:]: the session
        answers again (an answer the killed replica sent just before its end may still arrive
        after it, and is not one of them)."""
        sent_after = killed_at - self.session.clock_start
        return [(at, seq) for at, seq in self.answers[start:] if seq * self.dt > sent_after]

    def late(self, since: float = -float("inf"), until: float = float("inf")) -> int:
        """Answers that arrived after their tick's deadline (its time plus the grace), between
        `since` and `until` (monotonic)."""
        start, grace = self.session.clock_start, self.session.opened.grace
        return sum(
            1 for at, seq in self.answers if since <= at <= until and at - start > seq * self.dt + grace
        )

    def start(self) -> None:
        self.thread = threading.Thread(target=self.drive, daemon=True)
        self.thread.start()

    def finish(self) -> tuple[int, int]:
        """Stop sending, close; (missed ticks, resumes) from the SDK's summary."""
        self.stop.set()
        assert self.thread is not None
        self.thread.join(timeout=30)
        if self.error is not None:
            raise self.error
        summary = self.session.close()
        return summary.missed, summary.resumes


def _options(rate: float) -> SessionOptions:
    return SessionOptions(model_name="pendulum_3", dt=1.0 / rate, clock="REALTIME", scenario="PASSIVE")


def _holder(replicas: Sequence[Replica]) -> Replica | None:
    for replica in replicas:
        with contextlib.suppress(Exception):
            if replica.process.poll() is None and replica.metrics().get("jitdyn_open_sessions", 0) > 0:
                return replica
    return None


def _restart(replicas: list[Replica], index: int, index_url: str, balancer: Balancer) -> None:
    old = replicas[index]
    old.close()
    replicas[index] = Replica.start(
        old.name, host=old.host, port=old.port, data=old.data, index_url=index_url, extra=FAST
    )
    wait_for(
        lambda: balancer.server_states().get(old.name) == "UP",
        timeout=15,
        what=f"haproxy did not see {old.name} come back",
    )


def _pct(values: Sequence[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q))


def kills(replicas: list[Replica], balancer: Balancer, index_url: str, *, count: int, rate: float) -> None:
    print(f"kills: one REALTIME pendulum_3 session at {rate:g} Hz; {count} times kill -9 its replica")
    with Client(balancer.address, timeout=30) as client:
        run = Run(client.open_session(_options(rate)), 1.0 / rate)
        run.start()
        took: list[float] = []
        missed_per_kill: list[int] = []
        late_per_kill: list[int] = []
        for n in range(count):
            time.sleep(1.0)
            holder = _holder(replicas)
            if holder is None:
                raise RuntimeError("no replica reports the session open")
            before = len(run.answers)
            killed_at = time.monotonic()
            holder.kill()
            wait_for(
                lambda k=killed_at, b=before: run.error is not None or bool(run.after(k, b)),
                timeout=20,
                what="no answer after the kill",
            )
            if run.error is not None:
                raise run.error
            first_at, first_seq = run.after(killed_at, before)[0]
            last_seq = max((seq for at, seq in run.answers if at <= killed_at), default=-1)
            took.append(first_at - killed_at)
            missed_per_kill.append(max(0, first_seq - last_seq - 1))
            time.sleep(0.5)
            late_per_kill.append(run.late(killed_at, killed_at + 0.5 + took[-1]))
            print(
                f"  kill {n + 1:2d}: {holder.name} -> first answer after {1e3 * took[-1]:6.0f} ms "
                f"(tick {first_seq}; {missed_per_kill[-1]} ticks never answered, {late_per_kill[-1]} late)",
                flush=True,
            )
            _restart(replicas, replicas.index(holder), index_url, balancer)
        missed, resumes = run.finish()
    frames_lost = _acknowledged_lost([run], replicas, index_url)
    print(
        f"kills: {count}; failover p50 {1e3 * _pct(took, 50):.0f} ms, p99 {1e3 * _pct(took, 99):.0f} ms, "
        f"max {1e3 * max(took):.0f} ms; resumes {resumes}; ticks missed {missed} "
        f"(per kill p50 {_pct(missed_per_kill, 50):.0f}, max {max(missed_per_kill)}); answered late per kill "
        f"p50 {_pct(late_per_kill, 50):.0f}, max {max(late_per_kill)}; session lost: no; "
        f"acknowledged frames lost {frames_lost} of {run.acknowledged + 1}"
    )


def rolling(
    replicas: list[Replica], balancer: Balancer, index_url: str, *, sessions: int, rate: float
) -> None:
    print(f"rolling: {sessions} REALTIME pendulum_3 sessions at {rate:g} Hz; SIGTERM each replica in turn")
    with contextlib.ExitStack() as stack:
        runs: list[Run] = []
        refused: list[str] = []
        for _ in range(sessions):
            client = stack.enter_context(Client(balancer.address, timeout=30))
            try:
                runs.append(Run(client.open_session(_options(rate)), 1.0 / rate))
            except JitdynError as error:  # admission: the machine or a replica is full
                refused.append(str(error))
                continue
            runs[-1].start()
            time.sleep(0.05)
        if refused:
            print(
                f"  {len(refused)} of {sessions} opens refused (the replicas' logs say why): {refused[0][:120]}"
            )
        time.sleep(2.0)
        for index in range(len(replicas)):
            started = time.monotonic()
            _restart(replicas, index, index_url, balancer)  # close() is SIGTERM: the replica drains
            print(
                f"  {replicas[index].name}: drained and back in {time.monotonic() - started:.1f} s",
                flush=True,
            )
            time.sleep(2.0)
        lost, missed, resumes = 0, 0, 0
        for run in runs:
            try:
                m, r = run.finish()
                missed, resumes = missed + m, resumes + r
            except JitdynError as error:
                lost += 1
                print(f"  lost {run.session.opened.session_id}: {error}")
    late = sum(run.late() for run in runs)
    took = [r.took for run in runs for r in run.session.resumptions]
    attempts = [r.attempts for run in runs for r in run.session.resumptions]
    if took:
        print(
            f"  resumes took p50 {1e3 * _pct(took, 50):.0f} ms, p99 {1e3 * _pct(took, 99):.0f} ms, "
            f"max {1e3 * max(took):.0f} ms; attempts max {max(attempts)}"
        )
    lag = [x for run in runs for x in run.send_lag]
    print(
        f"  the clients sent their frames late by p50 {1e3 * _pct(lag, 50):.1f} ms, p99 {1e3 * _pct(lag, 99):.1f} ms"
    )
    answered = sum(len(run.answers) for run in runs)
    frames_lost = _acknowledged_lost(runs, replicas, index_url)
    print(
        f"rolling: {len(replicas)} replicas restarted under {len(runs)} sessions; sessions lost {lost}; "
        f"acknowledged frames lost {frames_lost}; resumes {resumes}; ticks missed {missed}; "
        f"answered late {late} of {answered}"
    )


def _acknowledged_lost(runs: Sequence[Run], replicas: Sequence[Replica], index_url: str) -> int:
    """Frames some answer's durable_seq covered that the stored session does not hold."""
    engine = sa.create_engine(index_url)
    lost = 0
    try:
        with engine.connect() as conn:
            for run in runs:
                row = conn.execute(
                    sa.text("SELECT location FROM sessions WHERE session_id = :id"),
                    {"id": run.session.opened.session_id},
                ).one_or_none()
                files = [r.data / row[0] for r in replicas if row and (r.data / row[0]).exists()]
                if not files:
                    lost += run.acknowledged + 1
                    continue
                # A frame is kept when its values are in the record: the tick's result, or the
                # rejection of a frame that came too late to be used (TOO_OLD keeps them).
                table = pq.read_table(
                    files[0], columns=["kind", "seq", "frame_received", "frame_qpos", "source", "server_time"]
                )
                columns = (table[c].to_pylist() for c in table.column_names)
                kept = {
                    seq
                    for kind, seq, got, qpos, _, _ in zip(*columns, strict=True)
                    if (kind == "result" and got) or (kind == "rejected" and qpos is not None)
                }
                missing = [seq for seq in range(run.acknowledged + 1) if seq not in kept]
                if missing:
                    print(f"  {run.session.opened.session_id}: acknowledged, not in the record: {missing}")
                    near = {k for m in missing for k in range(m - 2, m + 3)}
                    rows = zip(*(table[c].to_pylist() for c in table.column_names), strict=True)
                    print("   ", [(k, s, g, src, round(t, 3)) for k, s, g, q, src, t in rows if s in near])
                lost += len(missing)
    finally:
        engine.dispose()
    return lost


@contextlib.contextmanager
def cluster(workdir: Path) -> Iterator[tuple[list[Replica], Balancer, str]]:
    with postgres_database() as index_url, contextlib.ExitStack() as stack:
        replicas = [
            Replica.start(f"r{n}", host=host, data=workdir / f"r{n}", index_url=index_url, extra=FAST)
            for n, host in enumerate(HOSTS)
        ]
        stack.callback(lambda: [r.close() for r in replicas])
        balancer = stack.enter_context(Balancer.start(replicas, workdir=workdir))
        yield replicas, balancer, index_url


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=["kills", "rolling", "both"], default="both")
    parser.add_argument("--kills", type=int, default=20, help="kill -9 this many times (default 20)")
    parser.add_argument("--sessions", type=int, default=30, help="sessions under the rolling restart")
    parser.add_argument("--rate", type=float, default=20.0, help="frames per second of every session")
    parser.add_argument(
        "--workdir", type=Path, help="keep the replicas' folders and logs here (default: a temporary folder)"
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="  %(name)s: %(message)s")
    logging.getLogger("jitdyn.client").setLevel(logging.INFO)  # every failed resume attempt, and why
    with contextlib.ExitStack() as stack:
        workdir = args.workdir or Path(
            stack.enter_context(tempfile.TemporaryDirectory(prefix="jitdyn-failover-"))
        )
        replicas, balancer, index_url = stack.enter_context(cluster(workdir))
        try:
            if args.part in ("kills", "both"):
                kills(replicas, balancer, index_url, count=args.kills, rate=args.rate)
            if args.part in ("rolling", "both"):
                rolling(replicas, balancer, index_url, sessions=args.sessions, rate=args.rate)
        except BaseException:
            for log in [*(r.log for r in replicas), balancer.log]:
                print(f"--- the end of {log.name}:", *log.read_text().splitlines()[-15:], sep="\n")
            raise


if __name__ == "__main__":
    main()
