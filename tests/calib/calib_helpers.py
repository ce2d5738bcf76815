"""Helpers of the calib tests: small session folders, small phantom meshes and twin presets."""

from __future__ import annotations

from pathlib import Path

from calib.twin import Posture, TwinPreset

# Two lateral postures on a coarse phantom and 2 mm voxels: a twin in a few seconds.
SMALL_PRESET = TwinPreset(
    phantom_resolution_mm=14,
    truth_mesh_mm=14,
    spacing_mm=(2.0, 2.0, 2.0),
    postures=(
        Posture("left_lateral", 0, "reference"),
        Posture("right_lateral", 180, "calibration"),
    ),
)

# The same with a 50 deg tilt as a validation scan (the validation report needs one).
SMALL_VALIDATION_PRESET = TwinPreset(
    phantom_resolution_mm=14,
    truth_mesh_mm=14,
    spacing_mm=(2.0, 2.0, 2.0),
    postures=(
        Posture("left_lateral", 0, "reference"),
        Posture("right_lateral", 180, "calibration"),
        Posture("tilt_50", 50, "validation"),
    ),
)

VALID_TOML = """\
[scanner]
gravity = [0.0, 2.0, 0.0]
[phantom]
density_kg_m3 = 1050.0
fiducials = 4
[landmarks]
tumour = [12.0, -30.5, 40.2]
[[scans]]
name = "left"
path = "left"
role = "reference"
posture = { plane = "transverse", angle_deg = 0.0 }
[[scans]]
name = "right"
path = "right.nii.gz"
role = "calibration"
posture = { plane = "transverse", angle_deg = 180 }
[[scans]]
name = "tilt"
path = "tilt"
role = "validation"
"""


def make_scan_folder(folder: Path, toml: str | None = VALID_TOML) -> Path:
    """A scan folder with series folders ``left``, ``tilt`` and a volume file ``right.nii.gz``.

    The scan contents are placeholders: the session layer only checks that the paths exist.
    """
    folder.mkdir(parents=True, exist_ok=True)
    for series in ("left", "tilt"):
        (folder / series).mkdir(exist_ok=True)
        (folder / series / "IM00001.dcm").write_bytes(b"placeholder")
    (folder / "right.nii.gz").write_bytes(b"placeholder")
    if toml is not None:
        (folder / "session.toml").write_text(toml)
    return folder


def small_phantom_mesh(*, skin_thickness_mm: float = 3.0):
    """A coarse phantom (4 inclusions) and its tet mesh with bulk, inclusion and skin regions."""
    from fem.geometry import PhantomSpec, build_phantom
    from fem.meshing import mesh_phantom

    phantom = build_phantom(PhantomSpec(resolution_mm=14, n_inclusions=4))
    mesh = mesh_phantom(phantom, size_mm=14, skin_thickness_mm=skin_thickness_mm)
    return phantom, mesh


def stub_work_commands(monkeypatch, worked: list) -> list:
    """``validate`` and ``diagnose`` that read a stub work folder and record their work.

    The stub (no states, a c1) lets each command reach its work, which only appends the
    work's name to ``worked``: a check a command makes before its work is all that keeps
    ``worked`` empty. Returns ``(run folder, command)`` pairs: ``command(work)``.
    """
    from types import SimpleNamespace

    import calib.workflows.diagnose as diagnose_mod
    import calib.workflows.validate as validate_mod

    commands = []
    for mod, folder, work_fn, run in (
        (validate_mod, "validation", "validate_work", validate_mod.run_validation),
        (diagnose_mod, "diagnosis", "diagnose", diagnose_mod.run_diagnosis),
    ):
        monkeypatch.setattr(
            mod, "read_work", lambda w: SimpleNamespace(path=Path(w), states={}, c1_pa=420.0)
        )
        monkeypatch.setattr(mod, "input_records", lambda files: {})
        monkeypatch.setattr(mod, work_fn, lambda *a, name=work_fn, **k: worked.append(name))
        commands.append((folder, run))
    return commands


def polyhedron_volume_mm3(vertices_mm, faces) -> float:
    """The volume a closed triangle surface bounds (divergence theorem), mm^3."""
    import numpy as np

    a, b, c = (vertices_mm[faces[:, k]] for k in range(3))
    return abs(np.einsum("ij,ij->i", a, np.cross(b, c)).sum()) / 6.0
