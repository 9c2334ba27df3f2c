"""The pieces one UnscentedFilter is made of, built whole from its config: its layout, the numeric
core of the engine it runs (native or Python, estimation/core.py), the noises, the guard, the
adaptive noise, the forecast combination, and its mutable state. The filter's steps
(estimation/ukf.py's table) each read what they need of one `FilterParts`::

    parts = build_parts(model, config, pool=pool)
    parts.kf.predict()              # the engine's core
    parts.state.ticks_since_update  # the filter's bookkeeping (estimation/snapshot.py)
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Final

import mujoco
import numpy as np
from filterpy.kalman import unscented_transform

from jitdyn.server.estimation.adaptive import NoiseAdapter
from jitdyn.server.estimation.answer import Answers
from jitdyn.server.estimation.batched import BatchedUKF, tangent_unscented_transform
from jitdyn.server.estimation.config import Engine, EstimatorConfig
from jitdyn.server.estimation.core import FilterCore, PythonCore
from jitdyn.server.estimation.fast import FastUKF
from jitdyn.server.estimation.foresight import Foresight
from jitdyn.server.estimation.guard import Guard
from jitdyn.server.estimation.layout import FilterLayout, filter_layout
from jitdyn.server.estimation.linear_force import LinearForceUKF
from jitdyn.server.estimation.manifold import SplitManifold
from jitdyn.server.estimation.native.adaptive import NativeNoiseAdapter
from jitdyn.server.estimation.native.filter import NativeUKF
from jitdyn.server.estimation.noise import UkfNoise
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.estimation.process import SigmaProcess
from jitdyn.server.estimation.propagate import Inputs, Propagator, process_model
from jitdyn.server.estimation.sigma import (
    MerweScaled,
    RobustCholesky,
    Simplex,
    UniformSpherical,
    make_sigma_points,
)
from jitdyn.server.estimation.snapshot import FilterState
from jitdyn.vocabulary import NoiseModel, Scenario, SigmaScheme, WrongModel

__all__ = ["FilterParts", "build_parts"]

# What moves the sigma points besides the model's own forces, per scenario.
_INPUTS: Final = {
    Scenario.PASSIVE: Inputs.NONE,
    Scenario.CONTROLLED: Inputs.CTRL,
    Scenario.EXTERNAL: Inputs.QFRC,
    Scenario.DRIVEN: Inputs.QFRC,
}


@dataclass(frozen=True, eq=False)
class FilterParts:
    """One UKF's pieces (module docstring). kf's x, P, Q and R, and `state`, change tick by tick;
    the rest is fixed."""

    config: EstimatorConfig
    layout: FilterLayout
    model: mujoco.MjModel  # the process model (estimation/propagate.py process_model)
    data: mujoco.MjData  # for mj_forward / mj_inverse at single states
    kf: FilterCore
    points: MerweScaled | Simplex | UniformSpherical
    sqrt: RobustCholesky
    propagator: Propagator
    process: SigmaProcess
    ut: Callable[..., tuple[np.ndarray, np.ndarray]]  # the unscented transform of an extrapolation
    noise: UkfNoise
    Q: np.ndarray  # the process noise of one tick
    P0: np.ndarray
    adapter: NoiseAdapter | NativeNoiseAdapter | None
    guard: Guard
    foresight: Foresight | None
    state: FilterState
    answers: Answers


def build_parts(model: mujoco.MjModel, config: EstimatorConfig, *, pool: WorkerPool) -> FilterParts:
    """`config`'s UKF on `model`, built whole on the shared `pool`; its state not yet initialised."""
    scenario = Scenario(config.scenario)
    m = process_model(model, scenario=scenario)
    data = mujoco.MjData(m)
    layout = filter_layout(
        m,
        scenario=scenario,
        force_model=config.force_model,
        measured=config.measured,
        linear=config.sigma_points == SigmaScheme.SIMPLEX_LINEAR_FORCE,
    )
    x_manifold = SplitManifold(m, rest=layout.size - layout.nq) if layout.manifold else None
    sqrt = RobustCholesky()
    points = _sigma_points(config, layout, sqrt=sqrt, x_manifold=x_manifold)
    propagator = Propagator(
        m,
        pool=pool,
        nsigma=points.num_sigmas(),
        nstep=config.steps_per_tick,
        inputs=_INPUTS[scenario],
        want_qacc=layout.controlled,
    )
    # Plain vectors keep filterpy's own transform (and its arithmetic, bit for bit).
    ut = tangent_unscented_transform if layout.manifold else unscented_transform
    process = SigmaProcess(
        m, data, propagator=propagator, points=points, size=layout.size, fblocks=layout.fblocks,
        controlled=layout.controlled, steps_per_tick=config.steps_per_tick,
    )  # fmt: skip
    kf = _core(
        config, layout, model=m, data=data, points=points, process=process, ut=ut, sqrt=sqrt,
        x_manifold=x_manifold,
    )  # fmt: skip
    noise = UkfNoise.of(m, data, config)
    Q = noise.process_noise(config.dt)
    kf.Q = Q
    kf.R = config.r * np.eye(layout.z_tangent)
    P0 = noise.initial_covariance()
    state = FilterState.cleared(layout.na, layout.nu, layout.nv)
    restart = config.wrong_model == WrongModel.RESTART
    return FilterParts(
        config=config, layout=layout, model=m, data=data, kf=kf, points=points, sqrt=sqrt,
        propagator=propagator, process=process, ut=ut, noise=noise, Q=Q, P0=P0,
        adapter=_noise_adapter(config, layout, noise=noise, Q=Q),
        guard=Guard(m=layout.z_tangent, restart=restart, driven=layout.driven),
        foresight=Foresight.of(m, config, fblocks=layout.fblocks, manifold=layout.manifold),
        state=state,
        answers=Answers(layout, model=m, data=data, kf=kf, state=state, dt=config.dt),
    )  # fmt: skip


def _sigma_points(
    config: EstimatorConfig,
    layout: FilterLayout,
    *,
    sqrt: RobustCholesky,
    x_manifold: SplitManifold | None,
) -> MerweScaled | Simplex | UniformSpherical:
    """The sigma scheme; SIMPLEX_LINEAR_FORCE is SIMPLEX, over [q, qd] where it applies."""
    linear = config.sigma_points == SigmaScheme.SIMPLEX_LINEAR_FORCE
    return make_sigma_points(
        SigmaScheme.SIMPLEX if linear else config.sigma_points,
        n=layout.order * layout.nv if layout.linear_force else layout.n,
        alpha=config.alpha,
        beta=config.beta,
        kappa=config.kappa,
        sqrt=sqrt,
        add=x_manifold.add if x_manifold is not None else None,
    )


def _core(
    config: EstimatorConfig,
    layout: FilterLayout,
    *,
    model: mujoco.MjModel,
    data: mujoco.MjData,
    points: MerweScaled | Simplex | UniformSpherical,
    process: SigmaProcess,
    ut: Callable[..., tuple[np.ndarray, np.ndarray]],
    sqrt: RobustCholesky,
    x_manifold: SplitManifold | None,
) -> FilterCore:
    """The engine's core over this state and measurement: the native one, or filterpy's (or its
    faster FastUKF, or the LinearForceUKF) with the process model in Python."""
    if config.engine == Engine.NATIVE and not layout.linear_force:
        return NativeUKF(
            model, points=points, z_index=layout.z_index, nstep=config.steps_per_tick,
            inputs=_INPUTS[layout.scenario], fblocks=layout.fblocks, controlled=layout.controlled,
            manifold=x_manifold,
        )  # fmt: skip
    z_manifold = SplitManifold(model, rest=layout.z_size - layout.nq) if layout.manifold else None
    z_index = layout.z_index
    kwargs: dict[str, object] = {
        "dim_x": layout.n,
        "dim_z": layout.z_tangent,
        "dt": config.dt,
        "hx": lambda x: np.asarray(x[z_index]),
        "fx": None,
        "points": points,
        "sqrt_fn": sqrt,
        "x_mean_fn": x_manifold.mean if x_manifold is not None else None,
        "z_mean_fn": z_manifold.mean if z_manifold is not None else None,
        "residual_x": x_manifold.residual if x_manifold is not None else None,
        "residual_z": z_manifold.residual if z_manifold is not None else None,
        "state_add": x_manifold.add if x_manifold is not None else None,
    }
    inner: BatchedUKF
    if layout.linear_force:
        inner = LinearForceUKF(
            motion=layout.order * layout.nv, propagate_forced=process.propagate_linear_force,
            response=process.force_response, z_index=z_index, propagate=process.propagate,
            vector=True, **kwargs,
        )  # fmt: skip
    elif config.engine == Engine.FAST:
        inner = FastUKF(propagate=process.propagate, vector=not layout.manifold, z_index=z_index, **kwargs)
    else:
        inner = BatchedUKF(propagate=process.propagate, vector=not layout.manifold, **kwargs)
    return PythonCore(inner, process=process, ut=ut, model=model, data=data)


def _noise_adapter(
    config: EstimatorConfig, layout: FilterLayout, *, noise: UkfNoise, Q: np.ndarray
) -> NoiseAdapter | NativeNoiseAdapter | None:
    if config.noise_model != NoiseModel.ADAPTIVE:
        return None
    adapter = NativeNoiseAdapter if config.engine == Engine.NATIVE else NoiseAdapter
    return adapter(
        r0=np.full(layout.z_tangent, config.r),
        q0=Q,
        adapt_q=noise.adapt_q_mask(),
        inflate=layout.driven,
    )
