"""The differentiable half of the rasterizer: the winning (pixel, face) pairs recomputed with autograd.

The no-grad passes (:mod:`meshmei.render.passes`) decide which face each pixel sees and which contour
segment is nearest; here only those pairs get values with gradients: the screen-space barycentrics of a
covered pixel's centre, and the nearest silhouette point of a fringe pixel with its soft coverage. Both read
one per-face table built for the faces some sample lies on, so the cost follows the pixels and the
visible faces, not the mesh.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .settings import RenderSettings

__all__ = ["PixelSamples", "seg_dist", "face_table", "pixel_centres", "inside_samples", "fringe_samples", "used_faces"]


def seg_dist(ax, ay, bx, by, px, py, eps):
    """Distance from p to segment ab and the foot parameter t in [0, 1]."""
    dx, dy = bx - ax, by - ay
    L2 = dx * dx + dy * dy
    t = (((px - ax) * dx + (py - ay) * dy) / L2.clamp_min(eps)).clamp(0.0, 1.0)
    ex, ey = ax + t * dx - px, ay + t * dy - py
    return ex, ey, t


# --------------------------------------------------------------------------------------------------
# outputs of the passes

@dataclass(frozen=True)
class PixelSamples:
    """Pixels paired with a point of a face, the point given by screen-space barycentrics.

    Attributes
    ----------
    pix : (N,) int64 tensor
        Flat pixel index into ``(B, S, S)``.
    b : (N,) int64 tensor
        Batch member.
    f : (N,) int64 tensor
        Face.
    l : (3, N) float tensor
        Screen-space barycentrics in the face's corners (differentiable). Per-sample fields are stored
        corner-major, ``(3, N)``: sums over corners then add rows, which is what keeps them cheap.
    iz : (3, N) float tensor
        Inverse view depth of the face's corners (differentiable).
    slot : (N,) int64 tensor
        The face's column in the per-face tables of the faces the samples use (:attr:`RasterPasses.used`).
    """

    pix: torch.Tensor
    b: torch.Tensor
    f: torch.Tensor
    l: torch.Tensor
    iz: torch.Tensor
    slot: torch.Tensor

    def __getitem__(self, mask) -> "PixelSamples":
        return PixelSamples(self.pix[mask], self.b[mask], self.f[mask], self.l[:, mask], self.iz[:, mask],
                            self.slot[mask])

    def join(self, other: "PixelSamples") -> "PixelSamples":
        """These samples followed by ``other``'s."""
        return PixelSamples(torch.cat([self.pix, other.pix]), torch.cat([self.b, other.b]),
                            torch.cat([self.f, other.f]), torch.cat([self.l, other.l], 1),
                            torch.cat([self.iz, other.iz], 1), torch.cat([self.slot, other.slot]))


_TABLE = (1, 1, 3, 3, 3, 3, 3, 3)  # rows of the face table, see face_table


def face_table(u, v, z, corner_index, eps) -> torch.Tensor:
    """What the per-pixel recomputation needs of each used face, one column per face (autograd).

    Rows: corner 0 ``(u0, v0)``; the corners relative to it ``du, dv`` (3 + 3); the screen-space
    barycentrics as affine functions of the pixel centre relative to corner 0, ``l = a + bu * pu + bv * pv``
    (3 + 3 + 3); the corners' inverse view depths (3). Relative coordinates keep float32 exact enough
    on small faces far from the image origin.
    """
    U = corner_index.shape[1]
    per_vertex = torch.stack([u, v, 1.0 / z]).reshape(3, -1)  # (u v iz, B * n)
    cu, cv, iz = per_vertex.index_select(1, corner_index.reshape(-1)).view(3, 3, U)  # (corner, U) each
    u0, v0 = cu[:1], cv[:1]
    du, dv = cu - u0, cv - v0
    ua, va = du.roll(-1, 0), dv.roll(-1, 0)  # corner i + 1
    eu, ev = du.roll(-2, 0) - ua, dv.roll(-2, 0) - va  # edge from corner i + 1 to corner i + 2
    a = ev * ua - eu * va  # twice the signed area of (i + 1, i + 2, corner 0)
    tot = a[0] + a[1] + a[2]
    tot = torch.where(tot.abs() > eps, tot, torch.full_like(tot, eps))
    return torch.cat([u0, v0, du, dv, a / tot, -ev / tot, eu / tot, iz], 0)  # (20, U)


def pixel_centres(pix, S, dt):
    return (pix % S).to(dt) + 0.5, ((pix // S) % S).to(dt) + 0.5


def inside_samples(pix, b, f, slot, table, S) -> PixelSamples:
    """Covered pixels with the screen-space barycentrics of their centre in the visible face (autograd)."""
    u0, v0, _, _, a, bu, bv, iz = table.index_select(1, slot).split(_TABLE, 0)
    pu, pv = pixel_centres(pix, S, table.dtype)
    return PixelSamples(pix, b, f, a + bu * (pu - u0) + bv * (pv - v0), iz, slot)


def fringe_samples(pix, b, f, slot, k_, hit, table, S, st: RenderSettings):
    """Soft pixels with the nearest point of their segment (autograd), and their coverage ``(Q,)``."""
    dt, dev, eps = table.dtype, table.device, st.eps
    u0, v0, du, dv, _, _, _, iz = table.index_select(1, slot).split(_TABLE, 0)
    ends = torch.stack([(k_ + 1) % 3, (k_ + 2) % 3])  # (2, Q): the segment's corners in the face
    au, bu = du.gather(0, ends)
    av, bv = dv.gather(0, ends)
    pu, pv = pixel_centres(pix, S, dt)
    ex, ey, t = seg_dist(au, av, bu, bv, pu - u0[0], pv - v0[0], eps)
    d = torch.sqrt((ex * ex + ey * ey).clamp_min(eps * eps))
    sign = torch.where(hit[pix], 1.0, -1.0).to(dt)
    cov = torch.sigmoid(sign * d / st.sigma)
    corners = torch.arange(3, device=dev).unsqueeze(1)
    l = (corners == ends[:1]).to(dt) * (1 - t) + (corners == ends[1:]).to(dt) * t
    return PixelSamples(pix, b, f, l, iz, slot), cov


def used_faces(in_b, in_f, fr_b, fr_f, F, B, n):
    """The faces some sample lies on (``b * m + f``, sorted), each sample's slot among them, their corners."""
    m = F.shape[0]
    mark = torch.zeros(B * m, dtype=torch.bool, device=F.device)
    g_in, g_fr = in_b * m + in_f, fr_b * m + fr_f
    mark[g_in] = True
    mark[g_fr] = True
    used = mark.nonzero().squeeze(1)
    slot_of = torch.cumsum(mark, 0) - 1
    corner_index = ((used // m) * n).unsqueeze(0) + F.index_select(0, used % m).t()  # (3, U)
    return used, corner_index, slot_of[g_in], slot_of[g_fr]
