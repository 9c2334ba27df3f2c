"""What the prior of human motion costs a tick, its lookup by a pass over every candidate against
its lookup by k-d tree, side by side in one run (server/estimation/prior.py;
docs/decisions/0190-prior-lookup-by-tree.md).

A 3-joint leg (hip, knee, ankle; experiments/recorded.py's chain, whose joint names give the roles)
replays a walk the prior does not hold (its person left out of the library) at 100 Hz, every frame
arriving; each arm is a DRIVEN session's forecast combination (learner on, horizon 0.5 s), fed the
walk's frames from the same tick: without the prior, with the prior searching every candidate
(`exhaustive`, what a match did before), and with the prior's tree; and the same combination in
the native engine (native/forecast.cc, prior.cc) without the prior and with it. A round runs each
arm for `--ticks` ticks with a frame (advance and observe: the scoring, a match every fourth tick),
in turn; the CPU time per tick of each arm is the best of the rounds, and the prior's cost is an
arm's less the arm of the same engine without it. The lookup alone (one match, both ways, on the
same frames) is printed too, with how many matches found the same library moments.

    python -m benchmarks.prior                       # moore's walk, left out
    python -m benchmarks.prior --subject fukuchi --rounds 7
    python -m benchmarks.prior --no-ankle            # a leg of hip and knee alone: more candidates
"""

from __future__ import annotations

import argparse
import time

import mujoco
import numpy as np

from jitdyn.experiments.recorded import chain_mjcf
from jitdyn.registry.info import describe_model
from jitdyn.roles import joint_roles
from jitdyn.server.estimation.forecast import ForecastCombiner
from jitdyn.server.estimation.native.combiner import NativeCombiner
from jitdyn.server.estimation.prior import PriorMatcher, legs_of, library
from jitdyn.server.estimation.propagate import process_model

DT = 0.01
ARMS = ("no prior", "prior, every candidate", "prior, k-d tree", "native, no prior", "native, prior")
# Each arm's baseline: the arm of the same engine without the prior.
BASELINE = {arm: ARMS[3] if arm.startswith("native") else ARMS[0] for arm in ARMS}


def walk(subject: str) -> tuple[np.ndarray, np.ndarray]:
    """(T, 3) q and qd of `subject`'s legs as the library holds them, clips end to end (each at its
    recorded speed and the four others)."""
    full = library()
    rows = np.flatnonzero(full.subject == full.subjects.index(subject))
    q = np.nan_to_num(full.q[rows])
    return q, np.gradient(q, DT, axis=0)


def leg(no_ankle: bool) -> mujoco.MjModel:
    """The chain; no_ankle: its ankle named so that it has no role (a leg of hip and knee alone,
    whose match searches some 32,000 candidates of 8 features against 9,500 of 12)."""
    joints = ("hip_flexion_r", "knee_flexion_r", "foot_hinge") if no_ankle else None
    return mujoco.MjModel.from_xml_string(chain_mjcf(joints=joints))


def combiner(arm: str, subject: str, no_ankle: bool = False) -> ForecastCombiner | NativeCombiner:
    model = leg(no_ankle)
    legs = legs_of(joint_roles(describe_model(model).joints, ()))
    prior = None
    if BASELINE[arm] != arm:
        prior = PriorMatcher(library((subject,)), legs=legs, nv=3, dt=DT, exhaustive=arm == ARMS[1])
    process = process_model(model, scenario="DRIVEN")
    if arm.startswith("native"):
        return NativeCombiner(process, dt=DT, steps_per_tick=5, horizon=50, prior=prior)
    return ForecastCombiner(process, dt=DT, steps_per_tick=5, horizon=50, learner=True, prior=prior)


def run(c: ForecastCombiner | NativeCombiner, q: np.ndarray, v: np.ndarray, ticks: range) -> float:
    """CPU seconds of `ticks` ticks with their frames."""
    zeros, act = np.zeros(3), np.zeros(0)
    began = time.thread_time()
    for k in ticks:
        j = k % q.shape[0]
        c.advance()
        c.observe(q[j], v[j], mean_qpos=q[j], mean_qvel=v[j], act=act, force=zeros, rate=None)
    return time.thread_time() - began


def lookups(subject: str, q: np.ndarray, v: np.ndarray, count: int, no_ankle: bool = False) -> None:
    model = leg(no_ankle)
    legs = legs_of(joint_roles(describe_model(model).joints, ()))
    matchers = [
        PriorMatcher(library((subject,)), legs=legs, nv=3, dt=DT, exhaustive=e) for e in (True, False)
    ]
    spent, same, found = [0.0, 0.0], 0, []
    for k in range(count):
        for m in matchers:
            m.record(k, q[k % q.shape[0]], v[k % q.shape[0]])
        if k < 20:
            continue
        for i, m in enumerate(matchers):
            began = time.thread_time()
            found.append(m.match(k)[0])
            spent[i] += time.thread_time() - began
        same += set(found[-2].ravel().tolist()) == set(found[-1].ravel().tolist())
    n = count - 20
    print(
        f"one match: every candidate {spent[0] / n * 1e6:.0f} us, k-d tree {spent[1] / n * 1e6:.0f} us "
        f"({spent[0] / spent[1]:.1f} x); the same library moments in {same} of {n} matches"
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--subject", default="moore", help="whose walk, left out of the prior")
    parser.add_argument("--ticks", type=int, default=300)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument(
        "--no-ankle", action="store_true", help="a leg of hip and knee alone (the ankle has no role)"
    )
    args = parser.parse_args()
    q, v = walk(args.subject)
    combiners = {arm: combiner(arm, args.subject, args.no_ankle) for arm in ARMS}
    warm = 60  # every probe alive
    for c in combiners.values():
        run(c, q, v, range(warm))
    best = dict.fromkeys(ARMS, float("inf"))
    start = warm
    for _ in range(args.rounds):
        for arm in ARMS:  # alternated, on the same frames
            best[arm] = min(best[arm], run(combiners[arm], q, v, range(start, start + args.ticks)))
        start += args.ticks
    per_tick = {arm: best[arm] / args.ticks * 1e6 for arm in ARMS}
    print(
        f"{args.subject}'s walk, left out, on a leg of {'hip and knee' if args.no_ankle else 'hip, knee and ankle'}; "
        f"a tick with a frame, the best of {args.rounds} rounds of {args.ticks}:"
    )
    for arm in ARMS:
        base = BASELINE[arm]
        extra = "" if arm == base else f"  (the prior adds {per_tick[arm] - per_tick[base]:.0f} us)"
        print(f"  {arm:24s} {per_tick[arm]:7.0f} us{extra}")
    python, native = per_tick[ARMS[2]], per_tick[ARMS[4]]
    print(f"  the combination with the prior, Python / native: {python / native:.1f} x")
    lookups(args.subject, q, v, 400, args.no_ankle)


if __name__ == "__main__":
    main()
