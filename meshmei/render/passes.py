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

On CPU, where a C compiler is found, :func:`run_passes` takes the no-grad front (cull, both passes, the soft
pixels, the samples and the used faces) from one compiled call, :func:`meshmei.render.native.front`, whose
decisions are those of the torch code below (up to the last bit of a square root, see there); the torch code
is the reference and the fallback.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as nnf

from ..topology import mesh_topology
from . import native
from .camera import Camera
from .samples import PixelSamples, sample_geometry, seg_dist, used_faces
from .settings import RenderSettings

__all__ = ["PixelSamples", "RasterPasses", "run_passes"]

_NONE = torch.iinfo(torch.int64).max  # z-buffer key of an empty pixel


# --------------------------------------------------------------------------------------------------
def _ranges(lo, hi, S):
    """Inclusive index range of pixel centres ``i + 0.5`` in ``[lo, hi]``, clipped to the image."""
    lo = torch.ceil(lo.clamp(-2.0, S + 2.0) - 0.5).long().clamp(0, S)
    hi = torch.floor(hi.clamp(-2.0, S + 2.0) - 0.5).long().clamp(-1, S - 1)
    return lo, hi


def _pairs(lo, hi, chunk):
    """Yield ``(item, row, col)`` for every pixel of every item's box, at most ``chunk`` at a time; ``lo`` and
    ``hi`` are ``(K, 2)`` inclusive (column, row) ranges (:func:`_ranges` of the box corners)."""
    n = (hi - lo + 1).clamp_min(0)
    nx = n[:, 0]
    cnt = nx * n[:, 1]
    if cnt.numel() == 0:
        return
    cum = torch.cumsum(cnt, 0)
    total = int(cum[-1])
    per_item = torch.stack([cum - cnt, nx, lo[:, 1], lo[:, 0]], 1)  # one gather per chunk instead of four
    for s in range(0, total, chunk):
        p = torch.arange(s, min(s + chunk, total), device=cnt.device)
        if total <= chunk:
            item = torch.repeat_interleave(torch.arange(cnt.shape[0], device=cnt.device), cnt, output_size=total)
        else:
            item = torch.searchsorted(cum, p, right=True)
        first, w, row0, col0 = per_item.index_select(0, item).unbind(1)
        local = p - first
        # local // w in float64, exact for any image (the fraction is at least 0.5 / w from an integer), and
        # local % w as the rest: CPU int64 division and remainder cost several times more
        row = ((local.double() + 0.5) / w.double()).long()
        yield item, row0 + row, col0 + (local - row * w)


def _edge_fn(ax, ay, bx, by, px, py):
    """Twice the signed area of (a, b, p): positive when p is left of a->b in (u, v) pixel coordinates."""
    return (bx - ax) * (py - ay) - (by - ay) * (px - ax)


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
    shaded : PixelSamples
        What the image shades: every covered pixel with the point of its visible face under the pixel
        centre (the first :attr:`n_inside` samples, :attr:`inside`), then every fringe pixel outside the
        surface with the nearest point of the nearest contour segment.
    n_inside : int
        Covered pixels.
    fringe_pix : (Q,) int64 tensor
        Every pixel within the soft margin of the silhouette (outside, or inside next to the background):
        those with a soft coverage.
    coverage : (B * S * S,) float tensor
        Soft coverage (differentiable).
    used : (U,) int64 tensor
        The (batch member, face) pairs some sample lies on, as ``b * m + f``, in increasing order; per-face
        tables are built for these alone, so their cost follows the visible faces, not the mesh.
    corner_index : (3, U) int64 tensor
        Their corners as rows ``b * n + vertex`` of the flattened ``(B * n, ...)`` per-vertex arrays.
    """

    B: int
    S: int
    Vc: torch.Tensor
    z: torch.Tensor
    front: torch.Tensor
    face_id: torch.Tensor
    hit: torch.Tensor
    shaded: PixelSamples
    n_inside: int
    fringe_pix: torch.Tensor
    coverage: torch.Tensor
    used: torch.Tensor
    corner_index: torch.Tensor

    @property
    def inside(self) -> PixelSamples:
        """Every covered pixel with its visible face."""
        return self.shaded.head(self.n_inside)

    def perspective_correct(self, samples: PixelSamples):
        """Perspective-correct barycentrics ``(N, 3)`` and view depth ``(N,)`` of ``samples``."""
        q = samples.l * samples.iz
        s = q[0] + q[1] + q[2]
        s = torch.where(s > 0, s, torch.ones_like(s))
        return (q / s).t(), 1.0 / s


# --------------------------------------------------------------------------------------------------
# the passes, step by step

class _Screen(NamedTuple):
    """Projected faces (no grad): the kept (batch member, face) pairs with their corners and screen boxes."""

    keep: torch.Tensor  # (B, m) bool: in depth range and near the image
    front: torch.Tensor  # (B, m) bool
    kb: torch.Tensor  # (K,) batch member of each kept face
    kf: torch.Tensor  # (K,) kept face
    ku: torch.Tensor  # (K, 3) corner u
    kv: torch.Tensor  # (K, 3) corner v
    box: torch.Tensor  # (K, 4) umin, umax, vmin, vmax
    u1: torch.Tensor  # (K, 3) u of corner k + 1: half-edge k runs from it ...
    u2: torch.Tensor  # (K, 3) ... to corner k + 2
    v1: torch.Tensor  # (K, 3)
    v2: torch.Tensor  # (K, 3)


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
    B, m = U.shape[0], F.shape[0]
    cyc = mesh_topology(F, U.shape[1]).corner_cycle  # (m, 9): corners k, k + 1, k + 2
    fu, fv = U[:, cyc], Vv[:, cyc]  # (B, m, 9)
    umin, umax = fu[..., :3].amin(-1), fu[..., :3].amax(-1)
    vmin, vmax = fv[..., :3].amin(-1), fv[..., :3].amax(-1)
    keep = ok[:, F].all(-1) & (umax >= -margin) & (umin <= S + margin) & (vmax >= -margin) & (vmin <= S + margin)
    area2 = _edge_fn(fu[..., 0], fv[..., 0], fu[..., 1], fv[..., 1], fu[..., 2], fv[..., 2])  # (B, m)
    front = area2 < 0  # outward (counter-clockwise) faces turn clockwise in (u, v) with v down
    kept = keep.view(-1).nonzero().squeeze(1)  # kb * m + kf
    rows = torch.cat([fu, fv, torch.stack([umin, umax, vmin, vmax], -1)], -1).view(B * m, 22).index_select(0, kept)
    ku, u1, u2, kv, v1, v2, box = rows.split((3, 3, 3, 3, 3, 3, 4), 1)
    return _Screen(keep, front, kept // m, kept % m, ku, kv, box, u1, u2, v1, v2)


def _zbuffer(sc: _Screen, Z, F, B, S, chunk, flip) -> torch.Tensor:
    """Pass 1: per pixel the smallest ``(depth bits << 32) | kept-face slot`` key, ``(B * S * S,)`` int64.
    ``flip``: ``(K, 3)`` bool, the kept faces' half-edges that run from the higher vertex id to the lower."""
    kb, kf = sc.kb, sc.kf
    zkey = torch.full((B * S * S,), _NONE, dtype=torch.int64, device=Z.device)
    if not kb.shape[0]:
        return zkey
    dt = sc.ku.dtype
    kiz = 1.0 / torch.take(Z, (kb * Z.shape[1]).unsqueeze(1) + F.index_select(0, kf))
    # canonical edge direction (lower vertex id first) so that a shared edge gives bitwise
    # opposite edge functions in its two faces: no cracks, no double-free pixels
    u1, u2, v1, v2 = sc.u1, sc.u2, sc.v1, sc.v2  # edge k runs from corner k + 1 to corner k + 2
    ax, ay = torch.where(flip, u2, u1), torch.where(flip, v2, v1)
    sg = torch.where(flip, -1.0, 1.0).to(dt)
    dx = sg * (torch.where(flip, u1, u2) - ax)
    dy = sg * (torch.where(flip, v1, v2) - ay)
    lo, hi = _ranges(sc.box[:, 0::2], sc.box[:, 1::2], S)  # (K, 2): columns, rows
    table = torch.cat([ax, ay, dx, dy, kiz], 1).t().contiguous()  # (15, K): one gather per chunk
    pix0 = kb * (S * S)
    for it, ii, jj in _pairs(lo, hi, chunk):
        px, py = jj.to(dt) + 0.5, ii.to(dt) + 0.5
        t_ax, t_ay, t_dx, t_dy, t_iz = table.index_select(1, it).view(5, 3, -1).unbind(0)  # (3, P) each
        w = t_dx * (py - t_ay) - t_dy * (px - t_ax)
        w0, w1, w2 = w.unbind(0)
        tot = w0 + w1 + w2
        # inside: every w_k on the side of their (non-zero) sum, i.e. all >= 0 with tot > 0 or all <= 0 with
        # tot < 0 (multiplying by the sign is exact)
        inside = ((w * torch.sign(tot)).amin(0) >= 0) & (tot != 0)
        wz = w * t_iz
        depth = tot / (wz[0] + wz[1] + wz[2])
        bits = depth.float().clamp_min(0).view(torch.int32).long()
        key = torch.where(inside, (bits << 32) | it, _NONE)  # pairs outside their face change nothing
        zkey.scatter_reduce_(0, pix0.index_select(0, it) + ii * S + jj, key, "amin")
    return zkey


def _contour_segments(sc: _Screen, U, Vv, F, edges):
    """The silhouette's candidate segments: ``(Q, 2)`` (kept-face slot, edge k) and their endpoints.
    ``edges``: the kept faces' rows of :attr:`~meshmei.topology.MeshTopology.edge_table`.

    An edge is a contour segment when its two faces project to the same side of it, when it is a
    boundary edge, or when its neighbour was culled; of two half-edges, one owns the segment.
    """
    kb, kf, ku, kv = sc.kb, sc.kf, sc.ku, sc.kv
    B, n, m = U.shape[0], U.shape[1], F.shape[0]
    lo, hi, opp, tf = edges[:, :12].view(-1, 4, 3).unbind(1)  # (K, 3) each
    has_twin = tf >= 0
    tf = tf.clamp_min(0)
    bm = (kb * m).unsqueeze(1)
    tkeep = has_twin & torch.take(sc.keep, bm + tf)
    # side tests with the edge in canonical order, so both half-edges classify it identically
    bn = (kb * n).unsqueeze(1)
    uv = torch.stack([U, Vv], -1).view(B * n, 2)
    pts = uv.index_select(0, (bn.unsqueeze(1) + edges[:, :9].view(-1, 3, 3)).view(-1))
    Lu, Lv, Hu, Hv, Ou, Ov = pts.view(-1, 3, 3, 2).permute(1, 3, 0, 2).reshape(6, -1, 3)
    side_f = _edge_fn(Lu, Lv, Hu, Hv, ku, kv)  # opposite corner k of this face
    side_g = _edge_fn(Lu, Lv, Hu, Hv, Ou, Ov)
    contour = ~(tkeep & (side_f * side_g < 0))
    fr, gfr = torch.take(sc.front, kb * m + kf).unsqueeze(1), torch.take(sc.front, bm + tf)
    owner = ~tkeep | (fr & ~gfr) | ((fr == gfr) & (kf.unsqueeze(1) < tf))
    sel = (contour & owner).nonzero()  # (Q, 2): kept-face slot, edge k
    s_, k_ = sel.unbind(1)
    flat = s_ * 3 + k_
    ends = (torch.take(sc.u1, flat), torch.take(sc.v1, flat), torch.take(sc.u2, flat), torch.take(sc.v2, flat))
    return sel, ends


def _segment_buffer(sc: _Screen, seg, ends, B, S, st: RenderSettings) -> torch.Tensor:
    """Pass 2: per pixel within the soft margin the smallest ``(distance bits << 32) | segment`` key."""
    margin, eps, dt = st.soft_margin, st.eps, sc.ku.dtype
    skey = torch.full((B * S * S,), _NONE, dtype=torch.int64, device=sc.ku.device)
    if not seg.shape[0]:
        return skey
    s_ = seg[:, 0]
    sa_u, sa_v, sb_u, sb_v = ends
    a, b = torch.stack([sa_u, sa_v], 1), torch.stack([sb_u, sb_v], 1)
    lo, hi = _ranges(torch.minimum(a, b) - margin, torch.maximum(a, b) + margin, S)  # (Q, 2): columns, rows
    table = torch.cat([a, b], 1)  # (Q, 4): one gather per chunk
    pix0 = sc.kb.index_select(0, s_) * (S * S)
    for it, ii, jj in _pairs(lo, hi, st.chunk_size):
        px, py = jj.to(dt) + 0.5, ii.to(dt) + 0.5
        ax, ay, bx, by = table.index_select(0, it).unbind(1)
        ex, ey, _ = seg_dist(ax, ay, bx, by, px, py, eps)
        d = torch.sqrt(ex * ex + ey * ey)
        key = torch.where(d <= margin, (d.float().view(torch.int32).long() << 32) | it, _NONE)
        skey.scatter_reduce_(0, pix0.index_select(0, it) + ii * S + jj, key, "amin")
    return skey


def _soft_pixels(skey, hit, B, S, margin) -> torch.Tensor:
    """Pixels that get a soft coverage value, ``(B * S * S,)`` bool: near a segment, and if covered, near
    an uncovered pixel (see docs: interior fold contours)."""
    soft = skey != _NONE
    check = (soft & hit).nonzero().squeeze(1)  # covered soft pixels: is an uncovered pixel within reach?
    if not check.numel():
        return soft
    reach = math.ceil(margin + 1.5)
    # box counts of uncovered pixels from an integral image; the box is clipped to the image
    bare = (~hit).view(B, S, S).to(torch.int32).cumsum(1).cumsum(2)
    table = nnf.pad(bare, (1, 0, 1, 0)).reshape(-1)  # (B, S + 1, S + 1): table[b, i, j] = sum over [0, i) x [0, j)
    b, i, j = check // (S * S), (check // S) % S, check % S
    i0, i1 = (i - reach).clamp_min(0), (i + reach + 1).clamp_max(S)
    j0, j1 = (j - reach).clamp_min(0), (j + reach + 1).clamp_max(S)
    base, W = b * (S + 1) ** 2, S + 1
    count = (torch.take(table, base + i1 * W + j1) - torch.take(table, base + i0 * W + j1)
             - torch.take(table, base + i1 * W + j0) + torch.take(table, base + i0 * W + j0))
    near_bg = count > 0
    return soft.index_put((check,), near_bg)


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
    Vc, z, u, v, ok = _project(Vw, eye, R, cam, S)
    if native.available(u):  # the same decisions from one compiled call (meshmei.render.native)
        d = native.front(u.detach(), v.detach(), z.detach(), ok, F, mesh_topology(F, n_vertices).edge_table, S,
                         st.soft_margin, st.eps)
    else:
        d = _torch_front(u, v, z, ok, F, S, st, n_vertices)
    hit, fr_pix, corner_index = d["face_id"] >= 0, d["fr_pix"], d["corner_index"]
    shaded, cov_s = sample_geometry(d["in_pix"], d["in_b"], d["in_f"], d["in_slot"], fr_pix, d["fr_b"], d["fr_f"],
                                    d["fr_slot"], d["fr_k"], hit, u, v, z, corner_index, S, st)
    cov = hit.to(Vw.dtype).index_put((fr_pix,), cov_s)
    return RasterPasses(B=B, S=S, Vc=Vc, z=z, front=d["front"], face_id=d["face_id"].view(B, S, S), hit=hit,
                        shaded=shaded, n_inside=d["in_pix"].shape[0], fringe_pix=fr_pix, coverage=cov, used=d["used"],
                        corner_index=corner_index)


@torch.no_grad()
def _torch_front(u, v, z, ok, F, S: int, st: RenderSettings, n_vertices: int) -> dict:
    """The passes' decisions in torch operations, as :func:`meshmei.render.native.front` returns them (the
    compiled kernel's reference, and what CUDA tensors run)."""
    B = u.shape[0]
    U, Vv = u.detach(), v.detach()
    sc = _cull(U, Vv, ok, F, S, st.soft_margin)
    edges = mesh_topology(F, n_vertices).edge_table.index_select(0, sc.kf)  # (K, 15)
    zkey = _zbuffer(sc, z.detach(), F, B, S, st.chunk_size, edges[:, 12:].bool())
    hit = zkey != _NONE
    slot = (zkey & 0xFFFFFFFF).masked_fill(~hit, 0)
    face_id = torch.full((B * S * S,), -1, dtype=torch.int64, device=u.device)
    if sc.kb.shape[0]:
        face_id[hit] = sc.kf[slot[hit]]
        seg, ends = _contour_segments(sc, U, Vv, F, edges)
        skey = _segment_buffer(sc, seg, ends, B, S, st)
    else:
        seg, skey = None, torch.full((B * S * S,), _NONE, dtype=torch.int64, device=u.device)
    soft = _soft_pixels(skey, hit, B, S, st.soft_margin)
    in_pix = hit.nonzero().squeeze(1)
    in_b, in_f = in_pix // (S * S), face_id[in_pix]
    fr_pix = soft.nonzero().squeeze(1)
    if fr_pix.numel():
        s_, k_ = seg[skey[fr_pix] & 0xFFFFFFFF].unbind(1)
        fr_b, fr_f = sc.kb[s_], sc.kf[s_]
    else:
        fr_b = fr_f = k_ = fr_pix
    used, corner_index, in_slot, fr_slot = used_faces(in_b, in_f, fr_b, fr_f, F, B, u.shape[1])
    return {"front": sc.front, "face_id": face_id, "in_pix": in_pix, "in_b": in_b, "in_f": in_f, "in_slot": in_slot,
            "fr_pix": fr_pix, "fr_b": fr_b, "fr_f": fr_f, "fr_k": k_, "fr_slot": fr_slot, "used": used,
            "corner_index": corner_index}


