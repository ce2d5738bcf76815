"""Fixtures of the nn tests: a sweep store of a tiny calibrated block (dissertation plan)."""

from __future__ import annotations

import pytest
from sweep_helpers import make_box_work


@pytest.fixture(scope="session")
def box_work(tmp_path_factory):
    return make_box_work(tmp_path_factory.mktemp("nn") / "work")


@pytest.fixture(scope="session")
def box_sweep(box_work, tmp_path_factory):
    """94 scenarios (46 training, 48 validation directions) of a 36-node block, ~10 s."""
    from calib.workflows.sweep import SweepOptions, run_sweep

    out = tmp_path_factory.mktemp("nn") / "sweep"
    run_sweep(box_work, out, SweepOptions(plan="dissertation", backend="serial"))
    return out


@pytest.fixture(scope="session")
def box_data(box_sweep):
    import nn

    return nn.load_sweep(box_sweep)
