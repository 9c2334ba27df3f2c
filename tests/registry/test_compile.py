"""Compiling untrusted MJCF: MuJoCo's errors surfaced, limits enforced with the setting named."""

from __future__ import annotations

import time

import numpy as np
import pytest

from jitdyn.errors import InvalidArgument, ResourceExhausted
from jitdyn.registry import ModelCompiler, RegistryLimits, compile_model
from jitdyn.registry.compile import check_request

PENDULUM = """<mujoco>
  <worldbody>
    <body><joint name="swing" type="hinge" axis="0 1 0"/><geom type="capsule" fromto="0 0 0 0 0 -1" size="0.05"/></body>
  </worldbody>
</mujoco>"""


def chain(n: int) -> str:
    bodies = "".join('<body pos="0 0 -0.1"><joint axis="0 1 0"/><geom size="0.01"/>' for _ in range(n))
    return f"<mujoco><worldbody>{bodies}{'</body>' * n}</worldbody></mujoco>"


def test_compile_model_compiles_from_memory() -> None:
    model = compile_model(PENDULUM, {})
    assert (model.nq, model.nv, model.nu) == (1, 1, 0)
    assert model.joint(0).name == "swing"


def test_mujoco_compile_errors_are_invalid_argument_with_mujocos_message() -> None:
    with pytest.raises(InvalidArgument) as error:
        compile_model(
            '<mujoco>\n<worldbody>\n<geom type="mesh" mesh="nothing"/>\n</worldbody>\n</mujoco>', {}
        )
    assert str(error.value) == (
        "MuJoCo could not compile the model: Error: mesh 'nothing' not found in geom 0\nElement name '', id 0, line 3"
    )


def test_unknown_elements_are_mujocos_schema_error() -> None:
    with pytest.raises(
        InvalidArgument, match="MuJoCo could not compile the model: XML Error: Schema violation"
    ):
        compile_model("<mujoco><worldbody><bodyy/></worldbody></mujoco>", {})


@pytest.mark.parametrize(
    ("limits", "mjcf", "assets", "message"),
    [
        (
            RegistryLimits(max_mjcf_bytes=100),
            PENDULUM,
            {},
            f"the MJCF is {len(PENDULUM)} bytes, over the limit of 100 bytes (registry setting max_mjcf_bytes)",
        ),
        (
            RegistryLimits(max_assets=2),
            PENDULUM,
            {f"{i}.obj": b"" for i in range(3)},
            "the number of assets is 3, over the limit of 2 (registry setting max_assets)",
        ),
        (
            RegistryLimits(max_asset_bytes=1000),
            PENDULUM,
            {"a.obj": bytes(600), "b.obj": bytes(600)},
            "the assets' total size is 1200 bytes, over the limit of 1000 bytes (registry setting max_asset_bytes)",
        ),
    ],
)
def test_sizes_over_a_limit_are_resource_exhausted(
    limits: RegistryLimits, mjcf: str, assets: dict[str, bytes], message: str
) -> None:
    with pytest.raises(ResourceExhausted) as error:
        check_request(mjcf, assets, limits=limits)
    assert str(error.value) == message


def test_state_dimension_over_the_limit_is_resource_exhausted() -> None:
    with ModelCompiler(limits=RegistryLimits(max_nv=5)) as compiler:
        assert compiler.compile(chain(5), {}).nv == 5
        with pytest.raises(ResourceExhausted) as error:
            compiler.compile(chain(6), {})
    assert str(error.value) == (
        "the model's number of degrees of freedom (nv) is 6, over the limit of 5 (registry setting max_nv)"
    )


def test_a_compile_over_the_time_limit_is_killed_and_the_compiler_recovers() -> None:
    # Replicating 10000 geoms takes MuJoCo seconds (its name checks are quadratic).
    slow = '<mujoco><worldbody><replicate count="10000" offset="0.01 0 0"><geom size="0.1"/></replicate></worldbody></mujoco>'
    with ModelCompiler(limits=RegistryLimits(compile_timeout=0.3)) as compiler:
        compiler.compile(PENDULUM, {})  # the worker is up before the clock starts
        started = time.perf_counter()
        with pytest.raises(ResourceExhausted) as error:
            compiler.compile(slow, {})
        assert time.perf_counter() - started < 3.0
        assert str(error.value) == (
            "compiling the model took longer than the limit of 0.3 s (registry setting compile_timeout, --compile-timeout)"
        )
        assert compiler.compile(PENDULUM, {}).nv == 1


def test_bad_arguments_name_what_was_expected() -> None:
    limits = RegistryLimits()
    with pytest.raises(InvalidArgument, match="mjcf must be a string of MJCF \\(XML\\), got bytes"):
        check_request(b"<mujoco/>", {}, limits=limits)  # type: ignore[arg-type]
    with pytest.raises(InvalidArgument, match="mjcf is empty"):
        check_request("  ", {}, limits=limits)
    with pytest.raises(InvalidArgument, match="asset 'a.obj' must be bytes, got str"):
        check_request(PENDULUM, {"a.obj": "text"}, limits=limits)  # type: ignore[dict-item]


def test_limits_are_validated() -> None:
    with pytest.raises(ValueError, match="RegistryLimits.max_nv must be a positive integer, got 0"):
        RegistryLimits(max_nv=0)
    with pytest.raises(
        ValueError, match="RegistryLimits.compile_timeout must be a positive number of seconds"
    ):
        RegistryLimits(compile_timeout=float("nan"))


def test_compiled_model_is_the_model_mujoco_compiles_in_process() -> None:
    import mujoco

    with ModelCompiler() as compiler:
        remote = compiler.compile(chain(3), {})
    local = mujoco.MjModel.from_xml_string(chain(3))
    np.testing.assert_array_equal(remote.body_mass, local.body_mass)
    np.testing.assert_array_equal(remote.qpos0, local.qpos0)
    assert remote.nv == local.nv


def test_close_is_safe_twice_and_refuses_later_compiles() -> None:
    compiler = ModelCompiler()
    compiler.compile(PENDULUM, {})
    compiler.close()
    compiler.close()
    with pytest.raises(RuntimeError, match="the ModelCompiler is closed"):
        compiler.compile(PENDULUM, {})
