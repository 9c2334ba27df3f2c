"""jitdyn's native estimation engine: the unscented filter's numeric work (sigma points, their
propagation through MuJoCo's C API, the unscented transform and the update) in one compiled
module, ukf.cc, which holds the filter's state and releases the GIL while it works; and a DRIVEN
session's forecast combination (forecast.cc, matching.cc, prior.cc; native/combiner.py wraps it); and a
tick's steps in one call over the three (tick.cc; native/tick.py).

The module is built by `pip install` (setup.py) against the headers of the pinned mujoco, and
handed that MuJoCo's pointers: importing it beside any other MuJoCo is refused, in one line.
"""

from __future__ import annotations

import mujoco  # loads libmujoco, which the compiled module then finds by its soname

from jitdyn.errors import FailedPrecondition

try:
    from jitdyn.server.estimation.native import _ukf
except ImportError as error:  # pragma: no cover - a broken install, said in one line
    raise ImportError(
        f"jitdyn's native engine is not built ({error}); reinstall jitdyn with a C++17 compiler "
        "present (pip install -e . in the checkout)"
    ) from error

__all__ = ["MUJOCO_VERSION", "AdapterState", "CombinerState", "SingularMatrix", "TickState", "Ukf"]

MUJOCO_VERSION = int(_ukf.MUJOCO_HEADER_VERSION)

if _ukf.mujoco_version() != MUJOCO_VERSION or mujoco.mj_version() != MUJOCO_VERSION:
    raise FailedPrecondition(
        f"jitdyn's native engine was built against MuJoCo {MUJOCO_VERSION} but MuJoCo "
        f"{mujoco.mj_version()} ({mujoco.__version__}) is installed: reinstall jitdyn"
    )

Ukf = _ukf.Ukf
AdapterState = _ukf.AdapterState
CombinerState = _ukf.CombinerState
SingularMatrix = _ukf.SingularMatrix
TickState = _ukf.TickState
