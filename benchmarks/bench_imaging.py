"""Benchmark: read + segment + surface one 256 x 256 x 200 synthetic DICOM MR series.

Target (issue 3): 10 s or less on the 2-core machine. Run with
``OMP_NUM_THREADS=2 .venv/bin/python benchmarks/bench_imaging.py``.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from imaging import (
    process_scan,
    read_volume,
    render_mr_volume,
    scan_grid_covering,
    write_dicom_series,
)
from imaging.testing import make_test_phantom


def main() -> None:
    ph = make_test_phantom(semi_axes_mm=(70.0, 55.0, 50.0), n_inclusions=19, seed=3)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [5.0, -8.0, 20.0], degrees=True).as_matrix()
    pts = np.r_[ph.body[0], ph.fiducial_centres_mm] @ T[:3, :3].T
    D = Rotation.from_euler("zyx", [10.0, 5.0, -8.0], degrees=True).as_matrix()
    grid = scan_grid_covering(
        pts, spacing_mm=(0.8, 0.8, 1.0), direction=D, min_shape=(256, 256, 200)
    )
    t0 = time.perf_counter()
    vol = render_mr_volume(
        ph.body,
        T_scanner_from_phantom=T,
        grid=grid,
        inclusions=ph.inclusions,
        fiducial_centres_mm=ph.fiducial_centres_mm,
        bias_amplitude=0.2,
        snr=25.0,
        seed=3,
    )
    t_render = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        write_dicom_series(vol, Path(tmp) / "series")
        t_write = time.perf_counter() - t0
        t0 = time.perf_counter()
        scan = read_volume(Path(tmp) / "series")
        t_read = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = process_scan(scan)
    t_process = time.perf_counter() - t0
    q = res.quality
    rows = [
        ("render (not timed)", t_render),
        ("write DICOM (not timed)", t_write),
        ("read DICOM series", t_read),
        ("segment body + bias", q["time_segment_s"]),
        ("fiducials + inclusions", q["time_detect_s"]),
        ("surface (MC, Taubin, decimate, repair)", q["time_surface_s"]),
        (
            "landmarks + rest",
            t_process - q["time_segment_s"] - q["time_detect_s"] - q["time_surface_s"],
        ),
    ]
    total = t_read + t_process
    print(f"volume {scan.shape} voxels {scan.spacing_mm.round(3).tolist()} mm")
    print(f"{'stage':<42}{'seconds':>9}")
    for name, t in rows:
        print(f"{name:<42}{t:>9.2f}")
    print(f"{'TOTAL read + segment + surface':<42}{total:>9.2f}   (target <= 10 s)")
    print(
        f"fiducials {len(res.fiducials_lps_mm)}, inclusions {len(res.inclusions.diameters_mm)}, "
        f"faces {len(res.surface.faces)}"
    )


if __name__ == "__main__":
    main()
