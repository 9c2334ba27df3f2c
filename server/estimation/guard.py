"""When a UKF starts again from a frame: the divergence guard and the wrong-model restart, as one
policy that the filter consults after each prediction and each update::

    guard = Guard(m=4, restart=True, driven=False)
    guard.count(nis)                                    # after each update
    if guard.restart_due(finite=True, largest_variance=float(P.diagonal().max())):
        ...                                             # start again from the frame; guard.start()

Divergence: the state or P turns non-finite, a posterior variance passes COVARIANCE_LIMIT, or the
NIS stays past NIS_LIMIT_PER_DIMENSION m for DIVERGENCE_TICKS updates in a row. Wrong model
(wrong_model RESTART): the NIS stays past chi-square(m)'s RESTART_QUANTILE for RESTART_UPDATES
updates in a row; an adaptive filter that is not DRIVEN also restarts after
ABSORPTIONS_BEFORE_REINIT absorptions in a row. Pure Python; `state`/`restore` for the timewarp.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

from scipy.stats import chi2

__all__ = [
    "ABSORPTIONS_BEFORE_REINIT",
    "COVARIANCE_LIMIT",
    "DIVERGENCE_TICKS",
    "NIS_LIMIT_PER_DIMENSION",
    "RESTART_QUANTILE",
    "RESTART_UPDATES",
    "Guard",
    "GuardState",
]

# An NIS of 1e6 per measured dimension is an innovation a thousand standard deviations out; one
# such tick can be a bad frame, DIVERGENCE_TICKS in a row is a filter that has lost track. A
# posterior variance of 1e14 (rad^2, m^2, (rad/s^2)^2, ...) is no estimate at all, and beyond it
# P - K S K^T loses every digit of R = 0.01.
NIS_LIMIT_PER_DIMENSION: Final = 1e6
DIVERGENCE_TICKS: Final = 10
COVARIANCE_LIMIT: Final = 1e14
# An adaptive filter whose NIS window stays far out after this many absorptions in a row starts
# again from the measurement.
ABSORPTIONS_BEFORE_REINIT: Final = 3
# wrong_model RESTART: a NIS past this quantile of chi-square(m) in RESTART_UPDATES updates in a
# row (about 1e-6 for a consistent filter) is a filter that has lost the body.
RESTART_QUANTILE: Final = 0.999
RESTART_UPDATES: Final = 2


@dataclass(frozen=True)
class GuardState:
    """A Guard's counts: updates in a row past the divergence limit (nis_run) and past the restart
    quantile (far_run), and absorptions since the NIS window last came back inside."""

    nis_run: int = 0
    far_run: int = 0
    absorptions: int = 0


class Guard:
    """The restart policy of one filter whose measurement has m dimensions (module docstring).
    restart: wrong_model RESTART; driven: a DRIVEN filter, which absorbs a wrong model into its force
    and is never restarted for absorbing."""

    def __init__(self, *, m: int, restart: bool, driven: bool) -> None:
        self._nis_limit = NIS_LIMIT_PER_DIMENSION * m
        self._restart_nis = float(chi2.ppf(RESTART_QUANTILE, m)) if restart else None
        self._driven = driven
        self._state = GuardState()

    @property
    def state(self) -> GuardState:
        return self._state

    def restore(self, state: GuardState) -> None:
        self._state = state

    def far_out(self, nis: float | None) -> bool:
        """An NIS past the divergence limit: as a run it restarts the filter; on the first frame
        after a gap it says the prediction was overconfident."""
        return nis is not None and nis > self._nis_limit

    def count(self, nis: float | None) -> None:
        """One update's NIS (None: not finite) into the runs."""
        s = self._state
        nis_run = s.nis_run + 1 if nis is None or self.far_out(nis) else 0
        far_run = s.far_run
        if self._restart_nis is not None:
            far_run = far_run + 1 if nis is None or nis > self._restart_nis else 0
        self._state = GuardState(nis_run=nis_run, far_run=far_run, absorptions=s.absorptions)

    def absorb(self) -> bool:
        """An absorption (the adaptive noise's NIS window far out); whether the filter should widen
        its covariance for it rather than wait for the restart it leads to."""
        s = self._state
        absorptions = s.absorptions + 1
        self._state = GuardState(nis_run=s.nis_run, far_run=s.far_run, absorptions=absorptions)
        return absorptions < ABSORPTIONS_BEFORE_REINIT or self._driven

    def settle(self) -> None:
        """A full NIS window that asked for no absorption: the absorptions in a row start again."""
        s = self._state
        self._state = GuardState(nis_run=s.nis_run, far_run=s.far_run, absorptions=0)

    def quiet(self) -> bool:
        """Whether the next update, whatever its NIS and short of an absorption, cannot restart the
        filter by the runs (only a divergence of x or P could): what a native tick checks itself."""
        s = self._state
        return (
            s.nis_run + 1 < DIVERGENCE_TICKS
            and (self._restart_nis is None or s.far_run + 1 < RESTART_UPDATES)
            and (self._driven or s.absorptions < ABSORPTIONS_BEFORE_REINIT)
        )

    def diverged(self, *, finite: bool, largest_variance: float) -> bool:
        """A state or covariance that is no estimate: non-finite, or a variance past the limit."""
        return not finite or largest_variance > COVARIANCE_LIMIT

    def restart_due(self, *, finite: bool, largest_variance: float) -> bool:
        """After an update: whether the filter starts again from its frame."""
        s = self._state
        return (
            self.diverged(finite=finite, largest_variance=largest_variance)
            or s.nis_run >= DIVERGENCE_TICKS
            or s.far_run >= RESTART_UPDATES
            or (s.absorptions >= ABSORPTIONS_BEFORE_REINIT and not self._driven)
        )

    def start(self) -> None:
        """The filter started from a frame: the runs start again (the absorptions do not)."""
        self._state = GuardState(absorptions=self._state.absorptions)

    def reset(self) -> None:
        """Everything starts again: a new session, or a restart after an update."""
        self._state = GuardState()
