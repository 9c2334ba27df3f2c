"""`jitdyn demo`: one REALTIME session of a simulated research object over an emulated network.

A session the server refuses REALTIME (a big MyoSuite model's tick does not fit its dt, or the
machine has no core free) runs LOCKSTEP instead unless a clock was asked for: each frame is
answered as it is sent, and a frame the network loses is a skipped tick, answered PREDICTED
(docs/decisions/0166).

The truth is simulated by MuJoCo on the client side; frames reach the server through a seeded
delaying sender (latency, jitter, loss), so some arrive after their tick's deadline: the server
answers those ticks PREDICTED by its estimator and CORRECTED when the frame comes. The summary
(experiments/feed.py, which `jitdyn replay` and `jitdyn lsl` share) gives the server's counts as
`jitdyn sessions list` shows them (storage.summary.format_counts), compares the predictions with
the truth and says where the session is stored. The progress bar goes to stderr, and only when it
is a terminal.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import mujoco
import numpy as np

from jitdyn.client import Client, FrameData, Session, SessionOptions
from jitdyn.experiments.feed import (
    Answers,
    Context,
    describe_network,
    describe_session,
    expectation,
    feed_lockstep,
    feed_realtime,
    finish,
    open_session,
    report,
)
from jitdyn.experiments.netem import NetworkProfile
from jitdyn.experiments.objects import qpos_limits
from jitdyn.experiments.progress import progress_bar
from jitdyn.experiments.truth import TruthSources, truth_model
from jitdyn.registry.info import joint_types
from jitdyn.storage.records import dof_units
from jitdyn.vocabulary import Channel, Clock, EstimatorKind, Output, Scenario

__all__ = ["DemoSettings", "run_demo"]


@dataclass(frozen=True)
class DemoSettings:
    # A registered model: NAME, NAME:VERSION or its id (sha256:...).
    model: str = "pendulum_3"
    # None: PASSIVE for a built-in model, else the server's choice for the model.
    scenario: Scenario | None = None
    seconds: float = 10.0
    dt: float | None = None  # None: 50 ms for pendulums, else 10 model timesteps
    latency: float = 0.035  # s, one way
    jitter: float = 0.010  # s
    loss: float = 0.05
    seed: int = 0
    # None: the server's choice (by the model's stored cost in REALTIME; `opened` says which).
    estimator: EstimatorKind | None = None
    # None: REALTIME, or LOCKSTEP (said so) when the server refuses the REALTIME session for its
    # cost or its machine's load, as it does a big MyoSuite model's.
    clock: Clock | None = None


def _start_pose(model: mujoco.MjModel, rng: np.random.Generator) -> np.ndarray:
    """(nq,) a deterministic start away from rest, so that gravity moves the body: each dof moved
    0.3 to 0.8 (rad or m) from qpos0, on the manifold of ball and free joints, inside the ranges of
    limited joints."""
    qpos = model.qpos0.copy()
    delta = rng.uniform(0.3, 0.8, model.nv) * np.sign(rng.standard_normal(model.nv))
    mujoco.mj_integratePos(model, qpos, delta, 1.0)
    lo, hi = qpos_limits(model)
    bounded = np.isfinite(lo)
    margin = 0.1 * (hi[bounded] - lo[bounded])
    qpos[bounded] = np.clip(qpos[bounded], lo[bounded] + margin, hi[bounded] - margin)
    return np.asarray(qpos, dtype=np.float64)


def _estimator(session: Session, asked: EstimatorKind | None) -> str:
    """', estimator X' as asked, or as the server chose it and why."""
    if asked is not None:
        return f", estimator {asked}"
    opened = session.opened
    reason = opened.estimator_reason or str(opened.estimator_choice or "")
    return f", estimator {opened.estimator.get('estimator', 'the preset')}" + (
        f" ({reason})" if reason else ""
    )


def run_demo(
    address: str,
    settings: DemoSettings,
    *,
    out: TextIO,
    progress: bool = True,
    local_data: Path | None = None,
    sources: TruthSources | None = None,
) -> dict[str, object]:
    """Run the demo session against the server at `address`; print and return its summary.

    `local_data`: the data folder of a server this process runs, so that the stored file is named
    by its path here; None for a remote server, whose data folder is its own. `sources`: where
    the model's MJCF is looked for (default: `local_data`'s store)."""
    answers = Answers()
    network = NetworkProfile(latency=settings.latency, jitter=settings.jitter, loss=settings.loss)
    with Client(address) as client:
        client.wait_ready()
        ref, model = truth_model(
            client, settings.model, sources or TruthSources(data=local_data), address=address
        )
        data = mujoco.MjData(model)
        data.qpos[:] = _start_pose(model, np.random.default_rng(settings.seed))
        mujoco.mj_forward(model, data)
        pendulum = ref.builtin and ref.name.startswith("pendulum")
        dt = settings.dt or (0.05 if pendulum else 10 * model.opt.timestep)
        ticks = max(1, round(settings.seconds / dt))
        scenario = settings.scenario or (Scenario.PASSIVE if ref.builtin else None)
        options = SessionOptions(
            model_id=ref.id,
            scenario=scenario,
            dt=dt,
            clock=settings.clock or Clock.REALTIME,
            estimator={} if settings.estimator is None else {"estimator": settings.estimator},
            measured=(Channel.QPOS, Channel.QVEL, Channel.CTRL)
            if scenario is Scenario.CONTROLLED
            else (Channel.QPOS, Channel.QVEL),
            outputs=(Output.INVERSE_DYNAMICS,),
        )
        session, clock = open_session(client, options, asked=settings.clock, out=out)
        lockstep = clock is Clock.LOCKSTEP
        told = describe_session(
            session,
            model=f"{ref.name} v{ref.version} ({model.nv} dof)",
            dt=dt,
            ticks=ticks,
            lockstep=lockstep,
            chosen=scenario is None,
            extra=_estimator(session, settings.estimator),
        )
        print(told, file=out)
        simulation = _Truth(model, data, dt=dt, controlled=scenario is Scenario.CONTROLLED)
        bar = progress_bar(total=ticks, desc="ticks answered", unit="tick", enabled=progress)
        if lockstep:
            print(describe_network(network, seed=settings.seed, lockstep=True), file=out)
            feed_lockstep(
                session, simulation.frames(ticks), answers, loss=settings.loss, seed=settings.seed, bar=bar
            )
        else:
            told = expectation(network, grace=session.opened.grace, history=session.opened.history, dt=dt)
            if told:
                print(told, file=out)
            print(describe_network(network, seed=settings.seed, lockstep=False), file=out)
            feed_realtime(
                session,
                simulation.frames(ticks),
                answers,
                dt=dt,
                network=network,
                seed=settings.seed,
                bar=bar,
            )
        summary = finish(session, answers, bar)
    context = Context(
        dt=dt,
        lockstep=lockstep,
        address=address,
        local_data=local_data,
        dof_units=tuple(dof_units(joint_types(model))),
    )
    return report(answers, summary, context, out=out)


class _Truth:
    """The simulated body: frame k is its state at k * dt, then it steps on to tick k + 1."""

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, *, dt: float, controlled: bool) -> None:
        self.model, self.data, self.dt, self.controlled = model, data, dt, controlled
        self.steps = max(1, round(dt / model.opt.timestep))

    def frames(self, ticks: int) -> Iterator[FrameData]:
        """Frames 0 to ticks - 1: each the state at k * dt, stepped on (zero controls) once taken."""
        ctrl = np.zeros(self.model.nu)
        for k in range(ticks):
            yield FrameData(
                seq=k,
                t=k * self.dt,
                qpos=self.data.qpos.copy(),
                qvel=self.data.qvel.copy(),
                ctrl=ctrl if self.controlled else None,
            )
            self.data.ctrl[:] = 0.0
            for _ in range(self.steps):
                mujoco.mj_step(self.model, self.data)


def default_data_root() -> Path:
    return Path("jitdyn-data")
