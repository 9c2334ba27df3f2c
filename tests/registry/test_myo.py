"""MyoSuite models packed from myo-sim compile in the registry as myo-sim compiles them."""

from __future__ import annotations

import warnings
from typing import Any

import mujoco
import numpy as np
import pytest

from jitdyn.client.myo import myo_model_names, pack_myo_model
from jitdyn.registry import RegistryLimits, compile_model
from jitdyn.v1 import model_registry_pb2

# Where file names sit in the name buffer: the packed model's files have other names.
_IGNORED = frozenset({"mesh_pathadr", "tex_pathadr", "hfield_pathadr", "skin_pathadr"})
# MuJoCo's XML writer, which packs the composed models, keeps 6 significant digits (rotations of unit
# quaternions rounded so differ by up to 1e-6).
_WRITTEN_RTOL = 1e-5


def myo_sim_model(name: str) -> mujoco.MjModel:
    import myo_sim

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "Attaching a spec with an empty prefix", UserWarning)
        return myo_sim.load_model(name)


def assert_same_model(packed: mujoco.MjModel, reference: mujoco.MjModel) -> None:
    assert (packed.nq, packed.nv, packed.nu, packed.na) == (
        reference.nq,
        reference.nv,
        reference.nu,
        reference.na,
    )
    np.testing.assert_array_equal(packed.qpos0, reference.qpos0)
    np.testing.assert_array_equal(packed.body_mass, reference.body_mass)
    for field in dir(reference):
        value = getattr(reference, field)
        if field.startswith("_") or field in _IGNORED or not isinstance(value, np.ndarray):
            continue
        if value.dtype.kind == "f":
            np.testing.assert_allclose(
                getattr(packed, field), value, rtol=_WRITTEN_RTOL, atol=1e-6, err_msg=field
            )
        else:
            np.testing.assert_array_equal(getattr(packed, field), value, err_msg=field)


@pytest.mark.parametrize("name", ["myoelbow", "myohand"])
def test_packed_model_compiles_as_myo_sim_compiles_it(name: str) -> None:
    mjcf, assets = pack_myo_model(name)
    assert all(not asset.startswith(("/", "..")) for asset in assets)
    assert_same_model(compile_model(mjcf, assets), myo_sim_model(name))


def test_packed_models_register_over_grpc(registry_stub: Any) -> None:
    for name, dimensions in (("myoelbow", (1, 1, 6, 6)), ("myohand", (23, 23, 39, 39))):
        mjcf, assets = pack_myo_model(name)
        request = model_registry_pb2.RegisterModelRequest(name=name, mjcf=mjcf, assets=assets)
        response = registry_stub.RegisterModel(request, timeout=120)
        found = response.model.dimensions
        assert (found.nq, found.nv, found.nu, found.na) == dimensions
        assert len(response.model.actuators) == dimensions[2]


def test_other_static_and_composed_models_pack() -> None:
    limits = RegistryLimits(max_nv=1000)
    for name in ("myofinger", "osl"):
        mjcf, assets = pack_myo_model(name)
        reference = myo_sim_model(name)
        packed = compile_model(mjcf, assets, limits=limits)
        assert (packed.nq, packed.nv, packed.nu) == (reference.nq, reference.nv, reference.nu)
        np.testing.assert_array_equal(packed.body_mass, reference.body_mass)


def test_models_myo_sim_cannot_write_back_are_refused_clearly() -> None:
    with pytest.raises(ValueError, match="cannot pack 'myofullbody'"):
        pack_myo_model("myofullbody")
    with pytest.raises(ValueError, match="no myo-sim model is named 'myoknee'; models: elbow, finger"):
        pack_myo_model("myoknee")
    assert {"myoelbow", "myohand"} <= set(myo_model_names())
