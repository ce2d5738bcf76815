"""The ``phantom-calib`` command line: typer commands that call :mod:`calib.workflows`."""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Annotated

import typer

from fem.discretize import Formulation
from fem.units import DEFAULT_DENSITY_KG_M3, STANDARD_GRAVITY_M_S2

from ..choices import BackSupport, PresetName
from ..fitting.options import MESH_SIZE_RANGE_MM, Objective, ReferenceState

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    rich_markup_mode=None,  # plain click help: flags without a fake <bool> value
    context_settings={"help_option_names": ["-h", "--help"]},
    help="Calibrate a breast phantom's hyperelastic material from multi-posture MRI.",
)


def _version_callback(value: bool) -> None:
    if value:
        from importlib.metadata import version

        typer.echo(f"phantom-calib {version('phantom-calib')}")
        raise typer.Exit()


@app.callback()
def _main(
    version: Annotated[
        bool,
        typer.Option("--version", callback=_version_callback, is_eager=True, help="Show version."),
    ] = False,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log progress details.")] = False,
) -> None:
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING, format="%(levelname)s: %(message)s"
    )
    # scikit-fem logs every basis it builds at INFO: hundreds of lines per calibration
    logging.getLogger("skfem").setLevel(logging.WARNING)


def fail(exc: Exception) -> None:
    """Report an expected error in one line and exit with status 2."""
    typer.secho(f"error: {exc}", fg=typer.colors.RED, err=True)
    raise typer.Exit(code=2)


@app.command()
def simulate(
    mesh: Annotated[
        Path, typer.Argument(metavar="MESH", help="Tetrahedral mesh (any meshio format), in mm.")
    ],
    c1: Annotated[float, typer.Option("--c1", help="Neo-Hookean c1 in Pa (shear modulus 2 c1).")],
    gravity: Annotated[
        str,
        typer.Option(
            "--gravity",
            metavar="X,Y,Z",
            help="Gravity direction in the mesh's own coordinates (its length is not used: "
            "the magnitude is --g; surrogate predict's --gravity is m/s^2 in the phantom frame).",
        ),
    ],
    out: Annotated[Path, typer.Option("--out", help="Deformed mesh to write, e.g. RESULT.vtu.")],
    nu: Annotated[float, typer.Option("--nu", help="Poisson's ratio (< 0.5).")] = 0.499,
    density: Annotated[
        float, typer.Option("--density", help="Density in kg/m^3 (500-3000).")
    ] = DEFAULT_DENSITY_KG_M3,
    g: Annotated[
        float, typer.Option("--g", help="Gravitational acceleration, m/s^2.")
    ] = STANDARD_GRAVITY_M_S2,
    bc: Annotated[
        BackSupport,
        typer.Option(
            "--bc",
            help="Back plate support: every back node fixed, or sliding (frictionless in "
            "the back plane, its rim held: the rim line carries the in-plane load).",
        ),
    ] = "clamped",
    back_plane: Annotated[
        str,
        typer.Option(
            "--back-plane",
            metavar="auto|z=MM",
            help="auto (the mesh's own set:back point data where it has it, else the "
            "largest flat face), or z=MM (the plane z = MM of the mesh's coordinates).",
        ),
    ] = "auto",
    formulation: Annotated[
        Formulation,
        typer.Option(
            "--formulation",
            help="Elements (displacement/pressure): taylor-hood (P2/P1), mini (P1+bubble/P1), "
            "p2 or p1 (displacement only).",
        ),
    ] = "taylor-hood",
) -> None:
    """Deform a mesh under gravity; write the deformed mesh and RESULT.json."""
    from ..workflows.simulate import SimulateOptions, parse_vector, run_simulate

    try:
        opts = SimulateOptions(
            c1_pa=c1, nu=nu, density_kg_m3=density, gravity=parse_vector(gravity), g_m_s2=g,
            bc=bc, back_plane=back_plane, formulation=formulation,
        )  # fmt: skip
        summary = run_simulate(mesh, out, opts)
    except (ValueError, OSError, RuntimeError) as exc:
        fail(exc)
    typer.echo(
        f"converged={summary['converged']}  nipple displacement "
        f"{summary['nipple_displacement_mm']:.2f} mm  max {summary['max_displacement_mm']:.2f} mm  "
        f"{summary['newton_iterations']} Newton iterations, {summary['load_steps']} load steps, "
        f"{summary['dofs']} dofs, {summary['wall_s']:.1f} s -> {out}"
    )
    back = summary["back"]  # review BU: which face was held, not only how many nodes
    typer.echo(
        f"  back face ({bc}): {back['source']}, {back['nodes']} nodes, outward normal "
        f"({', '.join(f'{v:.3g}' for v in back['normal'])}), offset {back['offset_mm']:.4g} mm"
    )
    # review AX: --gravity 0,4.9,0 and 0,1,0 gave one answer without a word (predict's
    # --gravity is m/s^2 in the phantom frame): say how it was read
    length = math.hypot(*opts.gravity)
    typer.echo(
        f"  gravity: the direction ({', '.join(f'{v + 0.0:.4g}' for v in opts.gravity)}) in the "
        f"mesh's own frame, of magnitude --g "
        f"{g:g} m/s^2" + ("" if abs(length - 1.0) < 1e-6 else f" (its length {length:g} unused)")
    )


def _indented(msg: str) -> None:
    """A progress message, every line indented (the ingest table calibrate prints is several)."""
    typer.echo("\n".join(f"  {line}" for line in msg.splitlines()))


@app.command()
def init(
    scans: Annotated[
        Path,
        typer.Argument(metavar="SCANS", help="Folder of DICOM series folders / volume files."),
    ],
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace session.toml.")] = False,
) -> None:
    """Scaffold a session.toml by finding the series in a folder."""
    from ..data.session import scaffold_session

    try:
        path = scaffold_session(scans, overwrite=overwrite)
    except (ValueError, OSError) as exc:
        fail(exc)
    typer.echo(f"wrote {path}; edit the roles and postures before ingest")


@app.command()
def ingest(
    scans: Annotated[Path, typer.Argument(metavar="SCANS", help="Scan folder with session.toml.")],
    out: Annotated[Path, typer.Option("--out", help="Work folder to write.")],
) -> None:
    """Segment, surface and register every scan of a session."""
    from rich.progress import Progress

    from ..data.session import load_session
    from ..workflows.ingest import run_ingest

    try:
        n = len(load_session(scans).scans)
        with Progress(transient=True) as bar:
            task = bar.add_task("ingest", total=n)
            result = run_ingest(scans, out, progress=lambda name: bar.advance(task))
    except (ValueError, OSError, RuntimeError) as exc:
        fail(exc)
    typer.echo(result.summary_table)
    typer.echo(f"wrote {out / 'scans'}")
    stale = [
        f for f in ("calibration.json", "validation.json", "diagnosis.json") if (out / f).is_file()
    ]
    if stale:  # review AX: said only when validate or diagnose refused them later
        typer.secho(
            f"WARNING: {out}: {', '.join(stale)} fitted to the previous ingest no longer "
            "apply (validate, diagnose and sweep refuse them): run `phantom-calib calibrate` "
            "again",
            fg=typer.colors.YELLOW, err=True,
        )  # fmt: skip


@app.command()
def synth(
    out: Annotated[
        Path, typer.Argument(metavar="OUT", help="Folder to create (scans/ and truth/).")
    ],
    preset: Annotated[
        PresetName,
        typer.Option(
            "--preset",
            help="quick (10 mm truth mesh, 1.5 mm voxels) or dissertation (5 mm, 0.8 mm).",
        ),
    ] = "quick",
    seed: Annotated[int, typer.Option("--seed", min=0, help="Seed of every random choice.")] = 0,
    effect: Annotated[
        list[str] | None,
        typer.Option(
            "--effect",
            metavar="NAME[=VALUE]",
            help="Hidden effect; repeat for several: none; skin[=MM:RATIO] (thickness, "
            "stiffness ratio to the bulk; 1.5:8); sliding[=PA_PER_MM] (the plate on "
            "tangential springs; bare: frictionless); inclusions[=RATIO] (5); "
            "mooney[=C2_PA] (210); poisson[=NU] (0.45); density[=KG_M3] (1100). Any replaces "
            "the preset's skin (1.5 mm, 8 times stiffer): add --effect skin to keep it.",
        ),
    ] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace OUT.")] = False,
) -> None:
    """Build a digital-twin scan set with sealed truth."""
    from ..model.effects import parse_effects
    from ..twin import PRESETS, synthesize

    try:
        effects = parse_effects(effect or [], default=PRESETS[preset].effects)
        record = synthesize(out, preset=preset, seed=seed, effects=effects, overwrite=overwrite,
                            progress=lambda msg: typer.echo(f"  {msg}"))  # fmt: skip
    except (ValueError, OSError, RuntimeError) as exc:
        fail(exc)
    active = ", ".join(record["effects"]["active"]) or "none"
    typer.echo(f"wrote {out}/scans (session.toml + {len(record['scans'])} DICOM series) and "
               f"{out}/truth (hidden effects: {active})")  # fmt: skip


@app.command()
def calibrate(
    scans: Annotated[Path, typer.Argument(metavar="SCANS", help="Scan folder with session.toml.")],
    out: Annotated[Path, typer.Option("--out", help="Work folder (ingest results go here).")],
    objective: Annotated[
        Objective,
        typer.Option(
            "--objective",
            help="surface (every scored surface point), nipple (the dissertation's: "
            "the nipple's distance to the measured surface) or landmarks (nipple and tumour "
            "centre).",
        ),
    ] = "surface",
    reference_state: Annotated[
        ReferenceState,
        typer.Option(
            "--reference-state",
            help="unload (recover the stress-free shape from the sagging reference scan), "
            "prestress (solve on the loaded scan mesh with its prestress) or "
            "shortcut (the dissertation's: the reference scan taken as stress-free).",
        ),
    ] = "unload",
    mesh_size: Annotated[
        float | None,
        typer.Option(
            "--mesh-size",
            min=MESH_SIZE_RANGE_MM[0],
            max=MESH_SIZE_RANGE_MM[1],
            help="Element edge length of the model, mm. Default: 12; where no stress-free "
            "reference exists on it, with straight or curved elements, 14 then 16 (each "
            "retry is reported). A size given here is the only one tried (no retries).",
        ),
    ] = None,
    mesh_max_dihedral: Annotated[
        float | None,
        typer.Option(
            "--mesh-max-dihedral",
            help="TetGen's optimisation bound on the model mesh's largest dihedral angle, "
            "degrees (default: the tetgen package's, 177); 165 removes most slivers, where "
            "the stress-free recovery fails first.",
        ),
    ] = None,
    nu: Annotated[float, typer.Option("--nu", help="Poisson's ratio of the model.")] = 0.499,
    profile: Annotated[
        int, typer.Option("--profile", min=0, help="Points of the likelihood profile (0: none).")
    ] = 5,
    mesh_check: Annotated[
        str,
        typer.Option(
            "--mesh-check",
            metavar="RATIO[,RATIO]",
            help="Element-size ratio of the check mesh whose c1 bounds the discretisation "
            "error in the 95 % interval: >1 coarser (cheap), <1 finer; two reciprocal "
            "ratios (1.4,0.714): coarser and finer, the observed order (0: off, noise only).",
        ),
    ] = "1.4",
    c1_guess: Annotated[
        float,
        typer.Option(
            "--c1-guess",
            help="c1 (Pa) of the first linear solve that scales to the first estimate; the "
            "estimate itself where the nipple moved < 0.5 mm (or 3 times its expected "
            "registration error, where more) in every calibration scan (a stiff phantom), "
            "and the search spans x/÷ 4 around the estimate.",
        ),
    ] = 500.0,
) -> None:
    """Fit c1 to the calibration scans; write calibration.json and error maps."""
    from ..fitting import CalibrationOptions
    from ..fitting.options import parse_mesh_check
    from ..io import check_replaceable
    from ..report.tables import format_calibration
    from ..workflows.calibrate import run_calibration

    try:
        mesh_check = parse_mesh_check(mesh_check)
        opts = CalibrationOptions(
            objective=objective, reference_state=reference_state,
            **({} if mesh_size is None else {"mesh_size_mm": mesh_size, "mesh_retry_mm": ()}),
            nu=nu, profile_points=profile, mesh_check_ratio=mesh_check,
            mesh_max_dihedral_deg=mesh_max_dihedral, c1_guess_pa=c1_guess,
        )  # fmt: skip
        # the command validates after the fit: a validation/ no run wrote is refused first
        check_replaceable(out, ("validation",), command="calibrate")
        doc = run_calibration(scans, out, opts, progress=_indented)
    except (ValueError, OSError, RuntimeError) as exc:
        fail(exc)
    typer.echo(format_calibration(doc))
    typer.echo(f"wrote {out / 'calibration.json'} and {out / 'calibration'}/")
    _validate(out)


def _validate(work: Path) -> None:
    from ..report.tables import format_validation
    from ..workflows.validate import run_validation

    try:
        doc = run_validation(work, progress=lambda msg: typer.echo(f"  {msg}"))
    except (ValueError, OSError, RuntimeError, KeyError) as exc:
        fail(exc)
    typer.echo(format_validation(doc))
    typer.echo(f"wrote {work / 'validation.json'} and {work / 'validation'}/report.html")


@app.command()
def validate(
    work: Annotated[
        Path, typer.Argument(metavar="WORK", help="A work folder that `calibrate` wrote.")
    ],
) -> None:
    """Validate the calibrated model against the validation scans (no FE: saved states)."""
    _validate(work)


def main(argv: list[str] | None = None) -> None:
    """Console-script entry point.

    ``-v``/``--verbose`` is a global option; given after the command
    (``phantom-calib calibrate -v ...``) it is moved in front of it.
    """
    import sys

    args = list(sys.argv[1:] if argv is None else argv)
    verbose = [a for a in args if a in ("-v", "--verbose")]
    if verbose and "--" not in args:
        args = verbose[:1] + [a for a in args if a not in ("-v", "--verbose")]
    try:
        app(args=args, prog_name="phantom-calib")
    except SystemExit as exc:  # typer turns Ctrl-C into a silent exit 130
        if exc.code == 130:  # review AN, AM: a run ended without a word
            command = next((a for a in args if not a.startswith("-")), "")
            typer.echo(f"\ninterrupted: {_INTERRUPTED.get(command, _KEPT_NOTHING)}", err=True)
        raise


_KEPT_NOTHING = (
    "the step that was running kept nothing (each writes its outputs whole at its end); "
    "outputs of finished steps (calibrate's fit before its closing validate) are kept"
)
_INTERRUPTED = {
    "sweep": "the scenarios solved so far are kept in the store; run the same command "
    "again to resume"
}
