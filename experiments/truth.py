"""The model the demo simulates its truth with: the registered model a session opens, compiled here
from its MJCF. A built-in comes with jitdyn; another is read from the registry's store in a local
data folder, or packed again from myo-sim for a MyoSuite model, and must have the registered
content id. What cannot be found says, in one line, why and what to do (docs/decisions/0141, 0181).

    ref, model = truth_model(client, "myoelbow", data=Path("jitdyn-data"), address=address)
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import mujoco

from jitdyn.client import Client, ModelRef
from jitdyn.errors import FailedPrecondition, InvalidArgument
from jitdyn.registry import builtin_model_path, content_id
from jitdyn.registry.store import blob_path, read_blob
from jitdyn.settings import parse_model_reference

__all__ = ["TruthSources", "truth_model"]


@dataclass(frozen=True)
class TruthSources:
    """Where the demo looks for a registered model's MJCF besides the built-ins and myo-sim."""

    # A data folder whose registry store may hold it: the server's, or one on this machine.
    data: Path | None = None
    # The MJCF file the model was registered from, and the folder of its assets (default: its own).
    mjcf: Path | None = None
    asset_dir: Path | None = None


def _file_source(ref: ModelRef, sources: TruthSources) -> tuple[str, dict[str, bytes]] | None:
    """The MJCF and assets of `sources.mjcf`, which must be the content registered as `ref`."""
    if sources.mjcf is None:
        return None
    from jitdyn.client.assets import read_model_files

    mjcf, assets = read_model_files(sources.mjcf, asset_dir=sources.asset_dir)
    if content_id(mjcf, assets) != ref.id:
        raise InvalidArgument(
            f"--mjcf {sources.mjcf} is not the content registered as {ref.name} v{ref.version}: its id is "
            f"{content_id(mjcf, assets)}, the registered one {ref.id} (another version, or other assets?)"
        )
    return mjcf, assets


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
    client: Client, reference: str, sources: TruthSources, *, address: str
) -> tuple[ModelRef, mujoco.MjModel]:
    """The registered model `reference` names (see parse_model_reference), and the MjModel of its
    MJCF, looked for in `sources`, then in myo-sim.

    Raises NotFound for a model the server does not have, FailedPrecondition when its MJCF is not
    to be had here, InvalidArgument for a --mjcf file of other content."""
    model_id, name, version = parse_model_reference(reference)
    ref = client.get_model(model_id=model_id, name=name, version=version)
    if ref.builtin:
        return ref, mujoco.MjModel.from_xml_path(str(builtin_model_path(ref.name)))
    source = _file_source(ref, sources)
    # A content id names one content wherever it is stored: any data folder's copy will do.
    if source is None and sources.data is not None and (sources.data / blob_path(ref.id)).is_file():
        source = read_blob(sources.data, blob_path(ref.id))
    source = source or _myo_source(ref)
    if source is None:
        looked = f", nor in {sources.data}" if sources.data is not None else ""
        raise FailedPrecondition(
            f"{ref.name} v{ref.version} is registered at {address}, but the demo simulates its truth here "
            f"and has no copy of its MJCF{looked}: give the file it was registered from (--mjcf FILE, "
            "with --asset-dir for its assets), or run the demo on the data folder that holds it (--data DIR)"
        )
    mjcf, assets = source
    try:
        return ref, mujoco.MjModel.from_xml_string(mjcf, assets)
    except ValueError as error:
        raise InvalidArgument(f"{ref.name} v{ref.version} does not compile here: {error}") from None
