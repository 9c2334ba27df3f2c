"""Regenerate the Python code of the v1 contract from proto/ into src/jitdyn/v1/.

    python scripts/gen_proto.py            # rewrite src/jitdyn/v1/*_pb2*.py(i)
    python scripts/gen_proto.py --out DIR  # write elsewhere (the freshness test compares)

The .pyi stubs of messages and of gRPC stubs and servicers come from mypy-protobuf, so that mypy
strict checks every call into the contract. Generated code is never edited by hand;
tests/jitdyn/test_generated.py fails when it is stale.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import sysconfig
from importlib import resources
from pathlib import Path

from grpc_tools import protoc

ROOT = Path(__file__).resolve().parent.parent
PROTO_ROOT = ROOT / "proto"


def _plugin(name: str) -> str:
    """The path of a protoc plugin installed beside this interpreter, else on PATH: a venv's scripts
    need not be on PATH when its python runs this file."""
    found = shutil.which(name, path=sysconfig.get_path("scripts")) or shutil.which(name)
    if found is None:
        raise SystemExit(f"{name} is not installed: pip install -e '.[test]' installs mypy-protobuf")
    return found


def generate(out: Path) -> list[Path]:
    """Run protoc on every proto/jitdyn/v1/*.proto; returns the files written."""
    protos = sorted(str(p.relative_to(PROTO_ROOT)) for p in (PROTO_ROOT / "jitdyn" / "v1").glob("*.proto"))
    well_known = str(resources.files("grpc_tools") / "_proto")
    out.mkdir(parents=True, exist_ok=True)
    args = [
        "grpc_tools.protoc",
        f"-I{PROTO_ROOT}",
        f"-I{well_known}",
        f"--python_out={out}",
        f"--grpc_python_out={out}",
        f"--plugin=protoc-gen-mypy={_plugin('protoc-gen-mypy')}",
        f"--mypy_out={out}",
        f"--plugin=protoc-gen-mypy_grpc={_plugin('protoc-gen-mypy_grpc')}",
        f"--mypy_grpc_out={out}",
        *protos,
    ]
    if protoc.main(args) != 0:
        raise SystemExit("protoc failed; see the messages above")
    package = out / "jitdyn" / "v1"
    written = sorted(p for p in package.iterdir() if p.suffix in {".py", ".pyi"} and "_pb2" in p.name)
    init = package / "__init__.py"
    init.write_text('"""Generated from proto/jitdyn/v1 by scripts/gen_proto.py; do not edit."""\n')
    return [*written, init]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--out",
        type=Path,
        default=ROOT / "src",
        help="root to write jitdyn/v1/ under (default: the checkout's src/)",
    )
    args = parser.parse_args(argv)
    for path in generate(args.out):
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
