"""Calibration outputs: error maps (PNG, PLY with per-vertex error) and deformed meshes."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .io import atomic_write

__all__ = ["write_error_ply", "write_error_png"]


def write_error_ply(path: Path, vertices_mm: np.ndarray, faces: np.ndarray, error_mm) -> Path:
    """ASCII PLY of a surface with a per-vertex ``error_mm`` property (MeshLab, ParaView)."""
    v = np.asarray(vertices_mm, float)
    f = np.asarray(faces, int)
    e = np.asarray(error_mm, float)
    head = (
        "ply\nformat ascii 1.0\ncomment phantom-calib error map (reference LPS mm)\n"
        f"element vertex {len(v)}\nproperty double x\nproperty double y\nproperty double z\n"
        f"property float error_mm\nelement face {len(f)}\nproperty list uchar int vertex_indices\n"
        "end_header\n"
    )

    def write(p: Path) -> None:
        with open(p, "w") as fh:
            fh.write(head)
            np.savetxt(fh, np.column_stack([v, e]), fmt="%.6f %.6f %.6f %.4f")
            np.savetxt(fh, np.column_stack([np.full(len(f), 3), f]), fmt="%d")

    return atomic_write(path, write)


def write_error_png(path: Path, points_mm: np.ndarray, error_mm: np.ndarray, title: str) -> Path:
    """Two orthogonal views of the measured surface coloured by the error (mm)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    e = np.abs(np.asarray(error_mm, float))
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.5), constrained_layout=True)
    vmax = max(float(np.percentile(e, 99)), 1e-3)
    for ax, (i, j), lab in zip(axes, ((0, 1), (0, 2)), (("x", "y"), ("x", "z")), strict=True):
        order = np.argsort(points_mm[:, 3 - i - j])
        sc = ax.scatter(points_mm[order, i], points_mm[order, j], c=e[order], s=4,
                        cmap="jet", vmin=0.0, vmax=vmax)  # fmt: skip
        ax.set_aspect("equal")
        ax.set_xlabel(f"{lab[0]} (mm, reference LPS)")
        ax.set_ylabel(f"{lab[1]} (mm)")
    fig.colorbar(sc, ax=axes, label="closest-point error (mm)")
    fig.suptitle(title)

    def write(p: Path) -> None:
        fig.savefig(p, dpi=110, format="png")

    try:
        return atomic_write(path, write)
    finally:
        plt.close(fig)
