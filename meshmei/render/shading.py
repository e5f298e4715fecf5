"""Grayscale Lambertian shading with one point light and an ambient term, at interpolated surface points."""

from __future__ import annotations

import torch
from torch.autograd.function import once_differentiable

from ..operators import scaled_norm
from . import native
from .transforms import unit

__all__ = ["lambert", "shade_samples"]


def lambert(points, normals, light, *, ambient=0.2, intensity=0.8, albedo=1.0, eps=1e-9):
    """``albedo * (ambient + intensity * max(0, n . l))`` for unit normal ``n`` and unit light direction ``l``.

    Parameters
    ----------
    points : (N, 3) float tensor
        Surface points in world coordinates.
    normals : (N, 3) float tensor
        Surface normals (need not be unit; lengths below ``eps`` are held at ``eps``).
    light : (N, 3) float tensor
        Point light position for each point.
    ambient, intensity, albedo : float
    eps : float
        Guard on the normal length and the light distance.

    Returns
    -------
    (N,) tensor

    Examples
    --------
    >>> p = torch.zeros(1, 3); n = torch.tensor([[0.0, 0.0, 1.0]])
    >>> float(lambert(p, n, torch.tensor([[0.0, 0.0, 2.0]])))
    1.0
    """
    n = unit(normals, eps)
    l = unit(light - points, eps)
    return albedo * (ambient + intensity * (n * l).sum(-1).clamp_min(0.0))


def _dot(a, b):
    """Sum over the leading axis of ``a * b`` (corner-major ``(3, N)`` layout)."""
    p = a * b
    return p[0] + p[1] + p[2]


def _unit(x, eps):
    length = torch.sqrt(_dot(x, x))
    if length.numel() and not float(length.amax()) < float("inf"):  # a square overflowed: a light 1e20 away
        length = scaled_norm(x, 0)
    norm = length.clamp_min(eps)
    return x / norm, norm, length > eps


def _unit_backward(g, x_hat, norm, unclamped):
    """Gradient of ``x / max(|x|, eps)`` given the output ``x_hat`` and the clamped norm."""
    return (g - (_dot(x_hat, g) * unclamped) * x_hat) / norm


class _ShadeSamples(torch.autograd.Function):
    """:func:`shade_samples` with a hand-written backward: one graph node instead of about sixty.

    Forward and backward are the same arithmetic autograd would record, on corner-major ``(k, N)``
    tensors; the saving is the per-operation overhead, which dominates at a few thousand pixels.
    """

    @staticmethod
    def forward(ctx, l, iz, corners, light, ambient, intensity, albedo, eps):
        ctx.native = native.available(l)
        if ctx.native:  # the same formulas, compiled (meshmei.render.native)
            ctx.save_for_backward(l, iz, corners, light)
            ctx.args = (ambient, intensity, albedo, eps)
            return native.shade_forward(l, iz, corners, light, ambient, intensity, albedo, eps)
        q = l * iz
        s = q[0] + q[1] + q[2]
        pos = s > 0
        s = torch.where(pos, s, torch.ones_like(s))
        bary = q / s
        PN = bary[0] * corners[0] + bary[1] * corners[1] + bary[2] * corners[2]  # (6 or 7, N)
        n_hat, n_norm, n_ok = _unit(PN[3:6], eps)
        d_hat, d_norm, d_ok = _unit(light - PN[:3], eps)
        c = _dot(n_hat, d_hat)
        lit = ambient + intensity * c.clamp_min(0.0)
        reflect = PN[6] * albedo if PN.shape[0] == 7 else torch.full_like(lit, albedo)  # surface albedo
        ctx.save_for_backward(l, iz, corners, bary, s, pos, n_hat, n_norm, n_ok, d_hat, d_norm, d_ok, c >= 0,
                              reflect, lit)
        ctx.intensity, ctx.albedo = intensity, albedo
        return reflect * lit

    @staticmethod
    @once_differentiable
    def backward(ctx, g):
        if ctx.native:
            return (*native.shade_backward(*ctx.saved_tensors, *ctx.args, g), None, None, None, None)
        (l, iz, corners, bary, s, pos, n_hat, n_norm, n_ok, d_hat, d_norm, d_ok, lit_side, reflect,
         lit) = ctx.saved_tensors
        gc = g * reflect * ctx.intensity * lit_side
        gN = _unit_backward(gc * d_hat, n_hat, n_norm, n_ok)
        gD = _unit_backward(gc * n_hat, d_hat, d_norm, d_ok)
        parts = [-gD, gN] + ([(g * lit * ctx.albedo).unsqueeze(0)] if corners.shape[1] == 7 else [])
        gPN = torch.cat(parts, 0)  # (6 or 7, N)
        g_corners = bary.unsqueeze(1) * gPN
        g_bary = (corners * gPN).sum(1)
        gq = torch.where(pos, (g_bary - _dot(g_bary, bary)) / s, g_bary)
        return gq * iz, gq * l, g_corners, gD, None, None, None, None


def shade_samples(l, iz, corners, light, *, ambient=0.2, intensity=0.8, albedo=1.0, eps=1e-9):
    """Lambertian shade of surface points given by screen-space barycentrics, differentiable in every input.

    Perspective-correct barycentrics ``b = l * iz / sum(l * iz)`` (``sum <= 0`` is taken as 1) interpolate
    the corners' positions and normals; the point is shaded with :func:`lambert`. Inputs are
    corner-major: the sample index is the last axis.

    Parameters
    ----------
    l : (3, N) float tensor
        Screen-space barycentrics.
    iz : (3, N) float tensor
        Inverse view depth of the corners.
    corners : (3, 6, N) or (3, 7, N) float tensor
        Per corner: world position (3), normal (3, need not be unit) and optionally a surface albedo (1),
        interpolated like the rest and multiplied into the shade (with ``albedo``).
    light : (3, N) float tensor
        Point light position for each point.
    ambient, intensity, albedo, eps : float
        As in :func:`lambert`.

    Returns
    -------
    (N,) tensor
    """
    return _ShadeSamples.apply(l, iz, corners, light, float(ambient), float(intensity), float(albedo), float(eps))
