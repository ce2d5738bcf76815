"""``phantom-calib sweep`` and ``phantom-calib surrogate train|predict``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from nn.device import Device

from ..choices import PredictFrame, SurrogateKind
from .app import app, fail

surrogate_app = typer.Typer(
    no_args_is_help=True, help="Train and query torch surrogates of a sweep (nn)."
)
app.add_typer(surrogate_app, name="surrogate")


def _progress_bar():
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TextColumn("ETA"),
        TimeRemainingColumn(),
        TextColumn("{task.fields[last]}"),
        transient=False,
    )


@app.command()
def sweep(
    work: Annotated[
        Path, typer.Argument(metavar="WORK", help="Calibrated work folder (calibration.json).")
    ],
    out: Annotated[Path, typer.Option("--out", help="Sweep store to write or resume (Zarr).")],
    plan: Annotated[
        str,
        typer.Option(
            "--plan",
            metavar="PLAN",
            help="dissertation (15 deg transverse + sagittal training, 48 validation "
            "directions), dissertation:transverse (24 transverse training), or sphere:N.",
        ),
    ] = "dissertation",
    c1: Annotated[
        str | None,
        typer.Option(
            "--c1",
            metavar="LO:HI:N",
            help="c1 axis in Pa, N values spaced geometrically; default: the calibrated c1.",
        ),
    ] = None,
    holdout: Annotated[
        float,
        typer.Option(
            "--holdout",
            metavar="FRACTION",
            help="Fraction of a sphere:N plan's directions held out for validation, in [0, 1).",
        ),
    ] = 0.0,
    seed: Annotated[int, typer.Option("--seed", min=0, help="Seed of the hold-out.")] = 0,
    workers: Annotated[
        int | None, typer.Option("--workers", help="Worker processes (default 2).")
    ] = None,
    serial: Annotated[bool, typer.Option("--serial", help="Solve in this process.")] = False,
    dask: Annotated[
        str | None,
        typer.Option(
            "--dask",
            metavar="local|tcp://HOST:PORT",
            help="A LocalCluster, or the scheduler at that address.",
        ),
    ] = None,
    chunk_size: Annotated[
        int, typer.Option("--chunk-size", help="Scenarios per continuation chunk.")
    ] = 12,
    overwrite: Annotated[
        bool,
        typer.Option(
            "--overwrite",
            help="Replace the store at --out, whatever it holds (its solved scenarios are "
            "lost); without it a store of this model and plan is resumed, another refused.",
        ),
    ] = False,
    retry_failed: Annotated[
        bool, typer.Option("--retry-failed", help="Solve failed scenarios again.")
    ] = False,
) -> None:
    """Solve the calibrated model over gravity directions; write a resumable Zarr store."""
    from ..sweep import CalibrationMissingError, PlanError
    from ..sweep.store import StoreError
    from ..workflows.sweep import SweepOptions, run_sweep

    if serial and dask:
        fail(ValueError("--serial and --dask exclude each other"))
    backend = "serial" if serial else "dask" if dask else "pool"
    bar = task = None  # started with the sweep: a refused input prints its error alone

    def progress(ev: dict) -> None:
        nonlocal bar, task
        if ev.get("start"):
            bar = _progress_bar()
            bar.start()
            task = bar.add_task("sweep", total=ev["total"], last="")
            return
        it = ev.get("newton_iterations")
        last = (
            f"#{ev['index']}: {int(it)} Newton, {ev['wall_s']:.1f} s"
            if ev["ok"]
            else f"#{ev['index']}: FAILED"
        )
        bar.update(task, advance=1, last=last)

    try:
        opts = SweepOptions(
            plan=plan,
            c1_axis=c1,
            holdout=holdout,
            seed=seed,
            backend=backend,
            workers=workers,
            dask=dask,
            chunk_size=chunk_size,
            overwrite=overwrite,
            retry_failed=retry_failed,
        )
        try:
            summary = run_sweep(work, out, opts, progress=progress)
        finally:
            if bar is not None:
                bar.stop()
    except (
        CalibrationMissingError,
        PlanError,
        StoreError,
        ValueError,
        OSError,
        RuntimeError,
    ) as exc:
        fail(exc)
    typer.echo(_format_summary(summary))
    typer.echo(_model_line(out, work))
    if summary["solved"] == 0 and summary["failed"]:  # review AD: this exited 0
        import zarr

        failures = dict(zarr.open_group(out, mode="r").attrs.get("failures", {}))
        first = min(failures.items(), key=lambda kv: int(kv[0]), default=("?", "?"))
        fail(
            RuntimeError(
                f"{out}: no scenario solved ({summary['failed']} failed; scenario {first[0]}: "
                f"{first[1]}); the store's `failures` attribute lists each"
            )
        )
    typer.echo(f"wrote {out}")


def _model_line(out: Path, work: Path) -> str:
    """Which model the store solved, and where a diagnosis named more (review AX)."""
    import json

    import zarr

    model = dict(zarr.open_group(out, mode="r").attrs["model"])
    named = (model.get("effects") or {}).get("named") or []
    what = f"with {', '.join(named)} (a diagnosis refit)" if named else "homogeneous"
    law = str(model.get("law", "neo-hookean")).split(",")[0]
    line = f"model: c1 {model['c1_pa']:.1f} Pa, {what}, {law}, from {work}"
    record = Path(work) / "diagnosis.json"
    if not named and record.is_file():
        try:
            found = json.loads(record.read_text()).get("named") or []
        except (OSError, ValueError):
            found = []
        if found:
            line += (
                f"\n  {record} names {', '.join(found)}: {Path(work) / 'diagnosis' / 'refit'} "
                "holds that model, and `phantom-calib sweep` of it solves it"
            )
    return line


def _format_summary(s: dict) -> str:
    run = s["this_run"]
    if run["solved"] == 0 and run.get("failed", 0) == 0 and not run["workers"]:
        # review AX: "0 solved in 0.0 s on pool (0 workers)" of a store already complete
        this = "this run: nothing to solve (none pending; --retry-failed solves the failed again)"
    else:
        this = (
            f"this run: {run['solved']} solved in {run['wall_s']:.1f} s on {run['backend']} "
            f"({run['workers']} workers)"
        )
    lines = [
        f"{s['solved']} of {s['n_scenarios']} scenarios solved, {s['failed']} failed, "
        f"{s['pending']} pending; {this}"
    ]
    for kind in ("warm", "cold"):
        k = s[kind]
        if k.get("n"):  # review BT: every solved scenario of the store, not this run's
            lines.append(
                f"  the store's {kind} starts: {k['n']}, Newton iterations per solve mean "
                f"{k['newton_mean']:.1f} (median {k['newton_median']:.0f}, max "
                f"{k['newton_max']}), median {k['wall_s_median']:.2f} s per solve"
            )
    return "\n".join(lines)


@surrogate_app.command("train")
def surrogate_train(
    sweep_store: Annotated[Path, typer.Argument(metavar="SWEEP", help="Sweep store.")],
    out: Annotated[Path, typer.Option("--out", help="Model file to write (TorchScript .pt).")],
    kind: Annotated[
        SurrogateKind,
        typer.Option("--kind", help="ours (reduced basis + kernel) or dissertation (MLPs)."),
    ] = "ours",
    device: Annotated[
        Device, typer.Option("--device", help="Where to train (auto: cuda where there is one).")
    ] = "auto",
    seed: Annotated[
        int,
        typer.Option(
            "--seed",
            min=0,
            help="Seed of the MLPs' initial weights and split (ours draws nothing).",
        ),
    ] = 0,
    iterations: Annotated[
        int | None,
        typer.Option(
            "--iterations",
            help="Training iterations (full-batch Adam steps) of the dissertation MLPs "
            "(--kind dissertation only; default: the dissertation's 30000).",
        ),
    ] = None,
) -> None:
    """Fit a surrogate on the training scenarios of a sweep; report validation errors."""
    from ..workflows.sweep import run_surrogate_train

    try:
        report = run_surrogate_train(
            sweep_store,
            out,
            kind=kind,
            device=device,
            seed=seed,
            iterations=iterations,
            progress=lambda m: typer.echo(f"  {m}"),
        )
    except (ValueError, OSError, RuntimeError) as exc:
        fail(exc)
    typer.echo(_format_report(report))
    typer.echo(f"wrote {out}")


def _format_report(r: dict) -> str:
    lines = [
        f"{r['kind']} surrogate: trained on {r['n_train']} scenarios in "
        f"{r['train_wall_s']:.1f} s on {r['device']}"
    ]
    for name, m in r.get("errors", {}).items():
        if m.get("n"):
            tum = (
                ""
                if m.get("tumour_mean_mm") is None
                else f", tumour mean {m['tumour_mean_mm']:.4f} max {m['tumour_max_mm']:.4f} mm"
            )
            lines.append(
                f"  {name} ({m['n']}): surface mean {m['surface_mean_mm']:.4f} mm, "
                f"max {m['surface_max_mm']:.4f} mm{tum}"
            )
    if not r.get("errors", {}).get("validation", {}).get("n"):  # review AM: "train" alone
        loo = r.get("loo_mean_error_mm")
        lines.append(
            "  validation: none (the sweep held no direction out: sweep --holdout F); "
            + (
                "the test split's errors are the estimate between training points"
                if loo is None
                else f"the leave-one-out mean error, {loo:.4f} mm, is the estimate between them"
            )
        )
    return "\n".join(lines)


@surrogate_app.command("predict")
def surrogate_predict(
    model: Annotated[Path, typer.Argument(metavar="MODEL", help="Surrogate (.pt).")],
    gravity: Annotated[
        str,
        typer.Option(
            "--gravity",
            metavar="X,Y,Z",
            help="Gravity in m/s^2 (length = magnitude; 0,0,0: none).",
        ),
    ],
    out: Annotated[Path, typer.Option("--out", help="R.vtu (mesh) or R.ply (surface).")],
    c1: Annotated[
        float | None, typer.Option("--c1", help="c1 in Pa (default: the calibrated c1).")
    ] = None,
    frame: Annotated[
        PredictFrame,
        typer.Option("--frame", help="phantom (posture-angle frame) or ref (model frame)."),
    ] = "phantom",
    extrapolate: Annotated[
        bool,
        typer.Option(
            "--extrapolate",
            help="Write a prediction not to be trusted at all (a load beyond 1.5 times the "
            "trained range, or nearer a scenario the sweep could not solve; else refused). "
            "Other extrapolations (a c1, load or gravity direction off the training "
            "scenarios) are written with a warning.",
        ),
    ] = False,
) -> None:
    """Predict the deformed phantom for one gravity vector; write a mesh."""
    import warnings

    import numpy as np

    from ..workflows.sweep import run_surrogate_predict

    try:
        try:
            parts = [float(p) for p in gravity.split(",")]
        except ValueError:
            parts = []
        if len(parts) != 3:
            raise ValueError(f"--gravity must be three numbers X,Y,Z in m/s^2, got {gravity!r}")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            res = run_surrogate_predict(
                model, out, gravity=parts, c1_pa=c1, frame=frame, extrapolate=extrapolate
            )
        for w in caught:
            typer.secho(f"WARNING: {w.message}", fg=typer.colors.YELLOW, err=True)
    except (ValueError, OSError, RuntimeError) as exc:
        fail(exc)
    extra = "".join(
        f", {name} {np.linalg.norm(res[key]):.3f} mm"
        for name, key in (("nipple", "nipple_mm"), ("tumour centre", "tumour_mm"))
        if res[key] is not None
    )
    typer.echo(f"max displacement {res['max_displacement_mm']:.3f} mm{extra} -> {out}")
    # review AT: calibration.json's gravity_ref given in the default phantom frame moved
    # the demo's body 25.5 mm instead of 17.6: the frame read is said
    other = (
        "ref: the model's, as calibration.json's gravity_ref" if frame == "phantom" else "phantom"
    )
    typer.echo(f"  gravity {gravity} m/s^2 read in the {frame} frame (--frame {other})")
