"""The rasterizer: a hard z-buffer over bounded (face, pixel) pairs plus a soft, differentiable silhouette.

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
import weakref
from dataclasses import dataclass

import torch
import torch.nn.functional as nnf

from ..mesh import _as_tensor, check_mesh
from ..topology import mesh_topology
from .camera import Camera
from .settings import RenderError, RenderSettings
from .transforms import _check_batch, apply_pose

__all__ = ["Fragments", "rasterize"]

_NONE = torch.iinfo(torch.int64).max  # z-buffer key of an empty pixel


@dataclass(frozen=True)
class Fragments:
    """What each pixel sees. Float fields carry gradients to the vertices, pose and camera.

    Attributes
    ----------
    face_id : (B, H, W) int64 tensor
        Index into ``F`` of the nearest face whose projection contains the pixel centre; -1 for background.
    bary : (B, H, W, 3) float tensor
        Perspective-correct barycentric coordinates of the pixel centre's surface point in the face's
        corners ``F[face_id]``; zero on background.
    depth : (B, H, W) float tensor
        View depth (distance along the viewing direction) of that point; zero on background.
    coverage : (B, H, W) float tensor
        Soft coverage in [0, 1]: ``sigmoid(s / sigma)`` of the signed distance ``s`` (pixels, positive
        inside) to the silhouette within ``settings.soft_margin`` of it, else 1 on covered and 0 on
        background pixels.
    """

    face_id: torch.Tensor
    bary: torch.Tensor
    depth: torch.Tensor
    coverage: torch.Tensor


# --------------------------------------------------------------------------------------------------
# topology: the twin of each half-edge, cached per MeshTopology
_TWINS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _twins(F: torch.Tensor, n: int) -> torch.Tensor:
    """``(m, 3)`` int64: the half-edge ``3 g + l`` sharing edge ``(f, k)`` when exactly two faces do, else -1.

    Half-edge ``(f, k)`` is the edge opposite corner ``k``, from ``F[f, k+1]`` to ``F[f, k+2]``.
    """
    topo = mesh_topology(F, n)
    hit = _TWINS.get(topo)
    if hit is not None:
        return hit
    fe = topo.face_edges.reshape(-1)  # (3m,) edge id or -1
    E = topo.n_edges
    key = torch.where(fe >= 0, fe, torch.full_like(fe, E))
    order = torch.argsort(key, stable=True)
    cnt = torch.bincount(key, minlength=E + 1)[:E]
    start = torch.cumsum(cnt, 0) - cnt
    two = (cnt == 2).nonzero().squeeze(1)
    h1, h2 = order[start[two]], order[start[two] + 1]
    twin = torch.full_like(fe, -1)
    twin[h1], twin[h2] = h2, h1
    twin = twin.view(-1, 3)
    _TWINS[topo] = twin
    return twin


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


class _Raster:
    """The outcome of the two no-grad passes plus the differentiable recomputation (internal)."""


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


def _raster(Vw, F, eye, R, cam: Camera, st: RenderSettings, n_vertices):
    """Run both passes and the differentiable recomputation. ``Vw``: (B, n, 3) world vertices."""
    S = st.image_size
    B = Vw.shape[0]
    dev, dt = Vw.device, Vw.dtype
    eps = st.eps
    margin = st.soft_margin
    Vc, z, u, v, ok = _project(Vw, eye, R, cam, S)
    out = _Raster()
    out.B, out.S, out.Vc, out.z, out.u, out.v = B, S, Vc, z, u, v

    with torch.no_grad():
        U, Vv, Z = u.detach(), v.detach(), z.detach()
        fu, fv = U[:, F], Vv[:, F]  # (B, m, 3)
        keep = ok[:, F].all(-1)
        umin, umax = fu.amin(-1), fu.amax(-1)
        vmin, vmax = fv.amin(-1), fv.amax(-1)
        keep &= (umax >= -margin) & (umin <= S + margin) & (vmax >= -margin) & (vmin <= S + margin)
        kb, kf = keep.nonzero().unbind(1)
        K = kb.shape[0]
        area2 = _edge_fn(fu[..., 0], fv[..., 0], fu[..., 1], fv[..., 1], fu[..., 2], fv[..., 2])  # (B, m)
        front = area2 < 0  # outward (counter-clockwise) faces turn clockwise in (u, v) with v down

        # ---- pass 1: z-buffer ------------------------------------------------------------------
        zkey = torch.full((B * S * S,), _NONE, dtype=torch.int64, device=dev)
        if K:
            Fk = F[kf]  # (K, 3)
            ku, kv = fu[kb, kf], fv[kb, kf]  # (K, 3)
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
            x0, x1 = _ranges(umin[kb, kf], umax[kb, kf], S)
            y0, y1 = _ranges(vmin[kb, kf], vmax[kb, kf], S)
            for it, ii, jj in _pairs(x0, x1, y0, y1, st.chunk_size):
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
        hit = zkey != _NONE
        slot = (zkey & 0xFFFFFFFF).masked_fill(~hit, 0)
        face_id = torch.full((B * S * S,), -1, dtype=torch.int64, device=dev)
        if K:
            face_id[hit] = kf[slot[hit]]
        # ---- pass 2: contour segments -------------------------------------------------------------
        seg = None
        skey = torch.full((B * S * S,), _NONE, dtype=torch.int64, device=dev)
        if K:
            twin = _twins(F, n_vertices)[kf]  # (K, 3)
            tf = twin.clamp_min(0) // 3
            tk = twin.clamp_min(0) % 3
            tkeep = (twin >= 0) & keep[kb.unsqueeze(1), tf]
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
            fr, gfr = front[kb, kf].unsqueeze(1), front[bu, tf]
            owner = ~tkeep | (fr & ~gfr) | ((fr == gfr) & (kf.unsqueeze(1) < tf))
            sel = (contour & owner).nonzero()  # (Q, 2): kept-face slot, edge k
            seg = sel
            if sel.shape[0]:
                s_, k_ = sel.unbind(1)
                sa_u, sa_v, sb_u, sb_v = Au[s_, k_], Av[s_, k_], Bu[s_, k_], Bv[s_, k_]
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
                    pix = (kb[s_[it[near]]] * S + ii[near]) * S + jj[near]
                    skey.scatter_reduce_(0, pix, key, "amin")
        soft = skey != _NONE
        covered = hit.view(B, 1, S, S)
        # interior pixels get a soft value only near uncovered pixels (see docs: interior fold contours)
        reach = math.ceil(margin + 1.5)
        near_bg = nnf.max_pool2d((~covered).to(dt), 2 * reach + 1, stride=1, padding=reach) > 0
        soft &= ~hit | near_bg.view(-1)

    out.face_id = face_id.view(B, S, S)
    out.keep_b, out.keep_f, out.front = kb, kf, front
    # ---- differentiable recomputation on winning pairs only ----------------------------------
    pix_in = hit.nonzero().squeeze(1)
    b_in = pix_in // (S * S)
    f_in = face_id[pix_in]
    pu = ((pix_in % S).to(dt) + 0.5).unsqueeze(1)
    pv = (((pix_in // S) % S).to(dt) + 0.5).unsqueeze(1)
    Fi = F[f_in]  # (N, 3)
    cu, cv = u[b_in.unsqueeze(1), Fi], v[b_in.unsqueeze(1), Fi]  # (N, 3)
    w = _edge_fn(cu[:, [1, 2, 0]], cv[:, [1, 2, 0]], cu[:, [2, 0, 1]], cv[:, [2, 0, 1]], pu, pv)
    tot = w.sum(1, keepdim=True)
    tot = torch.where(tot.abs() > eps, tot, torch.full_like(tot, eps))
    out.pix_in, out.b_in, out.f_in, out.l_in = pix_in, b_in, f_in, w / tot  # screen-space barycentrics

    pix_s = soft.nonzero().squeeze(1)
    if pix_s.numel():
        sl = (skey[pix_s] & 0xFFFFFFFF)
        s_, k_ = seg[sl].unbind(1)
        b_s, f_s = kb[s_], kf[s_]
        ia, ib = F[f_s, (k_ + 1) % 3], F[f_s, (k_ + 2) % 3]
        px = (pix_s % S).to(dt) + 0.5
        py = ((pix_s // S) % S).to(dt) + 0.5
        ex, ey, t = _seg_dist(u[b_s, ia], v[b_s, ia], u[b_s, ib], v[b_s, ib], px, py, eps)
        d = torch.sqrt((ex * ex + ey * ey).clamp_min(eps * eps))
        sign = torch.where(hit[pix_s], 1.0, -1.0).to(dt)
        cov_s = torch.sigmoid(sign * d / st.sigma)
        l_s = torch.zeros(pix_s.shape[0], 3, dtype=dt, device=dev)
        ar = torch.arange(pix_s.shape[0], device=dev)
        l_s = l_s.index_put((ar, (k_ + 1) % 3), 1 - t).index_put((ar, (k_ + 2) % 3), t)
    else:
        b_s = f_s = pix_s
        cov_s = torch.zeros(0, dtype=dt, device=dev)
        l_s = torch.zeros(0, 3, dtype=dt, device=dev)
    out.pix_s, out.b_s, out.f_s, out.l_s, out.cov_s = pix_s, b_s, f_s, l_s, cov_s
    out.hit, out.soft = hit, soft
    cov = torch.zeros(B * S * S, dtype=dt, device=dev).index_put((pix_in,), torch.ones_like(pix_in, dtype=dt))
    out.coverage = cov.index_put((pix_s,), cov_s)  # (B*S*S,)
    return out


def _perspective(r: _Raster, F, b, f, l):
    """Screen-space barycentrics ``l`` (N, 3) -> perspective-correct barycentrics and view depth."""
    iz = 1.0 / r.z[b.unsqueeze(1), F[f]]  # (N, 3)
    q = l * iz
    s = q.sum(1, keepdim=True)
    s = torch.where(s > 0, s, torch.ones_like(s))
    return q / s, 1.0 / s.squeeze(1)


def _prepare(V, F, camera, rotation, translation, settings):
    if settings is None:
        settings = RenderSettings()
    if not isinstance(settings, RenderSettings):
        raise RenderError(f"settings must be a RenderSettings, got {type(settings).__name__}")
    if camera is None:
        camera = Camera()
    if not isinstance(camera, Camera):
        raise RenderError(f"camera must be a Camera, got {type(camera).__name__}")
    V = _as_tensor(V, "V")
    V, F = check_mesh(V, F, batched=V.ndim == 3)
    n = V.shape[-2]
    Vb = apply_pose(V, rotation, translation)  # (Bv, n, 3)
    eye, R = camera.frame(V.dtype, V.device)
    _check_batch("camera", eye.shape[0], Vb.shape[0])
    return V, F, n, Vb, eye, R, camera, settings


def _broadcast(Vb, eye, R):
    B = max(Vb.shape[0], eye.shape[0])
    return Vb.expand(B, *Vb.shape[1:]), eye.expand(B, 3), R.expand(B, 3, 3)


def rasterize(V, F, *, camera: Camera | None = None, rotation=None, translation=None,
              settings: RenderSettings | None = None) -> Fragments:
    """Rasterize a mesh (or a batch of poses / cameras of it) into per-pixel fragments.

    Parameters
    ----------
    V : (n, 3) or (B, n, 3) float tensor
        Vertex positions in object coordinates; dtype and device of the outputs follow ``V``.
    F : (m, 3) int64 tensor
    camera : Camera, optional
        Default: overhead at (0, 0, 2.5) looking at the origin. A batch of B cameras is allowed.
    rotation : (3, 3) or (B, 3, 3) float tensor, optional
        Rotation matrix; :func:`~meshmei.render.axis_angle_to_matrix` makes one from axis-angle vectors.
    translation : (3,) or (B, 3) tensor, optional
        Object pose ``V @ R.T + t`` (rotation about the object origin, then translation).
    settings : RenderSettings, optional

    Returns
    -------
    Fragments
        ``(B, S, S)`` fields with B the broadcast batch size and S = ``settings.image_size``.

    Raises
    ------
    MeshError
        Malformed ``V`` / ``F`` (shapes, NaN, indices).
    RenderError
        Bad settings, camera, pose or incompatible batch sizes.
    """
    V, F, n, Vb, eye, R, camera, st = _prepare(V, F, camera, rotation, translation, settings)
    Vw, eye, R = _broadcast(Vb, eye, R)
    r = _raster(Vw, F, eye, R, camera, st, n)
    B, S = r.B, r.S
    bary_in, depth_in = _perspective(r, F, r.b_in, r.f_in, r.l_in)
    zero = 0.0 * (r.Vc.sum())  # keeps every output connected to the inputs, with zero gradient
    bary = torch.zeros(B * S * S, 3, dtype=V.dtype, device=V.device).index_put((r.pix_in,), bary_in) + zero
    depth = torch.zeros(B * S * S, dtype=V.dtype, device=V.device).index_put((r.pix_in,), depth_in) + zero
    return Fragments(face_id=r.face_id, bary=bary.view(B, S, S, 3), depth=depth.view(B, S, S),
                     coverage=(r.coverage + zero).view(B, S, S))
