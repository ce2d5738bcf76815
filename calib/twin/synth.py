"""``phantom-calib synth``: a digital twin of the multi-posture phantom experiment.

Builds the stress-free phantom, meshes it finer than calibration meshes, solves each
posture's gravity deformation with the truth model (which may hide effects), poses
the phantom in the scanner, renders MR-like DICOM series and seals the truth apart::

    OUT/scans/session.toml, OUT/scans/<name>/*.dcm     (what the pipeline sees)
    OUT/truth/truth.json, OUT/truth/<name>_surface.ply (never read by the pipeline)
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

import fem
from fem.discretize import Formulation
from fem.geometry import PhantomSpec, build_phantom, sphere_surface
from fem.meshing import mesh_phantom
from fem.postures import random_scanner_pose
from fem.units import DEFAULT_DENSITY_KG_M3

from ..choices import PresetName
from ..io import check_out_folder, clean_stale, provenance, write_json_atomic
from ..model.effects import TruthEffects, truth_model

__all__ = [
    "DISSERTATION_POSTURES",
    "PRESETS",
    "Posture",
    "PresetName",
    "TwinPreset",
    "scanner_poses",
    "synthesize",
]

log = logging.getLogger(__name__)
G_SCANNER = np.array([0.0, 1.0, 0.0])
#: Subdivisions of the icospheres the renderer draws the inclusions as (162 vertices):
#: each encloses 0.966 of its nominal sphere's volume (the truth's diameters are the
#: spheres'). The conforming truth mesh meshes the same icospheres from 6 mm diameter,
#: and smaller ones with 1 subdivision (0.873; ``fem.meshing.inclusion_spheres``).
RENDERED_SPHERE_SUBDIVISIONS = 2


@dataclass(frozen=True)
class Posture:
    """One scan of the experiment: name, nominal angle (deg) and session role.

    Attributes
    ----------
    name : str
        The scan's name: its folder under ``OUT/scans/``, its DICOM series description
        and its key in ``session.toml`` and ``truth.json``.
    angle_deg : float
        Nominal posture angle, degrees, in the transverse plane: the phantom-frame gravity
        direction is ``(cos a, 0, sin a)`` (:func:`fem.postures.gravity_for_angle`) before
        the random roll and tilt of :func:`fem.postures.random_scanner_pose`.
    role : {"reference", "calibration", "validation"}
        The scan's role in ``session.toml`` (:data:`calib.data.session.ROLES`).
    """

    name: str
    angle_deg: float
    role: str


DISSERTATION_POSTURES = (
    Posture("left_lateral", 0.0, "reference"),
    Posture("right_lateral", 180.0, "calibration"),
    Posture("tilt_25", 25.0, "validation"),
    Posture("tilt_50", 50.0, "validation"),
)


@dataclass(frozen=True)
class TwinPreset:
    """Resolution and imaging settings of a twin (see ``PRESETS``).

    Attributes
    ----------
    phantom_resolution_mm : float
        Target edge length of the stress-free phantom's surface triangulation, mm
        (:attr:`fem.geometry.PhantomSpec.resolution_mm`).
    truth_mesh_mm : float
        Element size of the truth model's tetrahedral mesh, mm.
    spacing_mm : tuple of float, shape (3,)
        Voxel spacing of the rendered scans along i, j (in-plane) and k (slices), mm; the
        grid's axes are the scanner's L, P and S.
    min_shape : tuple of int, shape (3,)
        Smallest grid size in voxels along i, j, k (grown symmetrically); 0: no minimum.
    snr : float
        Body intensity over the standard deviation of the Rician noise; ``inf`` or 0 for
        none.
    bias_amplitude : float
        Amplitude of the smooth multiplicative bias field (1 +- amplitude over the
        phantom's bounding box; dimensionless).
    c1_pa : float
        The truth model's bulk ``c1``, Pa.
    formulation : {"p1", "p2", "mini", "taylor-hood"}
        Finite element formulation of the truth solves.
    postures : tuple of Posture
        The scans, in order (one of them the ``"reference"``).
    effects : TruthEffects
        The hidden effects of the truth model where :func:`synthesize` is given none
        (default: a 1.5 mm skin 8 times stiffer than the bulk).
    """

    phantom_resolution_mm: float
    truth_mesh_mm: float
    spacing_mm: tuple[float, float, float]
    min_shape: tuple[int, int, int] = (0, 0, 0)
    snr: float = 30.0
    bias_amplitude: float = 0.2
    c1_pa: float = 420.0
    formulation: Formulation = "taylor-hood"
    postures: tuple[Posture, ...] = DISSERTATION_POSTURES
    effects: TruthEffects = field(
        default_factory=lambda: TruthEffects(skin_thickness_mm=1.5, skin_ratio=8.0)
    )


PRESETS = {
    "quick": TwinPreset(phantom_resolution_mm=10.0, truth_mesh_mm=10.0, spacing_mm=(1.5, 1.5, 1.5)),
    "dissertation": TwinPreset(
        phantom_resolution_mm=5.0,
        truth_mesh_mm=5.0,
        spacing_mm=(0.8, 0.8, 0.8),
        min_shape=(256, 256, 0),
    ),  # fmt: skip
}


def _truth_mesh(phantom, p: TwinPreset, eff: TruthEffects) -> fem.TetMesh:
    """The truth model's mesh: ``p.truth_mesh_mm`` elements, the skin band tagged."""
    return mesh_phantom(
        phantom,
        size_mm=p.truth_mesh_mm,
        skin_thickness_mm=eff.skin_thickness_mm,
        embed_inclusions=_conforming_inclusions(eff),
    )


def _conforming_inclusions(eff: TruthEffects) -> bool:
    """Whether the truth mesh holds the inclusions as conforming spheres.

    Where they differ from the bulk they are meshed as the spheres the renderer draws
    (:func:`fem.meshing.mesh_phantom` ``embed_inclusions``). Tagging the elements whose
    centroid lies in a sphere instead made a different body: on the quick twin (10 mm
    elements) seed 0's tagged volume is 3875 mm3 against the spheres' 3451, in elements
    reaching past them, and at a stiffness ratio of 30 its surface print was 1.42-1.47
    times the conforming spheres' (rms 0.28 against 0.19 mm on the right lateral,
    correlation 0.99; ``benchmarks/bench_twin_inclusions.py``), a larger effect than the
    images show. Elsewhere they are bulk material and the lighter mesh is the same body.
    """
    return eff.inclusion_ratio != 1.0


def _transform(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return np.asarray(p, float) @ T[:3, :3].T + T[:3, 3]


@dataclass(frozen=True)
class _Truth:
    """The true deformed state of one posture, phantom frame (mm)."""

    gravity_phantom: np.ndarray
    body: tuple[np.ndarray, np.ndarray]
    inclusions: list
    nipple_mm: np.ndarray
    tumour_mm: np.ndarray
    solution: fem.Solution


def _deform(phantom, mesh, model, disc, g_phantom, x0) -> _Truth:
    sol = fem.solve(model, gravity=g_phantom, disc=disc, x0=x0)
    u = np.round(sol.displacement_mm, 9)  # deterministic to well below any image effect
    faces = fem.boundary_faces(mesh.tets)
    incl = []
    for c, d in zip(phantom.inclusion_centres_mm, phantom.inclusion_diameters_mm, strict=True):
        v, f = sphere_surface(c, d / 2, subdivisions=RENDERED_SPHERE_SUBDIVISIONS)
        incl.append((v + np.round(fem.displacement_at(disc, sol.state, v), 9), f))
    tumour = phantom.tumour_mm + fem.displacement_at(disc, sol.state, phantom.tumour_mm[None])[0]
    nipple = mesh.node_set("nipple")[0]
    return _Truth(g_phantom, (mesh.nodes_mm + u, faces), incl,
                  mesh.nodes_mm[nipple] + u[nipple], tumour, sol)  # fmt: skip


def _warm_start(solved: list, g: np.ndarray, max_angle_deg: float = 60.0):
    """The solved state whose gravity is nearest to ``g``, if within ``max_angle_deg``.

    A warm start from an opposite posture costs more Newton iterations than none.
    """
    if not solved:
        return None
    cosines = [float(gs @ g) for gs, _ in solved]
    best = int(np.argmax(cosines))
    return solved[best][1] if cosines[best] > np.cos(np.radians(max_angle_deg)) else None


def _render(truth: _Truth, phantom, T: np.ndarray, preset: TwinPreset, seed: int):
    import imaging

    pts = np.vstack([truth.body[0], phantom.fiducials_mm])
    grid = imaging.scan_grid_covering(
        _transform(T, pts), spacing_mm=preset.spacing_mm, margin_mm=12.0,
        min_shape=preset.min_shape,
    )  # fmt: skip
    return imaging.render_mr_volume(
        truth.body, T_scanner_from_phantom=T, grid=grid, inclusions=truth.inclusions,
        fiducial_centres_mm=phantom.fiducials_mm, bias_amplitude=preset.bias_amplitude,
        snr=preset.snr, seed=seed,
    )  # fmt: skip


def _session_toml(p: TwinPreset, preset: str, tumour_hint_lps_mm: np.ndarray) -> str:
    from importlib import metadata

    import tomli_w

    try:
        version = metadata.version("phantom-calib")
    except metadata.PackageNotFoundError:
        version = "(not installed)"
    # review BY, F13: reports set the twin's figures beside the dissertation's MRI ones
    # without a word that the scans were simulated. The preset is said, the effects not
    # (the diagnosis is tested on scans whose effect is hidden).
    generator = f"phantom-calib {version} synth, preset {preset}"
    return tomli_w.dumps({
        "source": {"simulated": True, "generator": generator},
        "scanner": {"gravity": G_SCANNER.tolist()},
        "phantom": {"density_kg_m3": DEFAULT_DENSITY_KG_M3, "fiducials": 3},
        "landmarks": {"tumour": [round(float(c), 1) for c in tumour_hint_lps_mm]},
        "scans": [
            {"name": post.name, "path": post.name, "role": post.role,
             "posture": {"plane": "transverse", "angle_deg": post.angle_deg}}
            for post in p.postures
        ],
    })  # fmt: skip


def _scan_truth(name, truth: _Truth, T, phantom) -> dict:
    return {
        "T_scanner_from_phantom": T.tolist(),
        "gravity_phantom": truth.gravity_phantom.tolist(),
        "fiducials_lps_mm": _transform(T, phantom.fiducials_mm).tolist(),
        "nipple_lps_mm": _transform(T, truth.nipple_mm).tolist(),
        "tumour_lps_mm": _transform(T, truth.tumour_mm).tolist(),
        "nipple_phantom_mm": truth.nipple_mm.tolist(),
        "tumour_phantom_mm": truth.tumour_mm.tolist(),
        "newton_iterations": truth.solution.newton_iterations,
        "surface": f"{name}_surface.ply",
    }


def _write_truth_surface(path: Path, truth: _Truth, T) -> None:
    import imaging

    v, f = truth.body
    used = np.unique(f)  # the surface's own vertices only, not the interior nodes
    remap = np.full(len(v), -1)
    remap[used] = np.arange(len(used))
    v = v[used]
    surf = imaging.SurfaceMesh(_transform(T, v), remap[f], np.abs(v[:, 2]) < 1e-6)
    imaging.write_ply(path, surf)


def synthesize(
    out: str | os.PathLike,
    *,
    preset: PresetName | TwinPreset = "quick",
    seed: int = 0,
    effects: TruthEffects | None = None,
    overwrite: bool = False,
    progress=None,
) -> dict:
    """Build a synthetic scan set with sealed truth (see the module docstring).

    The folder is assembled beside ``out`` and moved into place only when complete,
    so an interrupted run leaves no scan folder that looks complete.

    Parameters
    ----------
    out : str or PathLike
        The folder to write: ``OUT/scans/`` (DICOM series and ``session.toml``) and
        ``OUT/truth/`` (``truth.json`` and each scan's true surface, ``.ply``).
    preset : {"quick", "dissertation"} or TwinPreset
        A named preset of :data:`PRESETS`, or a preset of one's own (recorded as
        ``custom`` with its ``preset_settings``).
    seed : int
        Seed of the phantom's shape, the scanner poses, the tumour hint and the MR
        renderer's noise and bias.
    effects : TruthEffects, optional
        The hidden effects (default: the preset's, a 1.5 mm skin 8 times stiffer).
    overwrite : bool
        Replace an existing ``out`` (else :class:`FileExistsError`).
    progress : callable, optional
        Called with a line of text at each step (default: the module's logger).

    Returns
    -------
    dict
        The truth record written to ``OUT/truth/truth.json``.

    Raises
    ------
    ValueError
        An unknown preset name.
    FileExistsError
        ``out`` exists and ``overwrite`` is false.
    PermissionError, NotADirectoryError
        ``out`` cannot be written (:func:`calib.io.check_out_folder`), checked before
        the truth solves.
    """
    if isinstance(preset, TwinPreset):
        p, preset = preset, "custom"
    elif preset in PRESETS:
        p = PRESETS[preset]
    else:
        raise ValueError(f"unknown preset {preset!r}; choose {sorted(PRESETS)}")
    settings = _preset_settings(p)  # a value truth.json cannot hold fails before any work
    out = Path(out)
    if out.exists() and not overwrite:
        raise FileExistsError(
            f"{out} exists; choose another folder or pass overwrite=True (--overwrite)"
        )
    check_out_folder(out, option="out (OUT)")  # before the truth solves, not after them
    eff = p.effects if effects is None else effects
    clean_stale(out.parent, (out.name,))  # partial folders of killed runs
    tmp = out.parent / f".{out.name}.partial-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        record = _build(
            tmp, p, preset, seed, eff, progress or (lambda msg: log.info(msg)), settings
        )
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return record


def _preset_settings(p: TwinPreset) -> dict:
    """The preset's fields but its effects, as JSON values (numpy numbers as Python's).

    Raises
    ------
    ValueError
        A field that is not finite, or of a type JSON cannot hold (review BK: found when
        ``truth.json`` was written, after every solve).
    """
    import json

    def plain(value):
        if isinstance(value, np.generic | np.ndarray):
            return value.tolist()
        raise TypeError(f"{type(value).__name__} is not a JSON value")

    raw = {k: v for k, v in asdict(p).items() if k != "effects"}
    try:
        return json.loads(json.dumps(raw, default=plain, allow_nan=False))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"preset: a TwinPreset field truth.json cannot record ({exc})") from exc


def _pose_rng(seed: int) -> np.random.Generator:
    # the poses' stream; the tumour hint draws from it after the poses
    return np.random.default_rng([seed, 2])


def _draw_poses(p: TwinPreset, rng: np.random.Generator) -> list[np.ndarray]:
    centre_mm = [0.0, 0.0, 35.0]  # the phantom's middle above the plate, in the bore's centre
    return [
        random_scanner_pose(post.angle_deg, G_SCANNER, rng, centre_mm=centre_mm)
        for post in p.postures
    ]


def scanner_poses(p: TwinPreset, seed: int) -> dict[str, np.ndarray]:
    """The scanner poses :func:`synthesize` draws for a preset and seed.

    Parameters
    ----------
    p : TwinPreset
    seed : int

    Returns
    -------
    dict of str to ndarray, shape (4, 4)
        ``T_scanner_from_phantom`` per posture name, in the preset's order; the phantom-frame
        gravity of a posture is ``T[:3, :3].T @ G_SCANNER``.
    """
    return dict(
        zip((post.name for post in p.postures), _draw_poses(p, _pose_rng(seed)), strict=True)
    )


def _build(
    tmp: Path, p: TwinPreset, preset: str, seed: int, eff: TruthEffects, say, settings: dict
) -> dict:
    import imaging

    t0 = time.perf_counter()
    spec = PhantomSpec(resolution_mm=p.phantom_resolution_mm, seed=seed)
    phantom = build_phantom(spec)
    mesh = _truth_mesh(phantom, p, eff)
    model = truth_model(mesh, p.c1_pa, eff)
    disc = fem.discretize(mesh, model.support, formulation=p.formulation)
    say(f"truth mesh: {mesh.n_tets} tets, {disc.pattern.n_free} dofs")
    rng = _pose_rng(seed)
    scans, solved = {}, []
    for i, (post, T) in enumerate(zip(p.postures, _draw_poses(p, rng), strict=True)):
        g_phantom = T[:3, :3].T @ G_SCANNER
        truth = _deform(phantom, mesh, model, disc, g_phantom, _warm_start(solved, g_phantom))
        solved.append((g_phantom, truth.solution.state))
        vol = _render(truth, phantom, T, p, seed=seed * 1000 + i)
        imaging.write_dicom_series(vol, tmp / "scans" / post.name, seed=seed * 1000 + i,
                                   series_description=post.name, series_number=i + 1)  # fmt: skip
        _write_truth_surface(tmp / "truth" / f"{post.name}_surface.ply", truth, T)
        scans[post.name] = _scan_truth(post.name, truth, T, phantom) | {
            "nominal_angle_deg": post.angle_deg, "role": post.role}  # fmt: skip
        say(f"scan {post.name}: nipple moved "
            f"{np.linalg.norm(truth.nipple_mm - phantom.nipple_mm):.1f} mm")  # fmt: skip
    # The experimenter names the tracked tumour by a rough point in the reference scan.
    ref = next(n for n, post in zip(scans, p.postures, strict=True) if post.role == "reference")
    hint = np.asarray(scans[ref]["tumour_lps_mm"]) + rng.normal(scale=1.5, size=3)
    (tmp / "scans" / "session.toml").write_text(_session_toml(p, preset, hint))
    record = _record(preset, p, seed, eff, phantom, mesh, disc, scans) | {
        "preset_settings": settings
    }
    write_json_atomic(tmp / "truth" / "truth.json", record)
    say(f"done in {time.perf_counter() - t0:.1f} s")
    return record


def _record(preset, p, seed, eff, phantom, mesh, disc, scans) -> dict:
    prov = provenance(parameters={"preset": preset, "seed": seed})
    prov.pop("created_utc")  # the truth must be identical for identical seeds
    prov.pop("command")
    prov.pop("entry")  # CLI or API: the same truth
    return {
        "preset": preset,
        "seed": seed,
        "material": {
            "law": "mooney-rivlin" if eff.c2_pa else "neo-hookean",
            "c1_pa": p.c1_pa,
            "c2_pa": eff.c2_pa,
            "nu": eff.nu,
        },  # fmt: skip
        "effects": asdict(eff) | {"active": eff.active()},
        "density_kg_m3": eff.density_kg_m3,
        "stress_free": {
            "nipple_phantom_mm": phantom.nipple_mm.tolist(),
            "tumour_phantom_mm": phantom.tumour_mm.tolist(),
            "fiducials_phantom_mm": phantom.fiducials_mm.tolist(),
            "inclusion_centres_phantom_mm": phantom.inclusion_centres_mm.tolist(),
            "inclusion_diameters_mm": phantom.inclusion_diameters_mm.tolist(),
        },
        "mesh": {
            "n_tets": mesh.n_tets,
            "n_nodes": mesh.n_nodes,
            "size_mm": p.truth_mesh_mm,
            "formulation": p.formulation,
            "dofs": int(disc.pattern.n_free),
            "inclusions": "conforming" if _conforming_inclusions(eff) else "bulk material",
        },  # fmt: skip
        "scans": scans,
        "versions": prov["versions"],
        # review BI: twins of two commits (each phantom-calib 0.1.0) read alike, and a
        # custom preset's settings were written as "custom" alone
        "source": prov["source"],
    }
