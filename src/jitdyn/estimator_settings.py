"""The estimator settings a session, a model's metadata or a client may set: one table, one row each.

The registry, the transport, the SDK, the estimator and the README's settings section all read
`SETTINGS`; each rule (a range, the dt multiple, which choice goes with which scenario) is written
here once::

    SETTINGS["alpha"].check(0.5, argument="open.estimator.alpha")         # 0.5
    check_settings({"alpha": 2.0}, argument="open.estimator")             # InvalidArgument
    check_for_scenario(Scenario.CONTROLLED, {"wrong_model": WrongModel.DRIVEN}, argument="open")
    steps_per_tick(0.05, 0.002, argument="open.dt")                       # 25

Enum settings take their vocabulary member (or its name); number settings a finite float.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Final

from jitdyn.errors import InvalidArgument
from jitdyn.vocabulary import (
    EstimatorKind,
    ForceModel,
    Forecast,
    NoiseModel,
    Preset,
    Scenario,
    SigmaScheme,
    WrongModel,
    parse,
)

__all__ = [
    "NUMBER_SETTINGS",
    "SETTINGS",
    "EstimatorSetting",
    "SettingValue",
    "check_for_scenario",
    "check_settings",
    "settings_markdown",
    "steps_per_tick",
]

SettingValue = enum.StrEnum | float


@dataclass(frozen=True, kw_only=True)
class EstimatorSetting:
    """One setting: its name (a field of jitdyn.v1.EstimatorSettings), its type (a vocabulary enum,
    or None for a number), its range for a number (`low`/`high`, open or closed ends), its default
    under each preset (as text, for people), and what it does."""

    name: str
    choices: type[enum.StrEnum] | None = None
    low: float | None = None
    low_open: bool = False
    high: float | None = None
    high_open: bool = False
    thesis: str
    jitdyn: str
    doc: str

    @property
    def range_text(self) -> str:
        """The range in interval notation ("(0, 1]", "> 0", "any finite number"), or the choices."""
        if self.choices is not None:
            return ", ".join(member.name for member in self.choices)
        if self.low is not None and self.high is not None:
            return (
                f"{'(' if self.low_open else '['}{self.low:g}, {self.high:g}{')' if self.high_open else ']'}"
            )
        if self.low is not None:
            return f"{'>' if self.low_open else '>='} {self.low:g}"
        if self.high is not None:
            return f"{'<' if self.high_open else '<='} {self.high:g}"
        return "any finite number"

    def check(self, value: object, *, argument: str) -> SettingValue:
        """`value` as this setting's type, inside its range; InvalidArgument naming `argument`."""
        if self.choices is not None:
            return parse(self.choices, value, argument=argument)
        if isinstance(value, bool) or not isinstance(value, (int, float)) and not _is_numpy_number(value):
            raise InvalidArgument(f"{argument} must be a number, got {value!r}")
        number = float(value)  # type: ignore[arg-type]
        if not math.isfinite(number):
            raise InvalidArgument(f"{argument} must be finite, got {number}")
        below = self.low is not None and (number <= self.low if self.low_open else number < self.low)
        above = self.high is not None and (number >= self.high if self.high_open else number > self.high)
        if below or above:
            raise InvalidArgument(f"{argument} must be {_in(self.range_text)}, got {number:g}")
        return number


def _in(range_text: str) -> str:
    return f"in {range_text}" if range_text[0] in "([" else range_text


def _is_numpy_number(value: object) -> bool:
    # numpy scalars without importing numpy here: they carry __float__ and a dtype
    return hasattr(value, "dtype") and hasattr(value, "__float__") and getattr(value, "shape", None) == ()


_ROWS: Final = (
    EstimatorSetting(
        name="estimator",
        choices=EstimatorKind,
        thesis="UKF",
        jitdyn="UKF",
        doc="The estimator: the UKF, the linearised filter (EKF: PASSIVE, EXTERNAL and DRIVEN, fixed "
        "noise, its own forecast), or an IEEE 1278 dead-reckoning extrapolator.",
    ),
    EstimatorSetting(
        name="preset",
        choices=Preset,
        thesis="-",
        jitdyn="-",
        doc="The preset that fills the settings left unset (JITDYN unless named).",
    ),
    EstimatorSetting(
        name="sigma_points",
        choices=SigmaScheme,
        thesis="MERWE",
        jitdyn="MERWE below a state dimension of 32, SIMPLEX from 32 (SIMPLEX_LINEAR_FORCE in DRIVEN where it applies)",
        doc="The sigma-point scheme.",
    ),
    EstimatorSetting(
        name="alpha",
        low=0.0,
        low_open=True,
        high=1.0,
        thesis="0.001",
        jitdyn="1 (0.3 in DRIVEN)",
        doc="Spread of the sigma points around the mean.",
    ),
    EstimatorSetting(
        name="beta", thesis="2", jitdyn="2", doc="Prior knowledge of the distribution (2: Gaussian)."
    ),
    EstimatorSetting(
        name="kappa",
        thesis="3 - n for pendulum-like models, else 0",
        jitdyn="max(0, 3 - n)",
        doc="Secondary scaling; n + kappa must be > 0 for MERWE points (n: the state dimension).",
    ),
    EstimatorSetting(
        name="p0", low=0.0, low_open=True, thesis="0.2", jitdyn="0.2", doc="Initial covariance P0 = p0 I."
    ),
    EstimatorSetting(
        name="q_var",
        low=0.0,
        thesis="0.1 PASSIVE, 0.2 CONTROLLED (5 not pendulum-like), 50 EXTERNAL",
        jitdyn="as THESIS; 1e-4 in DRIVEN",
        doc="Variance of the discrete white-noise process model, per joint block.",
    ),
    EstimatorSetting(
        name="r",
        low=0.0,
        low_open=True,
        thesis="0.01",
        jitdyn="0.01",
        doc="Measurement noise R = r I over the measured channels (ADAPTIVE: its start).",
    ),
    EstimatorSetting(
        name="force_model",
        choices=ForceModel,
        thesis="RANDOM_WALK",
        jitdyn="RANDOM_WALK",
        doc="DRIVEN: how the unknown force evolves between ticks.",
    ),
    EstimatorSetting(
        name="force_var",
        low=0.0,
        thesis="10",
        jitdyn="10",
        doc="DRIVEN: the unknown force's process noise, as the acceleration it would give each dof alone.",
    ),
    EstimatorSetting(
        name="noise_model",
        choices=NoiseModel,
        thesis="FIXED",
        jitdyn="ADAPTIVE in DRIVEN, else FIXED",
        doc="Fixed noise, or R and Q that follow the innovations within bounds.",
    ),
    EstimatorSetting(
        name="forecast",
        choices=Forecast,
        thesis="FILTER",
        jitdyn="COMBINED in DRIVEN below a state dimension of 32, else FILTER",
        doc="What answers a tick without a frame: the filter, or the scored combination of predictors.",
    ),
    EstimatorSetting(
        name="wrong_model",
        choices=WrongModel,
        thesis="KEEP",
        jitdyn="DRIVEN in PASSIVE, RESTART in CONTROLLED and EXTERNAL, KEEP in DRIVEN",
        doc="What a NIS far out does: nothing, PASSIVE becomes DRIVEN, or a restart from the frame.",
    ),
)

# Every setting by name, in jitdyn.v1.EstimatorSettings' field order.
SETTINGS: Final[Mapping[str, EstimatorSetting]] = {row.name: row for row in _ROWS}
# The number settings' names, in order.
NUMBER_SETTINGS: Final = tuple(row.name for row in _ROWS if row.choices is None)


def check_settings(values: Mapping[str, object], *, argument: str) -> dict[str, SettingValue]:
    """Every entry of `values` checked against its row; an unknown name is InvalidArgument naming
    `argument` and the settings there are."""
    if not isinstance(values, Mapping):
        raise InvalidArgument(f"{argument} must map setting names to values, got {values!r}")
    checked: dict[str, SettingValue] = {}
    for name, value in values.items():
        row = SETTINGS.get(name) if isinstance(name, str) else None
        if row is None:
            raise InvalidArgument(
                f"{argument} has unknown setting {name!r}; expected one of {', '.join(SETTINGS)}"
            )
        checked[name] = row.check(value, argument=f"{argument}.{name}")
    return checked


def check_for_scenario(scenario: Scenario, settings: Mapping[str, object], *, argument: str) -> None:
    """The rules between a scenario and its settings: wrong_model DRIVEN turns a PASSIVE filter into
    a DRIVEN one, so anywhere else it would be a silent KEEP."""
    if settings.get("wrong_model") == WrongModel.DRIVEN and scenario != Scenario.PASSIVE:
        raise InvalidArgument(
            f"{argument}.wrong_model DRIVEN turns a PASSIVE filter into a DRIVEN one; the scenario is "
            f"{scenario}: choose RESTART or KEEP"
        )


def steps_per_tick(dt: float, timestep: float, *, argument: str = "dt") -> int:
    """dt / timestep, which must be a whole number >= 1; InvalidArgument naming `argument`."""
    if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not math.isfinite(dt) or dt <= 0.0:
        raise InvalidArgument(f"{argument} must be a positive number of seconds, got {dt!r}")
    steps = round(dt / timestep)
    if steps < 1 or abs(steps * timestep - dt) > 1e-9 * max(dt, 1.0):
        raise InvalidArgument(
            f"{argument} must be a whole multiple (>= 1) of the model's timestep {timestep} s, got {dt} "
            f"({dt / timestep:.6g} timesteps)"
        )
    return int(steps)


def settings_markdown() -> str:
    """The README's settings table: one row per setting."""
    lines = ["| setting | values | THESIS | JITDYN | what it does |", "|---|---|---|---|---|"]
    lines += [f"| `{r.name}` | {r.range_text} | {r.thesis} | {r.jitdyn} | {r.doc} |" for r in _ROWS]
    return "\n".join(lines)
