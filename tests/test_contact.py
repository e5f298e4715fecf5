"""The contact barrier: exact point-triangle distances, no energy on a clean mesh, a repelling gradient at a
near-contact, and candidates that are never stale."""

from __future__ import annotations

import contextlib
import functools
import math

import numpy as np
import pytest
import torch

from meshmei.contact import (ContactBarrier, _closest_weights, _point_triangle, _segment_segment, contact_energies,
                             mean_edge_length, point_triangle_sqdist, segment_sqdist)
from meshmei.errors import MeshError
from meshmei.native import native_status, torch_reference
from meshmei.shapes import initial_mesh

needs_cc = pytest.mark.skipif(not native_status()["compiled"], reason="no compiled kernels on this machine")


def _brute_sqdist(P, A, B, C, n=400):
    """Squared distances to a dense barycentric grid of each triangle (an upper bound on the exact one)."""
    i, j = torch.meshgrid(torch.arange(n + 1), torch.arange(n + 1), indexing="ij")
    keep = i + j <= n
    u, v = i[keep].to(P.dtype) / n, j[keep].to(P.dtype) / n
    Q = A[:, None] + u[None, :, None] * (B - A)[:, None] + v[None, :, None] * (C - A)[:, None]
    return ((Q - P[:, None]) ** 2).sum(-1).min(1).values


def test_point_triangle_distance_is_the_closest_point_of_the_triangle():
    g = torch.Generator().manual_seed(0)
    P, A, B, C = (torch.randn(300, 3, generator=g, dtype=torch.float64) for _ in range(4))
    exact = point_triangle_sqdist(P, A, B, C)
    grid = _brute_sqdist(P, A, B, C)
    # the grid's points lie on the triangle, so it never beats the exact distance, and its spacing
    # (at most the longest edge / 400) bounds how far above it can be
    assert bool((grid >= exact - 1e-12).all())
    spacing = torch.stack([(B - A).norm(dim=1), (C - B).norm(dim=1), (A - C).norm(dim=1)]).max(0).values / 400
    assert bool((grid.sqrt() - exact.sqrt() <= spacing).all())


def test_point_triangle_distance_of_known_cases():
    A, B, C = (torch.tensor([[0.0, 0.0, 0.0]]), torch.tensor([[1.0, 0.0, 0.0]]), torch.tensor([[0.0, 1.0, 0.0]]))
    cases = {(0.25, 0.25, 2.0): 4.0,  # above the interior: the height
             (-1.0, 0.5, 0.0): 1.0,  # beside edge CA, in the plane
             (2.0, 2.0, 0.0): 4.5,  # off the hypotenuse, nearest to its middle (0.5, 0.5, 0)
             (-1.0, -1.0, 1.0): 3.0}  # nearest to corner A
    for (x, y, z), d2 in cases.items():
        got = float(point_triangle_sqdist(torch.tensor([[x, y, z]]), A, B, C)[0])
        assert got == pytest.approx(d2, rel=1e-6), (x, y, z)
    # a degenerate (collinear) triangle is its segments
    got = point_triangle_sqdist(torch.tensor([[0.5, 1.0, 0.0]]), A, B, torch.tensor([[2.0, 0.0, 0.0]]))
    assert float(got[0]) == pytest.approx(1.0)


def test_a_clean_well_shaped_mesh_has_no_contact_energy():
    for kind in ("sphere", "torus", "sheet"):
        V, F = initial_mesh(kind, n_vertices=600, dtype=torch.float64)
        barrier = ContactBarrier.for_mesh(V, F)
        assert barrier.distance == pytest.approx(mean_edge_length(V, F) / 3)
        V = V.clone().requires_grad_()
        e = barrier(V)
        e.backward()
        assert float(e.detach()) == 0.0 and barrier.active == 0
        assert float(V.grad.abs().max()) == 0.0


def _two_sheets(gap):
    V, F = initial_mesh("sheet", n_vertices=200, dtype=torch.float64)
    top = V.clone()
    top[:, 2] += gap
    return torch.cat([V, top]), torch.cat([F, F + V.shape[0]])


def test_the_barrier_rises_without_bound_and_pushes_close_surfaces_apart():
    V, F = _two_sheets(1.0)
    h = mean_edge_length(V, F)
    barrier = ContactBarrier(F, distance=h / 3)
    energies = []
    for gap in (0.5 * h, h / 6, h / 60, h / 6000):
        Vg, _ = _two_sheets(gap)
        Vg.requires_grad_()
        e = barrier(Vg)
        e.backward()
        energies.append(float(e.detach()))
        n = Vg.shape[0] // 2
        if gap < h / 3:
            assert barrier.active > 0
            # descent moves the lower sheet down and the upper one up, nothing sideways
            assert bool((Vg.grad[:n, 2] >= 0).all()) and bool((Vg.grad[n:, 2] <= 0).all())
            assert float(Vg.grad[:, :2].abs().max()) <= 1e-9 * float(Vg.grad[:, 2].abs().max())
    assert energies[0] == 0.0
    assert energies[1] < energies[2] < energies[3] and math.isfinite(energies[3])


@pytest.mark.parametrize("edges", [False, True])
def test_cached_candidates_give_the_energy_a_fresh_search_gives(edges):
    V, F = _two_sheets(0.0)
    h = mean_edge_length(V, F)
    g = torch.Generator().manual_seed(1)
    cached = ContactBarrier(F, distance=h / 3, edges=edges)
    for step in range(12):  # the sheets close in by small random steps
        V = V.clone()
        n = V.shape[0] // 2
        V[n:, 2] = 0.4 * h * (1 - step / 12) + 0.02 * h * torch.rand(n, generator=g, dtype=V.dtype)
        V[:, :2] += 0.005 * h * torch.randn(V.shape[0], 2, generator=g, dtype=V.dtype)
        fresh = ContactBarrier(F, distance=h / 3, edges=edges)
        assert float(cached(V)) == pytest.approx(float(fresh(V)), rel=1e-12, abs=0)
        assert cached.active == fresh.active
    assert 1 < cached.rebuilds < 12  # it did reuse candidates, and did search again


def test_bad_distances_are_refused():
    V, F = initial_mesh("sphere", n_vertices=100)
    with pytest.raises(ValueError, match="distance must be positive"):
        ContactBarrier(F, 0.0)
    with pytest.raises(ValueError, match="margin must be positive"):
        ContactBarrier(F, 0.1, margin=-1.0)
    with pytest.raises(ValueError, match="^distance must be positive and finite, got inf$"):
        ContactBarrier(F, math.inf)  # its energy came back inf
    with pytest.raises(MeshError, match=r"non-empty \(m, 3\)"):
        ContactBarrier(torch.zeros(0, 3, dtype=torch.long), 0.1)
    n = V.shape[0]
    with pytest.raises(MeshError, match=rf"^the contact barrier's faces need vertices of shape \(n, 3\) with "
                                        rf"n >= {n}, got \({n - 5}, 3\)$"):
        ContactBarrier(F, 0.1)(V[:-5])  # an IndexError from deep inside before
    cb = ContactBarrier(F.numpy().astype("int32"), 0.1)  # any face array, as everywhere else
    assert cb.F.dtype == torch.int64 and float(cb(V)) == float(ContactBarrier(F, 0.1)(V))


@pytest.mark.parametrize("edges", [False, True])
def test_batched_energies_equal_each_items_own_with_their_gradients(edges):
    V0, F = initial_mesh("sphere", n_vertices=150, dtype=torch.float64)
    g = torch.Generator().manual_seed(3)
    V = torch.stack([V0, V0 + 0.02 * torch.randn(V0.shape, generator=g, dtype=V0.dtype), 1.3 * V0])
    alone = [ContactBarrier.for_mesh(V0, F, 1.5, edges=edges) for _ in range(3)]  # reach 1.5 edges: many pairs
    batch = [ContactBarrier.for_mesh(V0, F, 1.5, edges=edges) for _ in range(3)]
    X = V.clone().requires_grad_(True)
    e = contact_energies(batch, X)
    e.sum().backward()
    for b in range(3):
        Y = V[b].clone().requires_grad_(True)
        one = alone[b](Y)
        one.backward()
        assert one.item() > 0 and batch[b].active == alone[b].active > 0
        torch.testing.assert_close(e[b], one, rtol=1e-12, atol=0)
        torch.testing.assert_close(X.grad[b], Y.grad, rtol=1e-10, atol=1e-14)


def test_segment_distance_is_the_closest_pair_of_points():
    g = torch.Generator().manual_seed(0)
    P1, Q1, P2, Q2 = (torch.randn(120, 3, generator=g, dtype=torch.float64) for _ in range(4))
    Q2[:30] = P2[:30] + 2.0 * (Q1[:30] - P1[:30])  # parallel pairs
    Q1[30:40] = P1[30:40]  # a segment that is a point
    Q2[40:50] = P2[40:50]  # the second segment a point (its distance was taken from the first's start)
    Q1[50:55], Q2[50:55] = P1[50:55], P2[50:55]  # both points
    exact = segment_sqdist(P1, Q1, P2, Q2)
    t = torch.linspace(0, 1, 201, dtype=torch.float64)
    A = P1[:, None] + t[None, :, None] * (Q1 - P1)[:, None]
    B = P2[:, None] + t[None, :, None] * (Q2 - P2)[:, None]
    grid = ((A[:, :, None] - B[:, None]) ** 2).sum(-1).flatten(1).min(1).values
    # the grid's points lie on the segments: never below the exact distance, and above it by at most the
    # grid's spacing (the longer segment / 200)
    assert bool((grid >= exact - 1e-12).all())
    spacing = torch.maximum((Q1 - P1).norm(dim=1), (Q2 - P2).norm(dim=1)) / 200
    assert bool((grid.sqrt() - exact.sqrt() <= spacing + 1e-12).all())
    X = torch.stack([P1, Q1, P2, Q2]).requires_grad_()
    segment_sqdist(*X).sum().backward()
    assert bool(torch.isfinite(X.grad).all())


def test_distance_gradients_are_the_closest_points_and_match_autograd():
    """The written-out gradients (2 (P - Q), spread over the corners by the closest point's weights)
    against autograd through the same formulas, and gradcheck, in every region of a triangle and for
    skew segment pairs."""
    g = torch.Generator().manual_seed(1)
    k = 200
    X = [torch.randn(k, 3, generator=g, dtype=torch.float64, requires_grad=True) for _ in range(4)]
    for fn, raw in ((point_triangle_sqdist, lambda *a: _point_triangle(*a)[0]),
                    (segment_sqdist, lambda *a: _segment_segment(*a)[0])):
        w = torch.randn(k, generator=g, dtype=torch.float64)
        mine = torch.autograd.grad((fn(*X) * w).sum(), X)
        ref = torch.autograd.grad((raw(*X) * w).sum(), X)
        for a, b in zip(mine, ref):
            torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9)
        assert torch.autograd.gradcheck(fn, [x[:20].detach().clone().requires_grad_() for x in X])
    # the closest point lies on the plane (interior), on an edge and at a corner among these points
    wts = _closest_weights(*_point_triangle(*(x.detach() for x in X))[1])
    torch.testing.assert_close(wts.sum(1), torch.ones(k, dtype=torch.float64))
    zeros = (wts == 0).sum(1)
    assert bool((zeros == 0).any()) and bool((zeros == 1).any()) and bool((zeros == 2).any())


def _crossing_edges(gap):
    """Two triangles in perpendicular planes whose edges cross like an X ``gap`` apart, every vertex about
    1 from the other triangle."""
    V = torch.tensor([[-1.0, 0, 0], [1, 0, 0], [0, 0, -1], [0, -1, gap], [0, 1, gap], [0, 0, 1 + gap]],
                     dtype=torch.float64)
    return V, torch.tensor([[0, 1, 2], [3, 4, 5]])


def _one_pair(d, d_hat, n_vertices):
    """The module docstring's energy of one pair at distance ``d``: the barrier over the vertex count."""
    return -(d - d_hat) ** 2 * math.log(d / d_hat) / n_vertices


def test_edge_pairs_see_two_edges_crossing_that_vertex_face_pairs_miss():
    V, F = _crossing_edges(0.05)
    plain, both = ContactBarrier(F, 0.5), ContactBarrier(F, 0.5, edges=True)
    assert float(plain(V)) == 0.0 and plain.active == 0
    X = V.clone().requires_grad_()
    e = both(X)
    e.backward()
    assert both.active == 1
    # one pair, the two edges gap apart: b(gap) over the 6 vertices (the band of edge pairs once drifted wider)
    assert float(e.detach()) == pytest.approx(_one_pair(0.05, 0.5, 6), rel=1e-12)
    # descent lifts the upper edge (vertices 3, 4) and lowers the lower one (0, 1)
    assert bool((X.grad[[3, 4], 2] < 0).all()) and bool((X.grad[[0, 1], 2] > 0).all())
    Y, _ = _crossing_edges(0.005)
    assert float(both(Y)) > float(e.detach())  # closer: more energy
    assert float(both(_crossing_edges(0.6)[0])) == 0.0  # beyond reach: none


def test_the_3d_meis_contact_barriers_see_two_edges_crossing():
    """The 3D-MEI pairs edges with edges: without them a torus start pushed into an X-shaped contact had
    every later step refused by the intersection test (docs/mei.md, *Edge contacts*)."""
    from meshmei.mei import MEISettings
    from meshmei.mei.optimize import contact_barriers

    V, F = _crossing_edges(0.05)
    barriers = contact_barriers(V, F, MEISettings(contact_weight=100.0), items=2)  # a batch of two, as alone
    assert barriers[0].distance == pytest.approx(0.25 * mean_edge_length(V, F)) and barriers[0].distance > 0.05
    assert float(ContactBarrier(F, barriers[0].distance)(V)) == 0.0  # no vertex within reach of a face
    X = torch.stack([V, V]).requires_grad_()
    e = contact_energies(barriers, X)
    e.sum().backward()
    assert bool((e.detach() > 0).all()) and all(b.active == 1 for b in barriers)
    assert bool((X.grad[:, [3, 4], 2] < 0).all()) and bool((X.grad[:, [0, 1], 2] > 0).all())  # pushed apart


@pytest.mark.parametrize("compiled", [True, False])
def test_the_edge_weight_scales_the_edge_pairs_energy_and_gradient_only(compiled):
    """``edge_weight`` (a reconstruction's ramp after a switch): the energy is the vertex-face pairs' plus the
    weight times the edge pairs', and so is its gradient, compiled or in torch."""
    V, F = _two_sheets(0.0)
    W, _ = _two_sheets(mean_edge_length(V, F) / 10)
    d = mean_edge_length(V, F) / 3

    def energy_and_grad(edges, weight=1.0):
        cb = ContactBarrier(F, d, edges=edges)
        cb.edge_weight = weight
        X = W.clone().requires_grad_()
        with contextlib.nullcontext() if compiled else torch_reference():
            e = cb(X)
        e.backward()
        return float(e), X.grad

    e_vf, g_vf = energy_and_grad(False)
    e_all, g_all = energy_and_grad(True)
    assert e_all > e_vf > 0
    for weight in (0.0, 0.3):
        e, g = energy_and_grad(True, weight)
        assert e == pytest.approx(e_vf + weight * (e_all - e_vf), rel=1e-10)
        torch.testing.assert_close(g, g_vf + weight * (g_all - g_vf), rtol=1e-9, atol=1e-12)


def test_edge_pairs_turned_on_later_give_the_energy_of_a_barrier_built_with_them():
    V, F = _crossing_edges(0.05)
    late, both = ContactBarrier(F, 0.5), ContactBarrier(F, 0.5, edges=True)
    assert float(late(V)) == 0.0  # its vertex-face candidates are cached now
    late.use_edges()
    assert float(late(V)) == float(both(V)) == pytest.approx(_one_pair(0.05, 0.5, 6), rel=1e-12)
    assert late.active == both.active == 1
    rebuilds = late.rebuilds
    late.use_edges()  # a second call changes nothing
    assert float(late(V)) == float(both(V)) and late.rebuilds == rebuilds


def test_the_half_plane_bound_is_a_lower_bound_exact_over_the_face():
    from meshmei.contact import _halfplane_sqdist, _halfplanes

    g = torch.Generator().manual_seed(2)
    P, A, B, C = (torch.randn(2000, 3, generator=g, dtype=torch.float64) for _ in range(4))
    C[:100] = A[:100] + 0.5 * (B[:100] - A[:100])  # degenerate (collinear) faces
    exact = point_triangle_sqdist(P, A, B, C).numpy()
    An, Bn, Cn = A.numpy(), B.numpy(), C.numpy()
    bound = _halfplane_sqdist(P.numpy(), _halfplanes(An, Bn, Cn))
    assert (bound <= exact * (1 + 1e-12) + 1e-15).all()
    # a point above the face's interior: the bound is the exact (plane) distance
    Q = torch.from_numpy((An + Bn + Cn) / 3 + 0.3 * _halfplanes(An, Bn, Cn)[:, 0, :3])
    inside = point_triangle_sqdist(Q, A, B, C).numpy()
    assert bound.shape == inside.shape
    assert np.allclose(_halfplane_sqdist(Q.numpy(), _halfplanes(An, Bn, Cn))[100:], inside[100:], rtol=1e-9)
    # and it is far from trivial: most random pairs are bounded to within a factor of two
    assert np.median(bound[100:] / exact[100:]) > 0.5


@pytest.mark.parametrize("compiled", [False, pytest.param(True, marks=needs_cc)])
@pytest.mark.parametrize("kind", ["sphere", "sheet"])
def test_candidates_are_exactly_the_pairs_within_reach(kind, compiled):
    """Against every (vertex, face) pair of a crumpled mesh, with a few faces stretched long (searched with
    their own radius): the cached search finds exactly the pairs, the vertex not in the face, within reach;
    with the NumPy and SciPy broad phase and the compiled one."""
    V, F = initial_mesh(kind, n_vertices=500, dtype=torch.float64)
    h = mean_edge_length(V, F)
    g = torch.Generator().manual_seed(3)
    V = V + 0.35 * h * torch.randn(V.shape, generator=g, dtype=V.dtype)
    V[:6] *= 1.3  # six vertices pulled out: their faces are long
    barrier = ContactBarrier(F, distance=h / 3)
    n, m = V.shape[0], F.shape[0]
    vi, fi = torch.arange(n).repeat_interleave(m), torch.arange(m).repeat(n)
    d2 = point_triangle_sqdist(V[vi], V[F[fi, 0]], V[F[fi, 1]], V[F[fi, 2]])
    apart = (F[fi] != vi[:, None]).all(1)
    reach = barrier.distance + 2 * barrier.margin
    vt, ft, _, _, d, _ = barrier._candidates(V.numpy(), compiled)  # the search: every pair within reach
    want = (d2 < reach * reach) & apart
    expected = set(zip(vi[want].tolist(), fi[want].tolist()))
    assert len(expected) > 50  # crumpled enough that the test means something
    assert set(zip(vt.tolist(), ft.tolist())) == expected
    assert torch.allclose(d, d2[want].sqrt()[torch.argsort(fi[want] * n + vi[want])], rtol=1e-12)
    # handed out right after a search: the pairs within distance
    vt, ft, _, _ = barrier.candidates(V)
    want = (d2 < barrier.distance ** 2) & apart
    assert set(zip(vt.tolist(), ft.tolist())) == set(zip(vi[want].tolist(), fi[want].tolist()))


def _edge_search_against_every_pair(barrier, V, compiled):
    """The barrier's edge search on ``V`` (its edges, the pairs ``(ea, eb)`` and their distances ``de``), the
    pairs it found as sorted ``(lower, higher)`` tuples, and the same for every pair of edges sharing no
    vertex within the search's reach, measured one by one."""
    E, k = barrier.E, barrier.E.shape[0]
    i, j = torch.triu_indices(k, k, 1)
    apart = (E[i][:, :, None] != E[j][:, None, :]).all(2).all(1)
    d2 = segment_sqdist(V[E[i, 0]], V[E[i, 1]], V[E[j, 0]], V[E[j, 1]])
    reach = barrier.distance + 2 * barrier.margin
    want = (d2 < reach * reach) & apart
    _, _, ea, eb, _, de = barrier._candidates(V.numpy(), compiled)
    found = sorted(zip(torch.minimum(ea, eb).tolist(), torch.maximum(ea, eb).tolist()))
    return E, (ea, eb, de), found, sorted(zip(i[want].tolist(), j[want].tolist()))


@pytest.mark.parametrize("compiled", [False, pytest.param(True, marks=needs_cc)])
def test_edge_candidates_are_exactly_the_edge_pairs_within_reach(compiled):
    """Against every pair of edges of a crumpled sphere with a few edges stretched long: exactly the pairs
    sharing no vertex within reach, each once, a long edge first where the other is not."""
    V, F = initial_mesh("sphere", n_vertices=300, dtype=torch.float64)
    h = mean_edge_length(V, F)
    V = V + 0.35 * h * torch.randn(V.shape, generator=torch.Generator().manual_seed(5), dtype=V.dtype)
    V[:6] *= 1.6
    barrier = ContactBarrier(F, distance=h / 3, edges=True)
    E, (ea, eb, de), found, want = _edge_search_against_every_pair(barrier, V, compiled)
    assert len(found) > 100 and found == want
    half = (V[E[:, 1]] - V[E[:, 0]]).norm(dim=1)
    long = half > torch.quantile(half, 0.98)
    assert bool((long[ea] | ~long[eb]).all()) and bool(((long[ea] != long[eb]) | (ea < eb)).all())
    assert int((long[ea] & ~long[eb]).sum()) > 0  # the case arose
    # the compiled search's own distances (edge i to edge j, as it measured them) agree to rounding
    torch.testing.assert_close(de, segment_sqdist(V[E[ea, 0]], V[E[ea, 1]], V[E[eb, 0]], V[E[eb, 1]]).sqrt(),
                               rtol=1e-15 if not compiled else 1e-12, atol=0)


@pytest.mark.parametrize("compiled", [False, pytest.param(True, marks=needs_cc)])
def test_edge_candidates_where_many_edges_are_stretched(compiled):
    """A fit stretches its start (at step 300 of a single-stage 10k bunny fit, 4 % of the edges are longer than
    twice the mean): a cap of a crumpled sphere widened 2.5 times, 11 % of its edges that long. The compiled
    search finds a long edge's pairs from its own box and pairs two long edges by a sweep: against every pair
    of edges, exactly the pairs sharing no vertex within reach, each once, with pairs of two long edges and
    of a long and a short one among them."""
    V, F = initial_mesh("sphere", n_vertices=400, dtype=torch.float64)
    h = mean_edge_length(V, F)
    V = V + 0.3 * h * torch.randn(V.shape, generator=torch.Generator().manual_seed(3), dtype=V.dtype)
    V[V[:, 2] > 0.2, :2] *= 2.5
    barrier = ContactBarrier(F, distance=h / 3, edges=True)
    E, (ea, eb, de), found, want = _edge_search_against_every_pair(barrier, V, compiled)
    assert found == want
    size = (0.5 * (V[E[:, 1]] - V[E[:, 0]]).abs()).max(1).values  # the compiled search's long edges
    long = size > 2 * size.mean()
    assert float(long.double().mean()) > 0.1
    assert int((long[ea] & long[eb]).sum()) > 20 and int((long[ea] != long[eb]).sum()) > 100
    torch.testing.assert_close(de, segment_sqdist(V[E[ea, 0]], V[E[ea, 1]], V[E[eb, 0]], V[E[eb, 1]]).sqrt(),
                               rtol=1e-15 if not compiled else 1e-12, atol=0)


@functools.lru_cache(maxsize=None)
def _hard_meshes():
    """Meshes for the two broad phases: crumpled closed and open surfaces, long stretched faces and edges, a
    vertex far out, coincident vertices (zero-length edges, zero-area faces), 200 vertices packed into a small
    box (more pairs than the compiled search's first guess of room), one face. Built once (tests read them,
    never change them)."""
    g = torch.Generator().manual_seed(11)
    out = []
    for kind in ("sphere", "sheet", "torus"):
        V, F = initial_mesh(kind, n_vertices=400, dtype=torch.float64)
        h = mean_edge_length(V, F)
        out.append((f"crumpled {kind}", V + 0.4 * h * torch.randn(V.shape, generator=g, dtype=V.dtype), F, h / 3))
    V, F = initial_mesh("sphere", n_vertices=400, dtype=torch.float64)
    h = mean_edge_length(V, F)
    W = V.clone()
    W[:20] *= 2.0
    W[21] *= 40.0
    out.append(("stretched", W, F, h / 3))
    W = V.clone()
    a, b, c = F[0].tolist()
    W[b] = W[a]
    W[c] = W[a]
    out.append(("coincident", W, F, h / 3))
    V, F = initial_mesh("sphere", n_vertices=200, dtype=torch.float64)
    out.append(("packed", 1e-3 * V + 1e-4 * torch.randn(V.shape, generator=g, dtype=V.dtype), F, 2e-3))
    out.append(("one face", torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.2, 0.1]], dtype=torch.float64),
                torch.tensor([[0, 1, 2]]), 0.3))
    return tuple(out)


@needs_cc
@pytest.mark.parametrize("name", [x[0] for x in _hard_meshes()])
def test_the_compiled_search_keeps_the_numpy_searchs_pairs_with_its_own_distances(name):
    """The compiled broad phase keeps its own pairs and distances (no torch pass over them): every pair the
    NumPy search keeps, in the same order (by face then vertex, by first then second edge), any other only
    within the kernel's slack of reach, the distances equal to rounding; vertex-face and edge-edge, with pairs
    left out, on hard meshes. (The energy, which torch measures, is the same bit for bit: the next tests.)"""
    from meshmei.contact import _SLACK

    _, V, F, d = next(x for x in _hard_meshes() if x[0] == name)
    Vn = V.numpy()
    a, b = ContactBarrier(F, d, edges=True), ContactBarrier(F, d, edges=True)
    if name == "coincident":
        assert a.leave_out(V) > 0 and b.leave_out(V) == len(a._out_vf) + len(a._out_ee)
    numpy_, compiled = a._candidates(Vn, False), b._candidates(Vn, True)
    assert len(compiled[0]) + len(compiled[2]) > 0
    reach = a.distance + 2.0 * a.margin
    big = len(V) + len(a.E)
    for first, second, dist in ((1, 0, 4), (2, 3, 5)):  # the sort keys: face then vertex; first then second edge
        kn, kc = numpy_[first] * big + numpy_[second], compiled[first] * big + compiled[second]
        assert bool((kn[1:] > kn[:-1]).all()) and bool((kc[1:] > kc[:-1]).all())
        both = torch.isin(kc, kn)
        assert int(both.sum()) == len(kn)  # every NumPy pair, and (both sorted) in the same order
        torch.testing.assert_close(compiled[dist][both], numpy_[dist], rtol=1e-12, atol=0)
        extra = compiled[dist][~both]  # pairs the torch distance puts at reach or beyond: only within the slack
        assert bool((extra >= reach * (1 - 1e-12)).all() and (extra < reach * (1 + _SLACK)).all())
        assert compiled[first].dtype == torch.int64 and compiled[dist].dtype == torch.float64


def _energies_over_steps(V, F, d, moves, reference, torch_energy=False, monkeypatch=None):
    """Each step's (energy, gradient, active count) of one barrier over the moves, and its search count;
    ``reference``: within torch_reference; ``torch_energy``: the compiled search with the torch energy."""
    import meshmei.contact as contact

    if torch_energy:
        monkeypatch.setattr(contact, "all_finite", lambda x: False)  # the compiled energy's gate: closed
    barrier, X, out = ContactBarrier(F, d, edges=True), V.clone(), []
    with torch_reference() if reference else contextlib.nullcontext():
        for m in moves:
            X = X + m
            Y = X.clone().requires_grad_(True)
            e = barrier(Y)
            e.backward()
            out.append((e.detach(), Y.grad, barrier.active))
    if torch_energy:
        monkeypatch.undo()
    return out, barrier.rebuilds


@needs_cc
@pytest.mark.parametrize("name", ["crumpled sphere", "crumpled torus", "stretched", "packed"])
def test_over_steps_the_compiled_search_changes_no_energy_gradient_or_count(name, monkeypatch):
    """Searches and cached handouts between them over a run of small moves (some beyond the margin, so the
    barrier searches again): with the torch energy, each step's energy, gradient and active count equal the
    torch reference's (NumPy search, torch distances) bit for bit, vertex-face and edge-edge pairs; with the
    compiled energy too (float64 here), the same counts and the energy and gradient to rounding."""
    _, V, F, d = next(x for x in _hard_meshes() if x[0] == name)
    g = torch.Generator().manual_seed(7)
    moves = [0.3 * d * torch.randn(V.shape, generator=g, dtype=V.dtype) * (k % 3) for k in range(8)]
    want, searches = _energies_over_steps(V, F, d, moves, reference=True)
    searched, _ = _energies_over_steps(V, F, d, moves, reference=False, torch_energy=True, monkeypatch=monkeypatch)
    compiled, _ = _energies_over_steps(V, F, d, moves, reference=False)
    assert searches > 1 and sum(k for _, _, k in want) > 0
    for (e1, g1, n1), (e2, g2, n2), (e3, g3, n3) in zip(searched, compiled, want):
        assert n1 == n3 and torch.equal(e1, e3) and torch.equal(g1, g3)
        assert n2 == n3
        torch.testing.assert_close(e2, e3, rtol=1e-11, atol=0)
        torch.testing.assert_close(g2, g3, rtol=1e-8, atol=1e-11 * float(g3.abs().max()))


def _energy_and_gradient(W, F, d_hat, reference):
    barrier = ContactBarrier(F, d_hat, edges=True)
    X = W.clone().requires_grad_(True)
    with torch_reference() if reference else contextlib.nullcontext():
        e = barrier(X)
        e.backward()
    return e.detach(), X.grad, barrier.active


@needs_cc
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("name", ["crumpled sphere", "crumpled sheet", "stretched", "packed"])
def test_the_compiled_energy_is_the_float64_energy_of_the_same_coordinates(name, dtype):
    """The compiled energy measures in float64 whatever ``V``'s dtype: in float32 too, its count is the torch
    code's in float64 on the same (float32) coordinates, and its energy and gradient are that code's to
    float32's rounding of the results (2e-8 here), far nearer than the torch code in float32 comes (1e-6 to
    1e-3, and gradients 1.4 to 4.7 times their size off 1,000 units from the origin). In float64 the two
    agree to rounding. With ``d_hat`` at pairs' own distances (pairs at the threshold) and 1,000 units from
    the origin (float32's spacing there is about 6e-5; the packed mesh, 2e-3 across, not there in float32:
    its coordinates collapse onto each other, and pairs at distance 0 get the dtype's clamp)."""
    _, V, F, d = next(x for x in _hard_meshes() if x[0] == name)
    for shift in (0.0, 1000.0) if name != "packed" or dtype == torch.float64 else (0.0,):
        W = (V + shift).to(dtype)
        vt, ft, _, _ = ContactBarrier(F, 3 * d).candidates(W)  # pairs within 3 d and some beyond
        at = point_triangle_sqdist(W[vt], W[F[ft, 0]], W[F[ft, 1]], W[F[ft, 2]]).sqrt()
        at = at[(at > 0) & (at < 3 * d)].sort().values
        for d_hat in (float(at[len(at) // 2]), float(at[len(at) // 5])):
            e, g, n = _energy_and_gradient(W, F, d_hat, reference=False)
            e64, g64, n64 = _energy_and_gradient(W.double(), F, d_hat, reference=True)
            assert e.dtype == g.dtype == dtype and n == n64 > 0, (shift, d_hat)
            # float64: rounding of coordinates 1,000 out, near-contact pairs amplify it in the gradient
            tol = 1e-6 if dtype == torch.float32 else 1e-10 + 1e-8 * shift
            err_e, err_g = float(abs(e.double() - e64) / e64), float((g.double() - g64).norm() / g64.norm())
            assert err_e < tol and err_g < tol, (shift, d_hat, err_e, err_g)
            if dtype == torch.float32:
                e32, g32, _ = _energy_and_gradient(W, F, d_hat, reference=True)
                assert err_e < float(abs(e32.double() - e64) / e64)
                assert err_g < float((g32.double() - g64).norm() / g64.norm())


def test_the_compiled_energys_gradient_is_its_derivative():
    """Central differences of the compiled energy (float64) on two meshes with vertex-face and edge pairs in
    the band at generic positions: torch's gradcheck."""
    for V, F, d_hat in (_crossing_edges(0.05) + (0.5,), next((x[1], x[2], x[3]) for x in _hard_meshes()
                                                              if x[0] == "crumpled sheet")):
        barrier = ContactBarrier(F, d_hat, edges=True)
        X = V.clone().requires_grad_(True)
        assert float(barrier(X).detach()) > 0 and barrier.active > 0
        assert torch.autograd.gradcheck(barrier, (X,), eps=1e-7, atol=1e-7, rtol=1e-5)


@needs_cc
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_a_non_finite_coordinate_between_searches_gives_the_torch_energy(bad):
    """A NaN or infinite coordinate between two searches (the cached pairs handed out): the energy is not
    the compiled one (C's comparisons would drop NaN pairs silently) but the torch code's: NaN, which the
    optimisers' guards refuse, and the same count."""
    _, V, F, d = next(x for x in _hard_meshes() if x[0] == "crumpled sphere")
    W = V.clone()
    W[int(F[0, 0])] = bad
    out = []
    for reference in (False, True):
        barrier = ContactBarrier(F, d, edges=True, min_interval=10)
        with torch_reference() if reference else contextlib.nullcontext():
            barrier(V)
            out.append((barrier(W), barrier.active))
    (e1, n1), (e2, n2) = out
    assert n1 == n2 > 0 and bool(e1.isnan()) and bool(e2.isnan())


@needs_cc
def test_a_non_finite_vertex_gives_what_the_numpy_search_gives(monkeypatch):
    """The compiled search does not take NaN or infinite coordinates: the NumPy search runs (the same
    outcome as within torch_reference)."""
    import meshmei.contact as contact

    V, F = initial_mesh("sphere", n_vertices=200, dtype=torch.float64)
    V[3] = float("nan")
    assert contact._compiled_pairs("contact_vertex_face", V.numpy(), F.numpy(), 0.1) is None
    outcomes = []
    for compiled in (False, True):
        try:
            outcomes.append(ContactBarrier(F, 0.05, edges=True)._candidates(V.numpy(), compiled))
        except Exception as e:  # noqa: BLE001 - whatever the NumPy search does, both do
            outcomes.append(type(e))
    if isinstance(outcomes[0], tuple):
        assert all(torch.equal(x, y) for x, y in zip(*outcomes))
    else:
        assert outcomes[0] is outcomes[1]


@needs_cc
def test_torch_reference_runs_the_numpy_search_in_the_prefetch_thread_too(monkeypatch):
    import meshmei.contact as contact

    calls = []
    real = contact._compiled_pairs
    monkeypatch.setattr(contact, "_compiled_pairs", lambda *a: calls.append(a[0]) or real(*a))
    V, F = _two_sheets(0.05)
    with torch_reference():
        cb = ContactBarrier(F, 0.05, edges=True)
        cb.prefetch(V)
        ref = cb.candidates(V)
        cb2 = ContactBarrier(F, 0.05, edges=True)
        cb2.candidates(V)
    assert calls == []
    cb = ContactBarrier(F, 0.05, edges=True)
    cb.prefetch(V)
    assert all(torch.equal(x, y) for x, y in zip(cb.candidates(V), ref))
    assert calls == ["contact_vertex_face", "contact_edge_edge"]


def _t_junction(n=200):
    """A sphere with one edge split at its midpoint on one side only: the new vertex lies on the face across
    the edge, which it is not part of."""
    V, F = initial_mesh("sphere", n_vertices=n)
    a, b, c = (int(x) for x in F[0])
    m = V.shape[0]
    V = torch.cat([V, (0.5 * (V[a] + V[b]))[None]])
    F = torch.cat([torch.tensor([[a, m, c], [m, b, c]]), F[1:]])
    return V, F, m


@pytest.mark.parametrize("edges", [False, True])
def test_pairs_in_contact_at_the_start_are_left_out_and_nothing_else(edges):
    V, F = _two_sheets(1.0)
    h = mean_edge_length(V, F)
    plain, left = ContactBarrier(F, h / 3, edges=edges), ContactBarrier(F, h / 3, edges=edges)
    assert left.leave_out(V) == 0
    W, _ = _two_sheets(h / 6)  # the sheets come close during the run: felt as without leave_out
    assert float(plain(W)) > 0 and float(left(W)) == float(plain(W))
    close = ContactBarrier(F, h / 3, edges=edges)  # a start whose pairs are close, not in contact: kept
    assert close.leave_out(W) == 0 and float(close(W)) == float(plain(W))
    V, F, m = _t_junction()
    cb = ContactBarrier.for_mesh(V, F, edges=edges)
    Vg = V.clone().requires_grad_()
    cb(Vg).backward()
    # the split vertex lies 1e-8 from the face across: the barrier's slope there is all but infinite
    assert cb.active >= 1 and float(Vg.grad.abs().max()) > 10.0
    n = cb.leave_out(V)
    assert n >= 1 and float(cb(V)) == 0.0 and cb.active == 0
    if not edges:  # edges switched on after leave_out: the edge pairs in contact at the start stay out
        cb.use_edges()
        assert float(cb(V)) == 0.0


def test_a_source_with_a_t_junction_is_fitted_as_without_the_barrier_and_says_so():
    """One T-junction held the whole rbf fit still (0.115 for 0.012): the barrier's gradient at the split vertex
    set AdamUniform's step scale for every kernel."""
    import warnings

    from meshmei.reconstruct import ReconstructionWarning, reconstruct

    V, F, _ = _t_junction()
    kw = dict(steps=30, n_samples=300, target_pool=2000, eval_samples=2000)
    with pytest.warns(ReconstructionWarning, match=r"stage 0: \d+ vertex-face or edge pairs of the start are in contact"):
        res = reconstruct((V, F), "bunny", "rbf", **kw)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ReconstructionWarning)
        free = reconstruct((V, F), "bunny", "rbf", w_contact=0.0, **kw)
    start = res.history[0]["chamfer"]
    assert res.final.chamfer_l2 < 0.15 * start
    assert res.final.chamfer_l2 == pytest.approx(free.final.chamfer_l2, rel=0.1)
    assert res.info["stages"][0]["contact_left_out"] >= 1 and res.final.self_intersections == 0


@pytest.mark.parametrize("edges", [False, True])
def test_a_prefetched_search_gives_what_the_call_would_have(edges):
    """ContactBarrier.prefetch runs the candidate search in a worker thread beside the caller's own work; the
    call that takes it gets the same pairs, energy and search count as without it, including when the
    vertices moved little (no search) or far (a search), and when the prefetch was for other vertices."""
    V, F = _two_sheets(0.05)
    h = mean_edge_length(V, F)
    plain, fetched = ContactBarrier(F, h / 3, edges=edges), ContactBarrier(F, h / 3, edges=edges)
    gen = torch.Generator().manual_seed(0)
    for step in range(12):
        W = V + (0.002 if step % 3 else 0.05) * step * torch.randn(V.shape, generator=gen, dtype=V.dtype)
        if step == 7:
            fetched.prefetch(W + 1.0)  # for other vertices: dropped, the call searches for its own
        else:
            fetched.prefetch(W)
        a, b = plain.candidates(W), fetched.candidates(W)
        if step < 7:  # from step 7 the two searched at different times: the same energy, other cached pairs
            assert all(torch.equal(x, y) for x, y in zip(a, b)) and plain.rebuilds == fetched.rebuilds, f"step {step}"
        assert float(plain(W)) == float(fetched(W)), f"step {step}"
    assert fetched.rebuilds > plain.rebuilds  # the prefetch for other vertices searched, and was dropped


def test_a_prefetched_search_raises_its_error_at_the_call():
    V, F = _two_sheets(0.05)
    cb = ContactBarrier(F, 0.01)
    cb.prefetch(V[:5])
    with pytest.raises(MeshError, match="the contact barrier's faces need vertices"):
        cb.candidates(V[:5])
    assert float(cb(V)) == float(ContactBarrier(F, 0.01)(V))  # and the barrier goes on, as a fresh one


def test_reconstruction_is_the_same_with_and_without_the_prefetch(monkeypatch):
    from meshmei.reconstruct import reconstruct

    src = initial_mesh("sphere", n_vertices=300)
    kw = dict(steps=20, stages=(200, 300), n_samples=500, target_pool=5000, eval_samples=2000)
    with_it = reconstruct(src, "bunny", "rbf", **kw)
    monkeypatch.setattr(ContactBarrier, "prefetch", lambda self, V: None)
    without = reconstruct(src, "bunny", "rbf", **kw)
    untimed = lambda res: [{k: v for k, v in rec.items() if k != "time"} for rec in res.history]  # noqa: E731
    assert torch.equal(with_it.V, without.V) and untimed(with_it) == untimed(without)
    assert sum(st["contact_rebuilds"] for st in with_it.info["stages"]) > 2


def _prefetch_in_child(queue):
    V, F = _two_sheets(0.05)
    cb = ContactBarrier(F, 0.01)
    cb.prefetch(V)
    queue.put(len(cb.candidates(V)[0]))


def test_a_forked_child_can_prefetch_after_its_parent_did():
    """A forked child inherits the worker's executor but not its thread: a prefetch there waited forever."""
    import multiprocessing

    V, F = _two_sheets(0.05)
    cb = ContactBarrier(F, 0.01)
    cb.prefetch(V)
    want = len(cb.candidates(V)[0])  # the parent's worker thread is running
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_prefetch_in_child, args=(queue,))
    child.start()
    child.join(60)
    alive = child.is_alive()
    if alive:
        child.kill()
    assert not alive and child.exitcode == 0 and queue.get(timeout=5) == want


def test_log_barrier_is_the_closed_form_of_incremental_potential_contact():
    """-(d - d_hat)^2 log(d / d_hat) inside the band and 0 outside, by the formula (not by itself)."""
    from meshmei.contact import log_barrier

    d_hat = 0.3
    d = torch.tensor([1e-6, 0.01, 0.1, 0.2, 0.299, 0.3, 0.5, math.inf], dtype=torch.float64)
    expected = [-(x - d_hat) ** 2 * math.log(x / d_hat) if x < d_hat else 0.0 for x in d.tolist()]
    assert log_barrier(d, d_hat).tolist() == pytest.approx(expected, rel=1e-14, abs=0)


def test_the_contact_energy_is_the_sum_over_every_near_vertex_face_pair_over_the_vertex_count():
    """Two parallel sheets 0.05 apart, closer than the barrier's distance: the energy equals a brute-force
    sum of the barrier over every (vertex, face not using it) pair, by libigl's exact distances, divided by
    the vertex count."""
    import igl

    from conftest import grid_sheet

    V1, F1 = grid_sheet(5, 5)  # spacing 0.25
    V2 = V1.clone()
    V2[:, 2] += 0.05
    V2[:, :2] += 0.03  # not vertex over vertex
    V, F = torch.cat([V1, V2]), torch.cat([F1, F1 + V1.shape[0]])
    d_hat = 0.25 / 3
    energy = float(ContactBarrier(F, distance=d_hat)(V))
    Vn, Fn = V.numpy(), F.numpy()
    total = 0.0
    for f in range(len(Fn)):
        d2 = igl.point_mesh_squared_distance(Vn, Vn, Fn[f:f + 1])[0]
        for v in range(len(Vn)):
            if v not in Fn[f] and math.sqrt(d2[v]) < d_hat:
                d = math.sqrt(d2[v])
                total += -(d - d_hat) ** 2 * math.log(d / d_hat)
    assert total > 0 and energy == pytest.approx(total / len(Vn), rel=1e-10)


def test_a_barrier_called_on_another_vertex_count_searches_afresh():
    """A barrier called again with fewer vertices (the same faces) failed in NumPy's broadcasting; an
    array failed on its missing .device."""
    V, F = initial_mesh("sphere", n_vertices=100)[:2]
    V = V.double()
    tri = torch.tensor([[0, 1, 2]])
    used = ContactBarrier(tri, 0.01)
    used(V)
    assert float(used(V[:10])) == float(ContactBarrier(tri, 0.01)(V[:10]))
    assert float(ContactBarrier(F, 0.05)(V.numpy())) == float(ContactBarrier(F, 0.05)(V))


@pytest.mark.parametrize("edges", [False, True])
def test_the_energy_of_every_kept_pair_is_the_energy_of_the_bounded_ones(edges, monkeypatch):
    """Up to _HAND_ALL kept pairs the energy measures every pair the last search kept, not only those the
    per-call bounds hand out: the kernel's distance test cuts them to the same pairs in the same order, so the
    energy, its gradient and the count of active pairs are the same bit for bit, whichever way is taken."""
    import meshmei.contact as contact

    V, F = _two_sheets(0.05)
    h = mean_edge_length(V, F)
    gen = torch.Generator().manual_seed(0)
    moves = [V + 0.01 * h * k * torch.randn(V.shape, generator=gen, dtype=V.dtype) for k in range(8)]
    outcomes = {}
    for hand_all in (0, 10**9):
        monkeypatch.setattr(contact, "_HAND_ALL", hand_all)
        cb, got = ContactBarrier(F, h / 3, edges=edges), []
        for W in moves:
            Wg = W.clone().requires_grad_()
            e = cb(Wg)
            e.backward()
            kept = len(cb._pairs_np[0]) + len(cb._pairs_np[2])
            handed = sum(len(x) for x in cb.candidates(W)[::2])
            got.append((float(e), Wg.grad.clone(), cb.active, kept, handed))
        outcomes[hand_all] = got
    for (e0, g0, a0, k0, n0), (e1, g1, a1, k1, n1) in zip(outcomes[0], outcomes[10**9]):
        assert e0 == e1 and torch.equal(g0, g1) and a0 == a1 and (k0, n0) == (k1, n1)
    assert any(e > 0 for e, *_ in outcomes[0])  # the sheets are within reach: pairs in the energy
    assert any(k > n for *_, k, n in outcomes[0])  # and some kept pairs were not handed out: two ways indeed
