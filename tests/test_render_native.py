"""The renderer's compiled kernels (``meshmei.render.native``) against the torch reference: the no-grad
passes decide the same faces, segments and fringe pixels, and fragments, images and gradients
agree to rounding, on easy and hard scenes. (The build, its cache and the fallback where no compiler
works: tests/test_native.py.)"""

from __future__ import annotations

import shutil
from contextlib import nullcontext

import pytest
import torch

from meshmei.render import Camera, RenderSettings, axis_angle_to_matrix, camera_from_angles, render
from meshmei.render import native
from meshmei.render.native import torch_reference
from meshmei.render.passes import run_passes
from meshmei.render.raster import prepare_inputs
from meshmei.shapes import initial_mesh, target_mesh

from test_render_hard import degenerate_mesh, uv_sphere

HAS_CC = any(shutil.which(c) for c in ("cc", "gcc", "clang"))
needs_cc = pytest.mark.skipif(not HAS_CC, reason="no C compiler on this machine: the torch code runs")


def both(V, F, **kw):
    """Passes, fragments, image and vertex gradient of one render: compiled kernels, then the torch code."""
    out = []
    for ctx in (nullcontext, torch_reference):
        with ctx():
            inp = prepare_inputs(V, F, kw.get("camera"), kw.get("rotation"), kw.get("translation"), kw["settings"])
            Vw, eye, R = inp.expanded(inp.batch_size)
            r = run_passes(Vw, inp.F, eye, R, inp.camera, inp.settings, inp.n_vertices)
            Vg = V.detach().clone().requires_grad_(True)
            img, fr = render(Vg, F, return_fragments=True, **kw)
            W = torch.randn(img.shape, generator=torch.Generator().manual_seed(1), dtype=img.dtype)
            (img * W).sum().backward()
            out.append((r, fr, img.detach(), Vg.grad))
    return out


def assert_same(a, b):
    """The passes' decisions equal; the values equal to rounding (a few ulps of the largest magnitude)."""
    (ra, fa, ia, ga), (rb, fb, ib, gb) = a, b
    for x, y in ((ra.face_id, rb.face_id), (ra.hit, rb.hit), (ra.fringe_pix, rb.fringe_pix),
                 (ra.shaded.pix, rb.shaded.pix), (ra.shaded.f, rb.shaded.f), (ra.used, rb.used)):
        assert torch.equal(x, y)
    assert torch.equal(fa.face_id, fb.face_id)
    tol = 64 * torch.finfo(ia.dtype).eps
    for x, y in ((fa.bary, fb.bary), (fa.depth, fb.depth), (fa.coverage, fb.coverage), (ia, ib)):
        torch.testing.assert_close(x, y, rtol=tol, atol=tol * float(y.detach().abs().max().clamp_min(1)))
    # a vertex gradient sums up to every pixel's term, in another order and with cancellation (a triangle
    # filling the screen: 1,600 terms whose sum is far smaller than they are); the backward formulas
    # themselves are held to gradcheck in test_render.py, for both the compiled and the torch code
    tol_g = 1e5 * torch.finfo(ia.dtype).eps
    torch.testing.assert_close(ga, gb, rtol=tol_g, atol=tol_g * float(gb.abs().max()))


@needs_cc
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("S", [16, 64, 131])
def test_compiled_kernels_agree_with_the_torch_code(dtype, S):
    V, F = initial_mesh("sphere", n_vertices=500, dtype=dtype)
    V = V + 0.05 * torch.randn(V.shape, generator=torch.Generator().manual_seed(0), dtype=dtype)
    a, b = both(V, F, camera=camera_from_angles(30.0, 20.0), settings=RenderSettings(image_size=S))
    assert int((a[1].face_id >= 0).sum()) > S * S // 10  # the scene is not empty
    assert_same(a, b)


@needs_cc
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_kernels_on_hard_scenes(dtype):
    S = RenderSettings(image_size=40)
    sphere = initial_mesh("sphere", n_vertices=500, dtype=dtype)
    big = torch.tensor([[-50.0, -50.0, 0.0], [50.0, -50.0, 0.0], [0.0, 80.0, 0.0]], dtype=dtype)
    poles = uv_sphere(60, 80)
    scenes = [
        (*degenerate_mesh(dtype), dict(camera=camera_from_angles(60.0, 0.0))),  # zero-area faces, an edge-on fin
        (*initial_mesh("sheet", n_vertices=200, dtype=dtype),
         dict(camera=Camera(eye=(2.5, 0.0, 0.0), up=(0.0, 0.0, 1.0)))),  # seen exactly edge-on
        (*sphere, dict(camera=Camera(eye=(0.05, -0.1, 0.2), at=(0.0, 0.3, -1.0)))),  # the camera inside
        (big, torch.tensor([[0, 1, 2]]), {}),  # larger than the screen
        (poles[0].to(dtype), poles[1], {}),  # subpixel slivers at the poles
        (*target_mesh("teapot", dtype=dtype), dict(camera=camera_from_angles(200.0, -30.0))),  # open, its own folds
    ]
    for V, F, kw in scenes:
        assert_same(*both(V, F, settings=S, **kw))


@needs_cc
def test_compiled_kernels_on_a_batch_of_poses_and_cameras():
    V, F = degenerate_mesh()
    B = 5
    cams = Camera(eye=torch.tensor([[0, 0, 2.5], [0, 0, 2.5], [0.05, -0.1, 0.2], [2.5, 0, 0], [0, 0, 0.6]],
                                   dtype=torch.float64),
                  at=torch.tensor([[0, 0, 0], [0, 0, 0], [0, 0.3, -1.0], [0, 0, 0], [0, 0, 0]], dtype=torch.float64),
                  up=(0.0, 1.0, 0.0))
    t = torch.tensor([[0, 0, 0], [0.4, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0]], dtype=torch.float64)
    rot = axis_angle_to_matrix(torch.tensor([[0, 0, 0], [0.1, 0.2, 0.3], [0, 0, 0], [0, 0, 0], [1.0, 0, 0]],
                                            dtype=torch.float64))
    a, b = both(V, F, camera=cams, translation=t, rotation=rot, settings=RenderSettings(image_size=24))
    assert a[2].shape == (B, 1, 24, 24)
    assert_same(a, b)


@needs_cc
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_shading_with_an_albedo_and_a_texture(dtype):
    """The shading kernel's seventh channel (a surface albedo), per vertex and from a texture, and a light."""
    V, F = initial_mesh("sphere", n_vertices=500, dtype=dtype)
    g = torch.Generator().manual_seed(2)
    st = RenderSettings(image_size=32)
    light = torch.tensor([1.0, 2.0, 3.0], dtype=dtype)
    a, b = both(V, F, settings=st, light=light, albedo=torch.rand(V.shape[0], generator=g, dtype=dtype))
    assert_same(a, b)
    uv = torch.rand(V.shape[0], 2, generator=g, dtype=dtype)
    a, b = both(V, F, settings=st, albedo=torch.rand(8, 8, generator=g, dtype=dtype), uv=uv)
    assert_same(a, b)


@needs_cc
def test_compiled_vertex_normals_match_the_operator_and_gradcheck():
    """The renderer's compiled normals against :func:`meshmei.operators.vertex_normals_from_corners` (values
    and gradients), on a sphere and on degenerate faces (zero area; a vertex whose face normals cancel,
    where the floor eps * area holds), and against gradcheck."""
    from meshmei.operators import corners, vertex_normals_from_corners

    V, F = degenerate_mesh()
    # two faces of opposite orientation on one triangle: their normals cancel at its vertices
    n = V.shape[0]
    V = torch.cat([V, torch.tensor([[0.0, 0.0, 0.9], [0.1, 0.0, 0.9], [0.0, 0.1, 0.9]], dtype=V.dtype)])
    F = torch.cat([F, torch.tensor([[n, n + 1, n + 2], [n, n + 2, n + 1]])])
    for Vb in (V.unsqueeze(0), torch.stack([V, 1.3 * V.roll(1, 1)])):
        Vb = Vb.clone().requires_grad_(True)
        mine = native.vertex_normals(Vb, F, 1e-12)
        ref = vertex_normals_from_corners(corners(Vb, F), F, Vb.shape[1], eps=1e-12)
        torch.testing.assert_close(mine, ref, rtol=1e-12, atol=1e-12)
        W = torch.randn(mine.shape, generator=torch.Generator().manual_seed(3), dtype=mine.dtype)
        ga, = torch.autograd.grad((mine * W).sum(), Vb)
        gb, = torch.autograd.grad((ref * W).sum(), Vb)
        torch.testing.assert_close(ga, gb, rtol=1e-9, atol=1e-9 * float(gb.abs().max()))
    Vs, Fs = initial_mesh("sphere", n_vertices=60, dtype=torch.float64)
    Vs = (Vs + 0.05 * torch.randn(Vs.shape, generator=torch.Generator().manual_seed(4), dtype=Vs.dtype))
    assert torch.autograd.gradcheck(lambda X: native.vertex_normals(X, Fs, 1e-12), (Vs.unsqueeze(0).requires_grad_(),),
                                    eps=1e-7, atol=1e-6, rtol=1e-5)
