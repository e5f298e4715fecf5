import igl
import numpy as np
import pytest
import scipy.sparse as sp
import torch

from meshmei import operators as ops
from meshmei.errors import MeshError
from meshmei.topology import mesh_topology

from conftest import grid_sheet, hard_cases, icosphere, perturbed_sphere, random_rotation


@pytest.fixture(scope="module", params=["bunny", "teapot", "sheet", "perturbed_sphere"])
def igl_mesh(request):
    if request.param in ("bunny", "teapot"):
        return request.getfixturevalue(f"{request.param}64")
    if request.param == "sheet":
        from meshmei.shapes import initial_mesh

        V, F = initial_mesh("sheet", n_vertices=400, dtype=torch.float64)
        return V, F
    return perturbed_sphere(3, 0.05)


def _to_scipy(L):
    idx = L.indices().numpy()
    return sp.coo_matrix((L.values().detach().numpy(), (idx[0], idx[1])), shape=L.shape).tocsr()


def test_cotmatrix_equals_igl(igl_mesh):
    V, F = igl_mesh
    Li = igl.cotmatrix(V.numpy(), F.numpy()).tocsr()
    L = _to_scipy(ops.cotmatrix(V, F))
    assert abs(L - Li).max() <= 1e-10 * abs(Li).max()
    # the matrix-free apply is the same operator
    X = torch.randn(V.shape[0], 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(ops.cot_laplacian(V, F, X), torch.from_numpy(Li @ X.numpy()), rtol=1e-10, atol=1e-10 * abs(Li).max())


def test_edges_equal_igl(igl_mesh):
    _, F = igl_mesh
    E = ops.edges(F).numpy()
    Ei = np.sort(igl.edges(F.numpy()), axis=1)
    Ei = Ei[np.lexsort((Ei[:, 1], Ei[:, 0]))]
    np.testing.assert_array_equal(E, Ei)


def test_adjacency_equals_igl(igl_mesh):
    V, F = igl_mesh
    ours = ops.adjacency_list(F, V.shape[0])
    ref = igl.adjacency_list(F.numpy())
    assert len(ours) == len(ref)
    assert all(set(a) == set(b) and len(a) == len(b) for a, b in zip(ours, ref))


def test_doublearea_equals_igl(igl_mesh):
    V, F = igl_mesh
    ref = torch.from_numpy(igl.doublearea(V.numpy(), F.numpy()))
    torch.testing.assert_close(ops.doublearea(V, F), ref, rtol=1e-12, atol=1e-12 * ref.max())


def test_massmatrix_equals_igl_voronoi(igl_mesh):
    V, F = igl_mesh
    ref = igl.massmatrix(V.numpy(), F.numpy(), igl.MASSMATRIX_TYPE_VORONOI).diagonal()
    M = ops.massmatrix(V, F).numpy()
    assert np.abs(M - ref).max() <= 1e-10 * ref.max()


def test_vertex_and_face_normals_equal_igl(igl_mesh):
    V, F = igl_mesh
    Vn, Fn = V.numpy(), F.numpy()
    ref = igl.per_vertex_normals(Vn, Fn, igl.PER_VERTEX_NORMALS_WEIGHTING_TYPE_AREA)
    torch.testing.assert_close(ops.vertex_normals(V, F), torch.from_numpy(ref), rtol=0, atol=1e-10)
    ref_f = igl.per_face_normals(Vn, Fn, np.array([0.0, 0.0, 0.0]))
    torch.testing.assert_close(ops.face_normals(V, F), torch.from_numpy(ref_f), rtol=0, atol=1e-10)


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_a_face_repeating_a_vertex_leaves_the_cotmatrix_as_it_was(dtype, tol):
    """A zero-area face [a, a, b] (welding an STL sliver gives them) adds nothing in exact arithmetic; its
    corner facing the edge a-a has a guarded cotangent of about 1 / (2 eps), whose +C and -C on L[a, a] left
    the entry off by 1.9e-5 in float64 and 5.6e-3 in float32, and its row no longer summing to zero."""
    V, F = icosphere(2)
    V = V.to(dtype)
    a, b = int(F[0, 0]), int(F[0, 1])
    with_face = torch.cat([F, torch.tensor([[a, a, b]])])
    L, Ld = ops.cotmatrix(V, F).to_dense(), ops.cotmatrix(V, with_face).to_dense()
    assert float((Ld - L).abs().max()) <= tol * float(L.abs().max())
    assert float(Ld.sum(1).abs().max()) <= tol * float(L.abs().max())
    torch.testing.assert_close(ops.cot_laplacian(V, with_face), Ld @ V, rtol=0, atol=tol * float(L.abs().max()))
    ref = igl.cotmatrix(V.double().numpy(), F.numpy()).toarray()
    assert np.abs(Ld.double().numpy() - ref).max() <= tol * np.abs(ref).max()


def test_cotmatrix_properties_on_adversarial_mesh():
    # symmetric, zero row sums, negative semi-definite, annihilates constants; unreferenced vertex row empty
    V, F = hard_cases()["unreferenced_vertices"]
    L = ops.cotmatrix(V, F).to_dense()
    torch.testing.assert_close(L, L.T, rtol=0, atol=0)
    torch.testing.assert_close(L.sum(1), torch.zeros(V.shape[0], dtype=V.dtype), rtol=0, atol=1e-12)
    assert torch.linalg.eigvalsh(L).max() < 1e-10
    assert torch.all(L[5] == 0) and torch.all(L[:, 5] == 0)


def test_operators_rigid_motion():
    V, F = perturbed_sphere(2)
    R, t = random_rotation(3), torch.tensor([0.3, -2.0, 5.0], dtype=torch.float64)
    W = V @ R.T + t
    torch.testing.assert_close(ops.doublearea(W, F), ops.doublearea(V, F))
    torch.testing.assert_close(ops.massmatrix(W, F), ops.massmatrix(V, F))
    torch.testing.assert_close(ops.cot_weights(W, F), ops.cot_weights(V, F))
    torch.testing.assert_close(ops.vertex_normals(W, F), ops.vertex_normals(V, F) @ R.T)
    torch.testing.assert_close(ops.uniform_laplacian(W, F), ops.uniform_laplacian(V, F) @ R.T)


def test_uniform_laplacian_matches_dense_reference():
    V, F = perturbed_sphere(1)
    nbrs = [set() for _ in range(V.shape[0])]
    for f in F.tolist():
        for a in range(3):
            for b in range(3):
                if f[a] != f[b]:
                    nbrs[f[a]].add(f[b])
    ref = torch.stack([V[i] - V[sorted(s)].mean(0) for i, s in enumerate(nbrs)])
    torch.testing.assert_close(ops.uniform_laplacian(V, F), ref, rtol=1e-12, atol=1e-14)


def test_sphere_normals_point_outward_and_mass_sums_to_area():
    V, F = icosphere(3)
    N = ops.vertex_normals(V, F)
    assert (torch.sum(N * V, 1) > 0.99).all()
    torch.testing.assert_close(ops.massmatrix(V, F).sum(), ops.face_areas(V, F).sum())


def test_batched_equals_looped_and_float32():
    V, F = perturbed_sphere(2)
    Vb = torch.stack([V, V * 2.0 + 1.0, V @ random_rotation(1).T])
    for fn in (ops.doublearea, ops.massmatrix, ops.vertex_normals, ops.face_normals, ops.uniform_laplacian, ops.cot_laplacian):
        out = fn(Vb, F)
        for b in range(3):
            torch.testing.assert_close(out[b], fn(Vb[b], F))
        out32 = fn(V.float(), F)
        assert out32.dtype == torch.float32
        torch.testing.assert_close(out32.double(), fn(V, F), rtol=1e-4, atol=1e-5)


def test_topology_is_cached_per_face_tensor_and_invalidated_by_mutation():
    V, F = icosphere(1)
    t1 = mesh_topology(F, V.shape[0])
    assert mesh_topology(F, V.shape[0]) is t1
    assert mesh_topology(F.clone(), V.shape[0]) is not t1
    G = F.clone()
    tg = mesh_topology(G, V.shape[0])
    G[0] = G[0, [1, 2, 0]]  # in-place change bumps the version counter
    assert mesh_topology(G, V.shape[0]) is not tg


def test_face_caches_see_edits_that_bypass_the_version_counter():
    """Faces edited through ``.numpy()`` (no version bump) get a fresh topology, index check and image."""
    from meshmei.render import RenderSettings, render
    V, F = icosphere(2)
    V = V.float()
    st = RenderSettings(image_size=32)
    render(V, F, settings=st)  # caches the topology and the index check of F
    F.numpy()[:40] = F.numpy()[:40, [0, 2, 1]]  # turn 40 faces over behind torch's back
    assert torch.equal(mesh_topology(F, V.shape[0]).edges, mesh_topology(F.clone(), V.shape[0]).edges)
    assert torch.equal(render(V, F, settings=st), render(V, F.clone(), settings=st))
    F.numpy()[0, 0] = V.shape[0]  # out of range, again unseen by torch
    with pytest.raises(MeshError, match="out of range"):
        render(V, F, settings=st)


def test_int32_faces_of_a_large_mesh_give_the_int64_topology():
    """Edge keys lo * n + hi overflowed int32 from n = 46,341 on: wrong edges, silently."""
    n = 70000
    F = torch.tensor([[n - 3, n - 2, n - 1], [n - 1, n - 2, 5]])
    t32, t64 = mesh_topology(F.int(), n), mesh_topology(F, n)
    assert t32.edges.dtype == torch.int64 and torch.equal(t32.edges, t64.edges)
    assert torch.equal(t32.cot_pattern[0], t64.cot_pattern[0]) and torch.equal(t32.boundary_vertex, t64.boundary_vertex)


@pytest.mark.parametrize("scale", [1e-12, 1e-10, 1e10, 1e15])
def test_float32_operators_hold_at_extreme_scales(scale):
    """Areas, normals, cotangents and masses of a float32 mesh scaled far up or down equal the float64
    results (the squared cross products left float32's range: area 0 or inf, normals 0, cotangents 0)."""
    V, F = icosphere(1)
    V = V.double()
    Vs = (V * scale).float().requires_grad_()
    ref, got = ops.doublearea(V * scale, F) / scale ** 2, ops.doublearea(Vs, F).double() / scale ** 2
    torch.testing.assert_close(got, ref, rtol=1e-5, atol=0)
    torch.testing.assert_close(ops.face_normals(Vs, F).double(), ops.face_normals(V, F), rtol=0, atol=1e-5)
    torch.testing.assert_close(ops.vertex_normals(Vs, F).double(), ops.vertex_normals(V, F), rtol=0, atol=1e-5)
    torch.testing.assert_close(ops.cot_weights(Vs, F).double(), ops.cot_weights(V, F), rtol=0, atol=1e-4)
    mass = ops.massmatrix(Vs, F)
    mass = (mass.to_dense() if mass.is_sparse else mass).double() / scale ** 2
    ref_mass = ops.massmatrix(V, F)
    torch.testing.assert_close(mass, ref_mass.to_dense() if ref_mass.is_sparse else ref_mass, rtol=1e-5, atol=0)
    ops.doublearea(Vs, F).sum().backward()
    assert bool(torch.isfinite(Vs.grad).all())


def test_topology_face_edges_and_degree():
    V, F = icosphere(2)
    topo = mesh_topology(F, V.shape[0])
    E = topo.edges
    for k in range(3):
        a, b = F[:, (k + 1) % 3], F[:, (k + 2) % 3]
        e = E[topo.face_edges[:, k]]
        assert torch.equal(e[:, 0], torch.minimum(a, b)) and torch.equal(e[:, 1], torch.maximum(a, b))
    assert topo.n_edges == 3 * F.shape[0] // 2  # closed manifold
    assert torch.equal(topo.degree, torch.bincount(E.reshape(-1), minlength=V.shape[0]))


def test_topology_rejects_bad_face_arrays():
    # these went on into torch and stopped there (bincount, max of an empty tensor, a size mismatch)
    from meshmei.errors import MeshError

    V, F = icosphere(1)
    with pytest.raises(MeshError, match=r"negative vertex index \(-1\)"):
        ops.edges(torch.tensor([[0, 1, -1]]))
    with pytest.raises(MeshError, match=r"negative vertex index \(-1\)"):
        ops.adjacency_list(torch.tensor([[0, 1, -1], [1, 2, 3]]), 4)
    with pytest.raises(MeshError, match="vertex index 41, out of range for n_vertices=5"):
        ops.adjacency_list(F, 5)
    with pytest.raises(MeshError, match=r"got shape \(0, 3\)"):
        ops.adjacency_list(torch.zeros(0, 3, dtype=torch.int64))
    with pytest.raises(MeshError, match=r"got shape \(1, 4\)"):
        mesh_topology(torch.tensor([[0, 1, 2, 3]]))
    with pytest.raises(MeshError, match="int64 tensor, got a ndarray"):
        mesh_topology(F.numpy())
    with pytest.raises(MeshError, match="int64 tensor, got a torch.float32 tensor"):
        mesh_topology(F.float())
    assert len(ops.adjacency_list(F, V.shape[0] + 2)) == V.shape[0] + 2  # unreferenced trailing vertices


@pytest.mark.parametrize("fn", [ops.doublearea, ops.massmatrix, ops.vertex_normals, ops.face_normals, ops.uniform_laplacian, ops.cot_laplacian, ops.cot_weights])
@pytest.mark.parametrize("case", sorted(hard_cases()))
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_operators_finite_on_hard_cases(fn, case, dtype):
    V, F = hard_cases(dtype)[case]
    V = V.clone().requires_grad_(True)
    out = fn(V, F)
    assert torch.isfinite(out).all()
    g = torch.randn(out.shape, dtype=dtype, generator=torch.Generator().manual_seed(0))
    (grad,) = torch.autograd.grad((out * g).sum(), V, allow_unused=True)
    assert grad is not None and torch.isfinite(grad).all()  # every operator has a graph to V


def test_cotmatrix_gradcheck():
    V, F = perturbed_sphere(0, 0.1)
    V = V.requires_grad_(True)
    X = torch.randn(V.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    assert torch.autograd.gradcheck(lambda V: ops.cot_laplacian(V, F, X), (V,))
    assert torch.autograd.gradcheck(lambda V: ops.massmatrix(V, F), (V,))
    assert torch.autograd.gradcheck(lambda V: ops.vertex_normals(V, F), (V,))


ARRAY_OPS = [ops.doublearea, ops.face_areas, ops.massmatrix, ops.vertex_normals, ops.face_normals,
             ops.uniform_laplacian, ops.cot_laplacian, ops.cot_weights]


@pytest.mark.parametrize("fn", ARRAY_OPS)
def test_operators_take_nested_lists_and_reject_non_arrays(fn):
    # check_mesh takes lists, so every operator does (they stopped at V.ndim with an AttributeError)
    from meshmei.errors import MeshError

    V, F = icosphere(1)
    torch.testing.assert_close(fn(V.tolist(), F.tolist()), fn(V, F))
    torch.testing.assert_close(fn(V.expand(2, -1, -1).tolist(), F), fn(V.expand(2, -1, -1), F))
    with pytest.raises(MeshError, match="V must be a torch tensor or numpy array, got NoneType"):
        fn(None, F)


def test_unchecked_kernels_equal_the_checked_operators():
    V, F = perturbed_sphere(2, 0.05)
    T = ops.corners(V, F)  # (m, 3, 3)
    assert T.shape == (F.shape[0], 3, 3) and torch.equal(T[5, 1], V[F[5, 1]])
    terms = ops.face_terms(T)
    assert isinstance(terms, ops.FaceTerms) and terms.l2.shape == terms.cot.shape == (F.shape[0], 3)
    assert torch.equal(terms.cot, ops.cot_weights(V, F))
    torch.testing.assert_close(terms.dbl, ops.doublearea(V, F), rtol=1e-12, atol=0)
    assert torch.equal(ops.doublearea_from_corners(T), ops.doublearea(V, F))
    torch.testing.assert_close(ops.sq_edge_sum_from_corners(T), terms.l2.sum(-1), rtol=1e-12, atol=0)
    assert torch.equal(ops.massmatrix_from_terms(F, V.shape[0], terms), ops.massmatrix(V, F))
    assert torch.equal(ops.cot_laplacian_from_cot(V, F, terms.cot), ops.cot_laplacian(V, F))
    topo = mesh_topology(F, V.shape[0])
    assert torch.equal(ops.uniform_laplacian_from_topology(V, topo), ops.uniform_laplacian(V, F))


def test_topology_twins_pair_the_two_half_edges_of_each_interior_edge():
    V, F = icosphere(1)
    tw = mesh_topology(F, V.shape[0]).twins.reshape(-1)
    assert bool((tw >= 0).all())  # closed: every half-edge has a twin
    assert torch.equal(tw[tw], torch.arange(tw.numel()))
    f, k = torch.arange(tw.numel()) // 3, torch.arange(tw.numel()) % 3
    g, l = tw // 3, tw % 3
    # the twin runs the other way along the same edge
    assert torch.equal(F[f, (k + 1) % 3], F[g, (l + 2) % 3]) and torch.equal(F[f, (k + 2) % 3], F[g, (l + 1) % 3])
    # an open sheet: boundary half-edges have none
    Vs, Fs = grid_sheet(3, 3)
    tws = mesh_topology(Fs, Vs.shape[0]).twins
    assert int((tws < 0).sum()) == 8  # the 2 x 2 grid's boundary has 8 edges


def test_topology_edge_table_and_corner_cycle_agree_with_the_faces_and_twins():
    """The rasterizer's per-half-edge table, checked against its definition on a sheet (with boundary)."""
    V, F = grid_sheet(4, 3)
    topo = mesh_topology(F, V.shape[0])
    cyc = topo.corner_cycle
    k = torch.arange(3)
    assert torch.equal(cyc[:, :3], F) and torch.equal(cyc[:, 3:6], F[:, (k + 1) % 3])
    assert torch.equal(cyc[:, 6:], F[:, (k + 2) % 3])
    lo, hi, opp, tf, flip = topo.edge_table.view(-1, 5, 3).unbind(1)
    a, b = F[:, (k + 1) % 3], F[:, (k + 2) % 3]
    assert torch.equal(lo, torch.minimum(a, b)) and torch.equal(hi, torch.maximum(a, b)) and bool((lo < hi).all())
    assert torch.equal(flip.bool(), a > b)
    tw = topo.twins
    assert torch.equal(tf, torch.where(tw >= 0, tw // 3, -1))
    inner = tw >= 0
    # the twin face's third corner: on that face, and off the shared edge
    assert bool(((F[tf[inner]] == opp[inner].unsqueeze(1)).any(1)).all())
    assert bool(((opp[inner] != lo[inner]) & (opp[inner] != hi[inner])).all())
    assert torch.equal(opp[~inner], lo[~inner]) and int((~inner).sum()) == 2 * (4 - 1) + 2 * (3 - 1)


@pytest.mark.parametrize("shape", [(7, 2), (1, 7, 2), (3, 7, 2), (1, 1, 7, 2)])
def test_gather_and_index_add_equal_torchs_with_their_gradients(shape):
    """The batch-of-one shortcut (indexing the unbatched rows) changes the speed, not the values."""
    g = torch.Generator().manual_seed(0)
    dim = len(shape) - 2
    X = torch.randn(shape, generator=g, dtype=torch.float64, requires_grad=True)
    idx = torch.randint(0, 7, (4, 3), generator=g)
    out = ops.gather(X, idx, dim)
    ref = X.index_select(dim, idx.reshape(-1)).reshape(*shape[:dim], 4, 3, shape[-1])
    assert torch.equal(out, ref)
    w = torch.randn(out.shape, generator=g, dtype=torch.float64)
    (gx,) = torch.autograd.grad((out * w).sum(), X)
    (gr,) = torch.autograd.grad((ref * w).sum(), X)
    assert torch.equal(gx, gr)
    src = torch.randn(*shape[:dim], 12, shape[-1], generator=g, dtype=torch.float64, requires_grad=True)
    base = torch.zeros(shape, dtype=torch.float64)
    got = ops.index_add(base, dim, idx.reshape(-1), src)
    want = base.index_add(dim, idx.reshape(-1), src)
    assert torch.allclose(got, want, rtol=0, atol=1e-15) and got.shape == want.shape
    (gs,) = torch.autograd.grad((got * X.detach()).sum(), src)
    assert torch.equal(gs, ops.gather(X.detach(), idx.reshape(-1), dim))


@pytest.mark.parametrize("call", [
    lambda: ops.edges(torch.tensor([[0.5, 1.7, 2.9]])),  # truncated to [0, 1, 2] before
    lambda: ops.adjacency_list([[0.9, 1.5, 2.2]], 3),
    lambda: ops.edges(torch.ones(2, 3, dtype=torch.bool)),  # no edges at all before
])
def test_faces_alone_must_be_integers(call):
    with pytest.raises(MeshError, match="F must have an integer dtype"):
        call()


def test_cot_laplacian_checks_the_values_it_is_applied_to():
    """X of another length was accepted, and another dtype, numpy or a missing batch axis gave torch errors."""
    V, F = icosphere(1)
    n = V.shape[0]
    ref = ops.cot_laplacian(V, F, V)
    torch.testing.assert_close(ops.cot_laplacian(V, F, V.float()), ref)  # cast to V's dtype
    torch.testing.assert_close(ops.cot_laplacian(V, F, V.numpy()), ref)
    for X, match in ((torch.ones(n + 1, 3), r"X must have shape \(n, d\)"),
                     (torch.full((n, 3), float("nan")), "X holds NaN"),
                     (torch.ones(n, 3, dtype=torch.complex64), "X must hold real numbers")):
        with pytest.raises(MeshError, match=match):
            ops.cot_laplacian(V, F, X)
    with pytest.raises(MeshError, match=r"\(B, n, d\)"):
        ops.cot_laplacian(torch.stack([V, V]), F, V)


@pytest.mark.parametrize("eps", [float("nan"), -1.0, float("inf"), "1e-9"])
def test_a_bad_eps_is_refused(eps):
    """eps=nan made the cotangent Laplacian loss silently 0 and the mass matrix NaN."""
    V, F = icosphere(1)
    with pytest.raises(MeshError, match="eps must be a finite non-negative number"):
        ops.massmatrix(V, F, eps=eps)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", [(1, 3), (750, 3), (4, 2000, 3), (20000, 3)])
def test_sum_xyz_is_torchs_sum_over_three_bit_for_bit_values_and_gradients(dtype, shape):
    from meshmei.operators import sum_xyz

    g = torch.Generator().manual_seed(shape[-2])
    x = torch.randn(shape, generator=g, dtype=torch.float64) * torch.exp(8 * torch.randn(shape, generator=g, dtype=torch.float64))
    x = x.to(dtype)
    special = torch.tensor([float("inf"), -float("inf"), float("nan"), 0.0, -0.0, 1.0], dtype=dtype)
    x.view(-1)[:6] = special[:x.numel()]
    a, b = x.clone().requires_grad_(), x.clone().requires_grad_()
    w = torch.randn(shape[:-1], generator=g, dtype=torch.float64).to(dtype)
    sa, sb = sum_xyz(a * a), (b * b).sum(-1)
    assert torch.equal(sa.nan_to_num(), sb.nan_to_num()) and torch.equal(sa.isnan(), sb.isnan())
    (w * sa.nan_to_num(0.0, 0.0, 0.0)).sum().backward()
    (w * sb.nan_to_num(0.0, 0.0, 0.0)).sum().backward()
    assert torch.equal(a.grad.nan_to_num(), b.grad.nan_to_num()) and torch.equal(a.grad.isnan(), b.grad.isnan())
    y = x.nan_to_num(0.0, 1.0, -1.0)  # signed terms: the order of the additions shows
    assert torch.equal(sum_xyz(y), y.sum(-1))
    # three negative zeros: -0 here, +0 from torch's reduction; equal as numbers
    z = torch.full((2, 3), -0.0, dtype=dtype)
    assert (sum_xyz(z) == z.sum(-1)).all()


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64, torch.complex64])
def test_all_finite_agrees_with_isfinite_at_every_position_and_extreme(dtype):
    """One reduction (the largest |x|) in place of isfinite().all(): NaN or Inf anywhere, alone or beside the
    dtype's largest finite values, is caught; huge finite values, zeros and empty tensors pass."""
    from meshmei._checks import all_finite

    big = torch.finfo(dtype).max if not dtype.is_complex else torch.finfo(torch.float32).max
    for bad in (float("nan"), float("inf"), float("-inf")):
        for i in range(7):
            x = torch.full((7,), big, dtype=dtype) * (-1) ** torch.arange(7)
            x[i] = bad
            assert not bool(torch.isfinite(x).all())
            assert all_finite(x) is False
    assert all_finite(torch.full((3, 4), big, dtype=dtype)) is True
    assert all_finite(torch.zeros(0, 3, dtype=dtype)) is True and all_finite(torch.zeros(5, dtype=dtype)) is True
    assert all_finite(torch.arange(5)) is True  # integers are finite
    import warnings

    x = torch.ones(3, dtype=dtype, requires_grad=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a tensor with a graph: no 'converting to a scalar' warning
        assert all_finite(x * 2) is True
