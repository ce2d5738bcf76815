"""Tumour tracking under large motion: constellation matching against the former tracker.

Issue 18: on a scan set where the phantom slides on its back plate, ingest tracked
another inclusion 42 mm from the tumour in one scan, silently. For each seed this
script builds a soft digital twin (large inclusion motion), ingests it once, and prints
per posture

* the motion: the tumour's and the largest inclusion displacement relative to the
  reference scan (truth, phantom frame, mm);
* the tracked tumour's error against ``OUT/truth/truth.json`` (``tumour_lps_mm``) for
  the constellation matching that ingest now uses, and for the former tracker (an
  affine fit of mutual nearest neighbours, then the nearest inclusion of the tumour's
  size: a peer, re-implemented here and run on the same detections);
* how many inclusions got a wrong identity (truth: every inclusion's deformed centre,
  captured while the twin is built), the tumour's match confidence, and the matching
  time per scan (median and spread of ``--repeat`` runs; the peer's beside it).

    python benchmarks/bench_tracking.py [--preset quick|small] [--c1 300] [--sliding]
                                        [--skin] [--seeds 0,1,2] [--repeat 3] [--keep DIR]
    python benchmarks/bench_tracking.py --synthetic 100

Defaults: quick preset (4 postures), c1 = 300 Pa, clamped, no skin, seeds 0-2.
``--synthetic N`` instead rates the matcher on N random constellations per variant (the
unit tests' generator, independent of the twin; see :func:`synthetic`).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
import warnings
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np
from _provenance import FE, IMAGING, print_header

import calib.twin.synth as synth
from calib.data.ingest import SIZE_SD_MM
from calib.data.session import load_session
from calib.model.effects import TruthEffects
from calib.twin import PRESETS, Posture, TwinPreset
from registration import apply_transform, match_constellation

SMALL = TwinPreset(
    phantom_resolution_mm=14,
    truth_mesh_mm=14,
    spacing_mm=(2.0, 2.0, 2.0),
    postures=(
        Posture("left_lateral", 0, "reference"),
        Posture("right_lateral", 180, "calibration"),
    ),
)


def build(out: Path, preset: TwinPreset, seed: int) -> dict:
    """Synthesize (or reuse) a twin; its truth gains every inclusion's deformed centre."""
    extra = out / "inclusion_truth.json"
    if extra.is_file():
        record = json.loads((out / "truth" / "truth.json").read_text())
        centres = json.loads(extra.read_text())
    else:
        captured, real = [], synth._deform

        def deform(*args, **kwargs):
            truth = real(*args, **kwargs)
            captured.append(np.array([v.mean(0) for v, _ in truth.inclusions]))
            return truth

        synth._deform = deform
        try:
            t0 = time.perf_counter()
            record = synth.synthesize(out, preset=preset, seed=seed, overwrite=True)
            print(f"  seed {seed}: synth {time.perf_counter() - t0:.0f} s", flush=True)
        finally:
            synth._deform = real
        record = json.loads(json.dumps(record))
        centres = {
            n: apply_transform(np.asarray(s["T_scanner_from_phantom"]), c).tolist()
            for (n, s), c in zip(record["scans"].items(), captured, strict=True)
        }
        extra.write_text(json.dumps(centres))
    for name, scan in record["scans"].items():
        scan["inclusions_lps_mm"] = np.asarray(centres[name])
    return record


def former_tracker(ref_pts, ref_d, t, pts, d):
    """The tracker ingest used before issue 18 (``_match_constellation`` and the nearest
    inclusion of similar size to the affinely mapped reference tumour)."""
    A = np.eye(4)
    for _ in range(15):
        moved = apply_transform(A, pts)
        dist = np.linalg.norm(moved[:, None] - ref_pts[None], axis=2)
        fwd, back = dist.argmin(axis=1), dist.argmin(axis=0)
        mutual = np.flatnonzero(back[fwd] == np.arange(len(pts)))
        if len(mutual) < 4:
            break
        src = np.column_stack([pts[mutual], np.ones(len(mutual))])
        sol, *_ = np.linalg.lstsq(src, ref_pts[fwd[mutual]], rcond=None)
        A = np.eye(4)
        A[:3, :] = sol.T
    same = np.flatnonzero(np.abs(d - ref_d[t]) <= max(1.0, 0.15 * ref_d[t]))
    cand = same if len(same) else np.arange(len(d))
    k = np.linalg.norm(apply_transform(A, pts[cand]) - ref_pts[t], axis=1).argmin()
    return int(cand[k])


def _timed(fn, repeat):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, 1e3 * np.median(times), 1e3 * (max(times) - min(times))


def run_seed(folder: Path, preset: TwinPreset, seed: int, repeat: int) -> list[dict]:
    from calib.data.ingest import ingest_scans

    record = build(folder, preset, seed)
    session = load_session(folder / "scans")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = ingest_scans(session)
    for w in caught:
        print(f"  seed {seed}: {w.category.__name__}: {w.message}")
    ref = session.reference.name
    r = result.scans[ref]
    X, dX = r.inclusions.centres_lps_mm, r.inclusions.diameters_mm
    t = result.tumour_choice.reference_index

    def truth_index(name):  # a detection 2 mm or more from every true inclusion: -1
        found = result.scans[name].inclusions.centres_lps_mm
        d = np.linalg.norm(
            found[:, None] - record["scans"][name]["inclusions_lps_mm"][None], axis=2
        )
        return np.where(d.min(1) < 2.0, d.argmin(1), -1)

    ref_true = truth_index(ref)
    T_ref = np.asarray(record["scans"][ref]["T_scanner_from_phantom"])
    ref_phantom = apply_transform(np.linalg.inv(T_ref), record["scans"][ref]["inclusions_lps_mm"])
    rows = []
    for name, res in result.scans.items():
        scan = record["scans"][name]
        true_tumour = np.asarray(scan["tumour_lps_mm"])
        T = np.asarray(scan["T_scanner_from_phantom"])
        moved = apply_transform(np.linalg.inv(T), scan["inclusions_lps_mm"]) - ref_phantom
        tumour_motion = np.linalg.norm(
            np.subtract(scan["tumour_phantom_mm"], record["scans"][ref]["tumour_phantom_mm"])
        )
        tr = result.tracking[name]
        err = (
            np.inf if res.tumour_lps_mm is None else np.linalg.norm(res.tumour_lps_mm - true_tumour)
        )
        seen = set(ref_true[ref_true >= 0].tolist())
        wrong = (name != ref) * sum(  # unmatched is right for a spurious or unseen one
            (i is None and k in seen) or (i is not None and (k < 0 or ref_true[i] != k))
            for i, k in zip(tr.reference_index, truth_index(name), strict=True)
        )
        row = {
            "seed": seed,
            "scan": name,
            "tumour_motion_mm": tumour_motion,
            "max_motion_mm": float(np.linalg.norm(moved, axis=1).max()),
            "error_mm": err,
            "wrong": wrong,
            "n": len(tr.reference_index),
            "confidence": tr.tumour_confidence,
            "time_ms": (np.nan, np.nan),
            "former_error_mm": err,  # the reference: both trackers choose alike
            "former_ms": (np.nan, np.nan),
        }
        if name != ref:
            T_rs = result.registrations[name].T_ref_from_scan
            Y = apply_transform(T_rs, res.inclusions.centres_lps_mm)
            dY = res.inclusions.diameters_mm
            nip = apply_transform(T_rs, res.nipple_lps_mm)[None]
            plane = (r.back_plane.point_lps_mm, r.back_plane.normal)
            ours = partial(
                match_constellation, X, dX, Y, dY, anchors_reference_mm=r.nipple_lps_mm[None],
                anchors_mm=nip, base_plane=plane, size_sd_mm=SIZE_SD_MM,
            )  # fmt: skip
            _, ms, spread = _timed(ours, repeat)
            k, fms, fspread = _timed(partial(former_tracker, X, dX, t, Y, dY), repeat)
            row |= {"time_ms": (ms, spread), "former_ms": (fms, fspread),
                    "former_error_mm": float(np.linalg.norm(res.inclusions.centres_lps_mm[k]
                                                            - true_tumour))}  # fmt: skip
        rows.append(row)
    return rows


def synthetic(first: int, count: int) -> None:
    """Error and confidence rates on the unit tests' synthetic constellations.

    The generator of ``tests/registration/test_registration_correspondence.py`` (random
    half-ellipsoids, 12-30 points, smooth random deformations of 40-50 mm), per variant:
    nipple anchor or none, 2 missed + 2 spurious detections, equal sizes (no size
    information), the nipple anchor 10 mm off.
    """
    import importlib.util

    path = Path(__file__).parents[1] / "tests/registration/test_registration_correspondence.py"
    spec = importlib.util.spec_from_file_location("synthetic_constellations", path)
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)

    def equal_sizes(s, rng):
        s["dX"] = 6.0 + rng.normal(scale=0.3, size=len(s["dX"]))
        s["dY"] = 6.0 + rng.normal(scale=0.3, size=len(s["dY"]))

    def bad_nipple(s, rng):
        v = rng.normal(size=3)
        s["nipple_scan"] = s["nipple_scan"] + 10.0 * v / np.linalg.norm(v)

    variants = {
        "nipple anchor": ({}, True, None),
        "no anchor": ({}, False, None),
        "2 missed + 2 extra": ({"n_miss": 2, "n_extra": 2}, True, None),
        "equal sizes": ({}, True, equal_sizes),
        "equal sizes, no anchor": ({}, False, equal_sizes),
        "nipple 10 mm off": ({}, True, bad_nipple),
    }
    head = ("variant", "scenarios", "with a wrong id", "wrong ids flagged (< 0.95)",
            "right but flagged", "proximity wrong", "ms per match")  # fmt: skip
    lines = [head]
    for name, (kw, anchors, edit) in variants.items():
        bad = flagged = total_wrong = low = nn = 0
        t0 = time.perf_counter()
        for seed in range(first, first + count):
            s = gen._scenario(seed, **kw)
            if edit is not None:
                edit(s, np.random.default_rng(seed + 7))
            m = gen._match(s, anchors=anchors)
            wrong = m.reference_index != s["truth"]
            bad += bool(wrong.any())
            total_wrong += int(wrong.sum())
            flagged += int((m.confidence[wrong] < 0.95).sum())
            low += bool(not wrong.any() and m.confidence.min() < 0.95)
            nn += bool(np.any(gen._nearest_neighbour(s) != s["truth"]))
        ms = 1e3 * (time.perf_counter() - t0) / count
        lines.append((name, str(count), str(bad), f"{flagged}/{total_wrong}", str(low), str(nn),
                      f"{ms:.0f}"))  # fmt: skip
    _print(lines)


def _print(lines) -> None:
    widths = [max(len(x[k]) for x in lines) for k in range(len(lines[0]))]
    for k, line in enumerate(lines):
        print("  ".join(c.ljust(w) for c, w in zip(line, widths, strict=True)).rstrip())
        if k == 0:
            print("  ".join("-" * w for w in widths))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="quick", choices=["quick", "small"])
    ap.add_argument("--c1", type=float, default=300.0, help="true c1 in Pa (soft: large motion)")
    ap.add_argument("--sliding", action="store_true", help="the back plate slides")
    ap.add_argument("--skin", action="store_true", help="keep the preset's hidden skin")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--repeat", type=int, default=3, help="timed repeats of each matching")
    ap.add_argument("--keep", type=Path, help="keep (and reuse) the twins in this folder")
    ap.add_argument(
        "--synthetic", type=int, metavar="N", help="instead: N random constellations per variant"
    )
    args = ap.parse_args()
    print_header((*FE, *IMAGING))
    if args.synthetic:
        synthetic(100, args.synthetic)
        return
    base = SMALL if args.preset == "small" else PRESETS["quick"]
    effects = replace(base.effects if args.skin else TruthEffects(), sliding=args.sliding)
    preset = replace(base, c1_pa=args.c1, effects=effects)
    seeds = [int(s) for s in args.seeds.split(",")]
    print(f"preset {args.preset}, c1 {args.c1:g} Pa, sliding {args.sliding}, skin {args.skin}, "
          f"seeds {seeds}")  # fmt: skip
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)
        tag = f"{args.preset}_c1{args.c1:g}{'_sliding' if args.sliding else ''}"
        tag += "_skin" if args.skin else ""
        for seed in seeds:
            rows += run_seed(root / f"{tag}_seed{seed}", preset, seed, args.repeat)
    head = (
        "seed", "scan", "tumour motion mm", "max incl. motion mm", "tumour err mm",
        "former err mm", "wrong ids", "tumour conf", "match ms (range)", "former ms",
    )  # fmt: skip
    lines = [head]
    for r in rows:
        lines.append((
            str(r["seed"]), r["scan"], f"{r['tumour_motion_mm']:.1f}", f"{r['max_motion_mm']:.1f}",
            f"{r['error_mm']:.2f}", f"{r['former_error_mm']:.2f}", f"{r['wrong']}/{r['n']}",
            "-" if r["confidence"] is None else f"{r['confidence']:.4f}",
            "-" if np.isnan(r["time_ms"][0]) else f"{r['time_ms'][0]:.0f} ({r['time_ms'][1]:.0f})",
            "-" if np.isnan(r["former_ms"][0]) else f"{r['former_ms'][0]:.1f}",
        ))  # fmt: skip
    _print(lines)
    worst = max(r["error_mm"] for r in rows)
    worst_former = max(r["former_error_mm"] for r in rows)
    moving = max(r["max_motion_mm"] for r in rows)
    print(
        f"\nworst tracked-tumour error {worst:.2f} mm (bar 0.5 mm; former tracker "
        f"{worst_former:.2f} mm); largest inclusion motion {moving:.1f} mm; "
        f"wrong identities {sum(r['wrong'] for r in rows)} of {sum(r['n'] for r in rows)}"
    )


if __name__ == "__main__":
    main()
