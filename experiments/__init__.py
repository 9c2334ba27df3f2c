"""jitdyn.experiments: the research harness (simulated and recorded objects, network emulation,
metrics, the thesis' experiments, reports and plots) and the demo.

`jitdyn experiments` (jitdyn.experiments.reproduce) needs jitdyn[experiments] for its plots; the
demo (jitdyn.experiments.demo) needs only the base install. Nothing heavy is imported here.
"""

from __future__ import annotations

from typing import Any

__all__ = ["EXPERIMENTS", "main", "parser", "run_experiments"]


def __getattr__(name: str) -> Any:
    # The names of jitdyn.experiments.reproduce, imported on first use: importing the package (for
    # the demo) must not import matplotlib.
    if name in __all__:
        from jitdyn.experiments import reproduce

        return getattr(reproduce, name)
    raise AttributeError(f"module 'jitdyn.experiments' has no attribute {name!r}")
