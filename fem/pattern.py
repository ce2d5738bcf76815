"""Sparsity pattern of the reduced (free-dof) matrix and the scatter map into it.

Unknowns come in blocks: a displacement node carries 3 dofs (``3 k + c``), a pressure
node 1 (after all displacement dofs). Two elements that share a pair of blocks share
its whole dof block, so the pattern is found on block pairs (``(3 A + B)^2 / (A + B)^2``
times fewer keys than dof pairs, about 6x for Taylor-Hood) and expanded afterwards.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

__all__ = ["Pattern", "build_pattern"]


@dataclass(frozen=True)
class Pattern:
    """CSR structure of the reduced (free-dof) matrix and the scatter map into it."""

    indptr: np.ndarray
    indices: np.ndarray
    keys: np.ndarray  # sorted row * n_free + col of every stored entry
    slot: np.ndarray  # data slot of every (element, local row, local col) entry
    n_free: int  # entries of fixed rows or columns go to the extra slot len(keys)

    def matrix(self, element_matrices: np.ndarray) -> sp.csr_matrix:
        """Sum element matrices ``(E, n, n)`` into the reduced CSR matrix."""
        n = len(self.keys)
        data = np.bincount(self.slot, weights=element_matrices.reshape(-1), minlength=n + 1)
        return sp.csr_matrix((data[:n], self.indices, self.indptr), shape=(self.n_free,) * 2)


def build_pattern(
    udofs: np.ndarray, pdofs: np.ndarray | None, n_scalar_u: int, fixed: np.ndarray
) -> Pattern:
    """Pattern of the free-dof matrix for element dofs ordered u (node-major), then p.

    Parameters
    ----------
    udofs : ndarray, shape (E, Au)
        Scalar displacement dofs of each element.
    pdofs : ndarray, shape (E, Ap), or None
        Pressure dofs of each element (mixed formulations).
    n_scalar_u : int
        Number of scalar displacement dofs (3 unknowns each).
    fixed : ndarray of bool, shape (n_dofs,)
        Dirichlet dofs of the full vector, excluded from the matrix.
    """
    blocks = udofs if pdofs is None else np.hstack([udofs, n_scalar_u + pdofs])
    blocks = blocks.astype(np.int64)  # pair keys reach n_blocks^2: beyond int32 at ~46k
    n_blocks = n_scalar_u + (0 if pdofs is None else int(pdofs.max()) + 1)
    pairs, inverse = np.unique(
        (blocks[:, :, None] * n_blocks + blocks[:, None, :]).ravel(), return_inverse=True
    )
    expanded = _expand(pairs, n_blocks, n_scalar_u, fixed)
    local_block, local_comp, local_size = _local_layout(udofs.shape[1], blocks.shape[1])
    # CSR slot of entry k of each block pair, as a (pairs, 9) table; fixed or absent
    # entries point to the extra slot len(keys)
    keys, n_free = expanded["keys"], expanded["n_free"]
    table = np.full((len(pairs), 9), len(keys), dtype=np.int64)
    table[expanded["pair_of"], expanded["k"]] = expanded["rank"]
    nb = blocks.shape[1]
    inv = inverse.reshape(-1, nb, nb) * 9
    offset = local_comp[:, None] * local_size[None, :] + local_comp[None, :]
    pick = inv[:, local_block[:, None], local_block[None, :]] + offset  # (E, n_loc, n_loc)
    slot = table.ravel()[pick.ravel()]
    indptr = np.searchsorted(keys // n_free, np.arange(n_free + 1)).astype(np.int64)
    return Pattern(indptr, (keys % n_free).astype(np.int64), keys, slot, n_free)


def _block_size(b: np.ndarray, n_scalar_u: int) -> np.ndarray:
    return np.where(b < n_scalar_u, 3, 1)


def _block_dof(b: np.ndarray, comp: np.ndarray, n_scalar_u: int) -> np.ndarray:
    return np.where(b < n_scalar_u, 3 * b + comp, 2 * n_scalar_u + b)


def _expand(pairs: np.ndarray, n_blocks: int, n_scalar_u: int, fixed: np.ndarray) -> dict:
    """Dof entries of every block pair, their sorted free keys and each one's CSR rank."""
    br, bc = np.divmod(pairs, n_blocks)
    sc = _block_size(bc, n_scalar_u)
    count = _block_size(br, n_scalar_u) * sc
    base = np.concatenate([[0], np.cumsum(count)[:-1]])
    pair_of = np.repeat(np.arange(len(pairs)), count)
    ci, cj = np.divmod(np.arange(pair_of.size) - base[pair_of], sc[pair_of])
    free_index = np.full(fixed.size, -1, dtype=np.int64)
    n_free = int((~fixed).sum())
    free_index[~fixed] = np.arange(n_free)
    fr = free_index[_block_dof(br[pair_of], ci, n_scalar_u)]
    fc = free_index[_block_dof(bc[pair_of], cj, n_scalar_u)]
    keep = np.flatnonzero((fr >= 0) & (fc >= 0))
    keys = fr[keep] * n_free + fc[keep]
    order = np.argsort(keys)
    rank = np.full(pair_of.size, keys.size, dtype=np.int64)  # fixed: the extra slot
    rank[keep[order]] = np.arange(order.size)
    k = ci * sc[pair_of] + cj
    return {"keys": keys[order], "rank": rank, "pair_of": pair_of, "k": k, "n_free": n_free}


def _local_layout(n_u_nodes: int, n_blocks: int):
    """Per local dof: its local block, component within the block, and that block's size."""
    n_p = n_blocks - n_u_nodes
    block = np.concatenate([np.repeat(np.arange(n_u_nodes), 3), n_u_nodes + np.arange(n_p)])
    comp = np.concatenate([np.tile(np.arange(3), n_u_nodes), np.zeros(n_p, dtype=int)])
    size = np.where(block < n_u_nodes, 3, 1)
    return block, comp, size
