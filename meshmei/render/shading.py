"""Grayscale Lambertian shading with one point light and an ambient term, at interpolated surface points."""

from __future__ import annotations

from .transforms import unit

__all__ = ["lambert"]


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
