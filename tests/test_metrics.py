"""Sampling, Chamfer distance (against brute force), the multi-level point index, surface metrics and health."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from meshmei.errors import MeshError
from meshmei.metrics import (PointIndex, chamfer_distance, mesh_health, nearest_neighbors, sample_points,
                             surface_metrics)

from conftest import grid_sheet, icosphere


def _brute_chamfer(P, Q):
    D = torch.cdist(P, Q) ** 2
    return D.min(1).values.mean() + D.min(0).values.mean()


def two_triangles():
    # areas 0.5 and 1.5 (the second three times the first), in z = 0
    V = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [3, 0, 0], [3, 1, 0], [6, 0, 0]], dtype=torch.float64)
    F = torch.tensor([[0, 1, 2], [3, 5, 4]])
    return V, F


def test_samples_lie_on_their_faces_and_are_seeded():
    V, F = icosphere(1)
    P, N, face = sample_points(V, F, 3000, generator=7, return_normals=True, return_faces=True)
    assert P.shape == (3000, 3) and N.shape == (3000, 3) and face.dtype == torch.int64
    # barycentric coordinates of each point in its face are non-negative and sum to one
    T = V[F[face]]
    A = torch.stack([T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]], dim=2)  # (n, 3, 2)
    uv = torch.linalg.lstsq(A, (P - T[:, 0]).unsqueeze(-1)).solution.squeeze(-1)
    torch.testing.assert_close(torch.bmm(A, uv.unsqueeze(-1)).squeeze(-1), P - T[:, 0])
    assert float(uv.min()) >= -1e-12 and float(uv.sum(1).max()) <= 1 + 1e-12
    torch.testing.assert_close(N.norm(dim=1), torch.ones(3000, dtype=V.dtype))
    P2 = sample_points(V, F, 3000, generator=7)
    assert torch.equal(P, P2)
    g = torch.Generator().manual_seed(7)
    assert torch.equal(sample_points(V, F, 3000, generator=g), P)
    assert not torch.equal(sample_points(V, F, 3000, generator=8), P)


def test_samples_are_uniform_by_area():
    V, F = two_triangles()
    n = 40_000
    P, face = sample_points(V, F, n, generator=0, return_faces=True)
    frac = float((face == 0).double().mean())
    sd = (0.25 * 0.75 / n) ** 0.5
    assert abs(frac - 0.25) < 4 * sd
    # uniform inside a face: the fraction of face 0's samples with x < 0.5 is 3/4 of its area
    x = P[face == 0, 0]
    assert abs(float((x < 0.5).double().mean()) - 0.75) < 0.02


def test_sample_gradients_reach_vertices():
    V, F = icosphere(1)
    V = V.clone().requires_grad_(True)
    P, face = sample_points(V, F, 500, generator=1, return_faces=True)
    P.sum().backward()
    # each sample is an affine combination of its face's corners: the weights per sample sum to one
    torch.testing.assert_close(V.grad.sum(0), torch.full((3,), 500.0, dtype=V.dtype))
    used = torch.zeros(V.shape[0], dtype=torch.bool)
    used[F[face].reshape(-1)] = True
    assert bool((V.grad[~used] == 0).all())


def test_sample_edge_cases():
    V, F = icosphere(0)
    P = sample_points(V, F, 0)
    assert P.shape == (0, 3)
    with pytest.raises(MeshError, match="zero area"):
        sample_points(torch.zeros(3, 3), torch.tensor([[0, 1, 2]]), 10)
    with pytest.raises(ValueError, match="non-negative integer"):
        sample_points(V, F, -1)
    with pytest.raises(MeshError):
        sample_points(V, torch.tensor([[0, 1, 99]]), 10)
    with pytest.raises(TypeError, match="generator"):
        sample_points(V, F, 5, generator="seed")
    # finite float32 coordinates whose squares overflow: torch.multinomial used to stop on an Inf weight
    with pytest.raises(MeshError, match=r"face areas overflow torch.float32 \(largest coordinate \S+e\+19, shape \(12, 3\)\)"):
        sample_points(V.float() * 1e20, F, 5)
    assert torch.isfinite(sample_points(V * 1e20, F, 5)).all()  # float64 has the range


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_chamfer_matches_brute_force_in_value_and_gradient(dtype):
    g = torch.Generator().manual_seed(0)
    P = torch.rand(300, 3, generator=g, dtype=dtype).requires_grad_(True)
    Q = (torch.rand(200, 3, generator=g, dtype=dtype) + 0.2).requires_grad_(True)
    cd = chamfer_distance(P, Q)
    ref = _brute_chamfer(P, Q)
    torch.testing.assert_close(cd, ref)
    gP, gQ = torch.autograd.grad(cd, [P, Q])
    rP, rQ = torch.autograd.grad(ref, [P, Q])
    torch.testing.assert_close(gP, rP)
    torch.testing.assert_close(gQ, rQ)
    a, b = chamfer_distance(P, Q, return_directions=True)
    torch.testing.assert_close(a + b, cd)
    D = torch.cdist(P, Q) ** 2
    torch.testing.assert_close(a, D.min(1).values.mean())


def test_chamfer_with_a_prebuilt_tree_and_errors():
    from scipy.spatial import cKDTree

    P, Q = torch.rand(50, 3, dtype=torch.float64), torch.rand(80, 3, dtype=torch.float64)
    tree = cKDTree(Q.numpy())
    torch.testing.assert_close(chamfer_distance(P, Q, Q_tree=tree), _brute_chamfer(P, Q))
    assert float(chamfer_distance(P, P)) == 0.0
    with pytest.raises(ValueError, match="empty"):
        chamfer_distance(torch.zeros(0, 3), Q)
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        chamfer_distance(torch.zeros(4, 2), Q)
    with pytest.raises(ValueError, match="tree holds"):
        nearest_neighbors(P, Q[:10], tree=tree)


def test_point_index_is_exact_near_and_close_to_exact_far():
    V, F = icosphere(3)
    Q = sample_points(V, F, 50_000, generator=0)
    index = PointIndex(Q, min_points=1000)
    assert len(index.sizes) >= 3
    near = sample_points(V, F, 2000, generator=1) * 1.001
    torch.testing.assert_close(torch.from_numpy(index.query(near)), nearest_neighbors(near, Q), rtol=0, atol=0)
    far = torch.randn(2000, 3, dtype=V.dtype, generator=torch.Generator().manual_seed(2))
    far = far / far.norm(dim=1, keepdim=True) * (1.2 + torch.rand(2000, 1, dtype=V.dtype))
    best = (far - Q[nearest_neighbors(far, Q)]).norm(dim=1)
    exact = nearest_neighbors(near, Q)
    # the search order follows the last call (bounded finest search after near queries, levels first after
    # far ones): both orders give exact answers near and close answers far
    for queries, near_first in ((far, None), (far, None), (near, None), (near, None), (far, None), (near, False),
                                (far, True)):
        got = torch.from_numpy(index.query(queries, near_first=near_first))
        if queries is near:
            assert torch.equal(got, exact) and index.far_share == 0.0
        else:
            assert float(((far - Q[got]).norm(dim=1) / best).max()) < 1.5 and index.far_share > 0.9
    with pytest.raises(ValueError):
        PointIndex(np.zeros((0, 3)))


def test_point_index_on_duplicated_points_stays_exact_near():
    # every point twice (as a mesh's seams or an STL file's vertices give them): the spacing estimate was
    # 0, so no answer was exact and near queries got points of the coarsest level, up to 20x too far
    V, F = icosphere(3)
    Q = sample_points(V, F, 20_000, generator=0)
    Qd = torch.cat([Q, Q])[torch.randperm(40_000, generator=torch.Generator().manual_seed(1))]
    index = PointIndex(Qd, min_points=1000)
    assert index.exact_within > 0
    near = sample_points(V, F, 2000, generator=1) * 1.001
    got = torch.from_numpy(index.query(near))
    want = nearest_neighbors(near, Qd)
    assert torch.equal((near - Qd[got]).norm(dim=1), (near - Qd[want]).norm(dim=1))
    # a single distinct point: every answer is that point, exactly
    assert PointIndex(np.zeros((10, 3))).exact_within == np.inf


def test_point_index_rejects_bad_input():
    Q = np.random.default_rng(0).normal(size=(100, 3))
    for kw, msg in (({"factor": 1}, "factor must be an integer of at least 2, got 1"),  # used to loop forever
                    ({"min_points": 0}, "min_points must be an integer of at least 1, got 0"),  # so did this
                    ({"exact_within": 0.0}, "exact_within must be positive, got 0.0"),
                    ({"exact_within": float("nan")}, "exact_within must be positive, got nan")):
        with pytest.raises(ValueError, match=msg):
            PointIndex(Q, **kw)
    bad = Q.copy()
    bad[7, 1] = np.nan
    with pytest.raises(ValueError, match=r"Q holds NaN or Inf \(1 of 100 points, first at index 7\)"):
        PointIndex(bad)
    with pytest.raises(ValueError, match=r"P holds NaN or Inf \(1 of 100 points, first at index 7\)"):
        PointIndex(Q).query(bad)
    with pytest.raises(ValueError, match=r"P must be an \(n, 3\) point array, got shape \(5, 2\)"):
        PointIndex(Q).query(np.zeros((5, 2)))


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
    V, F, V3 = _offset_sheets(0.02)
    m3 = surface_metrics(V3, F, V, F, n_samples=2000)
    assert m3.fscore == 0.0 and m3.precision == 0.0


def test_surface_metrics_identity_seed_and_flipped_orientation():
    V, F = icosphere(2)
    m = surface_metrics(V, F, V, F, n_samples=20_000)
    assert m.chamfer_l2 < 1e-25 and m.fscore == 1.0 and m.normal_consistency == pytest.approx(1.0)
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


def test_mesh_health_counts():
    # two triangles crossing each other, one degenerate triangle, none sharing vertices
    V = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0],
                      [0.2, 0.2, -0.5], [0.2, 0.2, 0.5], [0.8, -0.5, 0.0],
                      [5, 5, 5], [6, 5, 5], [7, 5, 5]], dtype=torch.float64)
    F = torch.tensor([[0, 1, 2], [3, 4, 5], [6, 7, 8]])
    h = mesh_health(V, F)
    assert h.self_intersections == 1
    assert h.degenerate_faces == 1
    assert h.flipped_faces is None
    Vs, Fs = grid_sheet(4, 4)
    W = Vs.clone()
    W[:, 0] *= -1  # mirror the flat sheet in x: every normal turns from +z to -z
    assert mesh_health(W, Fs, Vs).flipped_faces == Fs.shape[0]
    assert mesh_health(Vs, Fs, Vs).as_dict() == {"self_intersections": 0, "degenerate_faces": 0, "flipped_faces": 0}
    with pytest.raises(MeshError):
        mesh_health(Vs, Fs, Vs[:5])


def test_error_by_part_charges_each_piece_and_adds_up():
    from meshmei.metrics import error_by_part

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
    from meshmei.metrics import hidden_surface

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
    # the nearest visible point of a hidden one is at most the cap's chord away: completeness bounded
    assert 0 < out["completeness"] < 0.25 * 0.75
    alone = hidden_surface(Vs, Fs, n_samples=5000)
    assert alone["fraction"] == 0.0 and alone["completeness"] == 0.0


def test_face_components_labels_pieces_that_share_no_vertex():
    from meshmei.metrics import face_components

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
