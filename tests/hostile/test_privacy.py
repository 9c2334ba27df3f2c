"""Finding 7: subject attributes are typed, pseudonyms are keyed per tenant, stored files and
folders are the server's user's only."""

from __future__ import annotations

import stat
from collections.abc import Callable
from pathlib import Path

import grpc
import pytest
from _hostile import Served, close, frame, honest_session, open_request, stored

from jitdyn.v1 import dynamics_pb2

KEYS = {"lab-a": "a" * 24, "lab-b": "b" * 24}


def _opened(
    served: Served, request: dynamics_pb2.StreamSessionRequest, key: str
) -> dynamics_pb2.SessionOpened:
    responses = list(
        served.dynamics.StreamSession(
            iter([request, frame(0), close()]), metadata=[("authorization", f"Bearer {key}")], timeout=60
        )
    )
    return responses[0].opened


def test_free_text_attributes_are_refused_naming_the_attribute(serve: Callable[..., Served]) -> None:
    served = serve()
    for attributes, named in [
        ({"limb": "Jane Doe 555-1234"}, "open.subject.attributes['limb'] must be one of arm, forearm"),
        ({"name": "Jane Doe"}, "open.subject.attributes['name']: not an attribute this server keeps"),
        ({"age": "43 (born 1981-03-02)"}, "open.subject.attributes['age'] must be whole years"),
    ]:
        with pytest.raises(grpc.RpcError) as caught:
            list(served.dynamics.StreamSession(iter([open_request(attributes=attributes)]), timeout=30))
        assert caught.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert named in (caught.value.details() or "")
    honest_session(served, attributes={"sex": "f", "age": "43", "height_m": "1.83", "mass_kg": "77.4"})
    (session,) = stored(served, "COMPLETE")
    assert dict(session.subject_attributes) == {
        "sex": "F",
        "age_band": "40-44",
        "height_m": "1.85",
        "mass_kg": "75",
    }
    everything = b"".join(p.read_bytes() for p in served.data.rglob("*") if p.is_file())
    assert b"Jane" not in everything and b"555-1234" not in everything


def test_tenants_get_unlinkable_pseudonyms(serve: Callable[..., Served], tmp_path: Path) -> None:
    keys = tmp_path / "api-keys"
    keys.write_text("".join(f"{key} {tenant}\n" for tenant, key in KEYS.items()))
    keys.chmod(0o600)
    served = serve("--api-keys", str(keys))
    a = _opened(served, open_request(subject="patient-4711"), KEYS["lab-a"]).subject_pseudonym
    b = _opened(served, open_request(subject="patient-4711"), KEYS["lab-b"]).subject_pseudonym
    again = _opened(served, open_request(subject="patient-4711"), KEYS["lab-a"]).subject_pseudonym
    assert len(a) == len(b) == 64
    assert a == again  # stable within a tenant
    assert a != b  # a tenant cannot test candidate ids against another tenant's data


def test_stored_files_and_folders_are_private(serve: Callable[..., Served], tmp_path: Path) -> None:
    data = tmp_path / "data"
    data.mkdir(mode=0o755)
    data.chmod(0o755)
    served = serve(data=data)
    honest_session(served, subject="patient-4711")
    served.stop()
    paths = [data, *data.rglob("*")]
    assert any(p.suffix == ".parquet" for p in paths) and any(
        p.name.startswith("index.sqlite") for p in paths
    )
    loose = {
        str(p.relative_to(tmp_path)): oct(stat.S_IMODE(p.stat().st_mode))
        for p in paths
        if p.stat().st_mode & 0o077
    }
    assert loose == {}
