"""A field of view that cuts the body: its edge is not scored as the phantom's surface.

Where the volume's edge cuts the body the extracted surface is that edge. Ingest warned,
but the fit and the validation errors scored it: a perfect model of a 50 mm dome scored
1.62 +- 4.09 mm with the view cut 30 mm off its axis (audit H). Now ingest flags those
vertices ``fov_edge`` and every score leaves them out, as it does the back plate. The
closed form: a model equal to the measured dome where it was seen scores 0 up to the
distance from a vertex to the chords of the simulated triangles (a 5-times subdivided
icosphere of 50 mm: under 0.1 mm).
"""

from __future__ import annotations

import numpy as np
import pytest

from calib.data.measurements import ScanMeasurement
from calib.evaluation import scan_metrics

R_MM = 50.0


def _dome():
    import trimesh

    sph = trimesh.creation.icosphere(subdivisions=5, radius=R_MM)
    v, f = np.array(sph.vertices), np.array(sph.faces)
    open_back = f[(v[f][:, :, 2] >= -1e-9).all(axis=1)]  # the model's surface, no back face
    return v, f, open_back, int(np.argmax(v[:, 2]))


def _measured(v, f, top, cut_x_mm, *, flag: bool):
    m = v.copy()
    m[:, 2] = np.maximum(m[:, 2], 0.0)  # closed: the lower half flattened onto the plate
    m[:, 0] = np.minimum(m[:, 0], cut_x_mm)  # the field of view's edge: a flat cap
    back = m[:, 2] <= 1.5
    edge = (m[:, 0] >= cut_x_mm - 1e-9) & ~back
    return ScanMeasurement(
        name="cut",
        role="validation",
        gravity_ref=np.array([1.0, 0.0, 0.0]),
        vertices_mm=m,
        faces=f,
        back_plate=back,
        nipple_mm=m[top],
        tumour_mm=None,
        back_point_mm=np.zeros(3),
        back_normal=np.array([0.0, 0.0, -1.0]),
        T_ref_from_scan=np.eye(4),
        fov_edge=edge if flag else None,
    )


def test_the_edge_of_a_cut_field_of_view_is_not_scored():
    v, f, model_faces, top = _dome()
    unflagged = _measured(v, f, top, 30.0, flag=False)
    flagged = _measured(v, f, top, 30.0, flag=True)
    assert flagged.fov_edge.sum() > 100  # the cap holds many vertices
    bad = scan_metrics(unflagged, v, model_faces, top, None).surface_error_mm["fiducial"]
    good = scan_metrics(flagged, v, model_faces, top, None).surface_error_mm["fiducial"]
    assert bad["mean"] > 1.0  # the cap scored as surface (audit H: 1.62 mm)
    assert good["n"] == int(flagged.scored.sum()) == bad["n"] - int(flagged.fov_edge.sum())
    assert good["max"] < 0.1  # the chord error of the model's triangles (module docstring)
    # the fit's points leave the edge out too
    pts = flagged.surface_points(max_points=10**6)
    assert len(pts) == good["n"] and (pts[:, 0] < 30.0 - 1e-9).all()


def test_an_uncut_scan_scores_every_vertex_off_the_plate():
    v, f, model_faces, top = _dome()
    scan = _measured(v, f, top, 2 * R_MM, flag=False)
    assert scan.fov_edge is None and (scan.scored == ~scan.back_plate).all()
    err = scan_metrics(scan, v, model_faces, top, None).surface_error_mm["fiducial"]
    assert err["n"] == int((~scan.back_plate).sum()) and err["max"] < 0.1


def test_a_cut_reference_scan_is_refused_before_meshing():
    # the model's geometry is the reference scan's surface: a cut one would mesh the
    # volume's edge as the phantom (the other scans only lose the edge's points)
    import fem
    from calib.model.reference import reference_mesh

    v, f, _, top = _dome()
    with pytest.raises(fem.MeshError, match=r"reference scan 'cut': the field of view cuts"):
        reference_mesh(_measured(v, f, top, 30.0, flag=True), size_mm=12.0)
