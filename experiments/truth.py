"""The model the demo simulates its truth with: the registered model a session opens, compiled here
from its MJCF. A built-in comes with jitdyn; another is read from the registry's store in a local
data folder, or packed again from myo-sim for a MyoSuite model, and must have the registered
content id. What cannot be found says, in one line, why and what to do (docs/decisions/0141).

    ref, model = truth_model(client, "myoelbow", data=Path("jitdyn-data"), address=address)
"""

from __future__ import annotations

import re
from pathlib import Path

import mujoco

from jitdyn.client import Client, ModelRef
from jitdyn.errors import FailedPrecondition, InvalidArgument
from jitdyn.registry import builtin_model_path, content_id
from jitdyn.registry.store import blob_path, read_blob
from jitdyn.settings import parse_model_reference

__all__ = ["truth_model"]


def _myo_source(ref: ModelRef) -> tuple[str, dict[str, bytes]] | None:
    """The MJCF and assets of a MyoSuite model packed again from myo-sim, when myo-sim is installed
    and packs the very content registered. The myo-sim names tried are those in the model's name or
    description (`models register --myo` writes "MyoSuite NAME, ..."), longest first."""
    if "myosuite" not in ref.tags:
        return None
    try:
        from jitdyn.client.myo import myo_model_names, pack_myo_model

        names = myo_model_names()
    except ImportError:
        return None
    words = set(re.findall(r"[a-z0-9_]+", f"{ref.name} {ref.description}".lower()))
    for name in sorted(words.intersection(names), key=lambda n: (-len(n), n)):
        try:
            mjcf, assets = pack_myo_model(name)
        except ValueError:
            continue
        if content_id(mjcf, assets) == ref.id:
            return mjcf, assets
    return None


def truth_model(
    client: Client, reference: str, *, data: Path | None, address: str
) -> tuple[ModelRef, mujoco.MjModel]:
    """The registered model `reference` names (see parse_model_reference), and the MjModel of its
    MJCF. `data`: a local data folder whose registry store may hold it (None for a remote server).

    Raises NotFound for a model the server does not have, FailedPrecondition when its MJCF is not
    to be had here."""
    model_id, name, version = parse_model_reference(reference)
    ref = client.get_model(model_id=model_id, name=name, version=version)
    if ref.builtin:
        return ref, mujoco.MjModel.from_xml_path(str(builtin_model_path(ref.name)))
    source = None
    if data is not None and (data / blob_path(ref.id)).is_file():
        source = read_blob(data, blob_path(ref.id))
    source = source or _myo_source(ref)
    if source is None:
        raise FailedPrecondition(
            f"{ref.name} v{ref.version} is registered at {address}, but the demo simulates its truth here "
            "and has no copy of its MJCF: run the demo without --server, on the data folder that holds it "
            "(--data DIR)"
        )
    mjcf, assets = source
    try:
        return ref, mujoco.MjModel.from_xml_string(mjcf, assets)
    except ValueError as error:
        raise InvalidArgument(f"{ref.name} v{ref.version} does not compile here: {error}") from None
