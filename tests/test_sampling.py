"""Sampling, Chamfer distance (against brute force) and the multi-level point index."""

from __future__ import annotations

import doctest
import importlib
import math

import numpy as np
import pytest
import torch

from meshmei.errors import MeshError
import meshmei.sampling as sampling
from meshmei.sampling import (PointIndex, chamfer_distance, nearest_neighbors, nn_spacing, sample_points,
                              spatial_order)

from conftest import icosphere


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


@pytest.mark.parametrize("scale", [1e-10, 1e-12])
def test_a_tiny_float32_mesh_samples_like_float64(scale):
    """The faces' cross products go as size^4: at 1e-10 their squares underflowed float32, the normals came
    out 0.94 to 1.06 long and other faces were drawn; at 1e-12 every face had 'zero area'."""
    V, F = icosphere(2)
    V32, V64 = (V * scale).float(), (V * scale).double()
    P32, N32, f32 = sample_points(V32, F, 2000, generator=0, return_normals=True, return_faces=True)
    P64, N64, f64 = sample_points(V64, F, 2000, generator=0, return_normals=True, return_faces=True)
    assert torch.equal(f32, f64)
    torch.testing.assert_close(N32.norm(dim=1), torch.ones(2000), rtol=0, atol=1e-6)
    torch.testing.assert_close(N32.double(), N64, rtol=0, atol=1e-5)


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


def test_point_index_answers_the_same_with_query_threads():
    # workers only splits the queries among scipy's threads (reconstruction uses two beside its contact
    # search): every answer, near and far, by either search order, is the one-thread answer
    V, F = icosphere(3)
    Q = sample_points(V, F, 50_000, generator=0)
    near = sample_points(V, F, 3000, generator=1) * 1.001
    far = torch.randn(3000, 3, dtype=V.dtype, generator=torch.Generator().manual_seed(2)) * 2.0
    for queries in (near, far, torch.cat([near, far])):
        for near_first in (True, False):
            one, two = PointIndex(Q, min_points=1000), PointIndex(Q, min_points=1000)
            a = one.query(queries, near_first=near_first, workers=1)
            b = two.query(queries, near_first=near_first, workers=2)
            assert np.array_equal(a, b) and one.far_share == two.far_share


def test_a_large_index_answers_in_the_order_asked_whatever_order_it_searches(monkeypatch):
    # from SORT_QUERIES_FROM points the queries are searched in Morton order and the answers put back: the
    # same answers, near and far, by either search order and thread count, and the same far_share
    V, F = icosphere(3)
    Q = sample_points(V, F, sampling.SORT_QUERIES_FROM + 1000, generator=0)
    near = sample_points(V, F, 3000, generator=1) * 1.001
    far = torch.randn(3000, 3, dtype=V.dtype, generator=torch.Generator().manual_seed(2)) * 2.0
    mixed = torch.cat([near, far])[torch.randperm(6000, generator=torch.Generator().manual_seed(3))]
    sorted_index, plain_index = PointIndex(Q), PointIndex(Q)
    for queries in (near, far, mixed):
        for near_first in (True, False):
            for workers in (1, 2):
                got = sorted_index.query(queries, near_first=near_first, workers=workers)
                with monkeypatch.context() as m:
                    m.setattr(sampling, "SORT_QUERIES_FROM", math.inf)
                    want = plain_index.query(queries, near_first=near_first, workers=workers)
                assert np.array_equal(got, want) and sorted_index.far_share == plain_index.far_share
    assert np.array_equal(sorted_index.query(near), nearest_neighbors(near, Q).numpy())


def test_spatial_order_is_a_permutation_that_keeps_neighbours_together():
    rng = np.random.default_rng(0)
    X = rng.standard_normal((5000, 3))
    X /= np.linalg.norm(X, axis=1, keepdims=True)  # a sphere's surface, as samples lie
    order = spatial_order(X)
    assert np.array_equal(np.sort(order), np.arange(len(X)))

    def step(Y):
        return float(np.linalg.norm(np.diff(Y, axis=0), axis=1).mean())

    # consecutive points: random order steps about the sphere's mean chord (1.33); the curve's steps are short
    assert step(X[order]) < 0.1 * step(X)
    flat_cases = (np.zeros((7, 3)), np.ones((1, 3)), np.zeros((0, 3)), np.column_stack([X[:, :2], np.zeros(len(X))]))
    for flat in flat_cases:
        assert np.array_equal(np.sort(spatial_order(flat)), np.arange(len(flat)))


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


def test_nn_spacing_ignores_duplicates():
    X = np.array([[0.0, 0, 0], [1, 0, 0], [3, 0, 0]])
    assert nn_spacing(X) == pytest.approx((1 + 1 + 2) / 3)
    assert nn_spacing(np.concatenate([X, X])) == pytest.approx((1 + 1 + 2) / 3)  # seams do not shrink it
    assert nn_spacing(np.zeros((4, 3))) == float("inf")


@pytest.mark.parametrize("module", ["meshmei.sampling", "meshmei.metrics", "meshmei.quality", "meshmei.mesh"])
def test_docstring_examples_run(module):
    res = doctest.testmod(importlib.import_module(module))
    assert res.attempted > 0 and res.failed == 0


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_half_precision_points_find_the_neighbours_of_their_float32_values(dtype):
    # numpy has no bfloat16: the KD-tree side used to fail with "Got unsupported ScalarType BFloat16"
    V, F = icosphere(2)
    P = sample_points(V, F, 300, generator=0).to(dtype)
    Q = (1.1 * sample_points(V, F, 400, generator=1)).to(dtype)
    i_pq, i_qp = nearest_neighbors(P.float(), Q.float()), nearest_neighbors(Q.float(), P.float())
    assert torch.equal(nearest_neighbors(P, Q), i_pq)
    assert np.array_equal(PointIndex(Q).query(P), PointIndex(Q.float()).query(P.float()))
    cd = chamfer_distance(P, Q)
    assert cd.dtype == dtype
    assert torch.equal(cd, ((P - Q[i_pq]) ** 2).sum(-1).mean() + ((Q - P[i_qp]) ** 2).sum(-1).mean())


def test_nearest_neighbors_are_exact_within_the_radius():
    """A query truly within exact_within but reported beyond it by the approximate search kept the
    approximate answer (6 of 4,464 near queries, up to 1.28 times the true distance)."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(0)
    Q = rng.normal(size=(20000, 3))
    Q /= np.linalg.norm(Q, axis=1, keepdims=True)
    P = Q[rng.integers(0, len(Q), 5000)] + rng.normal(size=(5000, 3)) * 0.03
    idx = nearest_neighbors(torch.from_numpy(P), torch.from_numpy(Q), exact_within=0.05).numpy()
    d_true, _ = cKDTree(Q).query(P)
    d_got = np.linalg.norm(Q[idx] - P, axis=1)
    near = d_true < 0.05
    assert near.sum() > 4000 and bool(np.all(d_got[near] <= d_true[near] * (1 + 1e-12)))


def test_chamfer_names_the_argument_holding_nan():
    P = torch.rand(10, 3, dtype=torch.float64)
    bad = P.clone()
    bad[3, 1] = float("nan")
    for args, name in (((bad, P), "P"), ((P, bad), "Q")):
        with pytest.raises(ValueError, match=f"{name} holds NaN or Inf \\(1 of 10 points, first at index 3\\)"):
            chamfer_distance(*args)


def test_sample_counts_and_seeds_are_checked_before_torch_sees_them():
    V, F = icosphere(1)
    assert sample_points(V, F, 5.0, generator=3).shape == (5, 3)
    for n in (None, "10", math.inf, math.nan, -1, 2.5):
        with pytest.raises(ValueError, match="n must be a non-negative integer"):
            sample_points(V, F, n)
    with pytest.raises(ValueError, match="an int generator is a seed in \\[-2\\*\\*63, 2\\*\\*64 - 1\\]"):
        sample_points(V, F, 5, generator=2**64)
