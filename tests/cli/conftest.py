"""The cli tests' helpers live in _cli.py, importable from the tests as `_cli`; the fixture of a
real `jitdyn serve` with the recorded jump's leg registered lives here (replay and lsl)."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))

from _cli import jitdyn, ok, serving

from jitdyn.experiments.recorded import chain_mjcf


@pytest.fixture(scope="module")
def leg_data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("replay") / "data"


@pytest.fixture(scope="module")
def leg_server(leg_data: Path) -> Iterator[str]:
    """A real `jitdyn serve` on `leg_data`, with the hip-knee-ankle leg of the recorded jump registered."""
    folder = leg_data.parent
    with serving(data=leg_data) as address:
        leg = folder / "cmj_leg.xml"
        leg.write_text(chain_mjcf(), encoding="utf-8")
        ok(jitdyn("models", "register", str(leg), "--server", address))
        yield address
