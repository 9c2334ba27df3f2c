"""File references in untrusted MJCF: only the request's assets may be read, resolved as MuJoCo does."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import mujoco
import pytest

from jitdyn.errors import InvalidArgument, ResourceExhausted
from jitdyn.registry import ModelCompiler, RegistryLimits
from jitdyn.registry.compile import _Worker
from jitdyn.registry.references import check_asset_names, check_model

# A tetrahedron: the smallest mesh MuJoCo accepts.
OBJ = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


def mesh_model(file: str, *, compiler: str = "", name: str = "arm") -> str:
    return f"""<mujoco>
  <compiler {compiler}/>
  <asset><mesh name="{name}" file="{file}"/></asset>
  <worldbody><body><freejoint/><geom type="mesh" mesh="{name}"/></body></worldbody>
</mujoco>"""


@pytest.fixture(scope="module")
def compiler() -> Iterator[ModelCompiler]:
    with ModelCompiler() as opened:
        yield opened


@pytest.fixture()
def no_mujoco(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fail the test if MuJoCo is ever asked to compile: a refused model must never reach it."""

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("MuJoCo was asked to compile a model that should have been refused")

    monkeypatch.setattr(_Worker, "compile", refuse)
    monkeypatch.setattr(mujoco.MjModel, "from_xml_string", refuse)


def test_mesh_under_meshdir_compiles(compiler: ModelCompiler) -> None:
    model = compiler.compile(mesh_model("arm.obj", compiler='meshdir="meshes"'), {"meshes/arm.obj": OBJ})
    assert model.nmesh == 1
    assert model.nv == 6


def test_include_and_nested_mesh_compile(compiler: ModelCompiler) -> None:
    main = '<mujoco><compiler meshdir="m"/><include file="parts/body.xml"/></mujoco>'
    part = b"""<mujoco><asset><mesh name="arm" file="arm.obj"/></asset>
      <worldbody><body><freejoint/><geom type="mesh" mesh="arm"/></body></worldbody></mujoco>"""
    model = compiler.compile(main, {"parts/body.xml": part, "m/arm.obj": OBJ})
    assert model.nmesh == 1


def test_mesh_outside_assets_is_named_precisely(no_mujoco: None) -> None:
    with pytest.raises(InvalidArgument) as error:
        check_model(mesh_model("arm.stl", compiler='meshdir="meshes"'), {"a.stl": OBJ}, max_documents=10)
    assert str(error.value) == (
        "mesh 'arm' (line 3) attribute file refers to file 'meshes/arm.stl' (compiler meshdir 'meshes' + "
        "'arm.stl'), which is not among the request's assets (assets: 'a.stl')"
    )


def test_include_outside_assets(no_mujoco: None) -> None:
    with pytest.raises(InvalidArgument) as error:
        check_model('<mujoco>\n<include file="scene.xml"/>\n</mujoco>', {}, max_documents=10)
    assert str(error.value) == (
        "include (line 2) attribute file refers to file 'scene.xml', which is not among the request's "
        "assets (the request has no assets)"
    )


@pytest.mark.parametrize(
    ("mjcf", "message"),
    [
        (mesh_model("/etc/hostname"), "refers to file '/etc/hostname', which is an absolute path"),
        (mesh_model("../secret.obj"), "refers to file '../secret.obj', which goes up a directory ('..')"),
        (mesh_model("a/../../secret.obj"), "which goes up a directory ('..')"),
        (mesh_model("arm.obj", compiler='meshdir="/etc"'), "attribute meshdir='/etc' is an absolute path"),
        (mesh_model("arm.obj", compiler='meshdir=".."'), "attribute meshdir='..' goes up a directory"),
        (mesh_model("arm.obj", compiler='assetdir="../x"'), "attribute assetdir='../x' goes up a directory"),
        (mesh_model("arm.obj", compiler='texturedir="C:/x"'), "contains ':'"),
        (mesh_model("..\\secret.obj"), "contains '\\'"),
        (mesh_model("file:secret.obj"), "contains ':'"),
        ('<mujoco><include file="/etc/passwd"/></mujoco>', "'/etc/passwd', which is an absolute path"),
        ('<mujoco><include file="../x.xml"/></mujoco>', "goes up a directory"),
        (
            '<mujoco><asset><texture name="sky" type="skybox" fileback="/etc/hostname"/></asset></mujoco>',
            "texture 'sky' (line 1) attribute fileback refers to file '/etc/hostname', which is an absolute path",
        ),
        (
            '<mujoco><asset><hfield name="h" file="/etc/hostname" size="1 1 1 1"/></asset></mujoco>',
            "hfield 'h' (line 1) attribute file",
        ),
        ('<mujoco><asset><skin name="s" file="../s.skn"/></asset></mujoco>', "skin 's' (line 1)"),
        ('<mujoco><asset><model name="m" file="/tmp/m.xml"/></asset></mujoco>', "model 'm' (line 1)"),
        (
            '<mujoco><worldbody><flexcomp name="f" type="mesh" file="/etc/hostname" dim="2"/></worldbody></mujoco>',
            "flexcomp 'f' (line 1)",
        ),
        ('<mujoco><INCLUDE file="/etc/passwd"/></mujoco>', "an absolute path"),
        (mesh_model(""), "refers to file '', which is empty"),
    ],
)
def test_references_that_leave_the_assets_are_refused(mjcf: str, message: str, no_mujoco: None) -> None:
    with pytest.raises(InvalidArgument, match=None) as error:
        check_model(mjcf, {"arm.obj": OBJ}, max_documents=10)
    assert message in str(error.value)


def test_meshdir_cannot_reach_an_asset_under_another_name(no_mujoco: None) -> None:
    # The asset exists, but not where the MJCF says: the reference is refused, not guessed.
    with pytest.raises(InvalidArgument, match="refers to file 'other/arm.obj'"):
        check_model(
            mesh_model("arm.obj", compiler='meshdir="other"'), {"meshes/arm.obj": OBJ}, max_documents=10
        )


def test_assetdir_applies_to_meshes_and_meshdir_overrides_it(compiler: ModelCompiler) -> None:
    assets = {"shared/arm.obj": OBJ}
    assert compiler.compile(mesh_model("arm.obj", compiler='assetdir="shared"'), assets).nmesh == 1
    with pytest.raises(InvalidArgument, match=r"refers to file 'meshes/arm.obj' \(compiler meshdir 'meshes'"):
        check_model(
            mesh_model("arm.obj", compiler='assetdir="shared" meshdir="meshes"'), assets, max_documents=10
        )


def test_meshdir_set_in_an_included_file_counts(no_mujoco: None) -> None:
    main = '<mujoco><include file="settings.xml"/>' + mesh_model("arm.obj")[len("<mujoco>") :]
    settings = b'<mujoco><compiler meshdir="/etc"/></mujoco>'
    with pytest.raises(
        InvalidArgument, match=r"compiler \(line 1 of 'settings.xml'\) attribute meshdir='/etc'"
    ):
        check_model(main, {"settings.xml": settings, "arm.obj": OBJ}, max_documents=10)


def test_file_reference_inside_an_included_file_is_checked(no_mujoco: None) -> None:
    main = '<mujoco><include file="inc/part.xml"/></mujoco>'
    part = b'<mujoco>\n<asset><mesh name="leak" file="/etc/hostname"/></asset></mujoco>'
    with pytest.raises(InvalidArgument) as error:
        check_model(main, {"inc/part.xml": part}, max_documents=10)
    assert str(error.value).startswith("mesh 'leak' (line 2 of 'inc/part.xml') attribute file refers to file")


def test_attached_model_files_are_checked_in_their_own_directory(compiler: ModelCompiler) -> None:
    child = b"""<mujoco><asset><mesh name="arm" file="arm.obj"/></asset>
      <worldbody><body name="b"><freejoint/><geom type="mesh" mesh="arm"/></body></worldbody></mujoco>"""
    main = """<mujoco><asset><model name="child" file="robot/child.xml"/></asset>
      <worldbody><attach model="child" body="b" prefix="c_"/></worldbody></mujoco>"""
    assert compiler.compile(main, {"robot/child.xml": child, "robot/arm.obj": OBJ}).nmesh == 1
    with pytest.raises(InvalidArgument, match="refers to file 'robot/arm.obj'"):
        check_model(main, {"robot/child.xml": child, "arm.obj": OBJ}, max_documents=10)


def test_includes_that_loop_are_refused(no_mujoco: None) -> None:
    assets = {
        "a.xml": b'<mujoco><include file="b.xml"/></mujoco>',
        "b.xml": b'<mujoco><include file="a.xml"/></mujoco>',
    }
    with pytest.raises(InvalidArgument, match="includes 'a.xml' a second time"):
        check_model('<mujoco><include file="a.xml"/></mujoco>', assets, max_documents=10)


def test_attached_models_that_attach_themselves_are_refused(no_mujoco: None) -> None:
    loop = b'<mujoco><asset><model name="m" file="m.xml"/></asset></mujoco>'
    with pytest.raises(InvalidArgument, match="attaches 'm.xml', which attaches itself"):
        check_model(loop.decode(), {"m.xml": loop}, max_documents=10)


def test_too_many_xml_documents_are_refused(no_mujoco: None) -> None:
    # Each level attaches the next twice: 2^n parses from n small files.
    assets = {
        f"l{i}.xml": f'<mujoco><asset><model name="a" file="l{i + 1}.xml"/><model name="b" file="l{i + 1}.xml"/></asset></mujoco>'.encode()
        for i in range(12)
    }
    assets["l12.xml"] = b"<mujoco/>"
    with pytest.raises(ResourceExhausted, match="registry setting max_assets"):
        check_model(
            '<mujoco><asset><model name="m" file="l0.xml"/></asset></mujoco>', assets, max_documents=100
        )


@pytest.mark.parametrize(
    ("mjcf", "message"),
    [
        ('<!DOCTYPE m [<!ENTITY a "aaaa">]><mujoco>&a;</mujoco>', "declares a DTD or entities"),
        ("<mujoco><worldbody></mujoco>", "the MJCF is not well-formed XML: mismatched tag: line 1"),
        ('<robot name="r"><link name="a"/></robot>', "the MJCF's root element is <robot>"),
        ('<mujoco xmlns:x="urn:x"><x:mesh/></mujoco>', "uses XML namespaces (line 1)"),
        ("<mujoco>" + "<body>" * 600 + "</body>" * 600 + "</mujoco>", "nests elements deeper than 500"),
    ],
)
def test_xml_that_is_not_plain_mjcf_is_refused(mjcf: str, message: str, no_mujoco: None) -> None:
    with pytest.raises(InvalidArgument) as error:
        check_model(mjcf, {}, max_documents=10)
    assert message in str(error.value)


def test_attached_urdf_is_refused(no_mujoco: None) -> None:
    with pytest.raises(InvalidArgument, match=r"asset 'r.urdf' .* is a <robot> document"):
        check_model(
            '<mujoco><asset><model name="r" file="r.urdf"/></asset></mujoco>',
            {
                "r.urdf": b'<robot name="r"><link name="a"><visual><geometry><mesh filename="/etc/x"/></geometry></visual></link></robot>'
            },
            max_documents=10,
        )


@pytest.mark.parametrize(
    ("assets", "message"),
    [
        ({"/etc/hostname": b""}, "asset name '/etc/hostname' is an absolute path"),
        ({"a/../b.obj": b""}, "asset name 'a/../b.obj' goes up a directory"),
        ({"a//b.obj": b""}, "asset name 'a//b.obj' has an empty or '.' part"),
        ({"./b.obj": b""}, "has an empty or '.' part"),
        ({"a\\b.obj": b""}, "contains '\\'"),
        ({"": b""}, "asset name '' is empty"),
        (
            {"left/foot.stl": b"", "right/Foot.STL": b""},
            "assets 'left/foot.stl' and 'right/Foot.STL' have the same file name ignoring case",
        ),
    ],
)
def test_asset_names_must_be_clean_relative_paths(assets: dict[str, bytes], message: str) -> None:
    with pytest.raises(InvalidArgument) as error:
        check_asset_names(assets)
    assert message in str(error.value)


def test_an_existing_server_file_is_never_read(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, compiler: ModelCompiler
) -> None:
    # A real mesh on the server, by absolute path and relative to the working directory: MuJoCo on
    # its own reads both; the registry refuses both, before MuJoCo runs.
    secret = tmp_path / "secret.obj"
    secret.write_bytes(OBJ)
    monkeypatch.chdir(tmp_path)
    for reference in (str(secret), "secret.obj"):
        assert mujoco.MjModel.from_xml_string(mesh_model(reference), assets={"x.obj": OBJ}).nmesh == 1
    with pytest.raises(InvalidArgument, match="is an absolute path"):
        compiler.compile(mesh_model(str(secret)), {"x.obj": OBJ})
    with pytest.raises(
        InvalidArgument, match="refers to file 'secret.obj', which is not among the request's assets"
    ):
        compiler.compile(mesh_model("secret.obj"), {"x.obj": OBJ})
    with pytest.raises(InvalidArgument, match="'/etc/hostname', which is an absolute path"):
        compiler.compile('<mujoco><include file="/etc/hostname"/></mujoco>', {})


def test_refused_models_never_reach_mujoco(no_mujoco: None) -> None:
    with ModelCompiler() as fresh, pytest.raises(InvalidArgument, match="absolute path"):
        fresh.compile(mesh_model("/etc/hostname"), {})


def test_mujoco_compiles_the_text_that_was_checked(compiler: ModelCompiler) -> None:
    # expat turns a newline inside an attribute into a space, tinyxml2 keeps it: MuJoCo is handed
    # the parsed document, not the raw bytes, so both see 'a b.obj'.
    mjcf = mesh_model("a\nb.obj")
    checked = check_model(mjcf, {"a b.obj": OBJ}, max_documents=10)
    assert 'file="a b.obj"' in checked.mjcf
    assert compiler.compile(mjcf, {"a b.obj": OBJ}).nmesh == 1


def test_line_numbers_survive_the_reserialization(compiler: ModelCompiler) -> None:
    mjcf = '<?xml version="1.0"?>\n<!-- a model -->\n<mujoco>\n  <worldbody>\n    <geom type="box"/>\n  </worldbody>\n</mujoco>'
    with pytest.raises(InvalidArgument) as error:
        compiler.compile(mjcf, {})
    assert "line 5" in str(error.value)


def test_limits_on_documents_follow_max_assets() -> None:
    limits = RegistryLimits(max_assets=3)
    assets = {f"{i}.xml": b"<mujoco/>" for i in range(3)}
    mjcf = (
        "<mujoco>"
        + "".join(f'<asset><model name="m{i}" file="{i}.xml"/></asset>' for i in range(3))
        + "</mujoco>"
    )
    check_model(mjcf, assets, max_documents=limits.max_assets)
