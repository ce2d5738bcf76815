"""The example notebooks execute, at a tiny size, and give the numbers they promise.

Each notebook is the jupytext percent script ``examples/NN_*.py`` (the paired ``.ipynb``
holds the same cells); it is executed cell by cell in a real Jupyter kernel (nbclient)
with ``PHANTOM_CALIB_SIZE=tiny`` and writes a small ``NN_summary.json`` that the test
checks, in the style of scikit-fem's ``test_examples.py``.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

pytest.importorskip("nbclient")
pytest.importorskip("jupytext")


def test_01_twin_to_c1_recovers_the_truth(tiny_chain_notebooks):
    # executed once per session (tests/conftest.py): the validation suite's tiny case
    # reads the same run
    tiny_chain_notebooks.require("01_twin_to_c1.py")
    s = json.loads((tiny_chain_notebooks.out / "01_summary.json").read_text())
    # the tiny twin's bar (tests/validation/test_chain.py, C1_BAR): c1 within 5 % of the
    # truth (seed 0: +3.2 %, a bias of its 2 mm voxels that the interval does not hold;
    # the 3 % bar and the truth inside the interval are checked on the quick twin)
    assert s["c1_pa"] == pytest.approx(s["c1_true_pa"], rel=0.05)
    # (its interval holds c1 by construction: review AG found that check vacuous)
    # review AG: Work's figures showed as "<Figure size ... with 1 Axes>" text without
    # %matplotlib inline; the notebook draws its profile (section 3) and an error map
    assert tiny_chain_notebooks.images("01_twin_to_c1.py") >= 2


def test_02_validation_reports_every_validation_scan(tiny_chain_notebooks):
    tiny_chain_notebooks.require("02_validation.py")
    s = json.loads((tiny_chain_notebooks.out / "02_summary.json").read_text())
    # the tiny twin's 50 deg scan; with the right material the surface error is the
    # imaging and discretisation floor (0.1-0.2 mm on the twin), far below 0.5 mm
    assert set(s["surface_mean_mm"]) == {"tilt_50"}
    assert s["surface_mean_mm"]["tilt_50"] < 0.5
    assert tiny_chain_notebooks.images("02_validation.py") >= 2  # its maps and histograms


@pytest.fixture(scope="module")
def notebook_03(tiny_chain_notebooks):
    """Notebook 03 run once on the tiny chain's outputs: its summary."""
    tiny_chain_notebooks.require("01_twin_to_c1.py")
    tiny_chain_notebooks.run("03_sweep_surrogate.py")
    return json.loads((tiny_chain_notebooks.out / "03_summary.json").read_text())


@pytest.mark.slow  # a 94-scenario sweep and 2,000 MLP iterations: minutes on 2 cores
def test_03_sweep_surrogate_meets_the_mean_bars_and_beats_the_mlps(notebook_03):
    # review CG-1: the whole test was a strict expected failure, so only "it runs" was
    # checked. What holds at the tiny size (measured 2026-12-08: 46 of 48 validation
    # directions solved, surface mean 0.0030 mm, tumour max 0.013 mm, MLPs 13.7 mm after
    # 2,000 iterations): issue 12's mean and tumour bars against FE, and ours ahead of the
    # MLPs. At the quick size (`make notebooks`) every bar holds: 48 of 48, surface mean
    # 0.00025 mm, max 0.098 mm, tumour max 0.00044 mm.
    s = notebook_03
    assert s["n_validation"] >= 44  # the few sagittal directions README's Status names
    assert s["ours_surface_mean_mm"] <= 0.02 and s["ours_tumour_max_mm"] <= 0.02
    assert s["ours_surface_mean_mm"] < s["mlps_surface_mean_mm"]


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    raises=AssertionError,  # the bars; a notebook that fails to run is an error
    reason="known limit (README, Status): the tiny twin's prestressed sweep leaves a few "
    "sagittal directions near 200 and 345 deg unsolved (a limit point of the clamped rim "
    "pressed through the back plate's plane; no contact is modelled; `phantom-calib sweep` "
    "prints how many), and the surrogate's largest error lies beside the gap (1.77 mm)",
)
def test_03_every_validation_direction_and_the_max_bar_at_the_tiny_size(notebook_03):
    # issue 12's bars against FE on the dissertation plan's 48 validation directions
    assert notebook_03["n_validation"] == 48
    assert notebook_03["ours_surface_max_mm"] <= 0.2


@pytest.mark.slow  # two tiny twins calibrated and diagnosed: about 11 minutes on 2 cores
def test_04_missing_effect_names_the_hidden_skin_and_nothing_on_the_null_twin(
    run_notebook, tmp_path
):
    # issue 13 ("the notebook executes"), standalone: the hidden-skin twin is named and
    # the refit brings c1 back within the bench's 5 % of the truth (measured: 554.5 Pa
    # calibrated, 422.2 Pa refitted, truth 420); the null twin answers no missing effect
    run_notebook("04_missing_effect.py", tmp_path)
    s = json.loads((tmp_path / "04_summary.json").read_text())
    assert s["skin_verdict"] == "named: skin"
    assert s["c1_calibrated_pa"] > 1.2 * s["c1_true_pa"]  # the skin absorbed into c1
    assert s["c1_refit_pa"] == pytest.approx(s["c1_true_pa"], rel=0.05)
    assert s["none_verdict"] == "no missing effect"
    # review BB: the FE parameter limits (parameter_limits=True, the notebook's costliest
    # step) gave the null twin's skin a limit, a stiffness ratio under the hidden 8 that
    # the same size names (3.88 on this tiny twin, run 2026-12-07; 1.7-2.3 on the quick
    # null twins, docs/diagnose-evidence.md); review BC: a bare "> 1" held for any limit
    assert s["none_skin_limit"] is not None and 1.5 < s["none_skin_limit"] < 8.0


@pytest.mark.parametrize(
    "script",
    sorted(p.name for p in (Path(__file__).parents[2] / "examples").glob("0*.py")),
)
def test_each_example_has_its_paired_notebook_with_the_same_cells(script):
    # the .ipynb opened in Jupyter (make lab) is the script's pair: a script edited
    # without `jupytext --sync` would open as an older notebook
    import jupytext

    py = Path(__file__).parents[2] / "examples" / script
    ipynb = py.with_suffix(".ipynb")
    assert ipynb.is_file(), f"{ipynb} is missing: run `jupytext --sync {py}`"
    a, b = jupytext.read(py), jupytext.read(ipynb)
    assert [(c.cell_type, c.source) for c in a.cells] == [
        (c.cell_type, c.source) for c in b.cells
    ], f"{ipynb.name} holds other cells than {script}: run `jupytext --sync {py}`"
    assert all(not c.get("outputs") for c in b.cells if c.cell_type == "code"), (
        f"{ipynb.name} carries outputs; the tracked notebooks are output-free"
    )
