"""The renderer's compiled kernels: a small C file built on first use, with the torch code as its reference
and fallback.

At the image sizes of a 3D-MEI (64-100 px, a few thousand pixels) the torch renderer spends most of its
time dispatching some 1,100 small tensor operations per forward and backward, not computing. Three parts
are compiled (``_raster.c``), CPU tensors only:

- the no-grad front of :func:`~meshmei.render.passes.run_passes` (:func:`front`: cull, z-buffer, contour
  segments, nearest-segment buffer, soft pixels, the samples and the faces they use) in one call, without
  materialising a single (face, pixel) pair. It repeats the torch code's operations in their order and
  dtype without fused multiply-add, so its decisions are the torch code's: the depth keys bit for bit;
  the segment distances to the square root, which torch's CPU kernel does not round correctly (about one
  float32 value in six is an ulp away from C's correctly rounded ``sqrtf`` here), so a fringe pixel whose
  two nearest segments, or whose distance and the margin, lie within an ulp may be decided the other way
  (none in 192 random renders with 220,758 fringe pixels, nor in the tests' scenes);
- the per-pixel arithmetic with hand-written backwards (:class:`~meshmei.render.samples._SampleGeometry`,
  :class:`~meshmei.render.shading._ShadeSamples`): the same formulas, forward and backward, equal to the
  torch code to rounding (sums may associate differently);
- the smooth-shading vertex normals (:func:`vertex_normals`), forward and backward, to rounding.

The C file is built on first use with meshmei's other compiled kernels (:mod:`meshmei.native`: the
system's C compiler, a cache directory, ctypes). Where no compiler works, or with ``MESHMEI_NATIVE=0``, the
torch code runs instead, unchanged, with one warning; :func:`native_status` says which is in use and why.
CUDA tensors always run the torch code.
"""

from __future__ import annotations

import torch
from torch.autograd.function import once_differentiable

from ..native import available, library as _lib, native_status, torch_reference

__all__ = ["native_status", "front", "sample_forward", "sample_backward", "shade_forward",
           "shade_backward", "vertex_normals", "available", "torch_reference"]


def _ptr(t: torch.Tensor, dtype) -> int:
    assert t.dtype == dtype and t.is_contiguous() and t.device.type == "cpu", (t.dtype, t.shape)
    return t.data_ptr()


def front(U, Vv, Z, ok, F, edge_table, S: int, margin: float, eps: float) -> dict:
    """The no-grad front of :func:`~meshmei.render.passes.run_passes` in one call: ``U, Vv, Z`` ``(B, n)``
    pixel coordinates and depth (no grad), ``ok`` ``(B, n)`` in depth range, ``F`` ``(m, 3)``, ``edge_table``
    ``(m, 15)`` (:attr:`~meshmei.topology.MeshTopology.edge_table`). Returns the passes' decisions: ``front``
    ``(B, m)``, ``face_id`` ``(B * S * S,)``, the covered samples ``in_pix, in_b, in_f, in_slot``, the fringe
    samples ``fr_pix, fr_b, fr_f, fr_k, fr_slot``, the used faces ``used`` and ``corner_index`` ``(3, U)``."""
    lib, dt = _lib(), U.dtype
    U, Vv, Z, F, et = _c(U, Vv, Z, F, edge_table)
    ok = ok.contiguous().to(torch.uint8)
    B, n = U.shape
    m, P = F.shape[0], S * S
    BM, BP = B * m, B * P
    i64 = torch.int64
    byte, long = dict(dtype=torch.uint8, device="cpu"), dict(dtype=i64, device="cpu")  # the kernel's CPU buffers
    keep, front_ = torch.empty(BM, **byte), torch.empty(BM, **byte)
    slot_of, kept, seg = torch.empty(BM, **long), torch.empty(BM, **long), torch.empty(9 * BM, **long)
    zkey, skey = torch.empty(BP, **long), torch.empty(BP, **long)
    box = torch.empty(BM * 4, dtype=dt, device="cpu")
    integral = torch.empty(B * (S + 1) ** 2, dtype=torch.int32, device="cpu")
    face_id = torch.empty(BP, **long)
    pix = torch.empty(9, BP, **long)  # in_pix, in_b, in_f, in_slot, fr_pix, fr_b, fr_f, fr_k, fr_slot
    used, corner_index = torch.empty(BM, **long), torch.empty(3, BM, **long)
    counts = torch.zeros(4, **long)
    getattr(lib, f"front_{_suffix(dt)}")(
        B, n, m, _ptr(U, dt), _ptr(Vv, dt), _ptr(Z, dt), ok.data_ptr(), _ptr(F, i64), _ptr(et, i64), int(S),
        float(margin), float(eps), keep.data_ptr(), front_.data_ptr(), _ptr(slot_of, i64), _ptr(kept, i64),
        _ptr(seg, i64), _ptr(zkey, i64), _ptr(skey, i64), _ptr(box, dt), integral.data_ptr(), _ptr(face_id, i64),
        *(_ptr(pix[i], i64) for i in range(9)), _ptr(used, i64), _ptr(corner_index, i64), _ptr(counts, i64))
    _, Ni, Nf, Uc = counts.tolist()
    cov, fr = pix[:4, :Ni], pix[4:, :Nf]
    return {"front": front_.view(B, m).bool(), "face_id": face_id, "in_pix": cov[0], "in_b": cov[1],
            "in_f": cov[2], "in_slot": cov[3], "fr_pix": fr[0], "fr_b": fr[1], "fr_f": fr[2], "fr_k": fr[3],
            "fr_slot": fr[4], "used": used[:Uc], "corner_index": corner_index[:, :Uc]}


# --------------------------------------------------------------------------------------------------
# the differentiable per-pixel arithmetic (the autograd Functions of samples.py and shading.py call these)

def _suffix(dt) -> str:
    return "f32" if dt == torch.float32 else "f64"


def _c(*ts):
    return [t.contiguous() for t in ts]


def _shaded_columns(out, Q: int):
    """``(Q,)``: each fringe sample's column among the shaded samples after the covered ones, -1 for a fringe
    pixel inside the surface (not shaded)."""
    return torch.full((Q,), -1, dtype=torch.int64, device="cpu").index_put_((out,),
                                                                         torch.arange(out.shape[0], device="cpu"))


def sample_forward(u, v, z, corner_index, in_pix, in_slot, fr_pix, fr_slot, fr_k, fr_sign, out, S, sigma, eps):
    """:class:`~meshmei.render.samples._SampleGeometry`'s forward: ``(l, iz, cov, table, pos)``; the face
    ``table`` ``(U, 21)`` and the fringe samples' shaded columns ``pos`` ``(Q,)`` are kept for
    :func:`sample_backward`."""
    lib, dt = _lib(), u.dtype
    u, v, z, ci, in_pix, in_slot, fr_pix, fr_slot, fr_k, fr_sign, out = _c(u, v, z, corner_index, in_pix, in_slot,
                                                                           fr_pix, fr_slot, fr_k, fr_sign, out)
    U, Ni, Q, No = ci.shape[1], in_pix.shape[0], fr_pix.shape[0], out.shape[0]
    pos = _shaded_columns(out, Q)
    table = torch.empty(U, 21, dtype=dt, device="cpu")
    l, iz = torch.empty(3, Ni + No, dtype=dt, device="cpu"), torch.empty(3, Ni + No, dtype=dt, device="cpu")
    cov = torch.empty(Q, dtype=dt, device="cpu")
    i64 = torch.int64
    getattr(lib, f"sample_fwd_{_suffix(dt)}")(
        U, _ptr(u, dt), _ptr(v, dt), _ptr(z, dt), _ptr(ci, i64), Ni, _ptr(in_pix, i64), _ptr(in_slot, i64), Q,
        _ptr(fr_pix, i64), _ptr(fr_slot, i64), _ptr(fr_k, i64), _ptr(fr_sign, dt), No, _ptr(pos, i64), int(S),
        float(sigma), float(eps), _ptr(table, dt), _ptr(l, dt), _ptr(iz, dt), _ptr(cov, dt))
    return l, iz, cov, table, pos


def sample_backward(z, corner_index, in_pix, in_slot, fr_pix, fr_slot, fr_k, fr_sign, pos, table, cov, S, sigma, eps,
                    g_l, g_iz, g_cov):
    """:class:`~meshmei.render.samples._SampleGeometry`'s backward: gradients of ``u, v, z`` (shaped as ``z``)."""
    lib, dt = _lib(), z.dtype
    shape = z.shape
    z, ci, in_pix, in_slot, fr_pix, fr_slot, fr_k, fr_sign, g_l, g_iz, g_cov = _c(
        z, corner_index, in_pix, in_slot, fr_pix, fr_slot, fr_k, fr_sign, g_l, g_iz, g_cov)
    U, Ni, Q = ci.shape[1], in_pix.shape[0], fr_pix.shape[0]
    No = g_l.shape[1] - Ni
    g = torch.zeros(3, z.numel(), dtype=dt, device="cpu")
    i64 = torch.int64
    getattr(lib, f"sample_bwd_{_suffix(dt)}")(
        U, _ptr(z, dt), _ptr(ci, i64), z.numel(), Ni, _ptr(in_pix, i64), _ptr(in_slot, i64), Q, _ptr(fr_pix, i64),
        _ptr(fr_slot, i64), _ptr(fr_k, i64), _ptr(fr_sign, dt), No, _ptr(pos, i64), int(S), float(sigma),
        float(eps), _ptr(table, dt), _ptr(cov, dt), _ptr(g_l, dt), _ptr(g_iz, dt), _ptr(g_cov, dt),
        _ptr(g[0], dt), _ptr(g[1], dt), _ptr(g[2], dt))
    return g[0].view(shape), g[1].view(shape), g[2].view(shape)


def shade_forward(l, iz, corners, light, ambient, intensity, albedo, eps):
    """:class:`~meshmei.render.shading._ShadeSamples`'s forward: the shade ``(N,)``."""
    lib, dt = _lib(), l.dtype
    l, iz, corners, light = _c(l, iz, corners, light)
    N, C = l.shape[1], corners.shape[1]
    shade = torch.empty(N, dtype=dt, device="cpu")
    getattr(lib, f"shade_fwd_{_suffix(dt)}")(N, C, _ptr(l, dt), _ptr(iz, dt), _ptr(corners, dt), _ptr(light, dt),
                                              float(ambient), float(intensity), float(albedo), float(eps),
                                              _ptr(shade, dt))
    return shade


def shade_backward(l, iz, corners, light, ambient, intensity, albedo, eps, g):
    """:class:`~meshmei.render.shading._ShadeSamples`'s backward: gradients of ``l, iz, corners, light``."""
    lib, dt = _lib(), l.dtype
    l, iz, corners, light, g = _c(l, iz, corners, light, g)
    N, C = l.shape[1], corners.shape[1]
    g_l, g_iz, g_light = torch.empty_like(l), torch.empty_like(iz), torch.empty_like(light)
    g_corners = torch.empty_like(corners)
    getattr(lib, f"shade_bwd_{_suffix(dt)}")(N, C, _ptr(l, dt), _ptr(iz, dt), _ptr(corners, dt), _ptr(light, dt),
                                              float(ambient), float(intensity), float(albedo), float(eps),
                                              _ptr(g, dt), _ptr(g_l, dt), _ptr(g_iz, dt), _ptr(g_corners, dt),
                                              _ptr(g_light, dt))
    return g_l, g_iz, g_corners, g_light


class _VertexNormals(torch.autograd.Function):
    """Area-weighted unit vertex normals, compiled forward and backward (the arithmetic of
    :func:`~meshmei.operators.vertex_normals_from_corners`)."""

    @staticmethod
    def forward(ctx, V, F, eps):
        lib, dt = _lib(), V.dtype
        Vc, Fc = V.detach().contiguous(), F.contiguous()
        B, n, m = Vc.shape[0], Vc.shape[1], Fc.shape[0]
        acc, out = torch.empty(B, n, 4, dtype=dt, device="cpu"), torch.empty(B, n, 3, dtype=dt, device="cpu")
        getattr(lib, f"normals_fwd_{_suffix(dt)}")(B, n, m, _ptr(Vc, dt), _ptr(Fc, torch.int64), float(eps),
                                                    _ptr(acc, dt), _ptr(out, dt))
        ctx.save_for_backward(Vc, Fc, acc)
        ctx.eps = eps
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, g):
        lib = _lib()
        Vc, Fc, acc = ctx.saved_tensors
        dt = Vc.dtype
        B, n, m = Vc.shape[0], Vc.shape[1], Fc.shape[0]
        g = g.contiguous()
        work, gV = torch.empty(B, n, 4, dtype=dt, device="cpu"), torch.zeros(B, n, 3, dtype=dt, device="cpu")
        getattr(lib, f"normals_bwd_{_suffix(dt)}")(B, n, m, _ptr(Vc, dt), _ptr(Fc, torch.int64), float(ctx.eps),
                                                    _ptr(acc, dt), _ptr(g, dt), _ptr(work, dt), _ptr(gV, dt))
        return gV, None, None


def vertex_normals(V, F, eps: float):
    """Unit area-weighted vertex normals of ``V`` ``(B, n, 3)`` over ``F`` ``(m, 3)``, ``(B, n, 3)``;
    differentiable in ``V``. CPU float32/float64 only (see :func:`available`)."""
    return _VertexNormals.apply(V, F, eps)
