"""Atomic file and folder writes that honour the umask (imaging's one write helper).

A temporary file or folder is made beside the target, filled, and renamed over it, so
an interrupted write never leaves a half-written file. ``tempfile`` creates them
private (0600/0700); they get the mode an ordinary ``open``/``mkdir`` would give under
the current umask before the rename, so results in a shared folder stay readable.
(``fem.io.atomic_write`` does the same for fem and calib, which imaging may not import.)
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

__all__ = ["atomic_folder", "atomic_write", "umask_mode"]


def umask_mode(directory: bool = False) -> int:
    """The mode a new file (0666) or directory (0777) gets under the current umask."""
    mask = os.umask(0)
    os.umask(mask)
    return (0o777 if directory else 0o666) & ~mask


def atomic_write(
    path: str | os.PathLike, write: Callable[[Path], None], *, suffix: str = ""
) -> Path:
    """Call ``write(tmp)`` on a temporary file beside ``path``, then rename it to ``path``.

    Parameters
    ----------
    path : path-like
        The file to (re)place; its folder is created.
    write : callable
        Writes the content to the temporary path it is given.
    suffix : str
        Suffix of the temporary file (for writers that choose the format by it).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
    os.close(fd)
    try:
        write(Path(tmp))
        os.chmod(tmp, umask_mode())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def atomic_folder(folder: str | os.PathLike, fill: Callable[[Path], None]) -> Path:
    """Call ``fill(tmp)`` on a temporary folder beside ``folder``, then move it into place.

    An existing ``folder`` is replaced only once ``fill`` has returned.
    """
    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=folder.parent, prefix=f".{folder.name}."))
    try:
        fill(tmp)
        os.chmod(tmp, umask_mode(directory=True))
        if folder.exists():
            shutil.rmtree(folder)
        os.replace(tmp, folder)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)
    return folder
