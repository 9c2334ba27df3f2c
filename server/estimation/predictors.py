"""The forecast combination's predictors (estimation/forecast.py), as named objects in one place.

A predictor family reads what a probe holds, S probes at a time (`Probes`): the MODEL rollout's
state, carried forward by the combiner's physics; the anchor of the frame the probe started from
(q0, qd0, qdd0); its age t; and, with the learned predictor, motion matching's continuation. It
returns its predictors' (q, qd, qdd), each (S, len(names), nv). The combination weighs the
families' predictors in the order of FAMILIES, which is the order of `Result.forecast_weights`;
`Result.forecast_predictors` names them on the wire.

Adding a predictor is one family (a new file, or a class here) and one entry in FAMILIES::

    class DampedVelocity:
        names = ("DAMPED_VELOCITY",)
        learned = False

        def predict(self, probes):
            ...

The native engine computes the default families (MODEL, the IEEE 1278 extrapolators, LEARNED) in
C++ (native/forecast.cc); a combination with a family it lacks, such as one added here, runs the
Python combiner, estimation/forecast.py, with no other change (estimation/foresight.py checks the
names, native/combiner.py's NATIVE_PREDICTORS).

A `learned` family predicts from the session's own frames: it takes no weight at a horizon until
it has scored there LEARNED_SAMPLES times from a real match, and it has no vote on a regime change
(estimation/forecast.py). The combiner builds the LEARNED family's continuation itself (its probes
wait to be matched, and their scoring batched); the others read only the probe.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final, Protocol

import numpy as np

from jitdyn.server.estimation.extrapolators import EXTRAPOLATORS, moved

__all__ = [
    "FAMILIES",
    "LEARNED",
    "PRIOR",
    "Family",
    "Ieee1278",
    "Learned",
    "ModelRollout",
    "Prior",
    "Probes",
    "names",
]

Predictions = tuple[np.ndarray, np.ndarray, np.ndarray]


@dataclass(frozen=True)
class Probes:
    """S probes as the predictors read them: the MODEL rollout's qpos, qvel, qacc (S, nv); the
    anchor q0, v0, a0 (S, nv); t (S, 1) seconds since the anchor's frame; learned: motion
    matching's (qpos, qvel, qacc) (S, nv) each, when the combiner has the learned predictor; prior:
    the prior of human motion's, when it has that."""

    qpos: np.ndarray
    qvel: np.ndarray
    qacc: np.ndarray
    q0: np.ndarray
    v0: np.ndarray
    a0: np.ndarray
    t: np.ndarray
    learned: Predictions | None = None
    prior: Predictions | None = None


class Family(Protocol):
    """Predictors computed together: their names, in the weights' order, and their predictions."""

    names: tuple[str, ...]
    learned: bool

    def predict(self, probes: Probes) -> Predictions:
        """(q, qd, qdd) of each predictor, (S, len(names), nv) each."""
        ...


class ModelRollout:
    """MODEL: the filter's posterior mean rolled out by the process model under its estimated
    force (held, or ramped with its rate), one tick per tick: the physics' forecast."""

    names: tuple[str, ...] = ("MODEL",)
    learned: bool = False

    def predict(self, probes: Probes) -> Predictions:
        return probes.qpos[:, None, :], probes.qvel[:, None, :], probes.qacc[:, None, :]


class Ieee1278:
    """IEEE 1278's extrapolators from the probe's frame, in one pass (estimation/extrapolators.py)."""

    names: tuple[str, ...] = tuple(str(kind.value) for kind in EXTRAPOLATORS)
    learned: bool = False

    def predict(self, probes: Probes) -> Predictions:
        return moved(probes.q0, probes.v0, probes.a0, probes.t)


class Learned:
    """LEARNED: motion matching over the session's own frames (estimation/matching.py): what
    followed the past moments most like the probe's frame."""

    names: tuple[str, ...] = ("LEARNED",)
    learned: bool = True

    def predict(self, probes: Probes) -> Predictions:
        if probes.learned is None:
            raise ValueError("the learned predictor needs the combiner's motion matching")
        q, v, a = probes.learned
        return q[:, None, :], v[:, None, :], a[:, None, :]


class Prior:
    """PRIOR: motion matching over other people's walking (estimation/prior.py) for the joints whose
    role is a hip, knee or ankle; the others as the session's own history (LEARNED) answers them.
    Its weight before the session has scores of its own comes from its scores on those people
    (docs/decisions/0186-prior-predictor.md)."""

    names: tuple[str, ...] = ("PRIOR",)
    learned: bool = False

    def predict(self, probes: Probes) -> Predictions:
        if probes.prior is None:
            raise ValueError("the prior predictor needs the combiner's prior matcher")
        q, v, a = probes.prior
        return q[:, None, :], v[:, None, :], a[:, None, :]


# The families of every combination, in the weights' order; a combiner with the learned predictor
# adds LEARNED after them, and one with the prior of human motion PRIOR after that.
FAMILIES: Final[tuple[Family, ...]] = (ModelRollout(), Ieee1278())
LEARNED: Final[Family] = Learned()
PRIOR: Final[Family] = Prior()


def names(families: tuple[Family, ...]) -> tuple[str, ...]:
    """The predictors' names in the order of the weights; each name once."""
    out = tuple(name for family in families for name in family.names)
    if len(set(out)) != len(out):
        raise ValueError(f"predictor names must be unique, got {out}")
    return out
