"""What batching the sessions of a model whose ticks fall due together would save, per session.

For K sessions of pendulum_3 PASSIVE (Merwe points, n = 6, 13 points, 2 physics steps a tick):
    rollout   K rollout calls of 13 points against one call of 13 K points (the same Propagator,
              one worker)
    algebra   K FastUKF predict + update (the propagation a copy) against the same maths on stacked
              (K, n, n) arrays: one batched Cholesky, einsum, one batched inverse
CPU time per session and tick, medians of interleaved rounds.

    python -m benchmarks.batch_sessions [--sessions 1 4 16 64]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import mujoco
import numpy as np

from jitdyn.server.estimation.fast import FastUKF
from jitdyn.server.estimation.pool import WorkerPool
from jitdyn.server.estimation.propagate import Inputs, Propagator, process_model
from jitdyn.server.estimation.sigma import MerweScaled

MODEL = Path(__file__).resolve().parents[1] / "models" / "pendulum_3.xml"


def cpu(call: object, repeats: int) -> float:
    started = time.process_time()
    for _ in range(repeats):
        call()  # type: ignore[operator]
    return (time.process_time() - started) / repeats


def rollouts(model: mujoco.MjModel, pool: WorkerPool, k: int, repeats: int) -> tuple[float, float]:
    """(separate, batched) CPU per session of one tick's propagation."""
    one = Propagator(model, pool=pool, nsigma=13, nstep=2, inputs=Inputs.NONE)
    many = Propagator(model, pool=pool, nsigma=13 * k, nstep=2, inputs=Inputs.NONE)
    rng = np.random.default_rng(0)
    q, v = 0.3 * rng.standard_normal((13 * k, 3)), rng.standard_normal((13 * k, 3))
    act = np.zeros(0)

    def separate() -> None:
        for s in range(k):
            one(q[13 * s : 13 * s + 13], v[13 * s : 13 * s + 13], act=act)

    def batched() -> None:
        many(q, v, act=act)

    return cpu(separate, repeats) / k, cpu(batched, repeats) / k


def algebra(k: int, repeats: int) -> tuple[float, float]:
    """(separate, stacked) CPU per session of a predict + update's algebra, no physics."""
    n, m = 6, 6
    rng = np.random.default_rng(1)
    A = rng.standard_normal((k, n, n))
    P0 = A @ A.transpose(0, 2, 1) / n + np.eye(n)
    x0, z = rng.standard_normal((k, n)), rng.standard_normal((k, m))
    Q, R = 0.01 * np.eye(n), 0.01 * np.eye(m)
    points = MerweScaled(n, alpha=1.0, beta=2.0, kappa=0.0)
    filters = []
    for s in range(k):
        kf = FastUKF(
            propagate=lambda sigmas, nstep: sigmas * 1.0,
            vector=True,
            z_index=slice(0, m),
            dim_x=n,
            dim_z=m,
            dt=0.05,
            hx=None,
            fx=None,
            points=points,
        )
        kf.x, kf.P, kf.Q, kf.R = x0[s].copy(), P0[s].copy(), Q, R
        filters.append(kf)

    def separate() -> None:
        for s, kf in enumerate(filters):
            kf.x, kf.P = x0[s].copy(), P0[s].copy()
            kf.predict()
            kf.update(z[s])

    Wm, Wc, scale = points.Wm, points.Wc, points._scale

    def draw(x: np.ndarray, P: np.ndarray) -> np.ndarray:
        L = np.linalg.cholesky(scale * P)  # (K, n, n) lower: rows of U are columns of L
        U = L.transpose(0, 2, 1)
        return np.concatenate([x[:, None, :], x[:, None, :] + U, x[:, None, :] - U], axis=1)

    def stacked() -> None:
        sigmas = draw(x0, P0)
        moved = sigmas * 1.0
        x = np.einsum("p,kpn->kn", Wm, moved)
        y = moved - x[:, None, :]
        P = np.einsum("kpi,p,kpj->kij", y, Wc, y) + Q
        sigmas = draw(x, P)
        h = sigmas[:, :, :m]
        zp = np.einsum("p,kpn->kn", Wm, h)
        dz = h - zp[:, None, :]
        S = np.einsum("kpi,p,kpj->kij", dz, Wc, dz) + R
        Pxz = np.einsum("kpi,p,kpj->kij", sigmas - x[:, None, :], Wc, dz)
        K = Pxz @ np.linalg.inv(S)
        x = x + np.einsum("kij,kj->ki", K, z - zp)
        P = P - K @ S @ K.transpose(0, 2, 1)

    return cpu(separate, repeats) / k, cpu(stacked, repeats) / k


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sessions", type=int, nargs="+", default=[1, 4, 16, 64])
    parser.add_argument("--rounds", type=int, default=7)
    args = parser.parse_args(argv)
    model = process_model(mujoco.MjModel.from_xml_path(str(MODEL)), scenario="PASSIVE")
    print(
        f"# load average {os.getloadavg()[0]:.2f}; CPU us per session and tick, medians of {args.rounds} rounds"
    )
    print("| sessions K | rollout: K calls | one call | ratio | algebra: K filters | stacked | ratio |")
    print("|---|---|---|---|---|---|---|")
    with WorkerPool(1) as pool:
        for k in args.sessions:
            repeats = max(3, 200 // k)
            r: list[tuple[float, float]] = []
            a: list[tuple[float, float]] = []
            for _ in range(args.rounds):
                r.append(rollouts(model, pool, k, repeats))
                a.append(algebra(k, repeats))
            rs, rb = (statistics.median(t[i] for t in r) * 1e6 for i in (0, 1))
            sa, sb = (statistics.median(t[i] for t in a) * 1e6 for i in (0, 1))
            print(
                f"| {k} | {rs:.0f} | {rb:.0f} | {rb / rs:.2f} | {sa:.0f} | {sb:.0f} | {sb / sa:.2f} |",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
