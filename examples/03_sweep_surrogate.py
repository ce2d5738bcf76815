# ---
# jupyter:
#   jupytext:
#     formats: ipynb,py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#       jupytext_version: 1.19.6
#   kernelspec:
#     display_name: Python 3 (ipykernel)
#     language: python
#     name: python3
# ---

# %% [markdown]
# # Gravity sweeps and real-time surrogates
#
# The dissertation's chapter 4.4–4.5: the calibrated model is solved under many gravity
# directions, and a neural network learns the map from the gravity direction to the
# surface displacements and the tumour centre (two MLPs; what it reports of them against
# FE on its 48 validation directions is the last row of section 2's table).
#
# Here: the sweep of the calibrated work folder of `01_twin_to_c1`
# (`phantom-calib sweep`), the dissertation's two MLPs trained as it describes, and our
# surrogate (a POD basis of the FE snapshots and a kernel over the load vector
# ρ g / c1), compared on the same validation directions, then against the calibration's
# own FE states at every scan's own gravity. `PHANTOM_CALIB_SIZE` picks the size; the MLPs
# train for the dissertation's 30 000 iterations except at the `tiny` size.

# %%
import json
import sys
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

sys.path.insert(0, str(Path.cwd()))  # the notebooks' settings module, beside them
import _settings

import calib
import nn

out = _settings.OUT
work = out / "work"
if not (work / "calibration.json").is_file():
    raise FileNotFoundError(f"{work / 'calibration.json'}: run 01_twin_to_c1 first")
MLP_ITERATIONS = 2_000 if _settings.SIZE == "tiny" else 30_000
print(f"size {_settings.SIZE}, work folder {work}")

# %% [markdown]
# ## 1. The sweep
# The dissertation plan as we read it: training directions every 15° in the transverse
# (x–z) and sagittal (y–z) planes of the phantom frame (46 distinct: the planes share
# prone and supine), and 48 validation directions 10° past them in both planes. Each
# solve warm-starts from the nearest direction solved before it in its chunk of 12 of a
# nearest-neighbour tour (within 45°); the first of each chunk, and one far from the
# others, starts cold by load stepping (the `warm` and `cold` lines below). The store is
# resumable
# (re-running this cell solves only what is pending; a direction with no FE solution is
# recorded as failed and solved again only with `retry_failed=True`). The tiny size
# leaves a few sagittal directions unsolved (README, Status): the cell says how many.

# %%
summary = calib.gravity_sweep(
    work, out / "sweep", plan="dissertation", workers=2, progress=calib.sweep.progress_lines(print)
)
print(
    f"{summary['solved']} of {summary['n_scenarios']} scenarios solved, "
    f"{summary['failed']} with no FE solution, {summary['pending']} pending"
)
for kind in ("warm", "cold"):
    k = summary[kind]
    print(
        f"{kind} starts: {k['n']}, mean {k.get('newton_mean', 0):.1f} Newton iterations and "
        f"median {k.get('wall_s_median', 0):.2f} s per solve"
    )
data = nn.load_sweep(out / "sweep")
train, valid = data.subset(data.role == "train"), data.subset(data.role == "validation")
print(f"{len(train)} training and {len(valid)} validation directions solved")

# %%
fig = plt.figure(figsize=(6, 5))
ax = fig.add_subplot(projection="3d")
for subset, label, marker in ((train, "training", "o"), (valid, "validation", "^")):
    g = subset.gravity_phantom
    ax.scatter(g[:, 0], g[:, 1], g[:, 2], marker=marker, label=label)
ax.set(
    xlabel="x (left lateral)",
    ylabel="y",
    zlabel="z (prone)",
    title="gravity directions, phantom frame",
)
ax.legend()
plt.show()

# %% [markdown]
# ## 2. Two surrogates
# The dissertation's MLPs (unit gravity → 3 × n surface displacements, 60-60 ReLU; →
# tumour centre, 20 ReLU; Adam lr 1e-5, MAE, 80/20 hold-out) and ours (every training
# direction; the kernel's width and ridge chosen by leave-one-out).

# %%
ours = nn.Surrogate.from_fit(nn.fit_reduced_kernel(data), data)
mlps = nn.Surrogate.from_fit(
    nn.fit_dissertation_mlps(data, iterations=MLP_ITERATIONS, seed=0), data
)
rows = []
for name, sur in (("ours", ours), ("dissertation MLPs", mlps)):
    for role, e in sur.report["errors"].items():
        rows.append(
            f"| {name} | {role} | {e['n']} | {e['surface_mean_mm']:.3g} | "
            f"{e['surface_max_mm']:.3g} | {e['tumour_mean_mm']:.3g} | "
            f"{e['tumour_max_mm']:.3g} |"
        )
from IPython.display import Markdown

from nn.baseline import DISSERTATION_REPORTED as reported

rows.append(
    f"| dissertation MLPs, as published | validation | 48 | {reported['surface_mean_mm']} "
    f"± {reported['surface_sd_mm']} | – | – | {reported['tumour_max_mm']} |"
)
Markdown(
    "| surrogate | scenarios | n | surface mean mm | surface max mm | tumour mean mm | "
    "tumour max mm |\n|---|---|---|---|---|---|---|\n" + "\n".join(rows)
)

# %% [markdown]
# ## 3. Error maps at the dissertation MLPs' worst validation direction
# Surface vertices coloured by the point-to-point error against FE (the dissertation's
# Fig. 4.17), both surrogates on one colour scale (the larger 99th percentile), in the
# phantom frame (z from the back plate into the breast, as every other map).

# %%
from nn.surrogate import surface_errors

err = {"ours": surface_errors(ours, valid), "dissertation MLPs": surface_errors(mlps, valid)}
worst = int(np.argmax(err["dissertation MLPs"].mean(axis=1)))
pts = data.nodes_mm[data.surface_nodes] @ np.asarray(data.model["R_ref_from_phantom"])
top = max(float(np.percentile(e[worst], 99)) for e in err.values())
fig = plt.figure(figsize=(11, 4.5))
for k, (name, e) in enumerate(err.items()):
    ax = fig.add_subplot(1, 2, k + 1, projection="3d")
    sc = ax.scatter(
        pts[:, 0], pts[:, 1], pts[:, 2], c=e[worst], cmap="viridis", s=12, vmin=0.0, vmax=top
    )
    fig.colorbar(sc, ax=ax, shrink=0.6, label="error (mm)", extend="max")
    ax.set(xlabel="x (mm, phantom frame)", ylabel="y (mm)", zlabel="z (mm)")
    ax.set_title(f"{name}: {valid.plane[worst]} {valid.angle_deg[worst]:.0f}°")
plt.tight_layout()
plt.show()

# %% [markdown]
# ## 4. Errors by how far the surface moved
# The dissertation's Fig. 4.18: the share of surface vertices per error bin over the
# solved validation directions (its 48 where all solve), and the errors against the FE
# displacement of each vertex.

# %%
u_fe = np.linalg.norm(valid.displacement_mm[:, valid.surface_nodes], axis=2)
fig, axes = plt.subplots(1, 3, figsize=(14, 4))
for name, e in err.items():
    w = np.full(e.size, 100.0 / e.size)
    axes[0].hist(e.ravel(), bins=np.logspace(-6, 1, 50), weights=w, alpha=0.6, label=name)
    axes[1].scatter(u_fe.ravel(), e.ravel(), s=2, alpha=0.3, label=name)
axes[0].set(xscale="log", xlabel="error mm", ylabel="% of surface vertices")
axes[1].set(yscale="log", xlabel="FE displacement mm", ylabel="error mm")
axes[2].hist(u_fe.ravel(), bins=40, weights=np.full(u_fe.size, 100.0 / u_fe.size))
axes[2].set(
    xlabel="FE displacement mm", ylabel="% of surface vertices", title="displacement distribution"
)
axes[0].legend()
plt.tight_layout()
plt.show()

# %% [markdown]
# ## 5. The tumour centre along both planes
# The dissertation's Figs. 4.19–4.20: the tumour centre's displacement at every angle of
# a plane, FE (dots) against each surrogate (lines, 1° steps).

# %%
R = np.asarray(data.model["R_ref_from_phantom"])
g0 = float(data.model["g_m_s2"])
fig, axes = plt.subplots(1, 2, figsize=(11, 4))
for ax, plane in zip(axes, ("transverse", "sagittal"), strict=True):
    a = np.radians(np.arange(0.0, 361.0, 1.0))
    unit = (
        np.column_stack([np.cos(a), 0 * a, np.sin(a)])
        if plane == "transverse"
        else np.column_stack([0 * a, np.cos(a), np.sin(a)])
    )
    sel = data.plane == plane
    t_fe = data.tumour_mm[sel] @ R  # phantom frame
    for name, sur in (("ours", ours), ("dissertation MLPs", mlps)):
        t = sur.predict(g0 * unit).tumour_mm @ R
        ax.plot(np.degrees(a), np.linalg.norm(t, axis=1), label=name)
    ax.plot(data.angle_deg[sel], np.linalg.norm(t_fe, axis=1), "k.", label="FE")
    ax.set(title=f"{plane} plane", xlabel="posture angle deg", ylabel="tumour displacement mm")
axes[0].legend()
plt.show()

# %% [markdown]
# ## 6. Surrogates against FE at the scans
# `calibrate` saved the FE state of every scan at the calibrated c1
# (`calibration/<scan>_deformed.vtu`); each surrogate is queried at the scan's own
# gravity (registered, so slightly off the nominal postures): every scan but the
# reference, the calibration scans and the validation ones.

# %%
import meshio

doc = json.loads((work / "calibration.json").read_text())
at_scans = {}
for name, s in doc["scans"].items():
    path = work / "calibration" / f"{name}_deformed.vtu"
    if "gravity_ref" not in s or not path.is_file():
        continue
    # positions, not displacements: a prestressed reference is swept on its loaded mesh
    # (the store's nodes), while displacement_mm is measured from the stress-free mesh
    fe = np.asarray(meshio.read(path).points)[data.surface_nodes]
    rest = data.nodes_mm[data.surface_nodes]
    g = np.asarray(s["gravity_ref"]) * g0
    at_scans[name] = {
        k: float(
            np.linalg.norm(rest + sur.predict(g, frame="ref").surface_mm[0] - fe, axis=1).mean()
        )
        for k, sur in (("ours", ours), ("dissertation MLPs", mlps))
    }
    print(
        f"{name:14s} surface mean error: ours {at_scans[name]['ours']:.3g} mm, "
        f"MLPs {at_scans[name]['dissertation MLPs']:.3g} mm"
    )

# %% [markdown]
# ## 7. Deploying a surrogate
# A TorchScript file with its mesh and metadata: `phantom-calib surrogate predict` (or
# `torch.jit.load` anywhere) turns a gravity vector into the deformed phantom. Query
# timings are measured in `benchmarks/bench_surrogate.py`, not here.

# %%
nn.save_surrogate(ours, out / "surrogate.pt")
sur = nn.load_surrogate(out / "surrogate.pt")
prone = sur.predict([0.0, 0.0, g0])  # phantom frame: gravity towards +z
# displacements from the sweep's reference mesh: the loaded reference scan's shape where the
# calibration recovered a prestressed reference (the tiny twin), else the stress-free shape
origin = "the reference scan's shape" if sur.prestressed else "the stress-free shape"
print(
    f"prone, from {origin}: nipple displacement {np.linalg.norm(prone.nipple_mm[0]):.2f} mm, "
    f"largest {np.linalg.norm(prone.nodes_mm[0], axis=1).max():.2f} mm"
)

# %%
v_ours, v_mlps = ours.report["errors"]["validation"], mlps.report["errors"]["validation"]
result = {
    "n_validation": v_ours["n"],
    "ours_surface_mean_mm": v_ours["surface_mean_mm"],
    "ours_surface_max_mm": v_ours["surface_max_mm"],
    "ours_tumour_max_mm": v_ours["tumour_max_mm"],
    "mlps_surface_mean_mm": v_mlps["surface_mean_mm"],
    "at_scans_mean_mm": at_scans,
}
(out / "03_summary.json").write_text(json.dumps(result, indent=2))
result
