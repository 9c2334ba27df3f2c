"""What a tick of each estimator candidate costs on a model, stored with it: measured once on the
server when the model is registered (server/runtime/choice.py), read at every REALTIME open to
choose the session's estimator, never measured again
(docs/decisions/0204-the-estimator-chosen-by-stored-cost.md).

    store_costs(engine, model_id, costs)     # the first stored wins; returns what is stored
    read_costs(engine, [model_id])           # {model_id: costs} for those measured
"""

from __future__ import annotations

import datetime
import itertools
import json
import math
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass

import sqlalchemy as sa

from jitdyn.storage.schema import model_costs

__all__ = ["CandidateCost", "read_costs", "store_costs"]


@dataclass(frozen=True, kw_only=True)
class CandidateCost:
    """One estimator candidate of a model in one scenario, and its measured cost: `seconds[i]` of
    CPU for a tick spanning `steps[i]` physics steps of the model's timestep (steps ascending).
    Between two, a tick costs their straight line; past the last, the last two's, never falling."""

    scenario: str  # a Scenario's name
    estimator: str  # an EstimatorKind's name
    sigma_points: str  # a SigmaScheme's name; "" for dead reckoning
    steps: tuple[int, ...]
    seconds: tuple[float, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "steps", tuple(int(s) for s in self.steps))
        object.__setattr__(self, "seconds", tuple(float(s) for s in self.seconds))
        if len(self.steps) < 2 or len(self.steps) != len(self.seconds):
            raise ValueError(
                f"CandidateCost needs two or more (steps, seconds), got {self.steps}, {self.seconds}"
            )
        if any(b <= a for a, b in itertools.pairwise(self.steps)) or self.steps[0] < 1:
            raise ValueError(f"CandidateCost.steps must ascend from >= 1, got {self.steps}")
        if not all(math.isfinite(s) and s >= 0 for s in self.seconds):
            raise ValueError(f"CandidateCost.seconds must be finite and >= 0, got {self.seconds}")

    def at(self, steps: int) -> float:
        """CPU seconds of a tick that spans `steps` physics steps."""
        xs, ys = self.steps, self.seconds
        if steps <= xs[0]:
            return ys[0]
        i = next((k for k in range(1, len(xs)) if steps <= xs[k]), len(xs) - 1)
        slope = (ys[i] - ys[i - 1]) / (xs[i] - xs[i - 1])
        if steps > xs[-1]:
            slope = max(0.0, slope)
        return ys[i - 1] + slope * (steps - xs[i - 1])


def _encode(costs: Sequence[CandidateCost]) -> str:
    return json.dumps([asdict(cost) for cost in costs], sort_keys=True)  # tuples as lists


def _decode(text: str) -> tuple[CandidateCost, ...]:
    return tuple(CandidateCost(**entry) for entry in json.loads(text))


def read_costs(engine: sa.Engine, model_ids: Iterable[str]) -> dict[str, tuple[CandidateCost, ...]]:
    """The stored costs of those of `model_ids` that have been measured."""
    ids = sorted(set(model_ids))
    if not ids:
        return {}
    with engine.connect() as connection:
        rows = connection.execute(
            sa.select(model_costs.c.id, model_costs.c.costs_json).where(model_costs.c.id.in_(ids))
        ).all()
    return {row.id: _decode(row.costs_json) for row in rows}


def store_costs(
    engine: sa.Engine, model_id: str, costs: Sequence[CandidateCost]
) -> tuple[CandidateCost, ...]:
    """Store the costs of `model_id` unless some are stored already; return the stored ones. Two
    servers measuring the same model at once both end up choosing from the first one's figures."""
    try:
        with engine.begin() as connection:
            connection.execute(
                sa.insert(model_costs).values(
                    id=model_id, costs_json=_encode(costs), measured_at=datetime.datetime.now(datetime.UTC)
                )
            )
    except sa.exc.IntegrityError:
        pass  # measured first elsewhere: that measurement stands
    return read_costs(engine, [model_id])[model_id]
