"""A UKF's answer over a gap, where the forecast combination answers (estimation/foresight.py):
the combination's answer in place of the filter's prediction, and what the frame that ends the
gap says the answers were worth::

    estimate = combined(parts, estimate)     # a tick without its frame
    gap_nis = answer_nis(parts, z, None)     # the frame that ends the gap, before its update
"""

from __future__ import annotations

import numpy as np

from jitdyn.server.estimation.forecast import CombinedForecast
from jitdyn.server.estimation.interface import Estimate
from jitdyn.server.estimation.parts import FilterParts
from jitdyn.vocabulary import Channel

__all__ = ["answer_nis", "combined", "forecast"]


def combined(parts: FilterParts, estimate: Estimate) -> Estimate:
    """Over a gap: the forecast combination's answer, when its weights are learnt; else `estimate`."""
    if parts.foresight is None or parts.state.ticks_since_update == 0:
        return estimate
    answer = forecast(parts)
    if answer is None:
        return estimate
    # The unknown force answered is the one under which the physics follows the forecast: the
    # inverse dynamics of its q, qd and qdd (so torques over a gap agree with the motion).
    force = parts.answers.inverse(answer.qpos, answer.qvel, answer.qacc)
    return parts.foresight.combined(estimate, answer, force=force)


def forecast(parts: FilterParts, *, ended: bool = False) -> CombinedForecast | None:
    """The combination's answer now (ended: the gap's last), net of the frames' noise."""
    if parts.foresight is None:
        return None
    r = parts.adapter.r_diagonal if parts.adapter is not None else None
    measures_qvel = parts.layout.measures(Channel.QVEL)
    return parts.foresight.answer(r_diagonal=r, measures_qvel=measures_qvel, ended=ended)


def answer_nis(parts: FilterParts, z: np.ndarray, nis: float | None) -> float | None:
    """The NIS of the frame z that ends a gap against the gap's last answer, or `nis` where the
    filter answered (Foresight.gap_nis)."""
    if parts.foresight is None:
        raise RuntimeError("unreachable: a gap's answers are scored only where the combination answers")
    # The gap's last answer: mu learns what the answers given were worth (past the scored
    # horizon they were the filter's, and `forecast` says None).
    answer = forecast(parts, ended=True) if not parts.layout.manifold else None
    return parts.foresight.gap_nis(z, P=parts.kf.P, R=parts.kf.R, answer=answer, nis=nis)
