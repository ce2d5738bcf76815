"""The provenance header each benchmark prints first: command, commit, versions, threads.

Review BL (F5): the benchmarks did not say which code they measured. ``print_header``
prints, before any table, the command line, the git commit the ``calib`` package runs from
and whether its tree had uncommitted edits, the versions of the libraries that set the
script's numbers and the thread counts in use (``calib.io.provenance``). Scripts that only
print rows saved earlier say so, with the commits the rows record (``saved_commits``).

The benchmarks are not a package: each script puts this folder on ``sys.path`` and imports
``from _provenance import print_header``. Importing this module prints nothing and imports
nothing heavy (``calib.io`` is imported when the header is printed).
"""

from __future__ import annotations

import sys
from collections.abc import Iterable

#: the FE stack: the forward solves' numbers and times
FE = ("numpy", "scipy", "scikit-fem", "tetgen", "pypardiso", "mkl")
#: the imaging stack: the scans' reading, segmentation and surfaces
IMAGING = ("SimpleITK", "pydicom", "scikit-image", "open3d-cpu")


def short_commit(source: dict | None) -> str:
    """``abc1234`` (``+edits`` where the tree had uncommitted edits), or ``unknown``."""
    if not source or not source.get("commit"):
        return "unknown"
    return source["commit"][:7] + ("+edits" if source.get("uncommitted_edits") else "")


def source_line(source: dict | None) -> str:
    """The commit and whether the tree had uncommitted edits, in words."""
    if not source or not source.get("commit"):
        return "unknown (not a git checkout, or git missing)"
    edits = "with uncommitted edits" if source.get("uncommitted_edits") else "no uncommitted edits"
    return f"commit {source['commit']} ({edits})"


def saved_commits(rows: Iterable[dict], key: str = "source") -> str:
    """The commits saved rows record under ``key`` (``calib.io.provenance()["source"]``)."""
    counts: dict[str, int] = {}
    for r in rows:
        name = short_commit(r.get(key)) if r.get(key) else "not recorded"
        counts[name] = counts.get(name, 0) + 1
    if not counts:
        return "no rows"
    return ", ".join(
        f"commit {k} ({n} rows)" if k != "not recorded" else f"commit not recorded ({n} rows)"
        for k, n in counts.items()
    )


def print_header(
    names: Iterable[str] = ("numpy", "scipy"),
    *,
    command: str | None = None,
    saved: str | None = None,
) -> dict:
    """Print the provenance header; return ``calib.io.provenance()``.

    ``names``: the libraries whose versions set the script's numbers. ``command``: the
    command line as the script prints it (default ``' '.join(sys.argv)``). ``saved``: for
    a mode that prints rows measured earlier, where they come from and their commits
    (the commit printed is then the printing code's, not the measuring code's).
    """
    from calib.io import _version, provenance

    prov = provenance()
    print(f"command: {command if command is not None else ' '.join(sys.argv)}")
    print(f"source: {source_line(prov['source'])}")
    libs = ", ".join(f"{n} {_version(n) or 'not installed'}" for n in names)
    print(f"versions: python {prov['python']}, {libs}")
    pools = prov["thread_pools"]
    env = ", ".join(f"{k}={x}" for k, x in prov["threads"].items() if x is not None)
    loaded = ", ".join(f"{p} ({e['api']}) {e['num_threads']}" for p, e in pools["pools"].items())
    print(
        f"threads: {pools['cpu_count']} cores; {env or 'no thread variables set'}; "
        f"pools loaded so far: {loaded or 'none'}"
    )
    if saved is not None:
        print(f"rows: measured earlier, not by this run: {saved}")
    return prov
