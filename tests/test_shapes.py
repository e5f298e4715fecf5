"""Tests for meshmei.shapes: initial meshes (sheet, sphere, torus), targets (bunny, teapot), remeshing and
unit-diagonal normalisation."""

import doctest
import math
import os
import re
import subprocess
import sys

import igl
import numpy as np
import pytest
import torch

from meshmei import shapes
from meshmei.errors import MeshError
from meshmei.quality import signed_volume
from meshmei.shapes import initial_mesh, normalize_unit_diagonal, remesh, target_mesh
from meshmei.shapes.remeshing import MAX_REMESH_GROWTH

KINDS = ("sheet", "sphere", "torus")
EULER = {"sheet": 1, "sphere": 2, "torus": 0}
# Bounds on std/mean of the edge lengths at the default 2,500 vertices. Measured: sphere 0.050,
# torus 0.120, sheet 0.076. The remesher keeps edges within [4/5, 4/3] of the target, so the torus,
# which starts from a quad grid split into right triangles, ends noticeably less regular than the
# icosphere does.
EDGE_CV_BOUND = {"sphere": 0.08, "torus": 0.16, "sheet": 0.11}


@pytest.fixture(scope="module")
def default_meshes():
    return {kind: initial_mesh(kind, dtype=torch.float64) for kind in KINDS}


@pytest.fixture(scope="module")
def teapots():
    return {r: tuple(t.numpy() for t in target_mesh("teapot", resolution=r, dtype=torch.float64)) for r in (8, 16, 32)}


def _np(V, F):
    return V.detach().double().numpy(), F.numpy()


def _edge_lengths(V, F):
    E = igl.edges(F)
    return np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1)


def _face_normals(V, F):
    return np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])  # (m, 3), length = 2 * area


def _boundary_edges(F):
    """Undirected edges used by exactly one face, (b, 2)."""
    E = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    uniq, count = np.unique(E, axis=0, return_counts=True)
    return uniq[count == 1]


def _consistently_oriented(F):
    """Every directed edge occurs once, so the two faces at an interior edge traverse it oppositely."""
    D = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    return len(np.unique(D, axis=0)) == len(D)


def _check_clean(V, F):
    assert F.dtype == np.int64
    assert np.array_equal(np.unique(F), np.arange(len(V))), "unreferenced vertices"
    assert igl.is_edge_manifold(F)[0]
    assert np.asarray(igl.is_vertex_manifold(F)).all()
    assert (igl.doublearea(V, F) > 0).all(), "degenerate faces"
    assert len(np.unique(np.sort(F, axis=1), axis=0)) == len(F), "duplicate faces"
    assert _consistently_oriented(F)


# --- initial meshes -----------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
def test_initial_deterministic(kind):
    V1, F1 = initial_mesh(kind, n_vertices=600)
    V2, F2 = initial_mesh(kind, n_vertices=600)
    assert torch.equal(V1, V2) and torch.equal(F1, F2)


@pytest.mark.parametrize("kind", KINDS)
def test_initial_dtypes(kind):
    V, F = initial_mesh(kind, n_vertices=400)
    assert V.dtype == torch.float32 and F.dtype == torch.int64
    assert V.ndim == 2 and V.shape[1] == 3 and F.ndim == 2 and F.shape[1] == 3
    V64, F64 = initial_mesh(kind, n_vertices=400, dtype=torch.float64)
    assert V64.dtype == torch.float64 and torch.equal(F64, F)
    torch.testing.assert_close(V64.float(), V, rtol=0, atol=0)


@pytest.mark.parametrize("kind", KINDS)
def test_meshes_from_pymeshlab_are_c_ordered(kind):
    """pymeshlab hands out Fortran-ordered matrices; a tensor of strided rows gathers 18 times slower."""
    V, F = initial_mesh(kind, n_vertices=400)
    V2, F2 = remesh(V, F, 600)
    for X in (V, F, V2, F2):
        assert X.is_contiguous()


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("n", [400, 2500])
def test_initial_vertex_count(kind, n, default_meshes):
    V, _ = default_meshes[kind] if n == 2500 else initial_mesh(kind, n_vertices=n)
    assert abs(len(V) - n) <= 0.15 * n, (kind, n, len(V))


@pytest.mark.parametrize("kind", KINDS)
def test_initial_target_edge_length(kind):
    V, F = _np(*initial_mesh(kind, target_edge_length=0.05, size=2.0))
    mean = _edge_lengths(V, F).mean()
    assert abs(mean - 0.05) < 0.15 * 0.05, mean


@pytest.mark.parametrize("kind", KINDS)
def test_initial_size_scales_exactly(kind):
    V1, F1 = initial_mesh(kind, n_vertices=400, dtype=torch.float64)
    V3, F3 = initial_mesh(kind, n_vertices=400, size=3.0, dtype=torch.float64)
    assert torch.equal(F1, F3)
    torch.testing.assert_close(V3, 3.0 * V1, rtol=1e-15, atol=0)


@pytest.mark.parametrize("kind", KINDS)
def test_initial_topology(kind, default_meshes):
    V, F = _np(*default_meshes[kind])
    _check_clean(V, F)
    assert igl.euler_characteristic(F) == EULER[kind]
    n_boundary = len(_boundary_edges(F))
    if kind == "sheet":
        assert n_boundary > 0
    else:
        assert n_boundary == 0, "closed surfaces must be watertight"


@pytest.mark.parametrize("kind", KINDS)
def test_initial_edge_uniformity(kind, default_meshes):
    L = _edge_lengths(*_np(*default_meshes[kind]))
    assert L.std() / L.mean() < EDGE_CV_BOUND[kind]


def test_sphere_on_surface_and_outward(default_meshes):
    V, F = _np(*default_meshes["sphere"])
    np.testing.assert_allclose(np.linalg.norm(V, axis=1), 0.5, rtol=0, atol=1e-12)
    N = _face_normals(V, F)
    assert (np.einsum("ij,ij->i", N, V[F].mean(axis=1)) > 0).all()
    assert signed_volume(V, F) == pytest.approx(4 / 3 * math.pi * 0.5**3, rel=0.02)


def test_torus_on_surface_and_outward(default_meshes):
    V, F = _np(*default_meshes["torus"])
    R, r = 0.35, 0.15

    def tube_offset(P):  # vector from the nearest point of the core circle
        rho = np.linalg.norm(P[:, :2], axis=1, keepdims=True)
        core = np.column_stack([R * P[:, :2] / rho, np.zeros(len(P))])
        return P - core

    np.testing.assert_allclose(np.linalg.norm(tube_offset(V), axis=1), r, rtol=0, atol=1e-12)
    N = _face_normals(V, F)
    assert (np.einsum("ij,ij->i", N, tube_offset(V[F].mean(axis=1))) > 0).all()
    assert signed_volume(V, F) == pytest.approx(2 * math.pi**2 * R * r**2, rel=0.02)
    # It fits the box [-0.5, 0.5]^2 x [-0.15, 0.15] and nearly touches it (vertices need not hit the extremes).
    extent = np.abs(V).max(axis=0)
    assert (extent <= np.array([0.5, 0.5, 0.15]) + 1e-12).all()
    np.testing.assert_allclose(extent, [0.5, 0.5, 0.15], rtol=0, atol=2e-3)


def test_sheet_square_boundary_and_up_normals(default_meshes):
    V, F = _np(*default_meshes["sheet"])
    assert (V[:, 2] == 0).all()
    assert (_face_normals(V, F)[:, 2] > 0).all()
    np.testing.assert_allclose(V.min(axis=0)[:2], [-0.5, -0.5], atol=1e-12)
    np.testing.assert_allclose(V.max(axis=0)[:2], [0.5, 0.5], atol=1e-12)
    bnd = np.unique(_boundary_edges(F))
    # Every boundary vertex lies on a side of the square ...
    np.testing.assert_allclose(np.abs(V[bnd, :2]).max(axis=1), 0.5, rtol=0, atol=1e-12)
    # ... every vertex on a side is a boundary vertex, and the four corners survive remeshing.
    on_side = np.flatnonzero(np.abs(V[:, :2]).max(axis=1) > 0.5 - 1e-12)
    assert np.array_equal(on_side, bnd)
    for corner in ([-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]):
        assert np.linalg.norm(V[:, :2] - corner, axis=1).min() < 1e-12, corner
    assert np.sum(igl.doublearea(V, F)) / 2 == pytest.approx(1.0, rel=1e-12)


# --- targets -----------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["bunny", "teapot", "dumbbell", "fin", "cup", "bowl"])
def test_target_normalised(name):
    V, F = target_mesh(name, dtype=torch.float64)
    lo, hi = V.min(0).values, V.max(0).values
    torch.testing.assert_close(0.5 * (lo + hi), torch.zeros(3, dtype=torch.float64), rtol=0, atol=1e-6)
    assert float((hi - lo).norm()) == pytest.approx(1.0, abs=1e-6)
    assert F.dtype == torch.int64
    assert target_mesh(name)[0].dtype == torch.float32


@pytest.mark.parametrize("name, thickness", [("dumbbell", 0.10), ("fin", 0.06), ("cup", 0.05), ("bowl", 0.05)])
def test_thin_targets_are_clean_closed_outward_and_thin(name, thickness):
    from meshmei.quality import count_self_intersections

    V, F = target_mesh(name, dtype=torch.float64)
    Vn, Fn = V.numpy(), F.numpy()
    assert count_self_intersections(V, F) == 0
    boundary = igl.boundary_facets(Fn)
    assert len(boundary[0] if isinstance(boundary, tuple) else boundary) == 0  # closed
    a, b, c = Vn[Fn[:, 0]], Vn[Fn[:, 1]], Vn[Fn[:, 2]]
    assert np.einsum("ij,ij->i", a, np.cross(b, c)).sum() > 0  # outward: positive enclosed volume
    # the thin part is thin: as built, before scaling to unit diagonal, its thickness was given; after the
    # scaling some surface point has the opposite surface within that thickness (times the scale) below it
    raw = target_mesh.__globals__["_implicit"](name)[0]
    scale = 1.0 / float(np.linalg.norm(raw.max(0) - raw.min(0)))
    normals = igl.per_vertex_normals(Vn, Fn)
    hits = [igl.ray_mesh_intersect(Vn[i] - 1e-6 * normals[i], -normals[i], Vn, Fn) for i in range(0, len(Vn), 7)]
    depth = min(min(h[1] for h in hit if h[1] > 1e-5) for hit in hits if hit and any(h[1] > 1e-5 for h in hit))
    assert depth <= 1.2 * thickness * scale


def test_bunny_matches_pymeshlab_file():
    path = shapes.bunny_path()
    raw = [line.split() for line in path.read_text().splitlines()]
    n_raw = sum(1 for t in raw if t and t[0] == "v")
    m_raw = sum(1 for t in raw if t and t[0] == "f")
    V, F = _np(*target_mesh("bunny", dtype=torch.float64))
    assert n_raw == 28088  # the count DESIGN.md quotes
    assert (len(V), len(F)) == (n_raw, m_raw)
    _check_clean(V, F)
    assert len(_boundary_edges(F)) == 0
    assert igl.euler_characteristic(F) == 2
    assert signed_volume(V, F) > 0
    # Kept as stored: the normalised vertices are an affine image (shift and uniform scale) of the file's.
    P = np.array([[float(x) for x in t[1:4]] for t in raw if t and t[0] == "v"])
    Pn = (P - 0.5 * (P.min(0) + P.max(0))) / np.linalg.norm(np.ptp(P, axis=0))
    np.testing.assert_allclose(V, Pn, rtol=0, atol=1e-12)


@pytest.mark.parametrize("res", [8, 16])
def test_teapot_clean_mesh(res, teapots):
    V, F = teapots[res]
    _check_clean(V, F)
    assert len(F) == 32 * 2 * res**2 - 4 * 2 * res  # the lid tip and bottom centre each lose 4 * res
    # Four pieces (body with bottom, lid, handle, spout): disk + disk + tube + tube.
    assert len(np.unique(igl.bfs_orient(F)[1])) == 4
    assert igl.euler_characteristic(F) == 2


@pytest.mark.parametrize("res", [8, 16])
def test_teapot_seams_merged(res, teapots):
    V, F = teapots[res]
    # With every seam welded the only boundary left is 6 loops made of 16 patch sides, each split into
    # `res` edges: the rim's top edge (4 sides), the lid's outer edge (4), both ends of the handle
    # (2 + 2) and of the spout (2 + 2). An unwelded seam would add at least 2 * res more.
    assert len(_boundary_edges(F)) == 16 * res
    assert len(igl.boundary_loop_all(F)) == 6


def test_teapot_outward(teapots):
    V, F = teapots[8]
    assert signed_volume(V, F) > 0
    N = _face_normals(V, F)
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    C = V[F].mean(axis=1)
    # The teapot is open, so the winding number is not exactly 0/1, but it separates sides clearly.
    w_out = igl.winding_number(V, F, C + 1e-3 * N)
    w_in = igl.winding_number(V, F, C - 1e-3 * N)
    assert np.mean(w_out < 0.5) > 0.95
    assert np.mean(w_in > 0.5) > 0.99


def test_teapot_tessellation_converges(teapots):
    area = {r: igl.doublearea(*teapots[r]).sum() / 2 for r in teapots}
    err8, err16 = abs(area[8] - area[32]) / area[32], abs(area[16] - area[32]) / area[32]
    assert err8 < 0.01
    assert err16 < err8 / 3  # second-order convergence of the piecewise-linear area


def test_teapot_deterministic():
    V1, F1 = target_mesh("teapot", resolution=6)
    V2, F2 = target_mesh("teapot", resolution=6)
    assert torch.equal(V1, V2) and torch.equal(F1, F2)


# --- bad input ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(kind="cube"), "kind must be one of .* got 'cube'"),
        (dict(kind="sphere", target_edge_length=0.0), "target_edge_length must be positive .* got 0.0"),
        (dict(kind="sphere", target_edge_length=-0.1), "target_edge_length must be positive .* got -0.1"),
        (dict(kind="sphere", target_edge_length=float("nan")), "target_edge_length must be positive .* got nan"),
        (dict(kind="sphere", target_edge_length="0.1"), "target_edge_length must be a positive number, got '0.1'"),
        (dict(kind="sphere", target_edge_length=1e-5), "implies about .* vertices for a sphere"),
        (dict(kind="torus", target_edge_length=2.0), "implies about .* vertices for a torus"),
        (dict(kind="sphere", n_vertices=0), "n_vertices must be positive .* got 0"),
        (dict(kind="sphere", n_vertices=-5), "n_vertices must be positive .* got -5"),
        (dict(kind="sphere", n_vertices=2.5), "n_vertices must be a positive integer, got 2.5"),
        (dict(kind="sphere", n_vertices=True), "n_vertices must be a positive integer, got True"),
        (dict(kind="sphere", n_vertices=10), "n_vertices must lie between 32 and 5000000, got 10"),
        (dict(kind="sphere", n_vertices=500, target_edge_length=0.1), "not both"),
        (dict(kind="sheet", size=0.0), "size must be positive .* got 0.0"),
        (dict(kind="sheet", iterations=0), "iterations must be positive .* got 0"),
    ],
)
def test_initial_mesh_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        initial_mesh(**kwargs)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(name="dragon"), "name must be one of .* got 'dragon'"),
        (dict(name="teapot", resolution=0), "resolution must be positive .* got 0"),
        (dict(name="teapot", resolution=-2), "resolution must be positive .* got -2"),
        (dict(name="teapot", resolution=1.5), "resolution must be a positive integer, got 1.5"),
    ],
)
def test_target_mesh_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        target_mesh(**kwargs)


def test_bunny_missing_file(monkeypatch, tmp_path):
    import pymeshlab

    monkeypatch.setattr(pymeshlab, "__file__", str(tmp_path / "pymeshlab" / "__init__.py"))
    with pytest.raises(FileNotFoundError, match="bunny.obj does not exist"):
        target_mesh("bunny")


def test_docstring_examples():
    assert doctest.testmod(shapes, raise_on_error=True).failed == 0


@pytest.mark.parametrize("kind, n", [("sphere", 1000), ("sphere", 6000), ("sphere", 13000), ("torus", 1000),
                                     ("torus", 6000), ("sheet", 1000), ("sheet", 6000),
                                     ("sphere", 2000), ("sphere", 136), ("sphere", 144), ("torus", 80),
                                     ("torus", 120)])
def test_vertex_count_tracks_the_request_across_icosphere_levels(kind, n):
    # 13000 sits between icosphere levels 5 (10242) and 6 (40962): it once came out 21 % high. The retries
    # rescaled the edge from the best try's count, not the last one's, and jumped over the request: 2,000
    # gave 2,404, 144 gave 162 and 80 (torus) 65; they now bisect once the count is bracketed
    V, _ = initial_mesh(kind, n_vertices=n)
    assert abs(V.shape[0] - n) <= 0.11 * n


# --- remeshing (tests as they stand for meshmei.reconstruct.remesh in tests/test_reconstruct.py) ----------


@pytest.fixture(scope="module")
def sphere():
    return initial_mesh("sphere", n_vertices=300)


def test_remesh_reaches_about_the_requested_count(sphere):
    V, F = remesh(*sphere, 1000)
    assert abs(V.shape[0] - 1000) < 200
    assert F.dtype == torch.int64


def test_remesh_rejects_bad_counts_and_zero_area(sphere):
    # n_vertices=0 returned the input unchanged (with a division warning), NaN returned a coarse mesh,
    # -5 said 'math domain error'; a zero-area mesh came back from pymeshlab empty ('mesh is empty')
    V, F = sphere
    for n in (0, -5, float("nan"), float("inf")):
        with pytest.raises(ValueError, match=f"n_vertices must be positive and finite, got {n!r}"):
            remesh(V, F, n)
    with pytest.raises(ValueError, match="n_vertices must be a positive integer, got 2.5"):
        remesh(V, F, 2.5)
    with pytest.raises(ValueError, match="iterations must be positive and finite, got 0"):
        remesh(V, F, 200, iterations=0)
    with pytest.raises(MeshError, match=r"cannot remesh a mesh of zero surface area \(\d+ vertices"):
        remesh(V * 0, F, 200)


def test_remesh_refuses_a_result_many_times_the_count_asked_for():
    """A needle 1,000 long and 1e-3 thick asked for 160 vertices gave 108,102 (the remesher keeps the thin
    direction's short edges and splits the long ones), and a reconstruction's checks on it ran for minutes."""
    V, F = initial_mesh("sphere", n_vertices=160)[:2]
    needle = V.double() * torch.tensor([20.0, 0.02, 0.02], dtype=torch.float64)
    with pytest.raises(MeshError, match=r"^remeshing to about 40 vertices gave (\d+): the mesh has parts thinner than "
                                        r"the edge length for that count \(\S+\).*thicken the thin parts") as err:
        remesh(needle, F, 40)
    assert int(re.search(r"gave (\d+)", str(err.value)).group(1)) > MAX_REMESH_GROWTH * 40 + 100


def test_remesh_keeps_dtype_and_device_and_gives_a_clean_closed_mesh(sphere):
    V, F = remesh(sphere[0].double(), sphere[1], 600)
    assert V.dtype == torch.float64 and V.device == sphere[0].device
    _check_clean(*_np(V, F))
    assert igl.euler_characteristic(F.numpy()) == 2 and len(_boundary_edges(F.numpy())) == 0


def test_a_strong_coarsening_of_a_large_mesh_skips_the_distance_check_and_stays_on_the_input(monkeypatch):
    """The first stage of a coarse-to-fine schedule remeshes the start to n/4 or n/16 of its count; at 10k,
    pymeshlab's check of each collapse against the input was 70 % of that remesh's time. A remesh of a mesh of
    at least UNCHECKED_FROM vertices to at most half its count goes without it; a smaller mesh, a refinement
    and a remesh to more than half keep it."""
    from meshmei.shapes import remeshing

    big = initial_mesh("sphere", n_vertices=int(1.2 * remeshing.UNCHECKED_FROM))
    n = big[0].shape[0]
    assert n >= remeshing.UNCHECKED_FROM
    small = initial_mesh("sphere", n_vertices=2500)
    checked = []
    real = remeshing.isotropic_remesh
    monkeypatch.setattr(remeshing, "isotropic_remesh",
                        lambda *a, **k: checked.append(k["check_distance"]) or real(*a, **k))
    V, F = remesh(*big, n // 16)  # the first stage of three levels
    remesh(V, F, n // 4)  # a refinement
    remesh(*big, n // 2)
    remesh(*big, n // 2 + 1)
    remesh(*small, 156)  # a smaller input keeps it
    assert checked == [False, True, False, True, True]
    assert abs(V.shape[0] - n // 16) <= 0.1 * n // 16
    _check_clean(*_np(V, F))
    assert igl.euler_characteristic(F.numpy()) == 2 and len(_boundary_edges(F.numpy())) == 0
    # reprojected onto the input: every vertex on the fine sphere's faces, within their sagitta of it
    assert float((V.norm(dim=1) - 0.5).abs().max()) < 1e-3


def test_remesh_is_deterministic(sphere):
    V1, F1 = remesh(*sphere, 500)
    V2, F2 = remesh(*sphere, 500)
    assert torch.equal(V1, V2) and torch.equal(F1, F2)


# --- unit-diagonal normalisation ---------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_normalize_unit_diagonal_centres_and_scales(dtype):
    V = torch.tensor([[1.0, 2.0, 3.0], [5.0, 2.0, 3.0], [1.0, 5.0, 3.0], [2.0, 3.0, 3.0]], dtype=dtype)
    W = normalize_unit_diagonal(V)
    assert W.dtype == dtype
    lo, hi = W.min(0).values, W.max(0).values
    torch.testing.assert_close(hi + lo, torch.zeros(3, dtype=dtype))
    assert float((hi - lo).norm()) == pytest.approx(1.0, rel=1e-6)
    torch.testing.assert_close(W, (V - torch.tensor([3.0, 3.5, 3.0], dtype=dtype)) / 5.0)
    # a shifted and scaled copy normalises to the same vertices
    torch.testing.assert_close(normalize_unit_diagonal(7.0 * V - 2.0), W)


def test_normalize_unit_diagonal_rejects_a_mesh_of_zero_extent():
    V = torch.ones(4, 3)
    with pytest.raises(MeshError, match=r"mesh has zero extent \(all 4 vertices coincide\); cannot normalise it"):
        normalize_unit_diagonal(V)


@pytest.mark.parametrize("factor", [1.0, 1e-300, 1e300])
def test_normalize_unit_diagonal_gives_its_frame_in_the_meshs_own_units_at_any_scale(factor):
    """The frame was measured on the mesh as given: at 1e154 and beyond its squared diagonal overflowed, and
    the scale was inf (a target's ``p * scale + centre`` then mapped the result to inf)."""
    V = torch.tensor([[1.0, 2.0, 3.0], [5.0, 2.0, 3.0], [1.0, 5.0, 3.0], [2.0, 3.0, 3.0]], dtype=torch.float64)
    W, frame = normalize_unit_diagonal(V * factor, return_frame=True)
    assert torch.equal(W, normalize_unit_diagonal(V * factor))
    if factor == 1.0:  # as the box is measured in V's units: exactly
        assert frame == {"centre": [3.0, 3.5, 3.0], "scale": 5.0}
    assert frame["scale"] == pytest.approx(5.0 * factor, rel=1e-15)
    assert frame["centre"] == pytest.approx([3.0 * factor, 3.5 * factor, 3.0 * factor], rel=1e-15)
    back = W * frame["scale"] + torch.tensor(frame["centre"], dtype=torch.float64)
    torch.testing.assert_close(back, V * factor, rtol=1e-15, atol=0.0)
    with pytest.raises(MeshError, match="^return_frame must be True or False, got 'no'$"):
        normalize_unit_diagonal(V, return_frame="no")


def test_normalize_unit_diagonal_refuses_a_frame_whose_diagonal_float64_cannot_hold():
    V = torch.tensor([[-1e308, -1e308, -1e308], [1e308, 1e308, 1e308], [1e308, -1e308, 0.0]], dtype=torch.float64)
    assert torch.isfinite(normalize_unit_diagonal(V)).all()  # the unit-diagonal mesh itself is fine
    with pytest.raises(MeshError, match=r"^the mesh's bounding-box diagonal, .* is beyond float64's range "
                                        r"\(1\.8e\+308\); rescale it$"):
        normalize_unit_diagonal(V, return_frame=True)


@pytest.mark.parametrize("module", ["primitives", "targets", "remeshing"])
def test_module_docstring_examples(module):
    import importlib

    mod = importlib.import_module(f"meshmei.shapes.{module}")
    result = doctest.testmod(mod, raise_on_error=True)
    assert result.failed == 0 and result.attempted > 0


def test_pymeshlab_meshes_do_not_depend_on_earlier_filter_calls(sphere):
    """pymeshlab keeps a filter parameter's last value as its default for the whole process: a remesh that
    left ``featuredeg`` out gave the fin target 9,159 faces after a stage remesh (``featuredeg=180``) and
    9,917 before it. meshmei names every parameter, so its meshes do not depend on what ran before."""
    import pymeshlab

    from meshmei.shapes.remeshing import isotropic_parameters

    implicit = target_mesh.__globals__["_implicit"].__wrapped__  # uncached
    before = implicit("fin"), remesh(*sphere, 500)
    ms = pymeshlab.MeshSet()  # every parameter away from its default, on another mesh
    ms.create_sphere(radius=2.0, subdiv=3)
    odd = dict(isotropic_parameters(pymeshlab.PureValue(0.3), iterations=2, feature_degrees=180.0), adaptive=True,
               checksurfdist=False, maxsurfdist=pymeshlab.PureValue(0.5), swapflag=False, smoothflag=False,
               reprojectflag=False)
    ms.meshing_isotropic_explicit_remeshing(**odd)
    after = implicit("fin"), remesh(*sphere, 500)
    for a, b in zip(before[0], after[0]):
        assert np.array_equal(a, b)
    for a, b in zip(before[1], after[1]):
        assert torch.equal(a, b)


def test_an_integer_dtype_is_refused():
    """dtype=torch.int64 truncated every coordinate to 0."""
    with pytest.raises(ValueError, match="dtype must be a torch floating dtype"):
        initial_mesh("sphere", n_vertices=100, dtype=torch.int64)


@pytest.mark.parametrize("call, match", [
    (lambda: target_mesh("teapot", resolution=2, dtype=torch.int64), "dtype must be a torch floating dtype"),
    (lambda: target_mesh("teapot", resolution=1), "resolution must be at least 2"),  # not edge-manifold at 1
    (lambda: target_mesh("dumbbell", resolution=4), "resolution applies to the teapot only"),  # silently ignored
    (lambda: initial_mesh("sphere", n_vertices=100, size=1e40), "out of torch.float32's range"),  # inf vertices
    (lambda: initial_mesh("sphere", n_vertices=100, size=1e-50), "out of torch.float32's range"),  # all zero
])
def test_shape_arguments_that_gave_garbage_are_refused(call, match):
    with pytest.raises(ValueError, match=match):
        call()


@pytest.mark.parametrize("V, match", [
    (torch.tensor([[0.0, 0, 0], [1, float("inf"), 0]]), "NaN or Inf"),  # NaN vertices before
    (torch.tensor([[0.0, 0, 0], [1, float("nan"), 0]]), "NaN or Inf"),  # 'all vertices coincide' before
    (torch.tensor([[0, 0, 0], [3, 4, 0]]), r"non-empty \(n, 3\) float tensor"),  # zeros before
    (torch.zeros(0, 3), r"non-empty \(n, 3\) float tensor"),  # an IndexError before
    (torch.rand(2, 5, 3), r"non-empty \(n, 3\) float tensor"),  # each member scaled wrong before
])
def test_normalize_unit_diagonal_checks_its_input(V, match):
    with pytest.raises(MeshError, match=match):
        normalize_unit_diagonal(V)


def test_remesher_iterations_have_a_ceiling():
    """initial_mesh(iterations=10**6) ran for over an hour in pymeshlab's loop, which Python cannot
    interrupt."""
    from meshmei.shapes.remeshing import MAX_REMESH_ITERATIONS

    V, F = initial_mesh("sphere", n_vertices=100)[:2]
    for call in (lambda it: initial_mesh("sphere", n_vertices=50, iterations=it), lambda it: remesh(V, F, 100, iterations=it)):
        with pytest.raises(ValueError, match=f"iterations must be at most {MAX_REMESH_ITERATIONS:,}, got 1000000"):
            call(10**6)
        with pytest.raises(ValueError, match="iterations must be a positive integer, got 2.5"):
            call(2.5)


def test_subnormal_coordinates_are_normalised_too():
    """Below 2**-1022 the single power-of-two factor overflowed a float: OverflowError from the CLI."""
    V = torch.tensor([[0.0, 0, 0], [1e-310, 0, 0], [0, 1e-310, 0]], dtype=torch.float64)
    W = normalize_unit_diagonal(V)
    assert torch.allclose(W, normalize_unit_diagonal(V * 1e300 * 1e10), rtol=0, atol=1e-6)
    assert math.isclose(float((W.max(0).values - W.min(0).values).norm()), 1.0, rel_tol=1e-12)


def test_a_run_in_a_worker_thread_exits_cleanly():
    """pymeshlab is imported with meshmei: a process whose first pymeshlab import ran in a worker thread (a
    3D-MEI from a built-in start, run in a threading.Thread) aborted at exit with a corrupted heap
    (malloc_consolidate), after its results were out. Here the same run, in its own process, ends with code 0."""
    code = ("import threading\n"
            "from meshmei.mei import optimize_mei\n"
            "from meshmei.encoders import GaborSimpleCell\n"
            "t = threading.Thread(target=optimize_mei, args=(GaborSimpleCell(), 0, 'sphere'),\n"
            "                     kwargs=dict(steps=3, seeds=(0,), image_size=16, n_vertices=64))\n"
            "t.start(); t.join(); print('finished')\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0 and proc.stdout.strip() == "finished", proc.stderr[-2000:]
    assert "malloc" not in proc.stderr and "not the main thread" not in proc.stderr


def test_meshmei_imported_in_a_worker_thread_leaves_pymeshlab_out_and_exits_cleanly():
    """meshmei imported first in a worker thread (pytest-xdist's controlling process does so to look up a
    warning class) brought pymeshlab in there, and such processes aborted at exit: now pymeshlab waits for its
    first use, and the process ends with code 0."""
    code = ("import sys, threading\n"
            "t = threading.Thread(target=lambda: __import__('meshmei.reconstruct'), name='loader')\n"
            "t.start(); t.join(); print('meshmei' in sys.modules, 'pymeshlab' in sys.modules)\n")
    proc = subprocess.run([sys.executable, "-W", "default", "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0 and proc.stdout.strip() == "True False", proc.stdout + proc.stderr[-2000:]
    assert proc.stderr == "", proc.stderr[-2000:]


def test_pymeshlab_first_used_in_a_worker_thread_says_to_import_meshmei_in_the_main_thread():
    """Only the caller can bring pymeshlab into the main thread: first used in a worker thread (a start mesh
    made there) it says so, in a warning that names the thread (such a process aborted at exit; this one
    leaves by os._exit, past the crash, so that the test reads the warning alone)."""
    code = ("import os, threading\n"
            "make = lambda: __import__('meshmei').initial_mesh('sphere', n_vertices=64)\n"
            "t = threading.Thread(target=make, name='loader')\n"
            "t.start(); t.join(); print('made', flush=True); os._exit(0)\n")
    proc = subprocess.run([sys.executable, "-W", "default", "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0 and proc.stdout.strip() == "made", proc.stderr[-2000:]
    assert "RuntimeWarning: pymeshlab is first used in the thread 'loader', not the main thread" in proc.stderr
    assert "import meshmei at the top of your program, in the main thread" in proc.stderr
