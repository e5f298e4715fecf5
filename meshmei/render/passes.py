"""The rasterizer's passes: a hard z-buffer over bounded (face, pixel) pairs plus a soft, differentiable silhouette.

Two passes run without autograd and only decide *which* primitive each pixel sees:

1. the z-buffer enumerates, for every face kept after clipping and frustum culling, the pixel centres
   inside its screen bounding box, in chunks of at most ``settings.chunk_size`` pairs; a pair that passes
   the inside test writes ``(depth, face)`` packed into one int64 key with ``scatter_reduce('amin')``;
2. the silhouette pass does the same for the *contour segments* (mesh edges whose two faces project to
   the same side, boundary edges, and edges of clipped-away neighbours) over their boxes grown by the
   soft margin, keeping per pixel the nearest segment.

Then the winning (pixel, face) and (pixel, segment) pairs alone are recomputed with autograd: perspective
correct barycentrics and depth for covered pixels, and the signed distance to the silhouette, which gives
the soft coverage ``sigmoid(s / sigma)``. Nothing of size pixels x faces is ever formed and the autograd
graph holds O(pixels) values, so backward needs no re-enumeration. See ``docs/rendering.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as nnf

from ..topology import mesh_topology
from .camera import Camera
from .settings import RenderSettings

__all__ = ["PixelSamples", "RasterPasses", "run_passes"]

_NONE = torch.iinfo(torch.int64).max  # z-buffer key of an empty pixel


# --------------------------------------------------------------------------------------------------
def _ranges(lo, hi, S):
    """Inclusive index range of pixel centres ``i + 0.5`` in ``[lo, hi]``, clipped to the image."""
    lo = torch.ceil(lo.clamp(-2.0, S + 2.0) - 0.5).long().clamp(0, S)
    hi = torch.floor(hi.clamp(-2.0, S + 2.0) - 0.5).long().clamp(-1, S - 1)
    return lo, hi


def _pairs(x0, x1, y0, y1, chunk):
    """Yield ``(item, row, col)`` for every pixel of every item's box, at most ``chunk`` at a time."""
    nx = (x1 - x0 + 1).clamp_min(0)
    cnt = nx * (y1 - y0 + 1).clamp_min(0)
    if cnt.numel() == 0:
        return
    cum = torch.cumsum(cnt, 0)
    total = int(cum[-1])
    first = cum - cnt
    for s in range(0, total, chunk):
        p = torch.arange(s, min(s + chunk, total), device=cnt.device)
        item = torch.searchsorted(cum, p, right=True)
        local = p - first[item]
        w = nx[item]
        yield item, y0[item] + local // w, x0[item] + local % w


def _edge_fn(ax, ay, bx, by, px, py):
    """Twice the signed area of (a, b, p): positive when p is left of a->b in (u, v) pixel coordinates."""
    return (bx - ax) * (py - ay) - (by - ay) * (px - ax)


def _seg_dist(ax, ay, bx, by, px, py, eps):
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
    l : (N, 3) float tensor
        Screen-space barycentrics in the face's corners (differentiable).
    """

    pix: torch.Tensor
    b: torch.Tensor
    f: torch.Tensor
    l: torch.Tensor

    def __getitem__(self, mask) -> "PixelSamples":
        return PixelSamples(self.pix[mask], self.b[mask], self.f[mask], self.l[mask])


@dataclass(frozen=True)
class RasterPasses:
    """What the two no-grad passes decided, with the differentiable recomputation of the winners.

    Attributes
    ----------
    B, S : int
        Batch size and image size.
    Vc : (B, n, 3) float tensor
        View coordinates of the vertices.
    z : (B, n) float tensor
        View depth of the vertices (1 where outside ``[znear, zfar]``: such faces are culled).
    front : (B, m) bool tensor
        Faces that turn counter-clockwise towards the camera.
    face_id : (B, S, S) int64 tensor
        Nearest face at each pixel centre, -1 for background.
    hit : (B * S * S,) bool tensor
        Covered pixels.
    inside : PixelSamples
        Every covered pixel with its visible face.
    fringe : PixelSamples
        Every pixel within the soft margin of the silhouette (outside, or inside next to the background),
        with the nearest point of the nearest contour segment.
    coverage : (B * S * S,) float tensor
        Soft coverage (differentiable).
    """

    B: int
    S: int
    Vc: torch.Tensor
    z: torch.Tensor
    front: torch.Tensor
    face_id: torch.Tensor
    hit: torch.Tensor
    inside: PixelSamples
    fringe: PixelSamples
    coverage: torch.Tensor

    def perspective_correct(self, F: torch.Tensor, samples: PixelSamples):
        """Perspective-correct barycentrics ``(N, 3)`` and view depth ``(N,)`` of ``samples``."""
        iz = 1.0 / self.z[samples.b.unsqueeze(1), F[samples.f]]  # (N, 3)
        q = samples.l * iz
        s = q.sum(1, keepdim=True)
        s = torch.where(s > 0, s, torch.ones_like(s))
        return q / s, 1.0 / s.squeeze(1)


# --------------------------------------------------------------------------------------------------
# the passes, step by step

class _Screen(NamedTuple):
    """Projected faces (no grad): corner pixel coordinates, screen boxes, kept (batch, face) pairs."""

    fu: torch.Tensor  # (B, m, 3) corner u
    fv: torch.Tensor  # (B, m, 3) corner v
    umin: torch.Tensor  # (B, m) screen box
    umax: torch.Tensor
    vmin: torch.Tensor
    vmax: torch.Tensor
    keep: torch.Tensor  # (B, m) bool: in depth range and near the image
    kb: torch.Tensor  # (K,) batch member of each kept face
    kf: torch.Tensor  # (K,) kept face
    front: torch.Tensor  # (B, m) bool


def _project(Vw, eye, R, cam: Camera, S):
    """View depth and pixel coordinates of every vertex; a vertex outside [znear, zfar] is flagged, not divided."""
    Vc = torch.matmul(Vw - eye.unsqueeze(1), R.transpose(-1, -2))  # (B, n, 3)
    z = Vc[..., 2]
    ok = (z >= cam.znear) & (z <= cam.zfar)
    zs = torch.where(ok, z, torch.ones_like(z))  # divide only where valid, so no Inf reaches backward
    f = cam.focal_pixels(S)
    u = 0.5 * S + f * torch.where(ok, Vc[..., 0], torch.zeros_like(z)) / zs
    v = 0.5 * S - f * torch.where(ok, Vc[..., 1], torch.zeros_like(z)) / zs
    return Vc, zs, u, v, ok


def _cull(U, Vv, ok, F, S, margin) -> _Screen:
    """Keep the faces whose corners all lie in the depth range and whose box reaches the (grown) image."""
    fu, fv = U[:, F], Vv[:, F]  # (B, m, 3)
    keep = ok[:, F].all(-1)
    umin, umax = fu.amin(-1), fu.amax(-1)
    vmin, vmax = fv.amin(-1), fv.amax(-1)
    keep &= (umax >= -margin) & (umin <= S + margin) & (vmax >= -margin) & (vmin <= S + margin)
    kb, kf = keep.nonzero().unbind(1)
    area2 = _edge_fn(fu[..., 0], fv[..., 0], fu[..., 1], fv[..., 1], fu[..., 2], fv[..., 2])  # (B, m)
    front = area2 < 0  # outward (counter-clockwise) faces turn clockwise in (u, v) with v down
    return _Screen(fu, fv, umin, umax, vmin, vmax, keep, kb, kf, front)


def _zbuffer(sc: _Screen, Z, F, B, S, chunk) -> torch.Tensor:
    """Pass 1: per pixel the smallest ``(depth bits << 32) | kept-face slot`` key, ``(B * S * S,)`` int64."""
    kb, kf = sc.kb, sc.kf
    zkey = torch.full((B * S * S,), _NONE, dtype=torch.int64, device=Z.device)
    if not kb.shape[0]:
        return zkey
    dt = sc.fu.dtype
    Fk = F[kf]  # (K, 3)
    ku, kv = sc.fu[kb, kf], sc.fv[kb, kf]  # (K, 3)
    kiz = 1.0 / Z[kb.unsqueeze(1), Fk]
    # canonical edge direction (lower vertex id first) so that a shared edge gives bitwise
    # opposite edge functions in its two faces: no cracks, no double-free pixels
    i1, i2 = [1, 2, 0], [2, 0, 1]
    va, vb = Fk[:, i1], Fk[:, i2]
    flip = va > vb
    ax = torch.where(flip, ku[:, i2], ku[:, i1])
    ay = torch.where(flip, kv[:, i2], kv[:, i1])
    sg = torch.where(flip, -1.0, 1.0).to(dt)
    dx = sg * (torch.where(flip, ku[:, i1], ku[:, i2]) - ax)
    dy = sg * (torch.where(flip, kv[:, i1], kv[:, i2]) - ay)
    x0, x1 = _ranges(sc.umin[kb, kf], sc.umax[kb, kf], S)
    y0, y1 = _ranges(sc.vmin[kb, kf], sc.vmax[kb, kf], S)
    for it, ii, jj in _pairs(x0, x1, y0, y1, chunk):
        px = (jj.to(dt) + 0.5).unsqueeze(1)
        py = (ii.to(dt) + 0.5).unsqueeze(1)
        w = dx[it] * (py - ay[it]) - dy[it] * (px - ax[it])  # (P, 3)
        tot = w.sum(1)
        inside = ((w >= 0).all(1) & (tot > 0)) | ((w <= 0).all(1) & (tot < 0))
        if not bool(inside.any()):
            continue
        it, ii, jj, w, tot = it[inside], ii[inside], jj[inside], w[inside], tot[inside]
        depth = tot / (w * kiz[it]).sum(1)
        bits = depth.float().clamp_min(0).view(torch.int32).long()
        key = (bits << 32) | it
        pix = (kb[it] * S + ii) * S + jj
        zkey.scatter_reduce_(0, pix, key, "amin")
    return zkey


def _contour_segments(sc: _Screen, U, Vv, F, n_vertices):
    """The silhouette's candidate segments: ``(Q, 2)`` (kept-face slot, edge k) and their endpoints.

    An edge is a contour segment when its two faces project to the same side of it, when it is a
    boundary edge, or when its neighbour was culled; of two half-edges, one owns the segment.
    """
    kb, kf = sc.kb, sc.kf
    Fk = F[kf]  # (K, 3)
    ku, kv = sc.fu[kb, kf], sc.fv[kb, kf]  # (K, 3)
    twin = mesh_topology(F, n_vertices).twins[kf]  # (K, 3)
    tf = twin.clamp_min(0) // 3
    tk = twin.clamp_min(0) % 3
    tkeep = (twin >= 0) & sc.keep[kb.unsqueeze(1), tf]
    ea = Fk[:, [1, 2, 0]]
    eb = Fk[:, [2, 0, 1]]
    opp_g = F[tf, tk]  # (K, 3): the twin face's corner off the edge
    bu = kb.unsqueeze(1)
    Au, Av, Bu, Bv = U[bu, ea], Vv[bu, ea], U[bu, eb], Vv[bu, eb]
    # side tests with the edge in canonical order, so both half-edges classify it identically
    lo, hi = torch.minimum(ea, eb), torch.maximum(ea, eb)
    Lu, Lv, Hu, Hv = U[bu, lo], Vv[bu, lo], U[bu, hi], Vv[bu, hi]
    side_f = _edge_fn(Lu, Lv, Hu, Hv, ku, kv)  # opposite corner k of this face
    side_g = _edge_fn(Lu, Lv, Hu, Hv, U[bu, opp_g], Vv[bu, opp_g])
    contour = ~(tkeep & (side_f * side_g < 0))
    fr, gfr = sc.front[kb, kf].unsqueeze(1), sc.front[bu, tf]
    owner = ~tkeep | (fr & ~gfr) | ((fr == gfr) & (kf.unsqueeze(1) < tf))
    sel = (contour & owner).nonzero()  # (Q, 2): kept-face slot, edge k
    s_, k_ = sel.unbind(1)
    return sel, (Au[s_, k_], Av[s_, k_], Bu[s_, k_], Bv[s_, k_])


def _segment_buffer(sc: _Screen, seg, ends, B, S, st: RenderSettings) -> torch.Tensor:
    """Pass 2: per pixel within the soft margin the smallest ``(distance bits << 32) | segment`` key."""
    margin, eps, dt = st.soft_margin, st.eps, sc.fu.dtype
    skey = torch.full((B * S * S,), _NONE, dtype=torch.int64, device=sc.fu.device)
    if not seg.shape[0]:
        return skey
    s_ = seg[:, 0]
    sa_u, sa_v, sb_u, sb_v = ends
    x0, x1 = _ranges(torch.minimum(sa_u, sb_u) - margin, torch.maximum(sa_u, sb_u) + margin, S)
    y0, y1 = _ranges(torch.minimum(sa_v, sb_v) - margin, torch.maximum(sa_v, sb_v) + margin, S)
    for it, ii, jj in _pairs(x0, x1, y0, y1, st.chunk_size):
        px, py = jj.to(dt) + 0.5, ii.to(dt) + 0.5
        ex, ey, _ = _seg_dist(sa_u[it], sa_v[it], sb_u[it], sb_v[it], px, py, eps)
        d = torch.sqrt(ex * ex + ey * ey)
        near = d <= margin
        if not bool(near.any()):
            continue
        key = (d[near].float().view(torch.int32).long() << 32) | it[near]
        pix = (sc.kb[s_[it[near]]] * S + ii[near]) * S + jj[near]
        skey.scatter_reduce_(0, pix, key, "amin")
    return skey


def _soft_pixels(skey, hit, B, S, margin, dt) -> torch.Tensor:
    """Pixels that get a soft coverage value, ``(B * S * S,)`` bool: near a segment, and if covered, near
    an uncovered pixel (see docs: interior fold contours)."""
    soft = skey != _NONE
    covered = hit.view(B, 1, S, S)
    reach = math.ceil(margin + 1.5)
    near_bg = nnf.max_pool2d((~covered).to(dt), 2 * reach + 1, stride=1, padding=reach) > 0
    return soft & (~hit | near_bg.view(-1))


def _inside_samples(hit, face_id, F, u, v, S, eps) -> PixelSamples:
    """Covered pixels with the screen-space barycentrics of their centre in the visible face (autograd)."""
    dt = u.dtype
    pix = hit.nonzero().squeeze(1)
    b = pix // (S * S)
    f = face_id[pix]
    pu = ((pix % S).to(dt) + 0.5).unsqueeze(1)
    pv = (((pix // S) % S).to(dt) + 0.5).unsqueeze(1)
    Fi = F[f]  # (N, 3)
    cu, cv = u[b.unsqueeze(1), Fi], v[b.unsqueeze(1), Fi]  # (N, 3)
    w = _edge_fn(cu[:, [1, 2, 0]], cv[:, [1, 2, 0]], cu[:, [2, 0, 1]], cv[:, [2, 0, 1]], pu, pv)
    tot = w.sum(1, keepdim=True)
    tot = torch.where(tot.abs() > eps, tot, torch.full_like(tot, eps))
    return PixelSamples(pix, b, f, w / tot)


def _fringe_samples(soft, skey, seg, sc: _Screen, hit, F, u, v, S, st: RenderSettings):
    """Soft pixels with the nearest point of their segment (autograd), and their coverage ``(Q,)``."""
    dt, dev, eps = u.dtype, u.device, st.eps
    pix = soft.nonzero().squeeze(1)
    if not pix.numel():
        empty = PixelSamples(pix, pix, pix, torch.zeros(0, 3, dtype=dt, device=dev))
        return empty, torch.zeros(0, dtype=dt, device=dev)
    sl = (skey[pix] & 0xFFFFFFFF)
    s_, k_ = seg[sl].unbind(1)
    b, f = sc.kb[s_], sc.kf[s_]
    ia, ib = F[f, (k_ + 1) % 3], F[f, (k_ + 2) % 3]
    px = (pix % S).to(dt) + 0.5
    py = ((pix // S) % S).to(dt) + 0.5
    ex, ey, t = _seg_dist(u[b, ia], v[b, ia], u[b, ib], v[b, ib], px, py, eps)
    d = torch.sqrt((ex * ex + ey * ey).clamp_min(eps * eps))
    sign = torch.where(hit[pix], 1.0, -1.0).to(dt)
    cov = torch.sigmoid(sign * d / st.sigma)
    l = torch.zeros(pix.shape[0], 3, dtype=dt, device=dev)
    ar = torch.arange(pix.shape[0], device=dev)
    l = l.index_put((ar, (k_ + 1) % 3), 1 - t).index_put((ar, (k_ + 2) % 3), t)
    return PixelSamples(pix, b, f, l), cov


def run_passes(Vw, F, eye, R, cam: Camera, st: RenderSettings, n_vertices: int) -> RasterPasses:
    """Run both passes and the differentiable recomputation.

    Parameters
    ----------
    Vw : (B, n, 3) float tensor
        World vertices (see :meth:`RenderInputs.expanded`).
    F : (m, 3) int64 tensor
    eye : (B, 3) float tensor
    R : (B, 3, 3) float tensor
    cam : Camera
    st : RenderSettings
    n_vertices : int

    Returns
    -------
    RasterPasses
    """
    S, B = st.image_size, Vw.shape[0]
    dt = Vw.dtype
    Vc, z, u, v, ok = _project(Vw, eye, R, cam, S)
    with torch.no_grad():
        U, Vv = u.detach(), v.detach()
        sc = _cull(U, Vv, ok, F, S, st.soft_margin)
        zkey = _zbuffer(sc, z.detach(), F, B, S, st.chunk_size)
        hit = zkey != _NONE
        slot = (zkey & 0xFFFFFFFF).masked_fill(~hit, 0)
        face_id = torch.full((B * S * S,), -1, dtype=torch.int64, device=Vw.device)
        if sc.kb.shape[0]:
            face_id[hit] = sc.kf[slot[hit]]
            seg, ends = _contour_segments(sc, U, Vv, F, n_vertices)
            skey = _segment_buffer(sc, seg, ends, B, S, st)
        else:
            seg, skey = None, torch.full((B * S * S,), _NONE, dtype=torch.int64, device=Vw.device)
        soft = _soft_pixels(skey, hit, B, S, st.soft_margin, dt)
    inside = _inside_samples(hit, face_id, F, u, v, S, st.eps)
    fringe, cov_s = _fringe_samples(soft, skey, seg, sc, hit, F, u, v, S, st)
    cov = torch.zeros(B * S * S, dtype=dt, device=Vw.device).index_put((inside.pix,), torch.ones_like(inside.pix, dtype=dt))
    return RasterPasses(B=B, S=S, Vc=Vc, z=z, front=sc.front, face_id=face_id.view(B, S, S), hit=hit, inside=inside,
                        fringe=fringe, coverage=cov.index_put((fringe.pix,), cov_s))


