"""The model registry on SQLite and PostgreSQL: registration, versions, lookup, paging, tenants,
storage and loading."""

from __future__ import annotations

import datetime
import threading
import zipfile
from pathlib import Path

import pytest
import sqlalchemy as sa

from jitdyn.errors import InvalidArgument, NotFound, Unavailable
from jitdyn.registry import BUILTIN_NAMES, ModelMetadata, ModelRegistry, content_id
from jitdyn.storage.schema import model_blobs, models
from jitdyn.vocabulary import JointType, Preset

OBJ = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


def arm(length: float = 1.0) -> str:
    """A two-link arm: a limited hinge, a slide carrying a mesh hand, two motors (one unnamed), a sensor."""
    return f"""<mujoco>
  <compiler angle="radian"/>
  <asset><mesh name="hand" file="hand.obj"/></asset>
  <worldbody>
    <body name="upper">
      <joint name="shoulder" type="hinge" axis="0 1 0" range="-1 2"/>
      <geom type="capsule" fromto="0 0 0 0 0 -{length}" size="0.05"/>
      <body name="lower" pos="0 0 -{length}">
        <joint name="slider" type="slide" axis="0 0 1"/>
        <geom type="mesh" mesh="hand"/>
        <site name="tip"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor joint="shoulder" ctrlrange="-5 5"/>
    <motor name="push" joint="slider"/>
  </actuator>
  <sensor><framepos objtype="site" objname="tip"/></sensor>
</mujoco>"""


ASSETS = {"hand.obj": OBJ}


def test_register_describes_the_compiled_model(registry: ModelRegistry) -> None:
    metadata = ModelMetadata(
        description="A two-link arm.",
        tags=("lab", "arm"),
        defaults={"PASSIVE": {"alpha": 0.001, "preset": "THESIS"}},
    )
    info, created = registry.register(name="arm", mjcf=arm(), assets=ASSETS, metadata=metadata)
    assert created
    assert info.id == content_id(arm(), ASSETS)
    assert (info.name, info.version, info.tenant, info.builtin) == ("arm", 1, "", False)
    assert (info.nq, info.nv, info.nu, info.na, info.nsensor, info.nbody) == (2, 2, 2, 0, 3, 3)
    assert info.timestep == 0.002
    shoulder, slider = info.joints
    assert (shoulder.name, shoulder.type, shoulder.limited, shoulder.lower, shoulder.upper) == (
        "shoulder",
        "hinge",
        True,
        -1.0,
        2.0,
    )
    assert (slider.name, slider.type, slider.limited, slider.qpos_address, slider.dof_address) == (
        "slider",
        "slide",
        False,
        1,
        1,
    )
    first, push = info.actuators
    assert (first.name, first.target, first.ctrl_limited, first.lower, first.upper) == (
        "actuator0",
        "shoulder",
        True,
        -5.0,
        5.0,
    )
    assert (push.name, push.target, push.ctrl_limited) == ("push", "slider", False)
    assert (info.description, info.tags) == ("A two-link arm.", ("lab", "arm"))
    assert info.defaults == {"PASSIVE": {"alpha": 0.001, "preset": "THESIS"}}
    # Stored as text, read back as the vocabulary's members.
    assert info.defaults["PASSIVE"]["preset"] is Preset.THESIS and shoulder.type is JointType.HINGE
    assert info.created_at.tzinfo is not None
    assert abs(info.created_at - datetime.datetime.now(datetime.UTC)) < datetime.timedelta(minutes=1)
    assert registry.get(model_id=info.id) == info


def test_identical_content_returns_the_stored_model_and_changes_make_versions(
    registry: ModelRegistry,
) -> None:
    first, created = registry.register(name="arm", mjcf=arm(), assets=ASSETS)
    assert created
    again, created = registry.register(name="other-name", mjcf=arm(), assets=ASSETS)
    assert not created
    assert again == first
    second, created = registry.register(name="arm", mjcf=arm(1.2), assets=ASSETS)
    assert created
    assert second.version == 2
    assert second.id != first.id
    changed_asset, _ = registry.register(name="arm", mjcf=arm(), assets={"hand.obj": OBJ + b"\n"})
    assert changed_asset.version == 3
    assert registry.get(name="arm").id == changed_asset.id
    assert registry.get(name="arm", version=1).id == first.id


def test_unnamed_joints_and_actuators_get_index_names(registry: ModelRegistry) -> None:
    mjcf = """<mujoco><worldbody>
      <body><joint/><geom size="0.1"/><body><joint type="ball"/><geom size="0.1"/></body></body>
      <body name="box"><freejoint/><geom size="0.1"/></body>
    </worldbody><actuator><motor joint="joint0"/></actuator></mujoco>"""
    # "joint0" is what the registry calls the unnamed joint, not a name MJCF knows.
    with pytest.raises(InvalidArgument, match="MuJoCo could not compile the model"):
        registry.register(name="anon", mjcf=mjcf, assets={})
    mjcf = mjcf.replace('<motor joint="joint0"/>', '<adhesion body="box" ctrlrange="0 1"/>')
    info, _ = registry.register(name="anon", mjcf=mjcf, assets={})
    assert [(joint.name, joint.type) for joint in info.joints] == [
        ("joint0", "hinge"),
        ("joint1", "ball"),
        ("joint2", "free"),
    ]
    assert [(j.qpos_address, j.dof_address) for j in info.joints] == [(0, 0), (1, 1), (5, 4)]
    assert [(a.name, a.target, a.ctrl_limited, a.upper) for a in info.actuators] == [
        ("actuator0", "box", True, 1.0)
    ]


def test_invalid_mjcf_surfaces_mujocos_message(registry: ModelRegistry) -> None:
    with pytest.raises(InvalidArgument) as error:
        registry.register(
            name="broken", mjcf="<mujoco><worldbody><geom type='sphere'/></worldbody></mujoco>", assets={}
        )
    assert str(error.value).startswith("MuJoCo could not compile the model: Error: size 0 must be positive")


@pytest.mark.parametrize(
    ("name", "metadata", "message"),
    [
        (
            "",
            ModelMetadata(),
            "name must be 1-64 characters of [A-Za-z0-9_.-] starting with a letter, got ''",
        ),
        ("1arm", ModelMetadata(), "starting with a letter, got '1arm'"),
        ("a" * 65, ModelMetadata(), "name must be 1-64 characters"),
        (
            "arm",
            ModelMetadata(tags=("ok", "not ok")),
            "metadata.tags[1] must be 1-64 characters of [A-Za-z0-9_.-], got 'not ok'",
        ),
        (
            "arm",
            ModelMetadata(tags=tuple(f"t{i}" for i in range(33))),
            "metadata.tags has 33 tags, more than 32",
        ),
        (
            "arm",
            ModelMetadata(description="x" * 4097),
            "metadata.description must be text of at most 4096 characters, got 4097 characters",
        ),
        (
            "arm",
            ModelMetadata(defaults={"WALKING": {}}),
            "metadata.defaults has scenario 'WALKING'; expected one of PASSIVE, CONTROLLED, EXTERNAL",
        ),
        (
            "arm",
            ModelMetadata(defaults={"PASSIVE": {}, "passive": {}}),
            "metadata.defaults has more than one entry for scenario PASSIVE",
        ),
        (
            "arm",
            ModelMetadata(defaults={"PASSIVE": {"gamma": 1}}),
            "metadata.defaults.PASSIVE has unknown setting 'gamma'; expected one of estimator, preset,",
        ),
        (
            "arm",
            ModelMetadata(defaults={"PASSIVE": {"alpha": 2.0}}),
            "metadata.defaults.PASSIVE.alpha must be in (0, 1], got 2",
        ),
        (
            "arm",
            ModelMetadata(defaults={"PASSIVE": {"r": float("inf")}}),
            "metadata.defaults.PASSIVE.r must be finite, got inf",
        ),
        (
            "arm",
            ModelMetadata(defaults={"PASSIVE": {"preset": "FAST"}}),
            "metadata.defaults.PASSIVE.preset must be one of JITDYN, THESIS, got 'FAST'",
        ),
        (
            "arm",
            ModelMetadata(defaults={"CONTROLLED": {"wrong_model": "DRIVEN"}}),
            "metadata.defaults.CONTROLLED.wrong_model DRIVEN turns a PASSIVE filter into a DRIVEN one",
        ),
    ],
)
def test_names_and_metadata_are_validated(
    registry: ModelRegistry, name: str, metadata: ModelMetadata, message: str
) -> None:
    with pytest.raises(InvalidArgument) as error:
        registry.register(name=name, mjcf=arm(), assets=ASSETS, metadata=metadata)
    assert message in str(error.value)


def test_get_names_what_is_missing(registry: ModelRegistry) -> None:
    registry.register(name="arm", mjcf=arm(), assets=ASSETS)
    registry.register(name="arm", mjcf=arm(2.0), assets=ASSETS)
    with pytest.raises(NotFound) as error:
        registry.get(name="arm", version=3)
    assert str(error.value) == "model 'arm' has no version 3 (versions: 1, 2)"
    with pytest.raises(NotFound, match="no model is named 'leg'"):
        registry.get(name="leg")
    missing = "sha256:" + "0" * 64
    with pytest.raises(NotFound, match=f"no model has id '{missing}'"):
        registry.get(model_id=missing)
    with pytest.raises(
        InvalidArgument, match="model_id must be 'sha256:' followed by 64 lowercase hex digits, got 'abc'"
    ):
        registry.get(model_id="abc")
    with pytest.raises(InvalidArgument, match="give model_id or name, not both"):
        registry.get(model_id=missing, name="arm")
    with pytest.raises(InvalidArgument, match="give model_id or name; got neither"):
        registry.get()


def test_list_pages_by_name_then_newest_version(registry: ModelRegistry) -> None:
    for length in (1.0, 1.1, 1.2):
        registry.register(name="arm", mjcf=arm(length), assets=ASSETS, metadata=ModelMetadata(tags=("lab",)))
    registry.register(name="b-arm", mjcf=arm(2.0), assets=ASSETS, metadata=ModelMetadata(tags=("Lab",)))
    registry.register(name="c-arm", mjcf=arm(3.0), assets=ASSETS, metadata=ModelMetadata(tags=("lab", "x_y")))
    seen = []
    token = ""
    while True:
        page, token = registry.list(page_size=2, page_token=token)
        assert len(page) <= 2
        seen += [(info.name, info.version) for info in page]
        if not token:
            break
    assert seen == [("arm", 3), ("arm", 2), ("arm", 1), ("b-arm", 1), ("c-arm", 1)]
    assert [(i.name, i.version) for i in registry.list(name="arm")[0]] == [("arm", 3), ("arm", 2), ("arm", 1)]
    # Tags match whole and case-sensitively; '_' is no wildcard.
    assert [i.name for i in registry.list(tag="lab")[0]] == ["arm", "arm", "arm", "c-arm"]
    assert [i.name for i in registry.list(tag="Lab")[0]] == ["b-arm"]
    assert [i.name for i in registry.list(tag="x_y")[0]] == ["c-arm"]
    assert registry.list(tag="xay")[0] == []
    page, token = registry.list(tag="lab", page_size=3)
    assert token
    rest, last = registry.list(tag="lab", page_size=3, page_token=token)
    assert ([i.name for i in rest], last) == (["c-arm"], "")


@pytest.mark.parametrize("token", ["garbage", "eyJhZnRlciI6MX0", "x" * 600])
def test_list_refuses_tokens_it_did_not_issue(registry: ModelRegistry, token: str) -> None:
    with pytest.raises(InvalidArgument, match="is not a next_page_token of this listing"):
        registry.list(page_token=token)


def test_list_refuses_a_token_of_another_filter_and_bad_page_sizes(registry: ModelRegistry) -> None:
    for length in (1.0, 1.1):
        registry.register(name="arm", mjcf=arm(length), assets=ASSETS)
    _, token = registry.list(page_size=1)
    with pytest.raises(InvalidArgument, match="not a next_page_token of this listing"):
        registry.list(page_size=1, page_token=token, name="arm")
    for size in (0, 1001):
        with pytest.raises(InvalidArgument, match=f"page_size must be between 1 and 1000, got {size}"):
            registry.list(page_size=size)


def test_tenants_see_their_own_models_and_the_builtins(registry: ModelRegistry) -> None:
    registry.register_builtins()
    mine, _ = registry.register(name="arm", mjcf=arm(), assets=ASSETS, tenant="acme")
    with pytest.raises(NotFound):
        registry.get(model_id=mine.id, tenant="other")
    with pytest.raises(NotFound):
        registry.get(model_id=mine.id)  # the default tenant is a tenant too
    with pytest.raises(NotFound):
        registry.load(mine.id, tenant="other")
    theirs, created = registry.register(name="arm", mjcf=arm(), assets=ASSETS, tenant="other")
    assert created and theirs.version == 1 and theirs.tenant == "other"
    names = [info.name for info in registry.list(tenant="acme")[0]]
    assert names == sorted(["arm", *BUILTIN_NAMES])
    assert registry.get(name="pendulum_1", tenant="acme").builtin
    # Registering a built-in's content returns the built-in; its name is not for registrants.
    pendulum = registry.get(name="pendulum_1")
    same, created = registry.register(
        name="my-pendulum",
        mjcf=Path(__file__).parents[2].joinpath("models/pendulum_1.xml").read_text(),
        assets={},
        tenant="acme",
    )
    assert not created and same.id == pendulum.id
    with pytest.raises(
        InvalidArgument, match="name 'biped' belongs to a built-in model; register under another name"
    ):
        registry.register(name="biped", mjcf=arm(5.0), assets=ASSETS, tenant="acme")


def test_builtins_are_registered_once_and_load(registry: ModelRegistry) -> None:
    infos = registry.register_builtins()
    assert [info.name for info in infos] == list(BUILTIN_NAMES)
    assert all(info.builtin and info.version == 1 and info.tags[0] == "builtin" for info in infos)
    assert infos[3].tags == ("builtin", "biped")
    assert infos[0].description.startswith("The thesis' 1-link pendulum")
    assert [info.id for info in registry.register_builtins()] == [info.id for info in infos]
    for info in infos:
        model = registry.load(info.id)
        assert (model.nq, model.nv, model.nu) == (info.nq, info.nv, info.nu)


def test_models_are_stored_as_zips_and_loaded_as_copies(
    registry: ModelRegistry, engine: sa.Engine, data_root: Path
) -> None:
    info, _ = registry.register(
        name="arm",
        mjcf=arm().replace('file="hand.obj"', 'file="meshes/hand.obj"'),
        assets={"meshes/hand.obj": OBJ},
    )
    with engine.connect() as connection:
        row = connection.execute(
            sa.select(models.c.blob_path, models.c.size_bytes).where(models.c.id == info.id)
        ).one()
    assert row.blob_path == f"models/{info.id.removeprefix('sha256:')}.zip"
    assert row.size_bytes == len(arm().encode()) + len("meshes/") + len(OBJ)
    with zipfile.ZipFile(data_root / row.blob_path) as archive:
        assert sorted(archive.namelist()) == ["assets/meshes/hand.obj", "model.xml"]
        assert archive.read("assets/meshes/hand.obj") == OBJ
    assert sorted(p.name for p in (data_root / "models").iterdir()) == [Path(row.blob_path).name]
    first = registry.load(info.id)
    first.opt.timestep = 1.0
    assert registry.load(info.id).opt.timestep == 0.002


def test_load_recompiles_from_the_stored_zip(engine: sa.Engine, data_root: Path) -> None:
    with ModelRegistry(engine=engine, data_root=data_root) as registry:
        info, _ = registry.register(name="arm", mjcf=arm(), assets=ASSETS)
    with ModelRegistry(engine=engine, data_root=data_root) as fresh:
        assert fresh.load(info.id).nv == 2


def test_a_server_with_another_data_folder_loads_the_content_from_the_index(
    engine: sa.Engine, tmp_path: Path
) -> None:
    """Replicas share the index, not a data folder: the zip is a row of model_blobs, fetched into
    the loading server's folder (its cache), identical to the registering server's."""
    first, second = tmp_path / "a", tmp_path / "b"
    with ModelRegistry(engine=engine, data_root=first) as registry:
        info, _ = registry.register(name="arm", mjcf=arm(), assets=ASSETS)
        again, _ = registry.register(name="arm", mjcf=arm(), assets=ASSETS)
    assert again.id == info.id
    with engine.connect() as connection:
        assert connection.execute(sa.select(sa.func.count()).select_from(model_blobs)).scalar_one() == 1
    with ModelRegistry(engine=engine, data_root=second) as other:
        assert other.load(info.id).nv == 2
    relative = f"models/{info.id.removeprefix('sha256:')}.zip"
    assert (second / relative).read_bytes() == (first / relative).read_bytes()


def test_an_unreachable_index_is_unavailable_without_a_path(
    engine: sa.Engine, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    with ModelRegistry(engine=engine, data_root=tmp_path / "a") as registry:
        info, _ = registry.register(name="arm", mjcf=arm(), assets=ASSETS)

    def lost(*_: object) -> None:
        raise sa.exc.OperationalError("SELECT", {}, OSError(f"could not connect: {tmp_path}"))

    monkeypatch.setattr("jitdyn.registry.registry.fetch_blob", lost)
    with ModelRegistry(engine=engine, data_root=tmp_path / "b") as other, pytest.raises(Unavailable) as error:
        other.load(info.id)
    assert "shared index" in str(error.value) and "OperationalError" in str(error.value)
    assert str(tmp_path) not in str(error.value)


def test_concurrent_registrations_of_one_name_get_distinct_versions(registry: ModelRegistry) -> None:
    results: list[tuple[int, bool]] = []
    errors: list[BaseException] = []

    def register(length: float) -> None:
        try:
            info, created = registry.register(name="arm", mjcf=arm(length), assets=ASSETS)
            results.append((info.version, created))
        except Exception as error:  # noqa: BLE001 - reported by the assert below
            errors.append(error)

    threads = [threading.Thread(target=register, args=(1.0 + i / 10,)) for i in range(6)]
    threads += [threading.Thread(target=register, args=(1.0,))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert errors == []
    assert sorted(version for version, _ in results if _) == [1, 2, 3, 4, 5, 6]
    assert sum(1 for _, created in results if not created) == 1


def test_close_is_safe_twice(engine: sa.Engine, data_root: Path) -> None:
    registry = ModelRegistry(engine=engine, data_root=data_root)
    registry.close()
    registry.close()
    with pytest.raises(RuntimeError, match="the ModelRegistry is closed"):
        registry.list()


def test_estimator_costs_are_stored_once_by_content(registry: ModelRegistry) -> None:
    """The first measurement stored for a content id stands: a second (another replica's, measured
    at the same time) returns the first, so every server chooses from the same figures."""
    from jitdyn.registry import CandidateCost

    info = registry.register_builtins()[0]
    assert registry.costs([info.id]) == {}
    first = CandidateCost(
        scenario="PASSIVE",
        estimator="UKF",
        sigma_points="MERWE",
        steps=(1, 2, 5, 10),
        seconds=(1e-4, 2e-4, 5e-4, 1e-3),
    )
    stored = registry.store_costs(info.id, [first])
    assert stored == (first,)
    later = CandidateCost(
        scenario="PASSIVE",
        estimator="UKF",
        sigma_points="MERWE",
        steps=(1, 2, 5, 10),
        seconds=(9.0, 9.0, 9.0, 9.0),
    )
    assert registry.store_costs(info.id, [later]) == (first,)
    assert registry.costs([info.id, "sha256:" + "0" * 64]) == {info.id: (first,)}
    # Between two timed steps a tick costs their straight line; past the last, the last two's.
    assert first.at(1) == pytest.approx(1e-4) and first.at(4) == pytest.approx(4e-4)
    assert first.at(20) == pytest.approx(2e-3)
    with pytest.raises(ValueError, match="ascend"):
        CandidateCost(scenario="PASSIVE", estimator="UKF", sigma_points="", steps=(2, 1), seconds=(1.0, 1.0))
