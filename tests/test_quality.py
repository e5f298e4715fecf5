"""Mesh health and triangle quality: self-intersections, degenerate and flipped faces."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from meshmei.errors import MeshError
from meshmei.quality import (closedness, count_degenerate_faces, count_flipped_faces, count_self_intersections,
                             health_line, health_report, mesh_health, mesh_quality, signed_volume,
                             triangle_measures, triangle_quality)

from conftest import grid_sheet, icosphere


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


def test_triangle_quality():
    V = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0.5, math.sqrt(3) / 2, 0], [2, 0, 0]], dtype=torch.float64)
    F = torch.tensor([[0, 1, 2], [0, 1, 3]])
    q = triangle_quality(V, F)
    torch.testing.assert_close(q, torch.tensor([1.0, 0.0], dtype=torch.float64))
    assert mesh_quality(V, F)["min_quality"] == 0.0


def _slow_counts(V, V0, F):
    # one face at a time, in numpy: (degenerate, flipped)
    degenerate = flipped = 0
    for f in F.tolist():
        a, b, c = V[f].numpy()
        a0, b0, c0 = V0[f].numpy()
        n, n0 = np.cross(b - a, c - a), np.cross(b0 - a0, c0 - a0)
        l2 = ((b - a) ** 2).sum() + ((c - b) ** 2).sum() + ((a - c) ** 2).sum()
        degenerate += np.linalg.norm(n) <= 1e-12 * l2
        flipped += np.linalg.norm(n) > 0 and np.linalg.norm(n0) > 0 and n @ n0 < 0
    return int(degenerate), int(flipped)


def test_counts_agree_with_mesh_health_and_a_slow_reference():
    Vs, Fs = grid_sheet(4, 4)
    W = Vs.clone()
    W[:, 0] *= -1
    W[5] = W[6]  # faces holding both vertices 5 and 6 collapse to segments
    degenerate, flipped = _slow_counts(W, Vs, Fs)
    # the two faces on edge 5-6 collapse; the mirror turns every other face over
    assert (degenerate, flipped) == (2, Fs.shape[0] - 2)
    h = mesh_health(W, Fs, Vs)
    assert count_flipped_faces(W, Vs, Fs) == h.flipped_faces == flipped
    assert count_degenerate_faces(W, Fs) == h.degenerate_faces == degenerate
    assert count_self_intersections(Vs, Fs) == 0
    with pytest.raises(MeshError, match=r"rest pose V0 of shape \(16, 3\) does not match V of shape \(15, 3\)"):
        count_flipped_faces(Vs[:15], Vs, Fs[:1])


def test_triangle_measures_are_scale_free_in_their_ratio():
    V = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0.5, math.sqrt(3) / 2, 0]], dtype=torch.float64)
    F = torch.tensor([[0, 1, 2]])
    dbl, l2 = triangle_measures(V, F)
    torch.testing.assert_close(dbl, torch.tensor([math.sqrt(3) / 2], dtype=torch.float64))
    torch.testing.assert_close(l2, torch.tensor([3.0], dtype=torch.float64))
    dbl7, l27 = triangle_measures(7 * V, F)
    torch.testing.assert_close(dbl7 / l27, dbl / l2)


def test_health_report_counts_boundary_and_nonmanifold_edges_and_reports_watertight():
    from meshmei.quality import edge_use, health_report
    from meshmei.shapes import initial_mesh

    V, F = initial_mesh("sphere", n_vertices=100)
    r = health_report(V, F, V)
    assert r["watertight"] and r["boundary_edges"] == 0 and r["nonmanifold_edges"] == 0
    assert r["self_intersections"] == 0 and r["flipped_faces"] == 0 and 0 < r["min_quality"] <= r["mean_quality"] <= 1
    Vs, Fs = initial_mesh("sheet", n_vertices=100)
    assert not health_report(Vs, Fs)["watertight"] and health_report(Vs, Fs)["flipped_faces"] is None
    # a fin: three triangles on one edge make it non-manifold; the other edges are boundary edges
    fin = torch.tensor([[0, 1, 2], [0, 1, 3], [0, 1, 4]])
    assert edge_use(fin) == (6, 1)
    # a face repeating an index has no edge from the vertex to itself (counted as a boundary edge before,
    # unlike the topology); its other two sides both run along (1, 3): one edge of that one face, so (1, 3)
    # has two faces, face 1 and it (its two sides counted as two faces made (1, 3) non-manifold here, and a
    # lone [0, 0, 1] watertight)
    assert edge_use(torch.tensor([[0, 1, 2], [2, 1, 3], [3, 1, 1]])) == (3, 0)
    assert edge_use(torch.tensor([[0, 0, 1]])) == (1, 0)
    assert not health_report(torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), torch.tensor([[0, 0, 1]]))["watertight"]


def _edge_use_by_sets(F):
    """edge_use's definition, written out: each face's set of undirected edges, then faces per edge."""
    faces_of = {}
    for f, (a, b, c) in enumerate(F.tolist()):
        for e in {tuple(sorted(p)) for p in ((a, b), (b, c), (c, a)) if p[0] != p[1]}:
            faces_of.setdefault(e, set()).add(f)
    counts = [len(s) for s in faces_of.values()]
    return sum(c == 1 for c in counts), sum(c > 2 for c in counts)


@pytest.mark.parametrize("seed", range(6))
def test_edge_use_counts_as_its_definition_on_random_faces_with_repeats(seed):
    """Faces over few vertices (shared edges, fins, faces repeating an index, the same face twice) and a real
    mesh; the definition's count, face by face."""
    from meshmei.quality import edge_use
    from meshmei.shapes import initial_mesh

    g = torch.Generator().manual_seed(seed)
    F = torch.randint(0, 4 + 3 * seed, (5 + 40 * seed, 3), generator=g)
    assert edge_use(F) == _edge_use_by_sets(F)
    _, Fs = initial_mesh("sheet", n_vertices=60 + 20 * seed)
    assert edge_use(Fs) == _edge_use_by_sets(Fs) and edge_use(Fs)[1] == 0 and edge_use(Fs)[0] > 0


@pytest.mark.parametrize("form", ["numpy", "list"])
def test_health_report_and_mesh_quality_take_arrays_and_lists_as_their_siblings_do(form):
    from meshmei.quality import health_report, mesh_quality
    from meshmei.shapes import initial_mesh

    V, F = initial_mesh("sphere", n_vertices=100, dtype=torch.float64)
    V0 = V * 1.1
    convert = (lambda x: x.numpy()) if form == "numpy" else (lambda x: x.tolist())
    assert health_report(convert(V), convert(F), convert(V0)) == health_report(V, F, V0)
    assert mesh_quality(convert(V), convert(F)) == mesh_quality(V, F)
    with pytest.raises(MeshError, match="out of range"):
        health_report(convert(V), convert(F + V.shape[0]))


def test_health_in_words_names_what_keeps_a_mesh_from_being_watertight():
    """The command line's closing lines: the counts as they are, and watertight only when no edge is open
    or used by more than two faces."""
    V, F = grid_sheet(3, 3)  # 2 x 2 squares: 8 boundary edges
    h = health_report(V, F, V)
    assert health_line(h) == (f"0 self-intersecting pairs, 0 flipped faces, min triangle quality "
                              f"{h['min_quality']:.3f}, open: 8 boundary edges")
    # without a rest pose no face is counted as flipped, and the line does not claim any count
    assert health_line(health_report(V, F)) == f"0 self-intersecting pairs, min triangle quality {h['min_quality']:.3f}, open: 8 boundary edges"
    Vs, Fs = icosphere(1)
    assert health_line(health_report(Vs, Fs)).endswith(", watertight")
    assert closedness(1, 0) == "open: 1 boundary edge"
    assert closedness(0, 2) == "2 non-manifold edges"
    assert closedness(3, 1) == "open: 3 boundary edges, 1 non-manifold edge"


@pytest.mark.parametrize("scale", [1e80, 1e150, 1e300, 1e-170, 1e-300])
def test_a_mesh_at_an_extreme_scale_gets_the_health_of_the_same_mesh_at_size_one(scale):
    """Found by fuzzing: at 1e300 the quality was NaN (squared lengths overflow), and libigl counted 1,131
    intersecting pairs on a clean sphere at 1e80 and 21 at 1e-170."""
    from meshmei.shapes import initial_mesh

    V, F = initial_mesh("sphere", n_vertices=400)
    V = V.double()
    far, near = health_report(V * scale, F, V * scale), health_report(V, F, V)
    for k in ("min_quality", "mean_quality"):  # V * scale is V rounded once: the same to rounding
        assert far.pop(k) == pytest.approx(near.pop(k), rel=1e-12, abs=0)
    assert far == near


def test_the_degenerate_face_tolerance_must_be_a_finite_non_negative_number():
    """eps=inf counted every face of a regular tetrahedron as degenerate; None failed in the comparison."""
    V = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    F = torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    assert count_degenerate_faces(V, F) == 0 and count_degenerate_faces(V, F, eps=0.0) == 0
    for eps in (None, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="eps must be a finite non-negative number"):
            count_degenerate_faces(V, F, eps=eps)


def test_signed_volume_of_a_box_is_its_volume_with_the_faces_winding():
    from scipy.spatial import ConvexHull

    V = np.array([[x, y, z] for x in (0, 0.6) for y in (0, 0.1) for z in (0, 0.2)]) + [3.0, -2.0, 5.0]
    F = ConvexHull(V).simplices.astype(np.int64)
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    inward = np.einsum("ij,ij->i", n, V[F].mean(1) - V.mean(0)) < 0
    F[inward] = F[inward][:, ::-1]  # every face outward
    assert signed_volume(V, F) == pytest.approx(0.6 * 0.1 * 0.2, rel=1e-12)  # off the origin too
    assert signed_volume(V, F[:, ::-1]) == pytest.approx(-0.6 * 0.1 * 0.2, rel=1e-12)
