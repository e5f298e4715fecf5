"""Surface metrics (exact distances, F-score, normals, area ratio), error by part and hidden surface."""

from __future__ import annotations

import math

import igl
import numpy as np
import pytest
import torch

from meshmei.errors import MeshError
from meshmei.metrics import error_by_part, face_components, hidden_surface, surface_metrics

from conftest import grid_sheet, icosphere


def _offset_sheets(delta):
    V, F = grid_sheet(11, 11)
    V2 = V.clone()
    V2[:, 2] += delta
    return V, F, V2


def test_surface_metrics_of_parallel_sheets_are_exact():
    V, F, V2 = _offset_sheets(0.003)
    m = surface_metrics(V2, F, V, F, n_samples=5000)
    # every point of either sheet is exactly delta from the other
    assert m.chamfer_l2 == pytest.approx(2 * 0.003**2, rel=1e-9)
    assert m.accuracy == pytest.approx(0.003**2, rel=1e-9)
    assert m.hausdorff == pytest.approx(0.003, rel=1e-9)
    assert m.fscore == 1.0  # delta < 1 % of the diagonal sqrt(2)
    assert m.normal_consistency == pytest.approx(1.0)
    assert m.self_intersections == 0 and m.degenerate_faces == 0 and m.inverted_faces == 0
    # right isosceles triangles: 4 sqrt(3) (h^2 / 2) / (h^2 + h^2 + 2 h^2) = sqrt(3) / 2; a 10 x 10 grid's rim
    assert m.min_quality == pytest.approx(np.sqrt(3) / 2, rel=1e-12)
    assert (m.boundary_edges, m.nonmanifold_edges, m.watertight) == (40, 0, False)
    V, F, V3 = _offset_sheets(0.02)
    m3 = surface_metrics(V3, F, V, F, n_samples=2000)
    assert m3.fscore == 0.0 and m3.precision == 0.0


def test_surface_metrics_identity_seed_and_flipped_orientation():
    V, F = icosphere(2)
    m = surface_metrics(V, F, V, F, n_samples=20_000)
    assert m.chamfer_l2 < 1e-25 and m.fscore == 1.0 and m.normal_consistency == pytest.approx(1.0)
    assert (m.boundary_edges, m.nonmanifold_edges, m.watertight) == (0, 0, True)
    l2 = (V[F] - V[F[:, [1, 2, 0]]]).pow(2).sum(-1).sum(-1)  # summed squared edge lengths
    assert m.min_quality == pytest.approx(float((2 * np.sqrt(3) * igl.doublearea(V.numpy(), F.numpy()) / l2.numpy()).min()),
                                          rel=1e-12)
    fin = surface_metrics(V, torch.cat([F, F[:1]]), V, F, n_samples=1000)  # a face twice: its edges used 3 times
    assert (fin.boundary_edges, fin.nonmanifold_edges, fin.watertight) == (0, 3, False)
    Vs = V * 1.01
    a = surface_metrics(Vs, F, V, F, n_samples=5000, seed=3)
    b = surface_metrics(Vs, F, V, F, n_samples=5000, seed=3)
    assert a == b
    assert 0 < a.chamfer_l2 < 2 * 0.01**2
    flipped = surface_metrics(V, F[:, [0, 2, 1]], V, F, n_samples=1000, health=False)
    assert flipped.inverted_faces == F.shape[0]
    assert flipped.normal_consistency == pytest.approx(1.0)  # unsigned
    assert flipped.self_intersections is None


def test_surface_metrics_errors():
    V, F = icosphere(0)
    with pytest.raises(MeshError):
        surface_metrics(V, F, torch.full((3, 3), float("nan")), torch.tensor([[0, 1, 2]]))
    with pytest.raises(ValueError, match="n_samples"):
        surface_metrics(V, F, V, F, n_samples=0)
    with pytest.raises(MeshError, match="zero area"):
        surface_metrics(V, F, torch.zeros(3, 3), torch.tensor([[0, 1, 2]]))


def test_error_by_part_charges_each_piece_and_adds_up():
    # Target: two unit spheres far apart (two pieces). Mesh: the first sphere exactly, the second scaled
    # by 1.05 about its centre, so all error belongs to the second piece.
    Vs, Fs = icosphere(3)
    n = Vs.shape[0]
    Vt = torch.cat([Vs, Vs + torch.tensor([5.0, 0, 0], dtype=Vs.dtype)])
    Ft = torch.cat([Fs, Fs + n])
    V = Vt.clone()
    V[n:] = 1.05 * Vs + torch.tensor([5.0, 0, 0], dtype=Vs.dtype)
    parts = error_by_part(V, Ft, Vt, Ft, n_samples=20_000)
    total = surface_metrics(V, Ft, Vt, Ft, n_samples=20_000, health=False)
    assert len(parts) == 2 and sum(p["faces"] for p in parts) == Ft.shape[0]
    assert sum(p["area_share"] for p in parts) == pytest.approx(1.0, abs=1e-12)
    assert sum(p["accuracy"] for p in parts) == pytest.approx(total.accuracy, rel=1e-9)
    assert sum(p["completeness"] for p in parts) == pytest.approx(total.completeness, rel=1e-9)
    exact, scaled = sorted(parts, key=lambda p: p["bbox_min"][0])
    assert exact["accuracy"] < 1e-20 and exact["completeness"] < 1e-20
    # the scaled sphere holds 1.05^2 / (1 + 1.05^2) of the mesh's area and its samples lie 0.05 times
    # their face-plane distance (0.98-1 on this icosphere) off the target: mean square about 0.05^2
    assert scaled["accuracy"] == pytest.approx(1.05**2 / (1 + 1.05**2) * 0.05**2, rel=0.03)


def test_hidden_surface_of_two_overlapping_spheres():
    # Two unit spheres with centres 1 apart: each has the cap of height 1/2 inside the other, a quarter
    # of its area (a cap's area is 2 pi r h). A single sphere hides nothing.
    Vs, Fs = icosphere(4)
    n = Vs.shape[0]
    V = torch.cat([Vs, Vs + torch.tensor([1.0, 0, 0], dtype=Vs.dtype)])
    F = torch.cat([Fs, Fs + n])
    out = hidden_surface(V, F, n_samples=20_000)
    assert out["fraction"] == pytest.approx(0.25, abs=0.01)
    assert out["hidden"].shape == (20_000,) and out["points"].shape == (20_000, 3)
    hidden_pts = out["points"][out["hidden"]]
    # hidden points of the first sphere lie in x > 0.5, of the second in x < 0.5; all within both balls
    r0 = np.linalg.norm(hidden_pts, axis=1)
    r1 = np.linalg.norm(hidden_pts - np.array([1.0, 0, 0]), axis=1)
    assert np.all(np.minimum(r0, r1) < 1.0) and np.all(np.maximum(r0, r1) > 0.97)
    # completeness: the squared distance from each hidden sample to the nearest visible one, summed and
    # divided by all samples (the docs' definition), against a brute-force search (the old bound let a mean
    # over the hidden samples alone, 4x larger, pass; review)
    from scipy.spatial.distance import cdist

    small = hidden_surface(V, F, n_samples=4000)
    Q, h = small["points"], small["hidden"]
    assert small["completeness"] == pytest.approx((cdist(Q[h], Q[~h]).min(1) ** 2).sum() / len(Q), rel=1e-9)
    # an inside-out sphere: no sample is inside the solid on both sides (the outer side's test alone called
    # every sample hidden)
    assert hidden_surface(Vs, Fs[:, [0, 2, 1]], n_samples=2000)["fraction"] == 0.0
    alone = hidden_surface(Vs, Fs, n_samples=5000)
    assert alone["fraction"] == 0.0 and alone["completeness"] == 0.0


def test_face_components_labels_pieces_that_share_no_vertex():
    Vs, Fs = icosphere(1)
    n = Vs.shape[0]
    # two spheres, faces interleaved, plus an unreferenced vertex at the end
    F = torch.stack([Fs, Fs + n], 1).reshape(-1, 3)
    labels = face_components(F, 2 * n + 1)
    assert labels.shape == (F.shape[0],) and set(labels.tolist()) == {0, 1}
    assert (labels[0::2] == labels[0]).all() and (labels[1::2] == labels[1]).all() and labels[0] != labels[1]
    # one face bridging the two spheres makes them one piece
    bridged = torch.cat([F, torch.tensor([[0, n, 1]])])
    assert set(face_components(bridged, 2 * n + 1).tolist()) == {0}


def test_surface_metrics_area_ratio():
    V, F = icosphere(2)
    assert surface_metrics(V, F, V, F, n_samples=500, health=False).area_ratio == pytest.approx(1.0, rel=1e-12)
    # twice the size, four times the area, whatever the target's orientation
    assert surface_metrics(2 * V, F, V, F[:, [0, 2, 1]], n_samples=500, health=False).area_ratio == pytest.approx(
        4.0, rel=1e-12)


def test_surface_metrics_ignore_vertices_the_target_faces_do_not_use():
    V, F = icosphere(2)
    Vm = 1.02 * V  # the mesh evaluated, a little off the target
    Vt_unused = torch.cat([V, torch.tensor([[50.0, 50.0, 50.0]], dtype=V.dtype)])
    plain = surface_metrics(Vm, F, V, F, n_samples=500)
    assert plain.threshold == pytest.approx(0.01 * float((V.max(0).values - V.min(0).values).norm()))
    assert surface_metrics(Vm, F, Vt_unused, F, n_samples=500) == plain


def test_surface_metrics_tell_the_two_directions_apart():
    """The mesh is the left half of the target sheet (in its plane): every mesh point lies on the target
    (accuracy 0, precision 1), while target points on the right half lie x - 1/2 from the mesh: completeness
    E[d^2] = 1/2 * E[t^2], t uniform on [0, 1/2], = 1/24; recall = 1/2 + tau; Hausdorff 1/2. Swapping
    precision and recall, or taking either direction for both, fails (review: every earlier case was
    symmetric)."""
    V, F = grid_sheet(21, 21)  # [0, 1]^2
    half = V.clone()
    half[:, 0] *= 0.5
    m = surface_metrics(half, F, V, F, n_samples=40_000)
    assert m.accuracy < 1e-25 and m.precision == 1.0
    assert m.completeness == pytest.approx(1 / 24, rel=0.03)
    assert m.chamfer_l2 == pytest.approx(m.accuracy + m.completeness, rel=1e-12)
    assert m.threshold == pytest.approx(0.01 * np.sqrt(2), rel=1e-12)
    assert m.recall == pytest.approx(0.5 + m.threshold, abs=0.01)
    assert m.fscore == pytest.approx(2 * m.recall / (1 + m.recall), rel=1e-12)
    assert m.hausdorff == pytest.approx(0.5, rel=0.01)
    assert m.area_ratio == pytest.approx(0.5, rel=1e-12)


def test_surface_metrics_count_health_defects_that_are_there():
    """Every earlier expectation of self_intersections, degenerate_faces and inverted_faces was 0 or None
    (hard-coding 0 passed; review). Half the faces of a sphere turned over are inverted against the sphere;
    two crossing triangles and a collinear one give one pair and one degenerate face."""
    V, F = icosphere(2)
    half = F.clone()
    half[: len(F) // 2] = half[: len(F) // 2][:, [0, 2, 1]]
    assert surface_metrics(V, half, V, F, n_samples=2000).inverted_faces == len(F) // 2
    W = torch.tensor([[-1, -1, 0], [1, -1, 0], [0, 1, 0], [0, -1, -1], [0, 1, -1], [0, 0, 1],
                      [5, 0, 0], [6, 0, 0], [7, 0, 0]], dtype=torch.float64)  # A, B through A, a segment
    T = torch.tensor([[0, 1, 2], [3, 4, 5], [6, 7, 8]])
    m = surface_metrics(W, T, W, T, n_samples=2000)
    assert (m.self_intersections, m.degenerate_faces) == (1, 1)


def test_face_components_and_hidden_surface_check_their_arguments():
    V, F = icosphere(1)
    n = V.shape[0]
    assert face_components(F, n).tolist() == [0] * F.shape[0]
    for faces, count, error, says in [(F, 2, MeshError, f"F holds vertex index {n - 1}, but n_vertices is 2"),
                                      (F.double(), n, MeshError, "integer dtype"),
                                      ([[0, 1, 2, 3]], n, MeshError, "shape \\(1, 4\\)"),
                                      (F, "4", ValueError, "n_vertices must be a positive integer"),
                                      (-F, n, MeshError, "negative vertex index")]:
        with pytest.raises(error, match=says):
            face_components(faces, count)
    for offset in (0, -1, math.inf):  # offset 0 reported 0.46 of a convex surface as hidden
        with pytest.raises(ValueError, match="offset must be positive and finite"):
            hidden_surface(V, F, n_samples=100, offset=offset)
    with pytest.raises(ValueError, match="offset must be below 0.1"):
        hidden_surface(V, F, n_samples=100, offset=0.5)
