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
# # From a digital twin to c1
#
# The whole calibration chain of the dissertation (chapters 3–4) on a **digital twin** of
# the phantom experiment, whose true material is known: MR scans in several postures are
# synthesised from a finer FE truth, segmented, registered by their fiducials, and the
# neo-Hookean c1 of the model is fitted by Gauss-Newton to the measured surfaces.
#
# The twin here hides no effect (`--effect none`): the model can be right, so the fitted
# c1 should land near the truth (420 Pa): within its interval on the quick twin; the
# tiny one's 2 mm voxels leave a bias of about 3 % that its interval does not hold (the
# misfit test cannot see it either: a uniform bias looks like c1). `PHANTOM_CALIB_SIZE` picks
# the size (`tiny`, `quick`, `dissertation`); outputs go to `PHANTOM_CALIB_OUT`.

# %%
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path.cwd()))  # the notebooks' settings module, beside them
import _settings

import calib
from calib.model.effects import TruthEffects

out = _settings.OUT
print(f"size {_settings.SIZE}, outputs in {out}")

# %% [markdown]
# ## 1. A twin scan set
# `calib.synthesize` writes `scans/` (DICOM series and `session.toml`: what a user
# would have) and `truth/` (sealed: never read by the pipeline).

# %%
truth = calib.synthesize(
    out / "twin", preset=_settings.preset(), seed=0, effects=TruthEffects(), overwrite=True
)
print("true c1:", truth["material"]["c1_pa"], "Pa; hidden effects:", truth["effects"]["active"])
print((out / "twin" / "scans" / "session.toml").read_text())

# %% [markdown]
# ## 2. Ingest: surfaces, landmarks, registration
# Every scan is segmented, its surface extracted, its fiducials, nipple and inclusions
# found, and it is registered to the reference scan by its fiducials (Arun's SVD).

# %%
ingested = calib.ingest(out / "twin" / "scans", out / "work")
print(ingested.summary_table)

# %% [markdown]
# ## 3. Calibrate c1
# The stress-free reference is recovered from the (sagging) reference scan, then c1 is
# fitted to the calibration scans' surfaces. `calib.calibrate` writes `calibration.json`
# and `calibration/` as `phantom-calib calibrate` does (the command then validates as
# well: notebook 02's `calib.validate`); `calib.load_work` reads it back as an object.

# %%
record = calib.calibrate(
    out / "twin" / "scans", out / "work", progress=print, **_settings.calibration_options()
)
work = calib.load_work(out / "work")
work

# %%
c1_true = truth["material"]["c1_pa"]
interval = record["c1_ci95_pa"]  # None where the fit could not give one (the record says why)
said = "no interval" if interval is None else "95 % interval {:.1f}-{:.1f} Pa".format(*interval)
print(f"c1 = {record['c1_pa']:.1f} Pa, {said}, truth {c1_true} Pa")
print(f"relative error {100 * (record['c1_pa'] / c1_true - 1):+.2f} %")
work.plot_profile()

# %% [markdown]
# ## 4. Where the calibrated model and the calibration scan disagree
# The measured surface coloured by its signed distance to the model along the model's
# outward normal (red: the scan lies outside the model, blue: inside), in the phantom
# frame, on this scan's own scale (±99th percentile of |error|; `WORK/calibration/`'s
# maps share one scale over the scans: pass `vmax=work.error_scale_mm()` for that).

# %%
calibration_scan = next(n for n, r in work.scans.items() if r == "calibration")
work.plot_error_map(calibration_scan)

# %%
summary = {"c1_pa": record["c1_pa"], "c1_true_pa": c1_true, "c1_ci95_pa": interval}
(out / "01_summary.json").write_text(json.dumps(summary, indent=2))
summary
