"""Sparsity pattern and scatter map of the reduced matrix against a brute-force assembly."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from fem.pattern import build_pattern


def _brute_force(udofs, pdofs, n_scalar_u, fixed, mats):
    """COO assembly over global dofs, then the free rows and columns (scipy sums)."""
    u = (3 * udofs[:, :, None] + np.arange(3)).reshape(len(udofs), -1)
    edofs = u if pdofs is None else np.hstack([u, 3 * n_scalar_u + pdofs])
    n = edofs.shape[1]
    rows, cols = np.repeat(edofs, n, axis=1).ravel(), np.tile(edofs, (1, n)).ravel()
    full = sp.csr_matrix((mats.ravel(), (rows, cols)), shape=(fixed.size,) * 2)
    free = np.flatnonzero(~fixed)
    return full[free][:, free]


@pytest.mark.parametrize("mixed", [False, True])
@pytest.mark.parametrize("offset", [0, 60_000])
def test_pattern_matches_brute_force_assembly(mixed, offset):
    """Random element connectivity; ``offset`` pushes int32 ids past the int32 pair range."""
    rng = np.random.default_rng(3)
    n_scalar_u, n_p, n_el = offset + 40, offset + 12, 30
    udofs = (offset + rng.choice(40, size=(n_el, 10))).astype(np.int32)
    pdofs = (offset + rng.choice(12, size=(n_el, 4))).astype(np.int32) if mixed else None
    fixed = np.zeros(3 * n_scalar_u + (n_p if mixed else 0), dtype=bool)
    fixed[: 3 * offset] = True  # unused dofs below the offset: fixed, out of the matrix
    fixed[3 * offset + rng.choice(120, 15, replace=False)] = True  # some u components
    if mixed:
        fixed[3 * n_scalar_u : 3 * n_scalar_u + offset] = True
    n_loc = 30 + (4 if mixed else 0)
    mats = rng.standard_normal((n_el, n_loc, n_loc))
    pattern = build_pattern(udofs, pdofs, n_scalar_u, fixed)
    expected = _brute_force(udofs, pdofs, n_scalar_u, fixed, mats)
    got = pattern.matrix(mats)
    assert got.shape == expected.shape
    # same sums in another order: round-off only
    assert abs(got - expected).max() <= 1e-12 * abs(expected).max()
    assert got.nnz >= expected.nnz  # every structural entry is stored
