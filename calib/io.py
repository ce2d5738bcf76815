"""Atomic output files and provenance records."""

from __future__ import annotations

import hashlib
import json
import os
import platform
import sys
from datetime import UTC, datetime
from importlib import metadata
from pathlib import Path

from fem.io import atomic_write

__all__ = ["atomic_write", "file_sha256", "provenance", "write_json_atomic"]

_PACKAGES = ("phantom-calib", "numpy", "scipy", "scikit-fem", "tetgen", "meshio", "open3d-cpu")


def write_json_atomic(path: str | os.PathLike, data: dict) -> Path:
    """Write ``data`` as indented JSON, atomically."""
    text = json.dumps(data, indent=2, sort_keys=False, allow_nan=False)
    return atomic_write(path, lambda p: p.write_text(text + "\n"))


def file_sha256(path: str | os.PathLike) -> str:
    """SHA-256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _version(name: str) -> str | None:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def provenance(*, inputs: dict[str, str | os.PathLike] | None = None, parameters=None) -> dict:
    """A provenance record: time, versions, input file hashes and parameters."""
    return {
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "versions": {p: _version(p) for p in _PACKAGES},
        "command": sys.argv,
        "inputs": {
            k: {"path": str(v), "sha256": file_sha256(v)} for k, v in (inputs or {}).items()
        },
        "parameters": parameters or {},
    }
