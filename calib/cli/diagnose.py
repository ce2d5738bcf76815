"""``phantom-calib diagnose WORK [--effects NAMES] [--holdout SCAN]``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ..choices import MeshErrorTreatment, NoiseProfile
from ..fitting.options import MESH_SIZE_RANGE_MM
from ..model.effects import SKIN_THICKNESS_MM
from ..stats.scores import SCREEN_ALPHA
from .app import app, fail


@app.command()
def diagnose(
    work: Annotated[
        Path, typer.Argument(metavar="WORK", help="A work folder that `calibrate` wrote.")
    ],
    effects: Annotated[
        str | None,
        typer.Option(
            "--effects",
            metavar="NAME,NAME",
            help="Comma-separated library effects to screen (skin, sliding, inclusions, "
            "mooney, poisson, density, gravity, registration). Default: all.",
        ),
    ] = None,
    holdout: Annotated[
        str | None,
        typer.Option(
            "--holdout",
            metavar="SCAN",
            help="Scan never fitted, to show the gap on (default: the first validation "
            "scan; 'none' for none).",
        ),
    ] = None,
    alpha: Annotated[
        float,
        typer.Option("--alpha", help="Family-wise error rate of the screening, in (0, 0.5)."),
    ] = SCREEN_ALPHA,
    rim_margin: Annotated[
        str | None,
        typer.Option(
            "--rim-margin",
            metavar="MM|element",
            help="Measured points nearer than this to the back plate (mm) are only mapped, "
            "not diagnosed (the clamped edge; default 5; 'element': one model element, the "
            "mesh size; 0 keeps them).",
        ),
    ] = None,
    skin_thickness: Annotated[
        float,
        typer.Option(
            "--skin-thickness",
            metavar="MM",
            help=f"Thickness (mm, in (0, 10]) of the skin effect's stiffer outer band (default "
            f"{SKIN_THICKNESS_MM:g}). The "
            "surface sees about (ratio - 1) x thickness of a thin layer: the fitted ratio "
            "stands for that product at this thickness (diagnosis.json: excess_mm).",
        ),
    ] = SKIN_THICKNESS_MM,
    explained_margin: Annotated[
        str | None,
        typer.Option(
            "--explained-margin",
            metavar="MM|element",
            help="The share of the residual a named effect must explain is measured beyond "
            "this distance from the back plate (mm; default 'element': one model element, "
            "where the clamped edge's discretisation error lies; 0: every diagnosed point).",
        ),
    ] = None,
    mesh_size: Annotated[
        float | None,
        typer.Option(
            "--mesh-size",
            min=MESH_SIZE_RANGE_MM[0],
            max=MESH_SIZE_RANGE_MM[1],
            help="Diagnose on a model mesh of this size (mm) instead of the calibration's: "
            "a finer one tells discretisation error from a missing effect (slower).",
        ),
    ] = None,
    inclusion_mesh: Annotated[
        float | None,
        typer.Option(
            "--inclusion-mesh",
            min=MESH_SIZE_RANGE_MM[0],
            max=MESH_SIZE_RANGE_MM[1],
            help="Diagnose on a model mesh (of --mesh-size, else the calibration's size) "
            "whose segmented inclusions are meshed as spheres with elements of this size "
            "(mm) inside: a stiff inclusion's print is local (slower). Without "
            "--mesh-size, where the calibration's size admits no straight stress-free "
            "reference, the next size is taken, and said.",
        ),
    ] = None,
    noise_profile: Annotated[
        NoiseProfile,
        typer.Option(
            "--noise-profile",
            help="'flat': one noise level at every height (default); 'plate': the noise "
            "level by height above the back plate, measured on the residual, weighting "
            "every residual (the clamped edge's larger spread).",
        ),
    ] = "flat",
    mesh_error: Annotated[
        MeshErrorTreatment,
        typer.Option(
            "--mesh-error",
            help="'ignored': the tests condition on c1, the per-scan offsets and the named "
            "effects (default); 'absorbed': also on one direction of the model mesh's own "
            "discretisation error, the residual change on a mesh 1.4 times coarser at the "
            "null fit's c1 (one more mesh, its stress-free recovery and an FE solve per "
            "scan; the refits and the gap are unchanged).",
        ),
    ] = "ignored",
    parameter_limits: Annotated[
        bool,
        typer.Option(
            "--parameter-limits",
            help="For each physical effect not found, also the size of its own parameter "
            "the scans would show, at the final model (with the named effects; full FE: a "
            "few solves of every diagnosis scan per effect; 30-250 s more on the quick twins).",
        ),
    ] = False,
) -> None:
    """Find where model and scans disagree, name the missing effect, refit, show the gap."""
    from ..discrepancy import DiagnosisError, DiagnosisOptions
    from ..discrepancy.problem import parse_rim_margin
    from ..report.diagnosis import format_diagnosis
    from ..workflows.diagnose import run_diagnosis

    try:
        names = None if effects is None else tuple(e.strip() for e in effects.split(",") if e)
        opts = DiagnosisOptions(
            **({} if names is None else {"effects": names}),
            holdout=holdout,
            alpha=alpha,
            skin_thickness_mm=skin_thickness,
            **({} if rim_margin is None else {"rim_margin_mm": parse_rim_margin(rim_margin)}),
            **(
                {}
                if explained_margin is None
                else {
                    "explained_margin_mm": parse_rim_margin(explained_margin, "--explained-margin")
                }
            ),
            mesh_size_mm=mesh_size,
            inclusion_mesh_mm=inclusion_mesh,
            noise_profile=noise_profile,
            mesh_error=mesh_error,
            parameter_limits=parameter_limits,
        )
        doc = run_diagnosis(work, opts, progress=lambda msg: typer.echo(f"  {msg}"))
    except (DiagnosisError, ValueError, OSError, RuntimeError, KeyError) as exc:
        fail(exc)
    typer.echo(format_diagnosis(doc))
    typer.echo(f"wrote {work / 'diagnosis.json'} and {work / 'diagnosis'}/report.html")
