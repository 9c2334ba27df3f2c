"""MyoSuite models packed from myo-sim compile in the registry as myo-sim compiles them."""

from __future__ import annotations

import io
import json
import warnings
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import pytest

from jitdyn.client.myo import (
    MyoModel,
    myo_model_names,
    pack_myo_model,
    registrable_myo_models,
    resolve_myo_name,
)
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


# -- the models `jitdyn models register --myo` offers -------------------------------------------------


@pytest.fixture(scope="module")
def registrable(tmp_path_factory: pytest.TempPathFactory) -> tuple[list[MyoModel], Path]:
    """The myo-sim models that compile, found once into a cache folder of this module's own."""
    cache = tmp_path_factory.mktemp("cache")
    return registrable_myo_models(cache_dir=cache, progress=None), cache


def test_the_models_offered_include_the_hand_the_elbow_and_the_legs(
    registrable: tuple[list[MyoModel], Path],
) -> None:
    models, _ = registrable
    by_name = {m.name: m for m in models}
    assert {"myoelbow", "myohand", "myolegs", "myolegs_osl"} <= set(by_name)
    assert by_name["myohand"].aliases == ("hand", "myohand_r")
    assert by_name["myolegs_osl"].aliases == ("osl",)
    # Every name myo-sim has is offered, once, or left out because it does not pack.
    offered = [n for m in models for n in (m.name, *m.aliases)]
    assert len(offered) == len(set(offered)) and set(offered) <= set(myo_model_names())
    for left_out in set(myo_model_names()) - set(offered):
        with pytest.raises(ValueError, match=f"cannot pack {left_out!r}"):
            pack_myo_model(left_out)


@pytest.mark.slow  # 15 s: every myo-sim model compiled again in the registry
def test_every_model_offered_compiles_in_the_registry(registrable: tuple[list[MyoModel], Path]) -> None:
    models, _ = registrable
    for myo in models:  # 13 sandboxed compiles: 18 s on the 2-core machine
        compiled = compile_model(*pack_myo_model(myo.name), limits=RegistryLimits(max_nv=1000))
        assert (compiled.nq, compiled.nv, compiled.nu, compiled.na) == (myo.nq, myo.nv, myo.nu, myo.na)


def test_the_list_is_found_once_then_read_from_the_cache(registrable: tuple[list[MyoModel], Path]) -> None:
    models, cache = registrable
    (cached,) = cache.glob("myo-models-*.json")
    note = io.StringIO()
    assert registrable_myo_models(cache_dir=cache, progress=note) == models
    assert note.getvalue() == "", "found again, not read from the cache"
    assert [m["name"] for m in json.loads(cached.read_text())] == [m.name for m in models]


def test_a_name_is_resolved_ignoring_case_and_an_unknown_one_lists_the_models(
    registrable: tuple[list[MyoModel], Path],
) -> None:
    models, cache = registrable
    assert resolve_myo_name("myoHand", cache_dir=cache) == "myohand"
    assert resolve_myo_name("MyoLegs_OSL", cache_dir=cache) == "myolegs_osl"
    names = ", ".join(m.name for m in models)
    with pytest.raises(ValueError) as error:
        resolve_myo_name("myoknee", cache_dir=cache)
    assert str(error.value) == (
        f"no myo-sim model is named 'myoknee'; models that compile: {names} "
        "(`jitdyn models register --myo list` shows them with their other names)"
    )
