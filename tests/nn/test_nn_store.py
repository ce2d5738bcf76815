"""nn reads the sweep store through its documented format, and refuses broken stores."""

from __future__ import annotations

import logging
import re
import shutil

import numpy as np
import pytest

import nn
from nn.data import StoreFormatError


def test_reads_every_solved_scenario(box_sweep, box_data):
    d = box_data
    assert len(d) == 94 and np.sum(d.role == "train") == 46 and np.sum(d.role == "validation") == 48
    assert d.displacement_mm.shape == (94, len(d.nodes_mm), 3)
    assert set(np.unique(d.plane)) == {"transverse", "sagittal"}
    # the load the solution depends on: rho g gravity_ref / c1 (1/m)
    rho, g = d.model["density_kg_m3"], d.model["g_m_s2"]
    assert np.allclose(d.load_per_m, rho * g * d.gravity_ref / d.c1_pa[:, None], rtol=1e-14)
    # gravity_ref = R_ref_from_phantom @ gravity_phantom
    R = np.asarray(d.model["R_ref_from_phantom"])
    assert np.allclose(d.gravity_ref, d.gravity_phantom @ R.T, atol=1e-15)
    # the clamped back does not move; the surface set excludes it
    assert np.all(d.displacement_mm[:, d.back_nodes] == 0.0)
    assert not set(d.back_nodes) & set(d.surface_nodes)
    assert d.has_tumour


def test_store_matches_its_documentation(box_sweep):
    """Every array of the format table in calib.sweep.store exists with the stated rank."""
    import zarr

    import calib.sweep.store as store

    rows = re.findall(r"^``([a-z_]+/[a-z_]+)``\s+\(([^)]*)\)\s+(\w+)", store.__doc__, flags=re.M)
    assert len(rows) >= 20
    g = zarr.open_group(box_sweep, mode="r")
    for path, shape, dtype in rows:
        rank = len([s for s in shape.split(",") if s.strip()])
        assert g[path].ndim == rank, path
        assert g[path].dtype == np.dtype(dtype), (path, g[path].dtype)  # review BF
    assert g.attrs["convergence_columns"] == list(store.CONVERGENCE_COLUMNS)


def test_the_readme_s_table_lists_every_array_of_a_store(box_sweep):
    # review BF: the README's copy of the contract is what other readers follow; only the
    # docstring's was checked
    from pathlib import Path

    import zarr

    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    section = readme.split("### The sweep store — public contract")[1].split("\n## ")[0]
    documented, group = set(), None
    for cell in re.findall(r"^\| (`[^|]+`) \|", section, flags=re.M):
        for name in re.findall(r"`([^`]+)`", cell):  # `scenarios/role`, `plane`: one group
            group, name = name.split("/") if "/" in name else (group, name)
            documented.add(f"{group}/{name}")
    g = zarr.open_group(box_sweep, mode="r")
    written = {f"{k}/{a}" for k in ("mesh", "scenarios", "results") for a in g[k].array_keys()}
    assert documented == written
    assert set(g.group_keys()) == {"mesh", "scenarios", "results"}
    # its "Types:" paragraph (review BH): the int64 and int8 arrays it names, float64 the rest
    types = section.split("Types:")[1]
    named = {}
    for kind, text in zip(("int64", "int8"), re.split(r" int64;| int8 ", types)[:2], strict=True):
        for name in re.findall(r"`([^`]+)`", text):
            group, name = name.split("/") if "/" in name else (group, name)
            named[f"{group}/{name}"] = kind
    for path in written:
        kind = named.get(path, "float64")
        assert g[path].dtype == np.dtype(kind), (path, g[path].dtype, kind)


def _copy(src, tmp_path):
    dst = tmp_path / "copy"
    shutil.copytree(src, dst)
    return dst


def test_truncated_store_names_the_file(box_sweep, tmp_path):
    s = _copy(box_sweep, tmp_path)
    chunk = s / "results" / "displacement_mm" / "c" / "5" / "0" / "0"
    chunk.unlink()
    with pytest.raises(StoreFormatError, match=r"results/displacement_mm/c/5/0/0.*truncated"):
        nn.load_sweep(s)
    (s / "results" / "tumour_mm" / "zarr.json").unlink()
    with pytest.raises(StoreFormatError, match=r"results/tumour_mm/zarr\.json not found"):
        nn.load_sweep(s)
    (s / "zarr.json").unlink()
    with pytest.raises(StoreFormatError, match=r"zarr\.json not found"):
        nn.load_sweep(s)
    with pytest.raises(StoreFormatError, match="no such sweep store"):
        nn.load_sweep(tmp_path / "nowhere")


def test_a_lost_tumour_chunk_or_a_corrupt_chunk_is_named(box_sweep, tmp_path):
    # review AD: a lost tumour chunk made a model with a tumour one without (train exited
    # 0 with no tumour output); a corrupt chunk gave the codec's words only
    s = _copy(box_sweep, tmp_path / "a")
    (s / "results" / "tumour_mm" / "c" / "7" / "0").unlink()
    with pytest.raises(StoreFormatError, match=r"results/tumour_mm/c/7/0: missing or not finite"):
        nn.load_sweep(s)
    s = _copy(box_sweep, tmp_path / "c")
    (s / "results" / "nipple_mm" / "c" / "3" / "0").unlink()  # review BF: it named no file
    with pytest.raises(StoreFormatError, match=r"results/nipple_mm/c/3/0: missing or not finite"):
        nn.load_sweep(s)
    s = _copy(box_sweep, tmp_path / "b")
    chunk = s / "results" / "displacement_mm" / "c" / "5" / "0" / "0"
    chunk.write_bytes(chunk.read_bytes()[:17])
    with pytest.raises(StoreFormatError, match=r"results/displacement_mm/c/5/0/0: unreadable"):
        nn.load_sweep(s)


@pytest.mark.parametrize(
    "edit, says",
    [
        (lambda g: g["scenarios/load_per_m"].__setitem__(4, np.nan), r"load_per_m: not finite at"),
        (lambda g: g["scenarios/role"].__setitem__(4, -1), r"scenarios/role: codes outside 0\.\.1"),
        (lambda g: g["mesh/surface_nodes"].__setitem__(0, 10**6), r"surface_nodes: node indices"),
        (lambda g: g.attrs.__setitem__("model", {"c1_pa": 420.0}), r"`model` block lacks density"),
        # review BF: an index past the mesh was an IndexError traceback in training; a
        # newer store said what it was but not what to do
        (
            lambda g: g.attrs.__setitem__("model", g.attrs["model"] | {"nipple_node": 10**6}),
            r"zarr\.json: model\.nipple_node 1000000 must be an integer node index below the "
            r"store's \d+ nodes",
        ),
        (
            lambda g: g.attrs.__setitem__("format_version", 2),
            r"zarr\.json: format version 2; this reader knows 1 \(written by a newer "
            r"phantom-calib: upgrade it to read this store\)",
        ),
        (lambda g: g.attrs.__setitem__("format_version", "1"), r"format version '1'; this reader"),
        (lambda g: g.attrs.__setitem__("format_version", True), r"format version True; this"),
        (lambda g: g.attrs.__delitem__("n_scenarios"), r"root attributes lack n_scenarios"),
        (lambda g: g["results/status"].__setitem__(2, 7), r"status: codes outside 0\.\.2"),
    ],
)
def test_scenarios_and_mesh_sets_are_checked(box_sweep, tmp_path, edit, says):
    # review AD: a NaN load gave LAPACK's "SVD did not converge", a role -1 was read as
    # validation, an out-of-range node set and a store without its model block tracebacks
    import zarr

    s = _copy(box_sweep, tmp_path)
    edit(zarr.open_group(s, mode="r+"))
    with pytest.raises(StoreFormatError, match=says):
        nn.load_sweep(s)


def test_store_of_another_mesh_is_refused(box_sweep, tmp_path):
    import zarr

    s = _copy(box_sweep, tmp_path)
    g = zarr.open_group(s, mode="r+")
    g["mesh/nodes_mm"][0] = g["mesh/nodes_mm"][0] + 1.0  # results from another geometry
    with pytest.raises(StoreFormatError, match=r"mesh_sha256 \(a store mixed from another mesh"):
        nn.load_sweep(s)


def test_pending_scenarios(box_sweep, tmp_path, caplog):
    import zarr

    s = _copy(box_sweep, tmp_path)
    zarr.open_group(s, mode="r+")["results/status"][3] = 0  # as if never solved
    with pytest.raises(StoreFormatError, match="1 of 94 scenarios pending"):
        nn.load_sweep(s, allow_pending=False)
    with caplog.at_level(logging.WARNING):
        d = nn.load_sweep(s)
    assert len(d) == 93 and 3 not in d.index and "pending" in caplog.text
