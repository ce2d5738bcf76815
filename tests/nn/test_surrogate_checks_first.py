"""``surrogate train`` and ``surrogate predict``: options are checked before any reading.

A bad ``--kind``, ``--device`` or ``--out`` used to be refused only after the whole
sweep store had been read, or after the model had been loaded and queried (audit item 1).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

import nn
from calib.cli import app
from calib.workflows.sweep import run_surrogate_predict, run_surrogate_train

runner = CliRunner()


@pytest.fixture
def no_reading(monkeypatch):
    """Fail the test if a sweep store or a surrogate file is read."""

    def refuse(path, *args, **kw):
        raise AssertionError(f"{path} was read before the options were checked")

    monkeypatch.setattr(nn, "load_sweep", refuse)
    monkeypatch.setattr(nn, "load_surrogate", refuse)


def _cuda() -> bool:
    import torch

    return torch.cuda.is_available()


@pytest.mark.parametrize(
    ("kw", "error", "match"),
    [
        ({"kind": "foo"}, ValueError, "unknown surrogate kind 'foo'; choose ours or dissertation"),
        (
            {"device": "tpu"},
            ValueError,
            r"^device \(--device\) must be auto, cpu or cuda, got 'tpu'",
        ),
        (
            {"kind": "dissertation", "iterations": 0},
            ValueError,
            "iterations \\(--iterations\\) must be >= 1",
        ),
        pytest.param(
            {"device": "cuda"},
            ValueError,
            r"^device \(--device\) cuda: no CUDA device",
            marks=pytest.mark.skipif("_cuda()", reason="a CUDA device is here"),
        ),
    ],
)
def test_train_refuses_bad_options_before_reading_the_store(tmp_path, no_reading, kw, error, match):
    with pytest.raises(error, match=match):
        run_surrogate_train(tmp_path / "SWEEP", tmp_path / "m.pt", **kw)
    assert not (tmp_path / "m.pt").exists()


def test_train_refuses_a_folder_as_out_before_reading(tmp_path, no_reading):
    (tmp_path / "m.pt").mkdir()
    with pytest.raises(IsADirectoryError, match=r"^out \(--out\) .*m\.pt: is a folder"):
        run_surrogate_train(tmp_path / "SWEEP", tmp_path / "m.pt", device="cpu")


def test_train_refuses_an_unwritable_out_before_reading(tmp_path, no_reading, monkeypatch):
    # the check simulate made; train found out after minutes of fitting (os.access is
    # replaced: the suite may run as root, for whom every folder is writable)
    import calib.io

    locked = tmp_path / "locked"
    locked.mkdir()
    real = calib.io.os.access
    monkeypatch.setattr(calib.io.os, "access", lambda p, m: Path(p) != locked and real(p, m))
    with pytest.raises(PermissionError, match=r"^out \(--out\) .*m\.pt: .*locked is not writable"):
        run_surrogate_train(tmp_path / "SWEEP", locked / "sub" / "m.pt", device="cpu")
    with pytest.raises(PermissionError, match="locked is not writable"):
        run_surrogate_predict(tmp_path / "m.pt", locked / "R.vtu", gravity=[0, 0, 9.81])


def test_cli_train_bad_kind_reads_nothing(tmp_path, no_reading):
    out = tmp_path / "m.pt"
    res = runner.invoke(
        app, ["surrogate", "train", str(tmp_path / "SWEEP"), "--out", str(out), "--kind", "gp"]
    )
    assert res.exit_code == 2, res.output
    assert "'gp' is not one of 'ours', 'dissertation'" in res.output and not out.exists()


@pytest.mark.parametrize(
    ("out", "kw", "error", "match"),
    [
        ("R.obj", {}, ValueError, r"R\.obj: write \.vtu or \.ply, got suffix '\.obj'"),
        ("R.vtu", {"frame": "world"}, ValueError, "frame \\(--frame\\) must be 'phantom' or 'ref'"),
        # review BD: a c1 <= 0 was found by the surrogate, once loaded
        (
            "R.vtu",
            {"c1_pa": 0.0},
            ValueError,
            "c1_pa \\(--c1\\) must be a positive stress in Pa, got 0.0",
        ),
        (
            "R.ply",
            {"c1_pa": float("nan")},
            ValueError,
            "c1_pa \\(--c1\\) must be a positive stress in Pa",
        ),
    ],
)
def test_predict_refuses_bad_options_before_loading(tmp_path, no_reading, out, kw, error, match):
    with pytest.raises(error, match=match):
        run_surrogate_predict(tmp_path / "m.pt", tmp_path / out, gravity=[0, 0, 9.81], **kw)
    assert not (tmp_path / out).exists()


def test_predict_refuses_a_folder_as_out_before_loading(tmp_path, no_reading):
    (tmp_path / "R.vtu").mkdir()
    with pytest.raises(IsADirectoryError, match="is a folder"):
        run_surrogate_predict(tmp_path / "m.pt", tmp_path / "R.vtu", gravity=[0, 0, 9.81])


def test_cli_predict_bad_suffix_loads_nothing(tmp_path, no_reading):
    out = tmp_path / "R.obj"
    args = ["surrogate", "predict", str(tmp_path / "m.pt"), "--gravity", "0,0,9.81"]
    res = runner.invoke(app, [*args, "--out", str(out)])
    assert res.exit_code == 2, res.output
    assert ".vtu or .ply" in res.output and not out.exists()
