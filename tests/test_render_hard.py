"""Hard cases for the renderer (finite images and gradients, never NaN) and bad-input errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from meshmei.errors import MeshError
from meshmei.render import (Camera, RenderError, Renderer, RenderSettings, apply_pose, axis_angle_to_matrix,
                            camera_from_angles, rasterize, render)
from meshmei.render.native import torch_reference
from meshmei.shapes import initial_mesh


def uv_sphere(n_lat, n_lon, r=0.5, dtype=torch.float64):
    """A latitude-longitude sphere: sliver faces at the poles, 2 n_lon (n_lat - 1) faces."""
    th = torch.linspace(0, math.pi, n_lat + 1, dtype=dtype)[1:-1]
    ph = torch.linspace(0, 2 * math.pi, n_lon + 1, dtype=dtype)[:-1]
    T, P = torch.meshgrid(th, ph, indexing="ij")
    ring = torch.stack([torch.sin(T) * torch.cos(P), torch.sin(T) * torch.sin(P), torch.cos(T)], -1).reshape(-1, 3)
    V = r * torch.cat([torch.tensor([[0, 0, 1.0]], dtype=dtype), ring, torch.tensor([[0, 0, -1.0]], dtype=dtype)])
    F = []
    idx = lambda i, j: 1 + i * n_lon + j % n_lon  # noqa: E731
    for j in range(n_lon):
        F.append([0, idx(0, j), idx(0, j + 1)])
        F.append([len(V) - 1, idx(n_lat - 2, j + 1), idx(n_lat - 2, j)])
    for i in range(n_lat - 2):
        for j in range(n_lon):
            F += [[idx(i, j), idx(i + 1, j), idx(i + 1, j + 1)], [idx(i, j), idx(i + 1, j + 1), idx(i, j + 1)]]
    return V, torch.tensor(F)


def degenerate_mesh(dtype=torch.float64):
    """A sphere plus zero-area faces (repeated index, collinear corners) and an edge-on fin."""
    V, F = initial_mesh("sphere", n_vertices=500, dtype=dtype)
    n = V.shape[0]
    extra_V = torch.tensor([[0.6, 0.0, 0.0], [0.7, 0.0, 0.0], [0.8, 0.0, 0.0],  # collinear
                            [-0.6, 0.2, 0.0], [-0.6, 0.2, 0.0], [-0.6, 0.2, 0.0],  # repeated point
                            [0.0, 0.6, 0.0], [0.0, 0.8, 0.0], [0.0, 0.7, 0.4]],  # fin in the x=0 plane: edge-on
                           dtype=dtype)
    extra_F = torch.tensor([[n, n + 1, n + 2], [n + 3, n + 4, n + 5], [n + 3, n + 3, n + 4],
                            [n + 6, n + 7, n + 8], [0, 0, 1]])
    return torch.cat([V, extra_V]), torch.cat([F, extra_F])


def check_finite(V, F, **kw):
    """Render, backprop a random weighting, and check image and all gradients are finite."""
    V = V.detach().clone().requires_grad_(True)
    tensors = {k: v.detach().clone().requires_grad_(True) for k, v in kw.items()
               if isinstance(v, torch.Tensor) and v.is_floating_point()}
    kw = {**kw, **tensors}
    img = render(V, F, **kw)
    assert torch.isfinite(img).all()
    W = torch.randn(img.shape, generator=torch.Generator().manual_seed(0), dtype=img.dtype)
    (img * W).sum().backward()
    assert torch.isfinite(V.grad).all()
    for t in tensors.values():
        assert t.grad is not None and torch.isfinite(t.grad).all()
    return img, V.grad


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_degenerate_and_edge_on_faces(dtype):
    V, F = degenerate_mesh(dtype)
    img, g = check_finite(V, F, settings=RenderSettings(image_size=48))
    # edge-on in the default view, the fin and the collinear face still render without NaN; seen at an
    # angle the fin becomes visible
    img2, _ = check_finite(V, F, camera=camera_from_angles(60.0, 0.0), settings=RenderSettings(image_size=48))
    assert not torch.equal(img, img2)


def test_sheet_seen_exactly_edge_on():
    V, F = initial_mesh("sheet", n_vertices=200, dtype=torch.float64)
    cam = Camera(eye=(2.5, 0.0, 0.0), up=(0.0, 0.0, 1.0))  # the sheet's plane contains the eye
    img, g = check_finite(V, F, camera=cam, settings=RenderSettings(image_size=32))
    fr = rasterize(V, F, camera=cam, settings=RenderSettings(image_size=32))
    # zero projected area: no pixel is covered; the line the sheet projects to keeps a faint soft fringe
    # (the silhouette distance model sees a zero-width region; see docs/rendering.md, thin features)
    assert bool((fr.face_id < 0).all())
    assert fr.coverage.max() <= torch.sigmoid(torch.tensor(-0.5 / 0.2, dtype=torch.float64)) + 1e-12


def test_subpixel_triangles_30k_faces():
    V, F = uv_sphere(100, 152)
    assert 29_000 < F.shape[0] < 31_000
    img, g = check_finite(V, F, settings=RenderSettings(image_size=64))
    fr = rasterize(V, F, settings=RenderSettings(image_size=64))
    # the disk of radius 0.5 at distance 2.5 (30 deg fov): no holes inside the outline
    rows, cols = torch.meshgrid(torch.arange(64), torch.arange(64), indexing="ij")
    rad = ((rows + 0.5 - 32) ** 2 + (cols + 0.5 - 32) ** 2).sqrt()
    r_px = 32 / math.tan(math.radians(15)) * 0.5 / math.sqrt(2.5**2 - 0.25)
    assert bool((fr.face_id[0][rad < r_px - 1] >= 0).all())
    assert bool((fr.face_id[0][rad > r_px + 1] < 0).all())


def test_triangle_larger_than_screen():
    V = torch.tensor([[-50.0, -50.0, 0.0], [50.0, -50.0, 0.0], [0.0, 80.0, 0.0]], dtype=torch.float64)
    F = torch.tensor([[0, 1, 2]])
    img, g = check_finite(V, F, settings=RenderSettings(image_size=32))
    fr = rasterize(V, F, settings=RenderSettings(image_size=32))
    assert bool((fr.face_id == 0).all()) and bool((fr.coverage == 1).all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_faces_behind_and_crossing_the_near_plane(dtype):
    # a ground plane passing under and behind the camera, and a triangle piercing the near plane
    V = torch.tensor([[-5.0, -0.3, 5.0], [5.0, -0.3, 5.0], [0.0, -0.3, -5.0],
                      [-0.2, 0.0, 2.45], [0.2, 0.0, 2.45], [0.0, 0.2, 2.6],  # straddles znear = 0.1
                      [-0.2, 0.0, 3.0], [0.2, 0.0, 3.0], [0.0, 0.2, 3.0]], dtype=dtype)  # wholly behind
    F = torch.tensor([[0, 1, 2], [3, 4, 5], [6, 7, 8]])
    img, g = check_finite(V, F, settings=RenderSettings(image_size=32))
    fr = rasterize(V, F, settings=RenderSettings(image_size=32))
    assert set(fr.face_id.unique().tolist()) <= {-1}  # clipped: every face has a vertex behind znear
    assert (g[6:] == 0).all()
    # one corner behind the eye, two in view and apart on the screen: culled too (faces whose corners were
    # all behind, or whose behind corners met on the screen, could not tell 'every corner in range' from
    # 'some corner': review)
    one = torch.tensor([[-0.3, -0.2, 0.0], [0.3, -0.2, 0.0], [0.0, 0.1, 3.0]], dtype=dtype)
    fr = rasterize(one, torch.tensor([[0, 1, 2]]), settings=RenderSettings(image_size=32))
    assert int((fr.face_id >= 0).sum()) == 0 and float(fr.coverage.max()) == 0.0


def test_object_outside_view_gives_background_and_zero_gradient():
    V, F = initial_mesh("sphere", n_vertices=500, dtype=torch.float64)
    t = torch.tensor([5.0, 0.0, 0.0], dtype=torch.float64, requires_grad=True)
    light = torch.tensor([0.0, 1.0, 3.0], dtype=torch.float64, requires_grad=True)
    Vg = V.clone().requires_grad_(True)
    img = render(Vg, F, translation=t, light=light, settings=RenderSettings(image_size=32))
    assert bool((img == 0.5).all())
    img.sum().backward()
    for x in (Vg, t, light):
        assert x.grad is not None and bool((x.grad == 0).all())


def test_camera_inside_mesh():
    V, F = initial_mesh("sphere", n_vertices=500, dtype=torch.float64)
    cam = Camera(eye=(0.05, -0.1, 0.2), at=(0.0, 0.3, -1.0))
    img, g = check_finite(V, F, camera=cam, settings=RenderSettings(image_size=32))
    fr = rasterize(V, F, camera=cam, settings=RenderSettings(image_size=32))
    assert bool((fr.face_id >= 0).all())  # the inside of the sphere fills the view


def test_batch_mixing_hard_cases():
    V, F = degenerate_mesh()
    B = 6
    cams = Camera(
        eye=torch.tensor([[0, 0, 2.5], [0, 0, 2.5], [0.05, -0.1, 0.2], [2.5, 0, 0], [0, 0, 0.6], [0, 0, 2.5]],
                         dtype=torch.float64),
        at=torch.tensor([[0, 0, 0], [0, 0, 0], [0, 0.3, -1.0], [0, 0, 0], [0, 0, 0], [0, 0, 0]], dtype=torch.float64),
        up=(0.0, 1.0, 0.0))
    t = torch.tensor([[0, 0, 0], [7, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 1.0]], dtype=torch.float64)
    rot = axis_angle_to_matrix(torch.tensor([[0, 0, 0], [0.1, 0.2, 0.3], [0, 0, 0], [0, 0, 0], [1.0, 0, 0],
                                             [0, 0, 0]], dtype=torch.float64))
    light = torch.tensor([[0, 0, 3.0]] * B, dtype=torch.float64)
    img, g = check_finite(V, F, camera=cams, translation=t, rotation=rot, light=light,
                          settings=RenderSettings(image_size=32))
    assert img.shape == (B, 1, 32, 32)
    assert bool((img[1] == 0.5).all())  # translated out of view


def test_renderer_class_and_flat_shading():
    V, F = initial_mesh("sphere", n_vertices=500, dtype=torch.float32)
    r = Renderer(F, settings=RenderSettings(image_size=32, shading="flat"))
    img = r(V)
    assert img.shape == (1, 1, 32, 32) and img.dtype == torch.float32
    smooth = render(V, F, settings=RenderSettings(image_size=32))
    assert (img - smooth).abs().max() > 1e-3
    torch.testing.assert_close(r(V, settings=RenderSettings(image_size=32)), smooth)


def test_two_sided_lighting_of_an_open_sheet():
    V, F = initial_mesh("sheet", n_vertices=200, dtype=torch.float64)
    below = Camera(eye=(0.0, 0.0, -2.5), up=(0.0, 1.0, 0.0))
    lit = render(V, F, camera=below, settings=RenderSettings(image_size=32))
    dark = render(V, F, camera=below, settings=RenderSettings(image_size=32, two_sided=False))
    assert lit[0, 0, 16, 16] > 0.9 and dark[0, 0, 16, 16] == pytest.approx(0.2)


def test_pose_helpers():
    R = axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64))
    torch.testing.assert_close(R @ R.T, torch.eye(3, dtype=torch.float64))
    aa = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    axis_angle_to_matrix(aa).sum().backward()
    assert torch.isfinite(aa.grad).all()
    V = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)
    torch.testing.assert_close(apply_pose(V, R, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)),
                               torch.tensor([[[0.0, 1.0, 1.0]]], dtype=torch.float64))
    cam = camera_from_angles(torch.tensor([0.0, 90.0]), torch.tensor([90.0, -90.0]), 2.0)
    eye, Rv = cam.frame(torch.float64)
    assert torch.isfinite(Rv).all()
    torch.testing.assert_close(Rv @ Rv.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(2, 3, 3),
                               atol=1e-6, rtol=0)


# ---------------------------------------------------------------------------------------------
# bad input
TRI = (torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), torch.tensor([[0, 1, 2]]))


@pytest.mark.parametrize("kw, match", [
    (dict(image_size=0), "image_size"),
    (dict(image_size=-4), "image_size"),
    (dict(image_size=32.0), "image_size"),
    (dict(sigma=0.0), "sigma"),
    (dict(sigma=-1.0), "sigma"),
    (dict(sigma=float("nan")), "sigma"),
    (dict(background=float("inf")), "background"),
    (dict(ambient=-0.1), "ambient"),
    (dict(light_intensity=-1.0), "light_intensity"),
    (dict(shading="phong"), "shading"),
    (dict(chunk_size=10), "chunk_size"),
    (dict(eps=0.0), "eps"),
    (dict(sigma=1e30), r"sigma must lie in \(0, 1000\] pixels"),  # an OverflowError in the pixel boxes before
    (dict(light_intensity=1e300), r"light_intensity must lie in \[0, 1e\+06\]"),  # an inf image before
    (dict(background=1e300), "background must lie within"),  # a NaN image before
    (dict(image_size=np.bool_(True)), "image_size"),
])
def test_bad_settings(kw, match):
    with pytest.raises(RenderError, match=match):
        RenderSettings(**kw)


def test_a_numpy_integer_image_size_is_taken_as_an_int():
    st = RenderSettings(image_size=np.int64(16))
    assert st.image_size == 16 and type(st.image_size) is int
    img = render(*TRI, settings=st)
    assert img.shape[-2:] == (16, 16) and bool(torch.isfinite(img).all())


@pytest.mark.parametrize("kw, match", [
    (dict(fov_degrees=0.0), "fov_degrees"),
    (dict(fov_degrees=180.0), "fov_degrees"),
    (dict(znear=0.0), "znear"),
    (dict(znear=2.0, zfar=1.0), "znear"),
    (dict(eye=(0.0, 0.0)), "eye"),
    (dict(eye=torch.zeros(2, 3), at=torch.ones(3, 3)), "batch sizes"),
])
def test_bad_camera(kw, match):
    with pytest.raises(RenderError, match=match):
        Camera(**kw)


def test_bad_camera_placement():
    with pytest.raises(RenderError, match="coincide"):
        render(*TRI, camera=Camera(eye=(0.0, 0, 0), at=(0.0, 0, 0)))
    with pytest.raises(RenderError, match="parallel"):
        render(*TRI, camera=Camera(eye=(0.0, 0, 2), up=(0.0, 0, 1)))
    with pytest.raises(RenderError, match="distance"):
        camera_from_angles(0.0, 0.0, -1.0)
    with pytest.raises(RenderError, match="NaN"):
        Camera(eye=(float("nan"), 0.0, 1.0)).frame()


def test_bad_mesh_and_scene_input():
    V, F = TRI
    with pytest.raises(MeshError, match="shape"):
        render(V[:, :2], F)
    with pytest.raises(MeshError, match="NaN"):
        render(torch.tensor([[0.0, 0, 0], [1, 0, 0], [float("nan"), 1, 0]]), F)
    with pytest.raises(MeshError, match="out of range"):
        render(V, torch.tensor([[0, 1, 3]]))
    with pytest.raises(MeshError, match="V must be a torch tensor or numpy array, got NoneType"):
        render(None, F)
    with pytest.raises(MeshError, match="V must be a torch tensor or numpy array, got NoneType"):
        rasterize(None, F)
    with pytest.raises(RenderError, match="rotation"):
        render(V, F, rotation=torch.zeros(3))
    with pytest.raises(RenderError, match="translation"):
        render(V, F, translation=torch.zeros(2))
    with pytest.raises(RenderError, match="light"):
        render(V, F, light=torch.zeros(4))
    with pytest.raises(RenderError, match="light"):
        render(V, F, light=torch.tensor([float("nan"), 0, 0]))
    with pytest.raises(RenderError, match="batch size"):
        render(V.expand(2, 3, 3), F, translation=torch.zeros(3, 3))
    with pytest.raises(RenderError, match="batch size"):
        render(V, F, light=torch.zeros(2, 3), translation=torch.zeros(3, 3))
    with pytest.raises(RenderError, match="settings"):
        render(V, F, settings=dict(image_size=32))
    with pytest.raises(RenderError, match="camera"):
        render(V, F, camera=(0, 0, 2))
    assert issubclass(RenderError, ValueError)


def test_chunking_does_not_change_the_result():
    """The torch code's chunks (the compiled passes, used where a C compiler is found, have none)."""
    V, F = initial_mesh("sphere", n_vertices=500, dtype=torch.float64)
    with torch_reference():
        a = render(V, F, settings=RenderSettings(image_size=48))
        b = render(V, F, settings=RenderSettings(image_size=48, chunk_size=1024))
    torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_a_far_light_in_float32_shades_as_a_near_one():
    """A point light 1e20 away (a stand-in for a directional light): its squared distance overflows float32,
    which left the surface at the ambient level (0.2 against 0.9994 at the centre) before."""
    V, F = initial_mesh("sphere", n_vertices=400)
    st = RenderSettings(image_size=32)
    Vg = V.clone().requires_grad_()
    far = render(Vg, F, settings=st, light=torch.tensor([0.0, 0.0, 1e20]))
    near = render(V, F, settings=st, light=torch.tensor([0.0, 0.0, 1e8]))
    torch.testing.assert_close(far, near, rtol=0, atol=1e-6)
    far.sum().backward()
    assert bool(torch.isfinite(Vg.grad).all())


@pytest.mark.parametrize("k", [40, -30])
def test_a_scene_scaled_by_a_power_of_two_renders_the_same_image(k):
    """Projection and shading do not depend on the scene's scale; in float32 the squares of the face cross
    products (extent^4) overflowed at 2^40 (an unlit image) and underflowed near 2^-32."""
    V, F = initial_mesh("sphere", n_vertices=400)
    st = RenderSettings(image_size=32)
    s = 2.0 ** k
    Vg = (V * s).requires_grad_()
    img = render(Vg, F, settings=st, camera=Camera(eye=(0.0, 0.0, 2.5 * s), znear=0.1 * s, zfar=100 * s))
    torch.testing.assert_close(img, render(V, F, settings=st), rtol=0, atol=1e-6)
    img.sum().backward()
    assert bool(torch.isfinite(Vg.grad).all()) and float(Vg.grad.abs().max()) > 0


def test_a_camera_follows_an_array_edited_after_it_was_made():
    """The frame of a camera made from a numpy array or a list was cached as if immutable: editing the
    array afterwards kept the old view, silently."""
    V, F = initial_mesh("sphere", n_vertices=100)
    st = RenderSettings(image_size=16)
    for eye in (np.array([0.0, 0.0, 2.5]), [0.0, 0.0, 2.5]):
        cam = Camera(eye=eye)
        before = render(V, F, camera=cam, settings=st)
        eye[0] = 1.5
        after = render(V, F, camera=cam, settings=st)
        assert torch.equal(after, render(V, F, camera=Camera(eye=(1.5, 0.0, 2.5)), settings=st))
        assert not torch.equal(after, before)


@pytest.mark.parametrize("call, match", [
    (lambda V, F, st: Renderer(torch.tensor([[0.9, 1.9, 2.9]]), settings=st)(V), "F must have an integer dtype"),
    (lambda V, F, st: render(V, F, translation=torch.tensor([0, 0, 5j]), settings=st),
     "translation must hold real numbers"),
    (lambda V, F, st: render(V, F, light=[0.0, 0.0, "a"], settings=st), "light must hold real numbers"),
    (lambda V, F, st: render(V, F, rotation=torch.eye(3, dtype=torch.complex64), settings=st),
     "rotation must hold real numbers"),
    (lambda V, F, st: render(V, F, albedo=torch.ones(V.shape[0], dtype=torch.bool), settings=st),
     "albedo must hold real numbers"),
    (lambda V, F, st: camera_from_angles(torch.tensor([90j]), 0.0), "azimuth must hold real numbers"),
    (lambda V, F, st: camera_from_angles(torch.tensor([True]), 0.0), "azimuth must hold real numbers"),
    (lambda V, F, st: camera_from_angles(torch.tensor([0.0, 10, 20]), torch.tensor([1.0, 2])),
     "incompatible batch sizes"),
])
def test_inputs_that_were_silently_cast_or_failed_in_torch_are_render_errors(call, match):
    """Float faces were truncated by Renderer, complex values lost their imaginary part, True read as 1 degree,
    and unbroadcastable angle batches raised torch's RuntimeError."""
    V, F = initial_mesh("sphere", n_vertices=100)
    with pytest.raises((RenderError, MeshError), match=match):
        call(V, F, RenderSettings(image_size=16))


def test_numpy_integer_chunk_size_is_taken_as_an_int():
    st = RenderSettings(chunk_size=np.int64(65536))
    assert st.chunk_size == 65536 and type(st.chunk_size) is int


def test_uv_without_a_texture_and_a_camera_inside_znear_are_errors():
    """uv without albedo was silently ignored; camera_from_angles took a distance within znear, against its
    docstring, and the view then lost the object's centre to the near plane."""
    V, F = initial_mesh("sphere", n_vertices=100)
    with pytest.raises(RenderError, match="uv gives texture coordinates for a texture albedo"):
        render(V, F, uv=torch.rand(V.shape[0], 2), settings=RenderSettings(image_size=16))
    with pytest.raises(RenderError, match=r"distance must be > znear \(0.1\)"):
        camera_from_angles(0.0, 0.0, 0.05)


def test_a_renderer_given_new_faces_renders_them():
    """The per-device copy of the faces was filled once: after ``r.F = ...`` (a remesh) the old faces were
    drawn, or checked against the new vertices."""
    V, F = initial_mesh("sphere", n_vertices=200)
    st = RenderSettings(image_size=16)
    r = Renderer(F, settings=st)
    before = r(V)
    half = F[: F.shape[0] // 2]
    r.F = half
    torch.testing.assert_close(r(V), render(V, half, settings=st), rtol=0, atol=0)
    assert not torch.equal(r(V), before)
    V2, F2 = initial_mesh("sphere", n_vertices=100)  # another vertex count too
    r.F = F2
    torch.testing.assert_close(r(V2), render(V2, F2, settings=st), rtol=0, atol=0)
    with pytest.raises(MeshError):
        r.F = F2.double()  # faces are checked on the way in, as at construction
