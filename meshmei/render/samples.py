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
from torch.autograd.function import once_differentiable

from . import native
from .settings import RenderSettings

__all__ = ["PixelSamples", "seg_dist", "face_table", "pixel_centres", "sample_geometry", "used_faces"]


def seg_foot(ax, ay, bx, by, px, py, eps):
    """The segment ab's direction ``(dx, dy)``, squared length ``L2`` and the unclamped parameter of the
    foot of p on its line, ``t_raw`` (``L2`` floored at ``eps`` in the division)."""
    dx, dy = bx - ax, by - ay
    L2 = dx * dx + dy * dy
    t_raw = ((px - ax) * dx + (py - ay) * dy) / L2.clamp_min(eps)
    return dx, dy, L2, t_raw


def seg_dist(ax, ay, bx, by, px, py, eps):
    """Offset from p to the nearest point of segment ab and its parameter t in [0, 1]."""
    dx, dy, _, t_raw = seg_foot(ax, ay, bx, by, px, py, eps)
    t = t_raw.clamp(0.0, 1.0)
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

    def head(self, k: int) -> "PixelSamples":
        """The first ``k`` samples."""
        return PixelSamples(self.pix[:k], self.b[:k], self.f[:k], self.l[:, :k], self.iz[:, :k], self.slot[:k])


_TABLE = (1, 1, 3, 3, 3, 3, 3, 3, 1)  # rows of the face table, see face_table
_ROLL1, _ROLL2 = (1, 2, 0), (2, 0, 1)  # row j of A[_ROLL1] is corner j + 1's, of A[_ROLL2] corner j + 2's


def face_table(u, v, z, corner_index, eps) -> torch.Tensor:
    """What the per-pixel recomputation needs of each used face, one column per face.

    Rows: corner 0 ``(u0, v0)``; the corners relative to it ``du, dv`` (3 + 3); the screen-space
    barycentrics as affine functions of the pixel centre relative to corner 0, ``l = a + bu * pu + bv * pv``
    (3 + 3 + 3); the corners' inverse view depths (3); twice the signed screen area ``tot`` (1; ``eps`` where
    its size is at most ``eps``). Relative coordinates keep float32 exact enough on small faces far from
    the image origin.
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
    tot = torch.where(tot.abs() > eps, tot, torch.full_like(tot, eps)).unsqueeze(0)
    return torch.cat([u0, v0, du, dv, a / tot, -ev / tot, eu / tot, iz, tot], 0)  # (21, U)


def pixel_centres(pix, S, dt):
    return (pix % S).to(dt) + 0.5, ((pix // S) % S).to(dt) + 0.5


class _SampleGeometry(torch.autograd.Function):
    """The winning pairs' screen-space barycentrics, inverse depths and soft coverage, with a hand-written
    backward: one graph node instead of about 120 (see :func:`sample_geometry`).

    The backward is the exact derivative of the forward's arithmetic: for a covered pixel,
    ``l_i = w_i / T`` with the edge functions ``w_i`` and twice the area ``T`` (held constant where the
    forward guarded it); for a fringe pixel, the distance to the segment through its clamped foot
    parameter ``t`` and the barycentrics ``(1 - t, t)``. Every formula is written in coordinates relative to
    corner 0, as the forward's, which the derivatives in absolute coordinates equal (they are
    differences). Per-sample corner gradients are summed per face, then per vertex.
    """

    @staticmethod
    def forward(ctx, u, v, z, corner_index, in_pix, in_slot, fr_pix, fr_slot, fr_k, fr_sign, out, S, sigma, eps):
        ctx.native = native.available(u)
        if ctx.native:  # the same formulas, compiled (meshmei.render.native)
            l, iz, cov, table, pos = native.sample_forward(u, v, z, corner_index, in_pix, in_slot, fr_pix, fr_slot,
                                                           fr_k, fr_sign, out, S, sigma, eps)
            ctx.save_for_backward(z, corner_index, in_pix, in_slot, fr_pix, fr_slot, fr_k, fr_sign, pos, table, cov)
            ctx.S, ctx.sigma, ctx.eps = S, sigma, eps
            return l, iz, cov
        dt = u.dtype
        table = face_table(u, v, z, corner_index, eps)
        # covered pixels: the affine barycentrics at the pixel centre
        Ti = table.index_select(1, in_slot)
        u0, v0, du, dv, a, bu, bv, iz_in, tot = Ti.split(_TABLE, 0)
        pu, pv = pixel_centres(in_pix, S, dt)
        Pu, Pv = pu - u0, pv - v0  # (1, Ni)
        l_in = a + bu * Pu + bv * Pv
        # fringe pixels: the nearest point of the segment, corners k + 1 and k + 2 of the face
        Tf = table.index_select(1, fr_slot)
        f_u0, f_v0, f_du, f_dv, _, _, _, iz_fr, _ = Tf.split(_TABLE, 0)
        ends = torch.stack([(fr_k + 1) % 3, (fr_k + 2) % 3])  # (2, Q)
        au, bu_ = f_du.gather(0, ends)
        av, bv_ = f_dv.gather(0, ends)
        fu, fv = pixel_centres(fr_pix, S, dt)
        Qu, Qv = fu - f_u0[0], fv - f_v0[0]
        dx, dy, L2, t_raw = seg_foot(au, av, bu_, bv_, Qu, Qv, eps)
        t = t_raw.clamp(0.0, 1.0)
        ex, ey = au + t * dx - Qu, av + t * dy - Qv
        d2 = ex * ex + ey * ey
        d = torch.sqrt(d2.clamp_min(eps * eps))
        cov = torch.sigmoid(fr_sign * d / sigma)
        corners = torch.arange(3, device=u.device).unsqueeze(1)
        l_fr = (corners == ends[:1]).to(dt) * (1 - t) + (corners == ends[1:]).to(dt) * t
        ctx.save_for_backward(z, corner_index, in_slot, fr_slot, du, dv, Pu, Pv, tot, l_in, ends, Qu, Qv, au, av,
                              dx, dy, L2, t_raw, t, ex, ey, d2, d, cov, fr_sign, out)
        ctx.shape, ctx.sigma, ctx.eps = u.shape, sigma, eps
        # the samples to shade: covered pixels, then the fringe pixels outside the surface
        return (torch.cat([l_in, l_fr.index_select(1, out)], 1), torch.cat([iz_in, iz_fr.index_select(1, out)], 1),
                cov)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_l, g_iz, g_cov):
        if ctx.native:
            g_u, g_v, g_z = native.sample_backward(*ctx.saved_tensors, ctx.S, ctx.sigma, ctx.eps, g_l, g_iz, g_cov)
            return (g_u, g_v, g_z) + (None,) * 11
        (z, corner_index, in_slot, fr_slot, du, dv, Pu, Pv, tot, l_in, ends, Qu, Qv, au, av, dx, dy, L2, t_raw, t,
         ex, ey, d2, d, cov, fr_sign, out) = ctx.saved_tensors
        eps, Ni = ctx.eps, in_slot.shape[0]
        r1 = torch.tensor(_ROLL1, device=z.device)
        r2 = torch.tensor(_ROLL2, device=z.device)
        # covered: l_i = w_i / T; w_i is the edge function of edge (i + 1, i + 2) at the pixel centre
        gl = g_l[:, :Ni]
        gw = gl / tot
        gT = torch.where(tot == eps, 0.0, -(gl * l_in).sum(0, keepdim=True) / tot)  # (1, Ni)
        W1, W2 = gw.index_select(0, r1), gw.index_select(0, r2)
        X1, X2, Y1, Y2 = du.index_select(0, r1), du.index_select(0, r2), dv.index_select(0, r1), dv.index_select(0, r2)
        gx_in = W2 * (Y1 - Pv) + W1 * (Pv - Y2) + gT * (Y1 - Y2)
        gy_in = W2 * (Pu - X1) + W1 * (X2 - Pu) + gT * (X2 - X1)
        # fringe: distance d from the pixel centre to a + t (b - a), coverage sigmoid(sign d / sigma)
        gd = torch.where(d2 >= eps * eps, g_cov * cov * (1 - cov) * fr_sign / ctx.sigma, 0.0)
        gex, gey = gd * ex / d, gd * ey / d
        Q = fr_slot.shape[0]
        glf = torch.zeros(3, Q, dtype=g_l.dtype, device=g_l.device).index_copy_(1, out, g_l[:, Ni:])
        gt = gex * dx + gey * dy + glf.gather(0, ends[1:])[0] - glf.gather(0, ends[:1])[0]
        gt = torch.where((t_raw >= 0) & (t_raw <= 1), gt, 0.0)
        L2c = L2.clamp_min(eps)
        gn = gt / L2c
        gL2 = torch.where(L2 >= eps, -gn * t_raw, 0.0)
        ru, rv = Qu - au, Qv - av
        ga_u = gex * (1 - t) - gn * (dx + ru) - 2 * gL2 * dx
        gb_u = gex * t + gn * ru + 2 * gL2 * dx
        ga_v = gey * (1 - t) - gn * (dy + rv) - 2 * gL2 * dy
        gb_v = gey * t + gn * rv + 2 * gL2 * dy
        g_iz_fr = torch.zeros(3, Q, dtype=g_iz.dtype, device=g_iz.device).index_copy_(1, out, g_iz[:, Ni:])
        gx_fr = torch.zeros(3, Q, dtype=gd.dtype, device=gd.device).scatter_(0, ends, torch.stack([ga_u, gb_u]))
        gy_fr = torch.zeros(3, Q, dtype=gd.dtype, device=gd.device).scatter_(0, ends, torch.stack([ga_v, gb_v]))
        # per sample (quantity u, v, iz; corner) -> per face -> per vertex
        G = torch.cat([torch.cat([gx_in, gy_in, g_iz[:, :Ni]], 0), torch.cat([gx_fr, gy_fr, g_iz_fr], 0)], 1)
        U = corner_index.shape[1]
        per_face = torch.zeros(9, U, dtype=G.dtype, device=G.device).index_add_(1, torch.cat([in_slot, fr_slot]), G)
        per_vertex = torch.zeros(3, z.numel(), dtype=G.dtype, device=G.device)
        per_vertex.index_add_(1, corner_index.reshape(-1), per_face.view(3, 3 * U))
        g_u, g_v, g_iz_v = per_vertex.view(3, *ctx.shape).unbind(0)
        return (g_u, g_v, -g_iz_v / (z * z)) + (None,) * 11


def sample_geometry(in_pix, in_b, in_f, in_slot, fr_pix, fr_b, fr_f, fr_slot, fr_k, hit, u, v, z, corner_index,
                    S, st: RenderSettings):
    """The samples to shade and the fringe's soft coverage ``(Q,)``.

    The samples are the covered pixels, with the screen-space barycentrics of their centre in the visible
    face, followed by the fringe pixels outside the surface, with the nearest point of their contour
    segment; the coverage is that of every fringe pixel. ``u, v, z``: ``(B, n)`` pixel coordinates and view
    depth of the vertices (differentiable); ``corner_index``: ``(3, U)`` rows of the used faces' corners in
    the flattened ``(B * n)`` arrays.
    """
    outside = ~hit[fr_pix]
    sign = torch.where(outside, -1.0, 1.0).to(u.dtype)
    out = outside.nonzero().squeeze(1)
    l, iz, cov = _SampleGeometry.apply(u, v, z, corner_index, in_pix, in_slot, fr_pix, fr_slot, fr_k, sign, out, S,
                                       float(st.sigma), float(st.eps))
    cat = lambda a, b: torch.cat([a, b.index_select(0, out)])  # noqa: E731
    return PixelSamples(cat(in_pix, fr_pix), cat(in_b, fr_b), cat(in_f, fr_f), l, iz, cat(in_slot, fr_slot)), cov


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
