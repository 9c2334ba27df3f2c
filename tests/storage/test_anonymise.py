"""Anonymisation: the key (environment, 0600 file apart from the data), pseudonyms, the attribute
allow-list, and no identifying byte anywhere after a recorded session."""

from __future__ import annotations

import hashlib
import hmac
import os
import stat
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import sqlalchemy as sa

from jitdyn.errors import FailedPrecondition, InvalidArgument
from jitdyn.storage.anonymise import DEFAULT_ALLOWED_ATTRIBUTES, Anonymiser, load_or_create_secret
from jitdyn.storage.index import SessionIndex
from jitdyn.storage.recorder import SessionRecorder
from jitdyn.storage.records import SessionHeader
from jitdyn.storage.schema import sessions

SECRET = bytes(range(32))


def test_environment_secret_wins(tmp_path: Path) -> None:
    env = {"JITDYN_SECRET": SECRET.hex(), "XDG_CONFIG_HOME": str(tmp_path)}
    assert load_or_create_secret(secret_file=None, env=env) == SECRET
    assert not (tmp_path / "jitdyn").exists()


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("zz", "environment variable JITDYN_SECRET must hold the secret as hex digits"),
        ("ab" * 16, "environment variable JITDYN_SECRET must hold at least 32 bytes (64 hex digits), got 16"),
    ],
)
def test_bad_environment_secret(value: str, message: str) -> None:
    with pytest.raises(InvalidArgument) as error:
        load_or_create_secret(secret_file=None, env={"JITDYN_SECRET": value})
    assert str(error.value).startswith(message)


def test_secret_file_created_once_with_mode_0600(tmp_path: Path) -> None:
    env = {"XDG_CONFIG_HOME": str(tmp_path / "config")}
    first = load_or_create_secret(secret_file=None, env=env)
    path = tmp_path / "config" / "jitdyn" / "secret.key"
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert len(first) == 32
    assert load_or_create_secret(secret_file=None, env=env) == first
    home = load_or_create_secret(secret_file=None, env={"HOME": str(tmp_path / "home")})
    assert (tmp_path / "home" / ".config" / "jitdyn" / "secret.key").is_file()
    assert home != first


def test_secret_file_readable_by_others_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "secret.key"
    path.write_text(SECRET.hex())
    os.chmod(path, 0o644)
    with pytest.raises(FailedPrecondition) as error:
        load_or_create_secret(secret_file=path, env={})
    assert str(error.value) == (
        f"the secret file {path} is accessible by group or others (mode 0644); run `chmod 600 {path}`"
    )
    os.chmod(path, 0o600)
    assert load_or_create_secret(secret_file=path, env={}) == SECRET


def test_secret_file_inside_the_data_root_is_refused(tmp_path: Path) -> None:
    data_root = tmp_path / "data"
    data_root.mkdir()
    with pytest.raises(FailedPrecondition, match="is inside the data root") as error:
        load_or_create_secret(secret_file=data_root / "keys" / "secret.key", env={}, data_root=data_root)
    assert "keep the key apart from the data" in str(error.value)
    assert not (data_root / "keys").exists()


def test_secret_file_from_environment_path(tmp_path: Path) -> None:
    path = tmp_path / "elsewhere.key"
    secret = load_or_create_secret(secret_file=None, env={"JITDYN_SECRET_FILE": str(path)})
    assert bytes.fromhex(path.read_text()) == secret


def test_pseudonym_is_hmac_sha256_under_a_key_per_tenant() -> None:
    anonymiser = Anonymiser(SECRET)
    pseudonym = anonymiser.pseudonym("patient-4711", tenant="")
    key = hmac.new(SECRET, b"jitdyn pseudonym key v1\x00", hashlib.sha256).digest()
    assert pseudonym == hmac.new(key, b"patient-4711", hashlib.sha256).hexdigest()
    # Pinned, so that a change of the scheme (which would orphan every stored pseudonym) is seen.
    assert pseudonym == "586352089bf4a624e0bc71fe127e719460f65c2a1e72db3f6176037b525509bc"
    other = anonymiser.pseudonym("patient-4711", tenant="lab-b")
    lab_b = hmac.new(SECRET, b"jitdyn pseudonym key v1\x00lab-b", hashlib.sha256).digest()
    assert other == hmac.new(lab_b, b"patient-4711", hashlib.sha256).hexdigest() != pseudonym
    assert Anonymiser(bytes(32)).pseudonym("patient-4711", tenant="") != pseudonym
    assert anonymiser.pseudonym("", tenant="") == ""
    with pytest.raises(InvalidArgument, match="subject.id must have at most 256 characters, got 257"):
        anonymiser.pseudonym("x" * 257, tenant="")


def test_attributes_are_typed_and_coarsened() -> None:
    assert {"sex", "age", "age_band", "height_m", "mass_kg", "side", "limb", "condition"} == (
        DEFAULT_ALLOWED_ATTRIBUTES
    )
    anonymiser = Anonymiser(SECRET)
    assert anonymiser.check_attributes(
        {"sex": "f", "age": "43", "height_m": "1.83", "mass_kg": "77.4", "side": "Left", "limb": "leg"}
    ) == {"sex": "F", "age_band": "40-44", "height_m": "1.85", "mass_kg": "75", "side": "left", "limb": "leg"}
    assert anonymiser.check_attributes({"age_band": "65-69", "condition": "stroke"}) == {
        "age_band": "65-69",
        "condition": "stroke",
    }


@pytest.mark.parametrize(
    ("attributes", "message"),
    [
        (
            {"name": "Erika"},
            r"open.subject.attributes\['name'\]: not an attribute this server keeps; allowed: ",
        ),
        (
            {"limb": "Jane Doe 555-1234"},
            r"attributes\['limb'\] must be one of arm, forearm, .*, got 'Jane Doe 555-1234'",
        ),
        (
            {"age": "43.5"},
            r"attributes\['age'\] must be whole years, 0 to 130 \(stored as a 5-year band\), got '43.5'",
        ),
        (
            {"age_band": "40-49"},
            r"attributes\['age_band'\] must be a 5-year band such as \"40-44\", got '40-49'",
        ),
        (
            {"height_m": "tall"},
            r"attributes\['height_m'\] must be a number of metres in \[0.3, 2.6\], got 'tall'",
        ),
        (
            {"mass_kg": "nan"},
            r"attributes\['mass_kg'\] must be a number of kilograms in \[1, 400\], got 'nan'",
        ),
        ({"condition": "x" * 33}, r"attributes\['condition'\] must have at most 32 characters, got 33"),
    ],
)
def test_anything_else_is_refused_naming_the_attribute(attributes: dict[str, str], message: str) -> None:
    with pytest.raises(InvalidArgument, match=message):
        Anonymiser(SECRET).check_attributes(attributes)


def test_only_typed_attributes_can_be_allowed() -> None:
    with pytest.raises(
        InvalidArgument, match=r"allowed attributes must be typed ones of .*, got \['cohort'\]"
    ):
        Anonymiser(SECRET, allowed_attributes={"cohort"})
    with pytest.raises(
        InvalidArgument, match=r"attributes\['sex'\]: not an attribute this server keeps; allowed: limb"
    ):
        Anonymiser(SECRET, allowed_attributes={"limb"}).check_attributes({"sex": "F"})


def test_no_stored_byte_identifies_the_subject(
    data_root: Path,
    index: SessionIndex,
    engine: sa.Engine,
    make_header: Callable[..., SessionHeader],
    make_records: Any,
) -> None:
    """A session as the runtime records it, with a subject id and a name among the attributes: no
    file under the data root (the SQLite index included) and no index row holds either."""
    anonymiser = Anonymiser(SECRET)
    kept = anonymiser.check_attributes({"sex": "F", "age": "43"})
    header = make_header(
        subject_pseudonym=anonymiser.pseudonym("patient-4711", tenant=""), subject_attributes=kept
    )
    with SessionRecorder(data_root=data_root, index=index, header=header) as recorder:
        for record in make_records(40):
            recorder.append(record)
        recorder.flush()
        # The open session's log, too.
        scan_for_identifiers(data_root)
        recorder.close()
    scan_for_identifiers(data_root)
    with engine.connect() as conn:
        for row in conn.execute(sa.select(sessions)):
            text = repr(tuple(row)).encode()
            for needle in (b"patient-4711", b"Erika", b"Mustermann"):
                assert needle not in text
    assert index.get(header.session_id, tenant="").subject_attributes == {"sex": "F", "age_band": "40-44"}


def scan_for_identifiers(root: Path) -> None:
    files = [p for p in root.rglob("*") if p.is_file()]
    assert files
    for path in files:
        data = path.read_bytes()
        for needle in ("patient-4711", "Erika", "Mustermann"):
            for encoded in (needle.encode("utf-8"), needle.encode("utf-16-le")):
                assert encoded not in data, (needle, path)
