"""Validation of the rasterizer against independent ray casting, autograd checks and finite differences."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from meshmei.render import (Camera, RenderError, RenderSettings, axis_angle_to_matrix, camera_from_angles, lambert,
                            rasterize, render)
from meshmei.render.native import native_status, torch_reference
from meshmei.render.passes import run_passes
from meshmei.render.raster import prepare_inputs
from meshmei.render.samples import _SampleGeometry, face_table, seg_dist
from meshmei.render.shading import shade_samples
from meshmei.shapes import initial_mesh, target_mesh


VIEWS = [(0.0, 0.0), (60.0, 20.0), (200.0, -30.0), (120.0, 70.0)]


# ---------------------------------------------------------------------------------------------
# references kept in the tests: a ray generator, libigl's AABB ray caster, and a brute-force
# float64 Moller-Trumbore that adjudicates every pixel where the two disagree
def pixel_rays(cam: Camera, S: int, sub: int = 1):
    """Ray origin and (B=1) directions through pixel centres (or ``sub x sub`` sub-pixel centres).

    Directions have unit component along the viewing axis, so the ray parameter is the view depth.
    """
    eye, R = cam.frame(torch.float64)
    eye, R = eye[0].numpy(), R[0].numpy()
    f = cam.focal_pixels(S)
    g = (np.arange(S)[:, None] + (np.arange(sub) + 0.5)[None, :] / sub).reshape(-1)
    v, u = np.meshgrid(g, g, indexing="ij")
    x, y = (u - S / 2) / f, -(v - S / 2) / f
    D = x[..., None] * R[0] + y[..., None] * R[1] + R[2]
    return eye, D.reshape(-1, 3)


def igl_first_hits(V, F, eye, D):
    import igl

    tree = igl.AABB()
    tree.init(V, F)
    I, T, _ = tree.intersect_ray_first(V, F, np.tile(eye, (len(D), 1)), D)
    return I, T


def brute_first_hit(V, F, o, d):
    """Nearest hit (face, t) of one ray over all faces, float64, inclusive edges; (-1, inf) when none."""
    A, B, C = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    e1, e2 = B - A, C - A
    p = np.cross(d, e2)
    det = (e1 * p).sum(1)
    ok = np.abs(det) > 1e-300
    det = np.where(ok, det, 1.0)
    s = o - A
    u = (s * p).sum(1) / det
    q = np.cross(s, e1)
    v = (d * q).sum(1) / det
    t = (e2 * q).sum(1) / det
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    if not hit.any():
        return -1, np.inf, np.inf
    idx = np.nonzero(hit)[0]
    order = idx[np.argsort(t[idx])]
    second = t[order[1]] if len(order) > 1 else np.inf
    return int(order[0]), float(t[order[0]]), float(second)


@pytest.fixture(scope="module")
def targets():
    return {name: target_mesh(name, dtype=torch.float64) for name in ("bunny", "teapot")}


@pytest.fixture(scope="module")
def sphere64():
    return initial_mesh("sphere", n_vertices=2500, dtype=torch.float64)


# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("name", ["bunny", "teapot"])
def test_visibility_matches_ray_casting(targets, name, dtype):
    V, F = targets[name]
    Vn, Fn = V.numpy(), F.numpy()
    S = 128
    tol_tie = 1e-5  # relative depth difference under which two faces tie for a pixel
    for az, el in VIEWS:
        cam = camera_from_angles(az, el, 2.0)
        fr = rasterize(V.to(dtype), F, camera=cam, settings=RenderSettings(image_size=S))
        eye, D = pixel_rays(cam, S)
        I, T = igl_first_hits(Vn, Fn, eye, D)
        fid = fr.face_id[0].reshape(-1).numpy()
        dep = fr.depth[0].reshape(-1).double().numpy()
        covered = (I >= 0) | (fid >= 0)
        agree = (I == fid)[covered].mean()
        assert covered.sum() > 1500
        assert agree >= 0.995, (name, az, el, agree)
        same = (I == fid) & (fid >= 0)
        rel = np.abs(dep[same] - T[same]) / T[same]
        assert rel.max() < 1e-5, (name, az, el, rel.max())
        # every disagreement: libigl missed or mis-ordered (the exact reference agrees with us), or a tie
        for p in np.nonzero(covered & (I != fid))[0]:
            f_ref, t_ref, t_next = brute_first_hit(Vn, Fn, eye, D[p])
            if f_ref == fid[p]:
                assert abs(dep[p] - t_ref) <= 1e-5 * t_ref
            else:
                assert fid[p] >= 0 and abs(dep[p] - t_ref) <= tol_tie * t_ref, (name, az, el, p, f_ref, fid[p])


def silhouette_band(ss):
    """Pixels partly covered by the supersampled reference, and their 8-neighbours."""
    from scipy.ndimage import binary_dilation

    return binary_dilation((ss > 0) & (ss < 1), structure=np.ones((3, 3), bool))


def supersampled_coverage(V, F, cam, S, sub=4):
    eye, D = pixel_rays(cam, S, sub)
    I, _ = igl_first_hits(V.numpy(), F.numpy(), eye, D)
    return (I.reshape(S, sub, S, sub) >= 0).mean((1, 3))


def test_coverage_matches_supersampled_ray_casting(targets, sphere64):
    """Mean |coverage - 16x supersampled coverage| along silhouettes (see docs/rendering.md for the table)."""
    S = 128
    meshes = {"sphere": sphere64, **targets}
    errs, hard_errs = [], []
    for name, (V, F) in meshes.items():
        for az, el in VIEWS[:2]:
            cam = camera_from_angles(az, el, 2.0)
            ss = supersampled_coverage(V, F, cam, S)
            band = silhouette_band(ss)
            fr = rasterize(V, F, camera=cam, settings=RenderSettings(image_size=S))
            c = fr.coverage[0].numpy()
            errs.append(np.abs(c - ss)[band].mean())
            hard_errs.append(np.abs((fr.face_id[0].numpy() >= 0) - ss)[band].mean())
            assert 0 <= c.min() and c.max() <= 1
    errs, hard_errs = np.array(errs), np.array(hard_errs)
    # measured 0.017 - 0.049 at the default sigma = 0.2 px; a hard (aliased) mask gives 0.065 - 0.076
    assert errs.max() < 0.06, errs
    assert errs.mean() < 0.045, errs
    assert errs.mean() < 0.5 * hard_errs.mean(), (errs, hard_errs)


def test_coverage_is_area_like_on_a_straight_edge():
    """A half-plane edge through a pixel centre gives coverage 1/2; far pixels give exactly 0 and 1."""
    # a big square whose left edge is x = 0: the boundary between the middle columns, u = S/2
    V = torch.tensor([[0.0, -5, 0], [5, -5, 0], [5, 5, 0], [0, 5, 0]], dtype=torch.float64)
    F = torch.tensor([[0, 1, 2], [0, 2, 3]])
    S = 16
    cam = Camera(fov_degrees=30.0)
    fr = rasterize(V, F, camera=cam, settings=RenderSettings(image_size=S))
    row = fr.coverage[0, S // 2]
    # pixel centres sit at +-0.5 px from the edge at u = 8
    sig = torch.sigmoid(torch.tensor(0.5 / 0.2, dtype=torch.float64))
    torch.testing.assert_close(row[S // 2], sig)
    torch.testing.assert_close(row[S // 2 - 1], 1 - sig)
    assert bool((row[: S // 2 - 3] == 0).all()) and bool((row[S // 2 + 3:] == 1).all())


# ---------------------------------------------------------------------------------------------
def _one_triangle():
    return (torch.tensor([[-0.31, -0.27, 0.05], [0.36, -0.21, -0.1], [0.02, 0.33, 0.12]], dtype=torch.float64),
            torch.tensor([[0, 1, 2]]))


def _two_triangles(shared: bool):
    if shared:  # a bent quad: two faces sharing an edge
        V = torch.tensor([[-0.33, -0.29, 0.0], [0.31, -0.26, 0.1], [0.29, 0.32, -0.05], [-0.28, 0.3, 0.15]],
                         dtype=torch.float64)
        return V, torch.tensor([[0, 1, 2], [0, 2, 3]])
    # two overlapping triangles at different depths (occlusion inside the silhouette)
    V = torch.tensor([[-0.37, -0.31, 0.0], [0.21, -0.27, 0.02], [-0.05, 0.29, -0.01],
                      [-0.12, -0.19, 0.3], [0.38, -0.05, 0.27], [0.09, 0.36, 0.33]], dtype=torch.float64)
    return V, torch.tensor([[0, 1, 2], [3, 4, 5]])


@pytest.mark.parametrize("S", [8, 16])
@pytest.mark.parametrize("case", ["one", "shared", "overlap"])
def test_gradcheck(case, S):
    V, F = _one_triangle() if case == "one" else _two_triangles(case == "shared")
    st = RenderSettings(image_size=S, sigma=0.5)
    cam = Camera(eye=(0.1, -0.2, 1.6), fov_degrees=40.0)
    light = torch.tensor([0.4, 0.6, 1.5], dtype=torch.float64, requires_grad=True)
    t = torch.tensor([0.02, -0.01, 0.03], dtype=torch.float64, requires_grad=True)
    Vg = V.clone().requires_grad_(True)

    def f(Vx, lx, tx):
        return render(Vx, F, camera=cam, light=lx, translation=tx, settings=st)

    img = f(Vg, light, t)
    assert (img[0, 0] != st.background).sum() > 4  # the triangle is in view and covers pixels
    assert torch.autograd.gradcheck(f, (Vg, light, t), eps=1e-6, atol=1e-5, rtol=1e-3)


@pytest.mark.parametrize("S", [8, 16])
def test_gradcheck_fragments(S):
    V, F = _two_triangles(shared=True)
    st = RenderSettings(image_size=S)
    cam = Camera(eye=(0.1, -0.2, 1.6), fov_degrees=40.0)

    def f(Vx):
        fr = rasterize(Vx, F, camera=cam, settings=st)
        return fr.bary, fr.depth, fr.coverage

    assert torch.autograd.gradcheck(f, (V.clone().requires_grad_(True),), eps=1e-6, atol=1e-5, rtol=1e-3)


def _fd_cosine(fn, X, dirs, h):
    X = X.detach().clone().requires_grad_(True)
    fn(X).backward()
    ad = torch.stack([(X.grad * d).sum() for d in dirs])
    with torch.no_grad():
        fd = torch.stack([(fn(X + h * d) - fn(X - h * d)) / (2 * h) for d in dirs])
    return torch.nn.functional.cosine_similarity(fd, ad, 0).item(), fd, ad


def test_finite_differences_along_vertex_directions(sphere64):
    V, F = sphere64
    g = torch.Generator().manual_seed(0)
    W = torch.randn(1, 1, 64, 64, generator=g, dtype=torch.float64)
    light = torch.tensor([1.0, 1.0, 3.0], dtype=torch.float64)
    st = RenderSettings(image_size=64)  # default softness
    dirs = [torch.randn(V.shape, generator=g, dtype=torch.float64) for _ in range(12)]
    cos, fd, ad = _fd_cosine(lambda X: (render(X, F, light=light, settings=st) * W).sum(), V, dirs, 1e-5)
    assert cos > 0.99, (cos, fd, ad)


def test_finite_differences_along_rigid_translation(sphere64):
    V, F = sphere64
    g = torch.Generator().manual_seed(1)
    W = torch.randn(1, 1, 64, 64, generator=g, dtype=torch.float64)
    st = RenderSettings(image_size=64)
    dirs = [torch.tensor(d, dtype=torch.float64) for d in ([1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0.6, -0.8, 0.3])]
    # translating every vertex == the translation argument; check both routes
    cos, fd, ad = _fd_cosine(lambda t: (render(V, F, translation=t, settings=st) * W).sum(),
                             torch.zeros(3, dtype=torch.float64), dirs, 1e-5)
    assert cos > 0.99, (cos, fd, ad)
    # the silhouette alone (uniform shade): only soft coverage carries the gradient
    flat = RenderSettings(image_size=64, ambient=1.0, light_intensity=0.0)
    cos, fd, ad = _fd_cosine(lambda t: (render(V + t, F, settings=flat) * W).sum(),
                             torch.zeros(3, dtype=torch.float64), dirs, 1e-5)
    assert cos > 0.99, (cos, fd, ad)
    assert ad.abs().max() > 1.0  # silhouette gradients are not vanishing


def test_finite_differences_light_and_camera(sphere64):
    V, F = sphere64
    g = torch.Generator().manual_seed(2)
    W = torch.randn(1, 1, 32, 32, generator=g, dtype=torch.float64)
    st = RenderSettings(image_size=32)
    dirs = [torch.randn(3, generator=g, dtype=torch.float64) for _ in range(4)]
    cos, *_ = _fd_cosine(lambda L: (render(V, F, light=L, settings=st) * W).sum(),
                         torch.tensor([0.5, 1.0, 2.0], dtype=torch.float64), dirs, 1e-5)
    assert cos > 0.99
    cos, *_ = _fd_cosine(lambda e: (render(V, F, camera=Camera(eye=e), settings=st) * W).sum(),
                         torch.tensor([0.1, 0.2, 2.4], dtype=torch.float64), dirs, 1e-5)
    assert cos > 0.99


def disk(n=48, r=0.4):
    a = torch.linspace(0, 2 * np.pi, n + 1, dtype=torch.float64)[:-1]
    V = torch.cat([torch.zeros(1, 3, dtype=torch.float64),
                   torch.stack([r * torch.cos(a), r * torch.sin(a), torch.zeros_like(a)], 1)])
    F = torch.tensor([[0, 1 + i, 1 + (i + 1) % n] for i in range(n)])
    return V, F


def test_silhouette_sign_disk():
    """Moving a disk right brightens its right edge (white disk on gray) and the gradient agrees."""
    V, F = disk()
    S = 64
    st = RenderSettings(image_size=S, ambient=1.0, light_intensity=0.0, background=0.0)
    t = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    img = render(V, F, translation=t, settings=st)[0, 0]
    cols = torch.nonzero((img > 0).any(0)).squeeze(1)
    right = slice(int(cols.max()) - 2, S)  # the columns at the disk's right edge
    left = slice(0, int(cols.min()) + 3)
    edge_sum = img[:, right].sum()
    edge_sum.backward()
    assert t.grad[0] > 0
    moved = render(V, F, translation=torch.tensor([0.01, 0.0, 0.0], dtype=torch.float64), settings=st)[0, 0]
    assert moved[:, right].sum() > edge_sum
    assert moved[:, left].sum() < img[:, left].sum().detach()
    t2 = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    render(V, F, translation=t2, settings=st)[0, 0][:, left].sum().backward()
    assert t2.grad[0] < 0


def test_default_camera_orientation():
    """World +x is image right and +y image up; the default camera is overhead on +z."""
    V = torch.tensor([[0.3, 0.0, 0.0], [0.5, 0.0, 0.0], [0.4, 0.2, 0.0]], dtype=torch.float64)
    F = torch.tensor([[0, 1, 2]])
    fr = rasterize(V, F, settings=RenderSettings(image_size=64))
    rows, cols = torch.nonzero(fr.face_id[0] >= 0).unbind(1)
    assert cols.float().mean() > 40 and rows.float().mean() < 32
    torch.testing.assert_close(fr.depth[0][fr.face_id[0] >= 0], torch.full_like(fr.depth[0][fr.face_id[0] >= 0], 2.5))
    torch.testing.assert_close(fr.bary.sum(-1)[0][fr.face_id[0] >= 0], torch.ones(len(rows), dtype=torch.float64))


def test_batch_equals_single_renders(sphere64):
    V, F = sphere64
    cam = camera_from_angles(torch.tensor([0.0, 40.0, 250.0]), torch.tensor([0.0, 10.0, -60.0]), 2.2)
    lights = torch.tensor([[0.0, 0.0, 3.0], [2.0, 0.0, 1.0], [-1.0, 2.0, 0.5]], dtype=torch.float64)
    rot = axis_angle_to_matrix(torch.tensor([[0.0, 0.0, 0.0], [0.3, 0.1, 0.0], [0.0, 1.0, 0.5]], dtype=torch.float64))
    st = RenderSettings(image_size=32)
    batch = render(V * torch.tensor([1.0, 0.7, 1.2], dtype=torch.float64), F, camera=cam, light=lights,
                   rotation=rot, settings=st)
    assert batch.shape == (3, 1, 32, 32)
    for b in range(3):
        one = render(V * torch.tensor([1.0, 0.7, 1.2], dtype=torch.float64), F,
                     camera=Camera(eye=cam.eye[b], at=cam.at[b], up=cam.up[b]), light=lights[b],
                     rotation=rot[b], settings=st)
        torch.testing.assert_close(batch[b], one[0])


def test_float32_matches_float64(sphere64):
    V, F = sphere64
    st = RenderSettings(image_size=64)
    a = render(V, F, settings=st)
    b = render(V.float(), F, settings=st)
    assert b.dtype == torch.float32
    assert (a.float() - b).abs().max() < 1e-3


# ---------------------------------------------------------------------------------------------
# the steps inside rasterize: checked inputs, then the passes
def test_prepare_inputs_broadcasts_poses_and_cameras():
    V, F = initial_mesh("sphere", n_vertices=80)
    cams = camera_from_angles(torch.tensor([0.0, 90.0, 180.0]), torch.zeros(3))
    inp = prepare_inputs(V, F, cams, None, None, None)
    assert inp.batch_size == 3 and inp.n_vertices == V.shape[0] and inp.settings == RenderSettings()
    Vw, eye, R = inp.expanded(3)
    assert Vw.shape == (3, V.shape[0], 3) and eye.shape == (3, 3) and R.shape == (3, 3, 3)
    with pytest.raises(RenderError, match="camera has batch size 3, incompatible with batch size 2"):
        prepare_inputs(torch.stack([V, V]), F, cams, None, None, None)


def test_run_passes_pairs_every_covered_pixel_with_its_face():
    V, F = initial_mesh("sphere", n_vertices=300)
    st = RenderSettings(image_size=32)
    inp = prepare_inputs(V, F, None, None, None, st)
    Vw, eye, R = inp.expanded(inp.batch_size)
    r = run_passes(Vw, inp.F, eye, R, inp.camera, st, inp.n_vertices)
    assert int(r.hit.sum()) == r.inside.pix.numel() == int((r.face_id >= 0).sum()) > 0
    assert torch.equal(r.face_id.view(-1)[r.inside.pix], r.inside.f)
    torch.testing.assert_close(r.inside.l.sum(0), torch.ones(r.inside.pix.numel()))
    assert r.fringe_pix.numel() > 0 and bool((r.coverage[r.fringe_pix] < 1).all())
    frags = rasterize(V, F, settings=st)
    torch.testing.assert_close(frags.coverage.view(-1), r.coverage, rtol=0, atol=0)


def _shade_inputs(N=40, seed=0):
    g = torch.Generator().manual_seed(seed)
    l = torch.rand(3, N, generator=g, dtype=torch.float64)
    l = l / l.sum(0)
    iz = 0.3 + torch.rand(3, N, generator=g, dtype=torch.float64)
    corners = torch.randn(3, 6, N, generator=g, dtype=torch.float64)
    light = 3 * torch.randn(3, N, generator=g, dtype=torch.float64)
    return l, iz, corners, light


def _shade_reference(l, iz, corners, light):
    """The same shade written with autograd: perspective correction, interpolation, then lambert."""
    q = (l * iz).t()
    s = q.sum(1, keepdim=True)
    bary = q / torch.where(s > 0, s, torch.ones_like(s))
    PN = (bary.unsqueeze(-1) * corners.permute(2, 0, 1)).sum(1)
    return lambert(PN[:, :3], PN[:, 3:], light.t(), ambient=0.2, intensity=0.8, albedo=0.9)


@pytest.fixture(params=["compiled", "torch"])
def kernels(request):
    """The hand-written backwards run twice: the compiled kernels (where a C compiler is found) and torch."""
    if request.param == "torch":
        with torch_reference():
            yield request.param
    else:
        if not native_status()["compiled"]:
            pytest.skip(f"no compiled kernels: {native_status()['reason']}")
        yield request.param


def test_shade_samples_gradient_matches_autograd_and_finite_differences(kernels):
    """The hand-written backward of shade_samples against gradcheck and against the autograd composition,
    including unlit points (n . l < 0), a zero-length normal and a sample with l * iz summing to zero."""
    l, iz, corners, light = _shade_inputs()
    corners[:, 3:, 0] = 0.0  # zero normal: held at eps, finite gradient
    l[:, 1] = torch.tensor([1.0, -1.0, 0.0], dtype=torch.float64)  # sum of l * iz is 0 when iz is equal
    iz[:, 1] = 0.5
    args = [x.clone().requires_grad_() for x in (l, iz, corners, light)]

    def f(*a):
        return shade_samples(*a, ambient=0.2, intensity=0.8, albedo=0.9)

    out = f(*args)
    assert bool((out == 0.9 * 0.2).any()) and bool((out > 0.9 * 0.2).any())  # both lit and unlit points
    torch.testing.assert_close(out, _shade_reference(*args), rtol=1e-13, atol=1e-13)
    w = torch.randn(out.shape, dtype=torch.float64)
    mine = torch.autograd.grad((f(*args) * w).sum(), args)
    ref = torch.autograd.grad((_shade_reference(*args) * w).sum(), args)
    for a, b in zip(mine, ref):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    smooth = [x.clone().requires_grad_() for x in _shade_inputs(N=12, seed=1)]
    assert torch.autograd.gradcheck(f, smooth, eps=1e-6, atol=1e-6, rtol=1e-4)


def _sample_reference(u, v, z, corner_index, in_pix, in_slot, fr_pix, fr_slot, fr_k, sign, out, S, sigma, eps):
    """sample_geometry's values written with autograd: barycentrics affine in the pixel centre, and the
    fringe's nearest segment point with its coverage."""
    table = face_table(u, v, z, corner_index, eps)
    u0, v0, du, dv, a, bu, bv, iz, _ = table.index_select(1, in_slot).split((1, 1, 3, 3, 3, 3, 3, 3, 1), 0)
    pu, pv = (in_pix % S).double() + 0.5, (in_pix // S % S).double() + 0.5
    l_in = a + bu * (pu - u0) + bv * (pv - v0)
    f_u0, f_v0, f_du, f_dv, _, _, _, iz_fr, _ = table.index_select(1, fr_slot).split((1, 1, 3, 3, 3, 3, 3, 3, 1), 0)
    ends = torch.stack([(fr_k + 1) % 3, (fr_k + 2) % 3])
    au, bu_ = f_du.gather(0, ends)
    av, bv_ = f_dv.gather(0, ends)
    qu, qv = (fr_pix % S).double() + 0.5 - f_u0[0], (fr_pix // S % S).double() + 0.5 - f_v0[0]
    ex, ey, t = seg_dist(au, av, bu_, bv_, qu, qv, eps)
    cov = torch.sigmoid(sign * torch.sqrt((ex * ex + ey * ey).clamp_min(eps * eps)) / sigma)
    corners = torch.arange(3).unsqueeze(1)
    l_fr = (corners == ends[:1]).double() * (1 - t) + (corners == ends[1:]).double() * t
    return torch.cat([l_in, l_fr[:, out]], 1), torch.cat([iz, iz_fr[:, out]], 1), cov


def test_sample_geometry_gradient_matches_autograd_and_finite_differences(kernels):
    """The hand-written backward of the per-pixel geometry against the autograd composition and gradcheck:
    covered pixels, and fringe pixels whose foot lies inside the segment or is clamped to an end."""
    g = torch.Generator().manual_seed(0)
    B, n, U, S = 2, 9, 7, 16
    u = (S * torch.rand(B, n, generator=g, dtype=torch.float64)).requires_grad_()
    v = (S * torch.rand(B, n, generator=g, dtype=torch.float64)).requires_grad_()
    z = (1 + torch.rand(B, n, generator=g, dtype=torch.float64)).requires_grad_()
    corner_index = torch.stack([torch.randperm(B * n, generator=g)[:3] for _ in range(U)], 1)  # (3, U)
    in_slot = torch.randint(0, U, (40,), generator=g)
    in_pix = torch.randint(0, B * S * S, (40,), generator=g)
    fr_slot = torch.randint(0, U, (30,), generator=g)
    fr_pix = torch.randint(0, B * S * S, (30,), generator=g)
    fr_k = torch.randint(0, 3, (30,), generator=g)
    sign = torch.where(torch.rand(30, generator=g) < 0.5, 1.0, -1.0).double()
    out = (sign < 0).nonzero().squeeze(1)
    rest = (in_pix, in_slot, fr_pix, fr_slot, fr_k, sign, out, S, 0.7, 1e-9)
    mine = _SampleGeometry.apply(u, v, z, corner_index, *rest)
    ref = _sample_reference(u, v, z, corner_index, *rest)
    for a, b in zip(mine, ref):
        torch.testing.assert_close(a, b, rtol=0, atol=0)  # the same arithmetic
    # the fringe feet: some inside their segment, some clamped to an end
    l_out = mine[0][:, 40:]
    inner = ((l_out > 0) & (l_out < 1)).any(0)
    assert bool(inner.any()) and bool((~inner).any())
    w = [torch.randn(x.shape, generator=g, dtype=torch.float64) for x in mine]
    gm = torch.autograd.grad(sum((x * y).sum() for x, y in zip(mine, w)), (u, v, z))
    gr = torch.autograd.grad(sum((x * y).sum() for x, y in zip(ref, w)), (u, v, z))
    for a, b in zip(gm, gr):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)
    assert torch.autograd.gradcheck(lambda *x: _SampleGeometry.apply(*x, corner_index, *rest), (u, v, z),
                                    eps=1e-7, atol=1e-6, rtol=1e-5)


def test_vertex_albedo_scales_the_shade_and_has_exact_gradients():
    """Uniform albedo c equals settings.albedo = c; a varying albedo passes gradcheck (float64) and a batch
    of albedos equals the single renders; bad shapes and NaN are refused."""
    V, F = _two_triangles(shared=True)
    st = RenderSettings(image_size=16, sigma=0.5)  # 12 px puts a pixel centre on an edge: a kink, albedo or not
    cam = Camera(eye=(0.1, -0.2, 1.6), fov_degrees=40.0)
    base = render(V, F, camera=cam, settings=st)
    torch.testing.assert_close(render(V, F, camera=cam, settings=st, albedo=torch.ones(V.shape[0], dtype=V.dtype)),
                               base, rtol=1e-13, atol=1e-13)
    from dataclasses import replace
    torch.testing.assert_close(render(V, F, camera=cam, settings=st, albedo=torch.full((V.shape[0],), 0.3, dtype=V.dtype)),
                               render(V, F, camera=cam, settings=replace(st, albedo=0.3)), rtol=1e-12, atol=1e-12)
    a = torch.linspace(0.2, 0.9, V.shape[0], dtype=V.dtype)
    assert torch.autograd.gradcheck(lambda x, al: render(x, F, camera=cam, settings=st, albedo=al),
                                    (V.clone().requires_grad_(), a.clone().requires_grad_()), eps=1e-6, atol=1e-5,
                                    rtol=1e-3)
    both = render(V.expand(2, -1, -1), F, camera=cam, settings=st, albedo=torch.stack([a, a.flip(0)]))
    torch.testing.assert_close(both[1:], render(V, F, camera=cam, settings=st, albedo=a.flip(0)))
    with pytest.raises(RenderError, match="albedo must have shape"):
        render(V, F, settings=st, albedo=torch.ones(V.shape[0] + 1, dtype=V.dtype))
    with pytest.raises(RenderError, match="NaN"):
        render(V, F, settings=st, albedo=torch.full((V.shape[0],), float("nan"), dtype=V.dtype))


def test_texture_albedo_matches_vertex_albedo_on_a_linear_ramp_and_has_exact_gradients():
    """A texture that is linear in u (at texel centres) gives the same image as the per-vertex albedo of
    that ramp (both interpolate a linear function exactly); gradcheck in the texture, uv and vertices."""
    V, F = _two_triangles(shared=True)
    st = RenderSettings(image_size=16, sigma=0.5)
    cam = Camera(eye=(0.1, -0.2, 1.6), fov_degrees=40.0)
    lo, hi = V[:, :2].min(0).values, V[:, :2].max(0).values
    uv = 0.15 + 0.7 * (V[:, :2] - lo) / (hi - lo)  # strictly inside the texel centres' span (no clamp kink)
    H, W = 5, 7
    ramp = lambda u: 0.2 + 0.6 * u  # noqa: E731
    T = ramp((torch.arange(W, dtype=V.dtype) + 0.5) / W).expand(H, W).contiguous()
    torch.testing.assert_close(render(V, F, camera=cam, settings=st, albedo=T, uv=uv),
                               render(V, F, camera=cam, settings=st, albedo=ramp(uv[:, 0])), rtol=1e-12, atol=1e-12)
    Tr = torch.rand(H, W, dtype=V.dtype, generator=torch.Generator().manual_seed(0))
    assert torch.autograd.gradcheck(lambda x, t, q: render(x, F, camera=cam, settings=st, albedo=t, uv=q),
                                    (V.clone().requires_grad_(), Tr.requires_grad_(), uv.clone().requires_grad_()),
                                    eps=1e-6, atol=1e-5, rtol=1e-3)
    with pytest.raises(RenderError, match="uv must have shape"):
        render(V, F, settings=st, albedo=T, uv=uv[:2])


def test_camera_numbers_given_as_text_are_kept_as_the_floats_checked():
    """Camera(fov_degrees='30') passed its check and failed inside the renderer with a TypeError."""
    V = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64) - 0.3
    F = torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    text = Camera(fov_degrees="30", znear="0.1", zfar="100")
    assert (text.fov_degrees, text.znear, text.zfar) == (30.0, 0.1, 100.0)
    assert torch.equal(render(V, F, camera=text), render(V, F, camera=Camera()))
    assert camera_from_angles(0.0, 0.0, znear="0.1").znear == 0.1
    with pytest.raises(RenderError, match="znear must be a real number, got 'x'"):
        camera_from_angles(0.0, 0.0, znear="x")
    for eye in ("abc", [True, False, True]):  # text failed inside torch; bools were read as 1 and 0
        with pytest.raises(RenderError, match="eye must hold real numbers"):
            Camera(eye=eye)


def test_a_texture_and_its_uv_must_hold_real_numbers():
    """A complex texture rendered a complex image (through the zero-weight anchor); bool ones were read as
    0 and 1."""
    V = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64) - 0.3
    F = torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    uv = torch.rand(4, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    assert render(V, F, albedo=torch.ones(4, 4), uv=uv).dtype == torch.float64
    for albedo, coords, says in [(torch.ones(4, 4, dtype=torch.complex64), uv, "albedo \\(a texture\\) .*complex64"),
                                 (torch.ones(4, 4, dtype=torch.bool), uv, "albedo \\(a texture\\) .*bool"),
                                 (torch.ones(4, 4), uv > 0.5, "uv must hold real numbers"),
                                 ("abc", uv, "albedo \\(a texture\\) must hold real numbers")]:
        with pytest.raises(RenderError, match=says):
            render(V, F, albedo=albedo, uv=coords)
