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
# # Validation against the postures the model was not fitted to
#
# The dissertation's headline results are the errors at the postures its model was not
# fitted to: its FE model against the MRI surface at 25° (3.63 ± 1.12 mm, tumour centre
# 3.65 mm) and its surrogate's prediction against it at 50° (2.69 ± 0.7 mm); the table's
# last column prints them beside a scan at that posture (`calib.validation.DISSERTATION`).
# Here the same figures for the work folder of `01_twin_to_c1`, with a 95 % band from
# the c1 interval, next to each scan's registration error. No FE solve: `calibrate`
# saved every posture's deformed state and its derivative in ln c1.

# %%
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path.cwd()))
import _settings
from IPython.display import Markdown, display

import calib

work_folder = _settings.OUT / "work"
work = calib.load_work(work_folder)
record = calib.validate(work)  # writes WORK/validation/; `work` keeps its figures
Markdown(work.validation_table())

# %% [markdown]
# ## Error maps on a shared colour scale
# Each map is the measured surface coloured by its signed distance to the model along the
# model's outward normal (red: the scan lies outside the model, blue: inside), in the
# phantom frame. The scale runs over ± the largest 99th percentile of |error| over every
# validated scan's scored vertices, as `WORK/validation/`'s maps do
# (`work.error_scale_mm()`; a few rim vertices would otherwise wash the rest out).

# %%
validation_scans = [n for n, r in work.scans.items() if r == "validation"]
vmax = work.error_scale_mm()  # validate's: over every scan it draws, the calibration's too
for name in validation_scans:
    display(work.plot_error_map(name, vmax=vmax))

# %% [markdown]
# ## Errors by how far the surface moved (the dissertation's Figs. 3.18–3.21)

# %%
work.plot_error_by_displacement(validation_scans)

# %% [markdown]
# ## Measured and simulated outlines in the scans' slices
# The report's figures, written by `calib.validate` into `WORK/validation/`.

# %%
from IPython.display import Image

for name in validation_scans:
    display(Image(filename=str(work_folder / "validation" / f"{name}_outlines.png")))

# %%
means = {
    n: record["scans"][n]["surface_error_mm"]["fiducial"]["mean"]["value"] for n in validation_scans
}
(_settings.OUT / "02_summary.json").write_text(json.dumps({"surface_mean_mm": means}, indent=2))
means
