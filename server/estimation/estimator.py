"""The names this module used to define, re-imported from where they live now, so that code outside
estimation keeps working until it imports them from there: the protocol and its value types from
estimation/interface.py, the settings from estimation/config.py, the state layouts from
estimation/layout.py and the words from jitdyn.vocabulary. New code imports from those.
"""

from __future__ import annotations

from jitdyn.server.estimation.config import (
    CHANNELS,
    DRIVEN_ALPHA,
    DRIVEN_FORCE_MODEL,
    DRIVEN_FORCE_VAR,
    DRIVEN_Q_VAR,
    DRIVEN_R,
    LARGE_STATE,
    SETTING_FIELDS,
    EstimatorConfig,
    check_against_model,
    default_scenario,
    is_driven,
    is_pendulum_like,
    preset_values,
    resolve_config,
    steps_per_tick,
)
from jitdyn.server.estimation.interface import (
    Estimate,
    Estimator,
    Measurement,
    check_measurement,
    check_vector,
    read_only,
)
from jitdyn.server.estimation.layout import (
    derivative_order,
    force_blocks,
    linear_force_applies,
    state_dimension,
)
from jitdyn.vocabulary import (
    Channel,
    EstimatorKind,
    ForceModel,
    Forecast,
    NoiseModel,
    Preset,
    Scenario,
    SigmaScheme,
    WrongModel,
)

__all__ = [
    "CHANNELS",
    "DRIVEN_ALPHA",
    "DRIVEN_FORCE_MODEL",
    "DRIVEN_FORCE_VAR",
    "DRIVEN_Q_VAR",
    "DRIVEN_R",
    "LARGE_STATE",
    "SETTING_FIELDS",
    "Channel",
    "Estimate",
    "Estimator",
    "EstimatorConfig",
    "EstimatorKind",
    "ForceModel",
    "Forecast",
    "Measurement",
    "NoiseModel",
    "Preset",
    "Scenario",
    "SigmaScheme",
    "WrongModel",
    "check_against_model",
    "check_measurement",
    "check_vector",
    "default_scenario",
    "derivative_order",
    "force_blocks",
    "is_driven",
    "is_pendulum_like",
    "linear_force_applies",
    "preset_values",
    "read_only",
    "resolve_config",
    "state_dimension",
    "steps_per_tick",
]
