"""A surrogate of a prestressed reference: zero gravity is not its no-displacement state.

A sweep of a calibration whose reference is the prestressed loaded mesh (the store's
``model.prestress``) stores displacements relative to that loaded mesh. Ours answers
exactly zero at zero load, i.e. the loaded reference shape, while the true answer is the
stress-free shape, which the sweep never solved: the query must warn (audit item 2).
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
from typer.testing import CliRunner

import nn
from calib.cli import app

ZERO = "zero gravity on a prestressed reference is the loaded reference shape's own state"


def _as_prestressed(data, **model):
    """The block's sweep relabelled as a sweep of a prestressed reference (metadata only)."""
    m = {**data.model, **model}
    return dataclasses.replace(data, model=m, attrs={**data.attrs, "model": m})


@pytest.fixture(scope="module")
def prestressed(box_data):
    # what calib.sweep.model writes for a spatial (prestressed) reference
    data = _as_prestressed(
        box_data,
        prestress={
            "mesh": "loaded reference mesh (mesh/nodes_mm)",
            "state_sha256": "0" * 64,
            "gravity_m_s2": [0.0, 0.0, -9.81],
        },
    )
    return nn.Surrogate.from_fit(nn.fit_reduced_kernel(data, device="cpu"), data)


def test_zero_gravity_warns_on_a_prestressed_reference(prestressed):
    assert prestressed.prestressed
    with pytest.warns(nn.ExtrapolationWarning, match=ZERO + ", not in the trained range"):
        p = prestressed.predict([0.0, 0.0, 0.0])
    assert np.all(p.nodes_mm == 0.0)  # the answer is the loaded shape: hence the warning
    # one zero query in a batch of trained loads is enough
    with pytest.warns(nn.ExtrapolationWarning, match=ZERO):
        prestressed.predict([[0.0, 0.0, 9.81], [0.0, 0.0, 0.0]])


def test_smaller_loads_name_the_prestressed_anchor(prestressed):
    with pytest.warns(nn.ExtrapolationWarning, match="extrapolates; on a prestressed reference"):
        prestressed.predict([0.0, 0.0, 4.9])
    with warnings.catch_warnings():  # a trained load: no warning
        warnings.simplefilter("error")
        prestressed.predict([0.0, 0.0, 9.81])


def test_reference_state_prestress_alone_counts(box_data):
    data = _as_prestressed(box_data, reference_state="prestress")
    sur = nn.Surrogate.from_fit(nn.fit_reduced_kernel(data, device="cpu"), data)
    assert sur.prestressed
    with pytest.warns(nn.ExtrapolationWarning, match=ZERO):
        sur.predict([0.0, 0.0, 0.0])


def test_cli_predict_warns_at_zero_gravity(prestressed, tmp_path):
    model = nn.save_surrogate(prestressed, tmp_path / "pre.pt")
    assert nn.load_surrogate(model).prestressed
    out = tmp_path / "zero.vtu"
    args = ["surrogate", "predict", str(model), "--gravity", "0,0,0", "--out", str(out)]
    res = CliRunner().invoke(app, args)  # warned, not refused: not a far extrapolation
    assert res.exit_code == 0, res.output
    assert f"WARNING: {ZERO}" in res.output and out.is_file()
