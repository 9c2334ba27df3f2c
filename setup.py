"""Builds jitdyn's one compiled module, the native estimation engine
(server/estimation/native/: C++17 on MuJoCo's C API, bound with pybind11, algebra by Eigen).

Everything it needs but a C++ compiler comes from pyproject.toml's build requirements: pybind11,
Eigen's headers (cmeel-eigen) and the pinned mujoco wheel, whose headers it compiles against and
whose libmujoco it links; the package metadata is pyproject.toml's. Why pybind11 and setuptools:
docs/decisions/0150-native-engine.md.
"""

from __future__ import annotations

import os
import shlex
import shutil
import sys
import sysconfig
from pathlib import Path

import mujoco
from pybind11.setup_helpers import ParallelCompile, Pybind11Extension, build_ext
from setuptools import setup

NATIVE = Path("server/estimation/native")


def eigen_include() -> str:
    """cmeel-eigen's headers: <site-packages>/cmeel.prefix/include/eigen3 of the build environment."""
    roots = [sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"], *sys.path]
    for root in roots:
        candidate = Path(root) / "cmeel.prefix" / "include" / "eigen3"
        if (candidate / "Eigen" / "Dense").is_file():
            return str(candidate)
    raise SystemExit("jitdyn: Eigen's headers were not found; pip install cmeel-eigen (a build requirement)")


def libmujoco() -> Path:
    """The pinned wheel's libmujoco.so.<version>, which the module links and imports beside."""
    found = sorted(Path(mujoco.__file__).parent.glob("libmujoco.so.*"))
    if not found:
        raise SystemExit(f"jitdyn: no libmujoco.so.* in {Path(mujoco.__file__).parent}")
    return found[0]


class BuildNative(build_ext):  # type: ignore[misc]
    """build_ext that says, in one line, which compiler to install when there is none."""

    def run(self) -> None:
        compiler = shlex.split(os.environ.get("CXX", "c++"))[0]
        if shutil.which(compiler) is None:
            raise SystemExit(
                f"jitdyn: building the native engine needs a C++17 compiler ({compiler!r} not found): "
                "install one, e.g. `apt-get install g++` on Debian or Ubuntu, then install jitdyn again"
            )
        super().run()


# The sources compile at once, on as many cores as there are (NPY_NUM_BUILD_JOBS caps it).
ParallelCompile("NPY_NUM_BUILD_JOBS").install()
library = libmujoco()
setup(
    ext_modules=[
        Pybind11Extension(
            "jitdyn.server.estimation.native._ukf",
            sources=[
                str(NATIVE / name)
                for name in (
                    "bindings.cc",
                    "ukf.cc",
                    "adaptive.cc",
                    "forecast.cc",
                    "matching.cc",
                    "prior.cc",
                    "linearised.cc",
                    "tick.cc",
                )
            ],
            include_dirs=[str(library.parent / "include"), eigen_include()],
            depends=[
                str(NATIVE / name)
                for name in (
                    "ukf.h",
                    "adaptive.h",
                    "forecast.h",
                    "matching.h",
                    "prior.h",
                    "extrapolators.h",
                    "linearised.h",
                    "tick.h",
                )
            ],
            cxx_std=17,
            # Linked by its full name (the wheel ships no unversioned libmujoco.so). At run time
            # the module finds it already loaded by `import mujoco` (by soname), or beside itself
            # in an installed wheel's site-packages.
            extra_link_args=[str(library), "-Wl,-rpath,$ORIGIN/../../../../mujoco"],
            extra_compile_args=["-O2"],
        )
    ],
    cmdclass={"build_ext": BuildNative},
)
