"""Fixtures of the imaging tests: synthetic scans with known truth."""

from __future__ import annotations

import pytest
from imaging_synth import PosedScan, make_scan

from imaging import process_scan


@pytest.fixture(scope="session")
def oblique_scan() -> PosedScan:
    """Oblique pose and slice orientation, anisotropic voxels, +-20 % bias, SNR 25."""
    return make_scan()


@pytest.fixture(scope="session")
def oblique_result(oblique_scan):
    return process_scan(oblique_scan.volume, target_faces=20000)
