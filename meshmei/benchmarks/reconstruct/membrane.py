"""The membrane floor: the least Chamfer accuracy a closed surface pays for blocking a target's opening."""

from __future__ import annotations

import math
from dataclasses import dataclass

import igl
import numpy as np
import scipy.ndimage as ndi
import torch

from ...errors import MeshError
from ...mesh import check_mesh
from ...reconstruct.openings import find_opening, opening_parts, plane_basis

__all__ = ["MembraneFloor", "membrane_floor"]

# Cells whose lines are measured at once: bounds the (cells, samples) distance arrays.
_CHUNK = 2048


@dataclass(frozen=True)
class MembraneFloor:
    """What blocking an opening costs a surface in Chamfer accuracy (see :func:`membrane_floor`).

    Attributes
    ----------
    integral : float
        Lower bound on ``integral of d^2 dA`` over any closed surface whose solid blocks the opening, ``d``
        the distance to the target (units: length^4).
    opening_area : float
        Area of the opening in its plane (the cells counted).
    target_area : float
        Area of the target surface.
    centre : (3,) float64 array, axis : (3,) float64 array, clearance : float
        The opening (as :func:`meshmei.reconstruct.openings.find_opening` returns it).
    spacing : float
        Grid spacing used.
    """

    integral: float
    opening_area: float
    target_area: float
    centre: np.ndarray
    axis: np.ndarray
    clearance: float
    spacing: float

    def accuracy(self, area=None) -> float:
        """Lower bound on the accuracy term of Chamfer-L2 (mean squared distance from the surface's samples
        to the target) for a blocking surface of ``area`` (default: the target's own area). Accuracy is a
        mean over the surface's area, so a larger surface (folds, wrinkles lying on the target) dilutes
        the membrane's share: the bound falls as ``1 / area``."""
        a = self.target_area if area is None else float(area)
        if not a > 0:
            raise ValueError(f"area must be positive, got {area!r}")
        return self.integral / a


def _spacing(spacing, diag):
    """The grid spacing: ``spacing``, checked, or the bounding-box diagonal / 400."""
    h = diag / 400 if spacing is None else spacing
    if isinstance(h, bool) or not (isinstance(h, (int, float, np.floating)) and math.isfinite(h) and h > 0):
        raise ValueError(f"spacing must be a positive finite number, got {spacing!r}")
    return float(h)


def _opening_cells(Vn, Fn, centre, axis, h):
    """Centres of the cells (k, 3) of the square grid of spacing ``h`` in the opening's plane that lie in the
    region around ``centre`` outside the target's solid and enclosed by its cross-section."""
    u, w = plane_basis(axis)
    rel = Vn - centre
    pu, pw = rel @ u, rel @ w
    a = np.arange(pu.min() - 2 * h, pu.max() + 2 * h, h)
    b = np.arange(pw.min() - 2 * h, pw.max() + 2 * h, h)
    if a.size * b.size > 4_000_000:
        raise ValueError(f"spacing {h:g} gives a grid of {a.size * b.size:,} cells (at most 4 million); raise it")
    ia, ib = int(np.argmin(np.abs(a))), int(np.argmin(np.abs(b)))
    a, b = a - a[ia], b - b[ib]  # put a cell centre on the opening's centre
    A, B = np.meshgrid(a, b, indexing="ij")
    P = centre + A[..., None] * u + B[..., None] * w  # (len(a), len(b), 3)
    outside = np.abs(igl.fast_winding_number(Vn, Fn, P.reshape(-1, 3))).reshape(A.shape) < 0.5
    labels, _ = ndi.label(outside)
    label = labels[ia, ib]
    if label == 0:
        raise MeshError("the opening's centre lies inside the target's solid")
    region = labels == label
    if region[0].any() or region[-1].any() or region[:, 0].any() or region[:, -1].any():
        raise MeshError("the region around the opening's centre is not enclosed by the target in its plane: "
                        "not an opening")
    return P[region]


def _distances_along(Vn, Fn, c, axis, t):
    """Distances to the target from the points ``c + t * axis``: ``c`` (k, 3), ``t`` (s,) or (k, s) -> (k, s)."""
    t = np.broadcast_to(t, (len(c), t.shape[-1]))
    d2 = igl.point_mesh_squared_distance((c[:, None, :] + t[..., None] * axis).reshape(-1, 3), Vn, Fn)[0]
    return np.sqrt(d2).reshape(t.shape)


def _least_line_distance(Vn, Fn, cells, centre, axis, h):
    """A lower bound on the distance to the target from any point of the line along ``axis`` through any
    point of each cell (centres ``cells`` (k, 3), side ``h``): (k,).

    Sampled at ``h`` over the target's extent along the axis (beyond it the distance only grows), then at
    ``h / 8`` around the best sample and its two neighbours; both made conservative with the distance's
    1-Lipschitz bound.
    """
    pa = (Vn - centre) @ axis
    ts = np.arange(pa.min(), pa.max() + h, h)
    lower = np.empty(len(cells))
    # h / 8 apart over the reach of the best coarse sample and its two neighbours, [-1.5 h, 1.5 h] about it
    fine = np.linspace(-1.5, 1.5, 25) * h
    for lo in range(0, len(cells), _CHUNK):
        c = cells[lo:lo + _CHUNK]
        D = _distances_along(Vn, Fn, c, axis, ts)
        best = D.argmin(1)
        Df = _distances_along(Vn, Fn, c, axis, ts[best][:, None] + fine[None, :])
        # 1-Lipschitz along the line: every t is within h/16 of a fine sample, or h/2 of a coarse one
        # that is not the best or beside it (those three are covered by the fine samples)
        near = np.abs(np.arange(len(ts))[None, :] - best[:, None]) <= 1
        lower[lo:lo + _CHUNK] = np.minimum((Df - h / 16).min(1), np.where(near, np.inf, D - h / 2).min(1))
    # and 1-Lipschitz across the cell, whose points lie within h / sqrt(2) of its centre
    return np.maximum(lower - h * math.sqrt(0.5), 0.0)


def membrane_floor(V, F, opening=None, *, spacing=None):
    """The least Chamfer accuracy a closed surface pays for blocking an opening of the target ``(V, F)``,
    such as a teapot's handle, instead of passing a hole through it.

    Take the opening's plane (through ``centre``, normal to ``axis``) and the region of it around the
    centre that lies outside the target's solid and is enclosed by the target's cross-section. A closed
    surface whose solid meets every line along the axis through that region (it *blocks* the opening:
    it covers the loop around the opening but has no tunnel through it, like a torus whose hole is
    elsewhere) crosses each such line at least twice, once going into its solid and once coming out.
    Each crossing lies at least ``m(p)``, the least distance from the line through ``p`` to the target,
    away from the target, and a surface's area is at least the area of its projection onto the plane. So
    its ``integral of d^2 dA`` is at least ``2 * integral over the region of m(p)^2``, and its accuracy
    (the mean of ``d^2`` over its area ``A``) is at least that over ``A``: :meth:`MembraneFloor.accuracy`.

    The region is found on a square grid of ``spacing`` in the plane (generalised winding numbers); ``m``
    is sampled along each line at ``spacing`` over the target's extent (beyond it the distance only
    grows), then at ``spacing / 8`` around the best sample and its two neighbours. Both discretisations are
    made conservative with the distance's 1-Lipschitz bound (a sample's value is lowered by half the step
    to its neighbours, and a cell's by ``spacing / sqrt(2)``, the reach of its corners), so the result is
    a lower bound that tightens as ``spacing`` falls. Cost: one winding number per cell of the target's
    projection and one distance per cell of the region per sample along the line (about 2 s on the teapot
    at the default).

    Parameters
    ----------
    V : (n, 3) float tensor or array
    F : (m, 3) integer tensor or array
        The target mesh (closed, so that inside and outside are defined).
    opening : (centre, axis, clearance) or None
        As :func:`meshmei.reconstruct.openings.find_opening` returns it (None: call it).
    spacing : float or None
        Grid spacing (default: the bounding-box diagonal / 400).

    Returns
    -------
    MembraneFloor

    Raises
    ------
    MeshError
        An invalid mesh, no opening found, a centre inside the solid, or a region around the centre that
        is not enclosed in the plane (not an opening).
    ValueError
        A bad ``spacing`` or ``opening``, or a grid of more than 4 million cells.
    """
    V, F = check_mesh(torch.as_tensor(V), torch.as_tensor(F))
    Vn = np.ascontiguousarray(V.detach().cpu().double().numpy())
    Fn = np.ascontiguousarray(F.cpu().numpy())
    if opening is None:
        opening = find_opening(Vn, Fn)
        if opening is None:
            raise MeshError("the target has no through-hole that find_opening can see")
    centre, axis, clearance = opening_parts(opening)
    h = _spacing(spacing, float(np.linalg.norm(Vn.max(0) - Vn.min(0))))
    cells = _opening_cells(Vn, Fn, centre, axis, h)
    lower = _least_line_distance(Vn, Fn, cells, centre, axis, h)
    area = 0.5 * float(igl.doublearea(Vn, Fn).sum())
    return MembraneFloor(integral=float(2.0 * (lower**2).sum() * h * h), opening_area=float(len(cells) * h * h),
                         target_area=area, centre=centre, axis=axis, clearance=clearance, spacing=h)
