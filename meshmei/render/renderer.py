"""The paper's renderer ``I = R(M)``: pose, camera, point light, Lambertian gray shading, soft silhouette."""

from __future__ import annotations

import math

import torch

from ..mesh import as_faces
from ..operators import corners, face_normals, vertex_normals_from_corners
from . import native
from .camera import Camera
from .passes import run_passes
from .raster import Fragments, prepare_inputs
from .settings import RenderError, RenderSettings
from .shading import shade_samples
from .texture import check_texture, sample_texture
from .transforms import as_points, check_batch, real_numbers

__all__ = ["render", "Renderer"]


def _light(light, eye, dtype, device):
    """Light positions ``(B, 3)``; default: at each camera centre."""
    if light is None:
        return eye.detach() if not eye.requires_grad else eye
    return as_points("light", light, dtype, device)


def _vertex_albedo(albedo, n: int, B: int, dtype, device) -> torch.Tensor:
    """Per-vertex albedo as ``(B * n,)`` for gathering by flat vertex row; RenderError for a bad one."""
    a = real_numbers("albedo", albedo, dtype).to(dtype=dtype, device=device)
    if a.ndim not in (1, 2) or a.shape[-1] != n or (a.ndim == 2 and a.shape[0] not in (1, B)):
        raise RenderError(f"albedo must have shape (n,) or (B, n) with n = {n} vertices and B = {B}, got "
                          f"{tuple(a.shape)}")
    if not bool(torch.isfinite(a).all()):
        raise RenderError("albedo holds NaN or Inf")
    return a.reshape(-1, n).expand(B, n).reshape(B * n)


def _in_normal_range(posed) -> torch.Tensor:
    """``posed`` itself, or divided by a power of two (exact) where the squares of its cross products, which
    grow as its size to the fourth, would leave the dtype's range (coordinates beyond about 3e8 or all below
    5e-9 in float32): the normals do not depend on the scale."""
    size = float(posed.detach().abs().amax())
    fi = torch.finfo(posed.dtype)
    if size == 0 or fi.tiny ** 0.25 * 16 <= size <= fi.max ** 0.25 / 16:
        return posed
    return posed * 2.0 ** -math.floor(math.log2(size))


def _corner_normals(posed, F, r, st: RenderSettings, B: int) -> torch.Tensor:
    """Shading normals at the corners of the used faces, ``(3, U, 3)``: interpolated vertex normals (smooth)
    or the face's own (flat), turned towards the camera on faces seen from behind (two-sided)."""
    posed = _in_normal_range(posed)
    n, m = posed.shape[-2], F.shape[0]
    if st.shading == "smooth":  # on the un-expanded batch, then the used faces' corners
        if native.available(posed):  # the same arithmetic, compiled (meshmei.render.native)
            normals = native.vertex_normals(posed, F, 1e-12).expand(B, n, 3)
        else:
            normals = vertex_normals_from_corners(corners(posed, F), F, n, eps=1e-12).expand(B, n, 3)
        normals = normals.reshape(B * n, 3).index_select(0, r.corner_index.reshape(-1)).view(3, -1, 3)
    else:
        normals = face_normals(posed, F).expand(B, m, 3).reshape(B * m, 3).index_select(0, r.used)
        normals = normals.unsqueeze(0).expand(3, -1, 3)
    if st.two_sided:
        normals = normals * torch.where(r.front.view(-1)[r.used], 1.0, -1.0).to(posed.dtype).view(1, -1, 1)
    return normals


def render(V, F, *, camera: Camera | None = None, light=None, rotation=None, translation=None,
           settings: RenderSettings | None = None, albedo=None, uv=None, return_fragments: bool = False):
    """Render grayscale images of a mesh, differentiable in vertices, pose, light and camera placement.

    The image is ``I = c * shade + (1 - c) * background`` with soft coverage ``c`` (``Fragments.coverage``)
    and ``shade = albedo * (ambient + light_intensity * max(0, n . l))`` evaluated at the visible surface
    point (covered pixels) or at the nearest silhouette point (the anti-aliased fringe just outside).

    Parameters
    ----------
    V : (n, 3) or (B, n, 3) float tensor
        Vertex positions (object coordinates). Output dtype and device follow ``V``.
    F : (m, 3) int64 tensor
    camera : Camera, optional
        One camera or a batch of B; default overhead at (0, 0, 2.5) looking at the origin, +y up.
    light : (3,) or (B, 3) float tensor, optional
        Point light position(s) in world coordinates; default: at the camera centre.
    rotation : (3, 3) or (B, 3, 3) float tensor, optional
        Rotation matrix; :func:`~meshmei.render.axis_angle_to_matrix` makes one from axis-angle vectors.
    translation : (3,) or (B, 3) tensor, optional
        Object pose ``V @ R.T + t``.
    settings : RenderSettings, optional
    albedo : (n,) or (B, n) float tensor, optional
        Per-vertex surface albedo (a reflectance in [0, 1] for a physical surface; not clamped here),
        interpolated perspective-correctly over each face and multiplied into the shade together with
        ``settings.albedo``. Differentiable. None: the uniform ``settings.albedo`` alone.
        With ``uv``, a texture instead: ``(H, W)`` or ``(B, H, W)``, sampled bilinearly at the surface
        point's perspective-correct texture coordinates (:func:`~meshmei.render.texture.sample_texture`).
    uv : (n, 2) float tensor, optional
        Per-vertex texture coordinates in [0, 1]^2 for a texture ``albedo``.
    return_fragments : bool
        Also return the :class:`~meshmei.render.raster.Fragments`.

    Returns
    -------
    image : (B, 1, S, S) tensor
        B is the broadcast batch size of ``V``, pose, camera and light; S = ``settings.image_size``.
    fragments : Fragments, only with ``return_fragments``

    Examples
    --------
    >>> import torch
    >>> V = torch.tensor([[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.0, 0.5, 0.0]])
    >>> F = torch.tensor([[0, 1, 2]])
    >>> render(V, F, settings=RenderSettings(image_size=32)).shape
    torch.Size([1, 1, 32, 32])
    """
    inp = prepare_inputs(V, F, camera, rotation, translation, settings)
    V, F, st = inp.V, inp.F, inp.settings
    L = _light(light, inp.eye, V.dtype, V.device)
    check_batch("light", L.shape[0], inp.batch_size)
    B = max(inp.batch_size, L.shape[0])
    Vw, eye, R = inp.expanded(B)
    L = L.expand(B, 3)
    r = run_passes(Vw, F, eye, R, inp.camera, st, inp.n_vertices)
    S, n = r.S, inp.n_vertices
    parts = [Vw.reshape(B * n, 3).index_select(0, r.corner_index.reshape(-1)).view(3, -1, 3),
             _corner_normals(inp.posed, F, r, st, B)]  # positions and normals at the used faces' corners
    texture = None
    if uv is not None and albedo is None:
        raise RenderError("uv gives texture coordinates for a texture albedo (H, W); pass the texture as albedo")
    if albedo is not None and uv is not None:
        texture, uv = check_texture(albedo, uv, n, B, V.dtype, V.device)
    elif albedo is not None:
        a = _vertex_albedo(albedo, n, B, V.dtype, V.device)
        parts.append(a.index_select(0, r.corner_index.reshape(-1)).view(3, -1, 1))
    # (corner * channel, used face), contiguous: a 2-D gather along its last axis is 4 times faster, forward
    # and backward, than the same gather along the last axis of the (corner, channel, face) view
    table = torch.cat(parts, 2)  # (corner, used face, channel)
    C = table.shape[2]
    table = table.permute(0, 2, 1).contiguous().view(3 * C, -1)
    Lt = L.t()

    def shade(samples):
        N = samples.pix.shape[0]
        Lb = Lt.expand(3, N) if B == 1 else Lt.index_select(1, samples.b)
        corners = table.index_select(1, samples.slot).view(3, C, N)
        if texture is not None:  # the texel under the surface point, as a seventh channel equal at the corners
            bary, _ = r.perspective_correct(samples)
            uv_c = uv.index_select(0, (r.corner_index.index_select(1, samples.slot) % n).reshape(-1)).view(3, N, 2)
            a = sample_texture(texture, (bary.t().unsqueeze(-1) * uv_c).sum(0), samples.b)
            corners = torch.cat([corners, a.expand(3, 1, N)], 1)
        return shade_samples(samples.l, samples.iz, corners, Lb, ambient=st.ambient, intensity=st.light_intensity,
                             albedo=st.albedo, eps=st.eps)

    dt, dev = V.dtype, V.device
    sh = torch.zeros(B * S * S, dtype=dt, device=dev).index_put((r.shaded.pix,), shade(r.shaded))
    c = r.coverage
    # zero-weight anchor: an empty image still depends (with zero gradient) on every differentiable input
    anchor = r.Vc.sum() + L.sum()
    if isinstance(albedo, torch.Tensor):
        anchor = anchor + albedo.sum()
    zero = 0.0 * anchor
    image = (c * sh + (1 - c) * st.background + zero).view(B, 1, S, S)
    if not return_fragments:
        return image

    bary_in, depth_in = r.perspective_correct(r.inside)
    bary = torch.zeros(B * S * S, 3, dtype=dt, device=dev).index_put((r.inside.pix,), bary_in)
    depth = torch.zeros(B * S * S, dtype=dt, device=dev).index_put((r.inside.pix,), depth_in)
    frags = Fragments(face_id=r.face_id, bary=bary.view(B, S, S, 3), depth=depth.view(B, S, S),
                      coverage=c.view(B, S, S))
    return image, frags


class Renderer:
    """A face array with fixed settings, camera and light, for optimisation loops: ``Renderer(F)(V)``.

    The only state is the topology (cached per face tensor) and the scene defaults; every call accepts
    the same keywords as :func:`render` to override them.
    """

    def __init__(self, F, *, camera: Camera | None = None, light=None, settings: RenderSettings | None = None):
        self.F = F
        self.camera = camera if camera is not None else Camera()
        self.light = light
        self.settings = settings if settings is not None else RenderSettings()
        if not isinstance(self.settings, RenderSettings):
            raise RenderError(f"settings must be a RenderSettings, got {type(self.settings).__name__}")

    @property
    def F(self) -> torch.Tensor:
        """The faces, ``(m, 3)`` int64; setting them (a remesh) replaces the per-device copies."""
        return self._F

    @F.setter
    def F(self, F) -> None:
        self._F = as_faces(F)  # float or bool faces are an error, as in render, not truncated
        self._F_on = {self._F.device: self._F}  # one copy per device, so the topology cache keeps hitting

    def __call__(self, V, **kw):
        kw.setdefault("camera", self.camera)
        kw.setdefault("light", self.light)
        kw.setdefault("settings", self.settings)
        F = self._F_on.setdefault(V.device, self.F.to(V.device))
        return render(V, F, **kw)

    def __repr__(self):
        return f"Renderer(m={self.F.shape[0]}, settings={self.settings!r})"
