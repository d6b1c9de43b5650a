#!/usr/bin/env python3
"""Regenerate the committed stubs in python/src/blapose/v1 from the repo's proto.

Usage: ``python python/tools/gen_stubs.py [OUT_DIR]`` (needs grpcio-tools; the
version pinned in pyproject.toml's ``test`` extra). Without OUT_DIR it writes
into ``python/src`` (the committed location).
"""

from __future__ import annotations

import sys
from pathlib import Path

PYTHON_DIR = Path(__file__).resolve().parent.parent
REPO = PYTHON_DIR.parent
PROTO_ROOT = REPO / "proto"
PROTO = PROTO_ROOT / "blapose" / "v1" / "blapose.proto"
STUB_FILES = ("blapose_pb2.py", "blapose_pb2.pyi", "blapose_pb2_grpc.py")


def generate(out: Path) -> None:
    """Run protoc (from grpcio-tools) writing ``out/blapose/v1/blapose_pb2*.py``."""
    from grpc_tools import protoc

    out.mkdir(parents=True, exist_ok=True)
    args = [
        "grpc_tools.protoc",
        f"-I{PROTO_ROOT}",
        f"--python_out={out}",
        f"--pyi_out={out}",
        f"--grpc_python_out={out}",
        str(PROTO),
    ]
    rc = protoc.main(args)
    if rc != 0:
        raise RuntimeError(f"protoc failed with exit code {rc}")


if __name__ == "__main__":
    generate(Path(sys.argv[1]) if len(sys.argv) > 1 else PYTHON_DIR / "src")
