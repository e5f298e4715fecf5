"""Texture albedo: a gray texture map sampled at the surface point's interpolated texture coordinates."""

from __future__ import annotations

import torch

from .settings import RenderError
from .transforms import real_numbers

__all__ = ["check_texture", "sample_texture"]


def check_texture(texture, uv, n: int, B: int, dtype, device):
    """``texture`` as ``(B, H, W)`` and per-vertex ``uv`` as ``(n, 2)``; RenderError for bad ones."""
    T = real_numbers("albedo (a texture)", texture, dtype).to(dtype=dtype, device=device)  # complex or bool: refused
    if T.ndim not in (2, 3) or min(T.shape[-2:]) < 2 or (T.ndim == 3 and T.shape[0] not in (1, B)):
        raise RenderError(f"a texture albedo must have shape (H, W) or (B, H, W) with H, W >= 2 and B = {B}, "
                          f"got {tuple(T.shape)}")
    u = real_numbers("uv", uv, dtype).to(dtype=dtype, device=device)
    if u.shape != (n, 2):
        raise RenderError(f"uv must have shape (n, 2) = ({n}, 2), got {tuple(u.shape)}")
    if not (bool(torch.isfinite(T).all()) and bool(torch.isfinite(u).all())):
        raise RenderError("texture or uv holds NaN or Inf")
    return T.reshape(-1, *T.shape[-2:]).expand(B, *T.shape[-2:]), u


def sample_texture(T: torch.Tensor, uv: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Bilinear samples ``(N,)`` of textures ``T (B, H, W)`` at points ``uv (N, 2)`` in [0, 1]^2 of members ``b``.

    Texel ``(i, j)`` has its centre at ``((j + 0.5) / W, (i + 0.5) / H)``; ``u`` runs along the columns and
    ``v`` along the rows; points beyond the outer texel centres take the edge texels (clamped).
    Differentiable in ``T`` and ``uv``.
    """
    B, H, W = T.shape
    x = (uv[:, 0] * W - 0.5).clamp(0, W - 1)
    y = (uv[:, 1] * H - 0.5).clamp(0, H - 1)
    x0 = x.detach().floor().clamp(max=W - 2)
    y0 = y.detach().floor().clamp(max=H - 2)
    fx, fy = x - x0, y - y0
    i = b * (H * W) + y0.long() * W + x0.long()
    flat = T.reshape(-1)
    t00, t01 = flat.index_select(0, i), flat.index_select(0, i + 1)
    t10, t11 = flat.index_select(0, i + W), flat.index_select(0, i + W + 1)
    return (1 - fy) * ((1 - fx) * t00 + fx * t01) + fy * ((1 - fx) * t10 + fx * t11)
