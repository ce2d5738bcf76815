"""Helpers shared by the mesh readers and writers of :mod:`fem.io`.

:func:`atomic_write` (re-exported as ``fem.io.atomic_write``) and the default
region name of a numeric tag.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path

from .mesh import REGION_IDS

__all__ = ["atomic_write"]


def _file_mode() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def atomic_write(path: str | os.PathLike, write: Callable[[Path], None]) -> Path:
    """Call ``write(tmp)`` on a temporary file next to ``path``, then rename it to ``path``.

    The temporary file keeps the suffix (format-sniffing writers work); on any error it
    is removed and ``path`` is left untouched. The file gets the mode an ordinary
    ``open`` would give under the current umask (not ``mkstemp``'s private 0600).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent
    )
    os.close(fd)
    try:
        write(Path(tmp))
        os.chmod(tmp, _file_mode())  # mkstemp's 0600 -> what open() would give (umask)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def _region_name_for(tag: int) -> str:
    known = {v: k for k, v in REGION_IDS.items()}
    return known.get(int(tag), f"region{int(tag)}")
