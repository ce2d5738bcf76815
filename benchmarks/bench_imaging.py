"""Benchmark: read + segment + surface one 256 x 256 x 200 synthetic DICOM MR series.

Target (issue 3): 10 s or less on the 2-core machine. Run with
``OMP_NUM_THREADS=2 .venv/bin/python benchmarks/bench_imaging.py [--repeat 3] [--seed 3]``:
the series is rendered and written once, then read and processed ``--repeat`` times; each
stage's median (min-max) is printed, with the commit and the versions.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/_provenance.py

from _provenance import IMAGING, print_header

from imaging import (
    process_scan,
    read_volume,
    render_mr_volume,
    scan_grid_covering,
    write_dicom_series,
)
from imaging.testing import make_test_phantom


def _stats(values: list[float]) -> str:
    """Median (min-max) of repeated timings, seconds."""
    v = np.asarray(values)
    return f"{np.median(v):7.2f} ({v.min():.2f}-{v.max():.2f})"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3, help="read + process runs (median)")
    parser.add_argument("--seed", type=int, default=3, help="phantom and renderer seed")
    args = parser.parse_args(argv)
    if args.repeat < 1:
        parser.error("--repeat must be >= 1")
    print_header(("numpy", "scipy", *IMAGING))
    ph = make_test_phantom(semi_axes_mm=(70.0, 55.0, 50.0), n_inclusions=19, seed=args.seed)
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
        seed=args.seed,
    )
    t_render = time.perf_counter() - t0
    names = [
        "read DICOM series",
        "segment body + bias",
        "fiducials + inclusions",
        "surface (MC, Taubin, decimate, repair)",
        "landmarks + rest",
        "TOTAL read + segment + surface",
    ]
    times: dict[str, list[float]] = {n: [] for n in names}
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        write_dicom_series(vol, Path(tmp) / "series")
        t_write = time.perf_counter() - t0
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            scan = read_volume(Path(tmp) / "series")
            t_read = time.perf_counter() - t0
            t0 = time.perf_counter()
            res = process_scan(scan)
            t_process = time.perf_counter() - t0
            q = res.quality
            stages = (q["time_segment_s"], q["time_detect_s"], q["time_surface_s"])
            for name, t in zip(
                names,
                [t_read, *stages, t_process - sum(stages), t_read + t_process],
                strict=True,
            ):
                times[name].append(t)
    print(f"volume {scan.shape} voxels {scan.spacing_mm.round(3).tolist()} mm")
    print(f"render {t_render:.2f} s, write DICOM {t_write:.2f} s (once each, not timed below)")
    print(f"{'stage':<42}{'median s (min-max), ' + str(args.repeat) + ' runs':>30}")
    for name in names:
        print(f"{name:<42}{_stats(times[name]):>30}")
    print("target: TOTAL <= 10 s (issue 3)")
    print(
        f"fiducials {len(res.fiducials_lps_mm)}, inclusions {len(res.inclusions.diameters_mm)}, "
        f"faces {len(res.surface.faces)}"
    )


if __name__ == "__main__":
    main()
