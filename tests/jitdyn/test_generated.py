"""The checked-in generated code matches proto/, and the proto passes buf lint."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from jitdyn.checksum import frame_checksum

ROOT = Path(__file__).resolve().parents[2]


def test_generated_code_is_fresh(tmp_path: Path) -> None:
    subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "gen_proto.py"), "--out", str(tmp_path)],
        check=True,
        capture_output=True,
    )
    fresh = {p.name: p.read_bytes() for p in (tmp_path / "jitdyn" / "v1").iterdir() if p.is_file()}
    checked_in = {p.name: p.read_bytes() for p in (ROOT / "src" / "jitdyn" / "v1").iterdir() if p.is_file()}
    stale = sorted(
        name for name in fresh.keys() | checked_in.keys() if fresh.get(name) != checked_in.get(name)
    )
    assert not stale, (
        f"src/jitdyn/v1 is stale for {stale}: run `python scripts/gen_proto.py` and commit the result"
    )


def test_buf_lint_is_clean() -> None:
    buf = shutil.which("buf") or str(Path(sys.executable).parent / "buf")
    if not Path(buf).exists():
        pytest.fail("buf is not installed: pip install -e '.[test]' installs buf-bin")
    result = subprocess.run([buf, "lint"], cwd=ROOT, capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stdout + result.stderr


def test_checksum_test_vector_of_the_proto() -> None:
    # The vector documented in dynamics.proto (Frame.checksum), so other languages can check theirs.
    assert frame_checksum(seq=1, t=0.05, qpos=[0.1], qvel=[-0.2]) == 0x698C163E
    proto = (ROOT / "proto" / "jitdyn" / "v1" / "dynamics.proto").read_text()
    assert "checksum 0x698c163e" in proto
