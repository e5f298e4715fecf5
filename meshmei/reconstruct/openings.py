"""A target's through-holes: find the most open one, and place the starting torus through it (``--init torus``)."""

from __future__ import annotations

import math

import igl
import numpy as np
import torch

from .._checks import float_dtype
from ..errors import MeshError
from ..mesh import check_mesh, remove_unreferenced
from ..shapes.primitives import DEFAULT_N_VERTICES, TORUS_MAJOR_RADIUS, TORUS_MINOR_RADIUS, initial_mesh

__all__ = ["find_opening", "torus_through_opening", "opening_parts", "plane_basis", "spans_opening"]

# An axis found within this angle of a coordinate axis is taken to be that axis: models are usually built
# in an aligned frame, and ray-cast estimates of a symmetric loop's axis are off by a fraction of a degree.
_SNAP_DEGREES = 1.0


def _hemisphere(n):
    """``n`` unit vectors spread evenly (equal area, golden-angle spiral) over the hemisphere ``z > 0``."""
    k = np.arange(n) + 0.5
    z = 1.0 - k / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def plane_basis(d):
    """Two unit vectors orthogonal to the unit vector ``d`` and to each other.

    Parameters
    ----------
    d : (3,) float64 array
        A unit vector.

    Returns
    -------
    u, w : (3,) float64 arrays
        ``(u, w, d)`` is a right-handed orthonormal frame.
    """
    a = np.zeros(3)
    a[int(np.argmin(np.abs(d)))] = 1.0
    u = np.cross(d, a)
    u /= np.linalg.norm(u)
    return u, np.cross(d, u)


def _largest_positive(d):
    """``d`` or ``-d``, whichever has its largest component (in magnitude) positive: one sign per line."""
    return -d if d[int(np.argmax(np.abs(d)))] < 0 else d


def _canonical_axis(d):
    """The line's direction as a unit vector whose largest component is positive."""
    return _largest_positive(np.asarray(d, dtype=np.float64) / np.linalg.norm(d))


class _Probe:
    """Ray casts against one mesh (at about unit size): which points the mesh surrounds about an axis.

    ``rays`` directions in the plane normal to the axis, the first four a quarter turn apart so that most
    points fail early.
    """

    def __init__(self, V, F, rays):
        self.V, self.F = V, F
        self.tree = igl.AABB()
        self.tree.init(V, F)
        first = [0, rays // 2, rays // 4, (3 * rays) // 4]
        order = np.array(first + [k for k in range(rays) if k not in first])
        self.angle = 2 * np.pi * order / rays

    def hits(self, Q, D):
        """Whether the ray from each point of ``Q`` (k, 3) along ``D`` (k, 3) meets the mesh: (k,) bool."""
        I, _, _ = self.tree.intersect_ray_first(self.V, self.F, np.ascontiguousarray(Q), np.ascontiguousarray(D))
        return I >= 0

    def surrounded(self, Q, d):
        """(k,) bool: the points ``Q`` (k, 3) open both ways along the unit vector ``d``, and surrounded in the
        plane normal to it (all rays but one hit: libigl's ray caster misses a hit now and then)."""
        u, v = plane_basis(d)
        n = len(Q)
        axial = self.hits(np.concatenate([Q, Q]), np.repeat(np.stack([d, -d]), n, 0)).reshape(2, n)
        idx = np.flatnonzero(~axial.any(0))
        misses = np.zeros(n, dtype=np.int64)
        for chunk in (self.angle[:4], self.angle[4:]):
            if len(idx) == 0:
                break
            D = np.cos(chunk)[:, None] * u + np.sin(chunk)[:, None] * v
            hit = self.hits(np.repeat(Q[idx], len(chunk), 0), np.tile(D, (len(idx), 1))).reshape(len(idx), len(chunk))
            misses[idx] += (~hit).sum(1)
            idx = idx[misses[idx] <= 1]
        out = np.zeros(n, dtype=bool)
        out[idx] = True
        return out

    def squared_distance(self, Q):
        """Squared distance from each point of ``Q`` (k, 3) to the mesh: (k,)."""
        return igl.point_mesh_squared_distance(Q, self.V, self.F)[0]


def spans_opening(V, F, Q, D, *, rays: int = 24) -> np.ndarray:
    """Whether each point of ``Q`` (k, 3) lies in an opening of the surface ``(V, F)`` (numpy arrays) across
    the unit direction in the same row of ``D`` (k, 3): open both ways along it and surrounded in the plane
    normal to it, as :func:`find_opening` tests its points. (k,) bool."""
    probe = _Probe(np.asarray(V, dtype=np.float64), np.asarray(F, dtype=np.int64), rays)
    return np.array([bool(probe.surrounded(q[None], d / np.linalg.norm(d))[0]) for q, d in zip(Q, D)],
                    dtype=bool)


# the search's sizes a call may ask for (defaults 28, 24, 64): grid 300 ran for minutes (grid^3 winding
# numbers), grid 1,000 and rays 100,000 ran out of memory inside numpy and libigl
SEARCH_LIMITS = {"grid": 128, "rays": 1024, "directions": 4096}


def _check_search(grid, rays, directions):
    for name, value, least in (("grid", grid, 4), ("rays", rays, 8), ("directions", directions, 0)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
            raise ValueError(f"{name} must be an integer of at least {least}, got {value!r}")
        if value > SEARCH_LIMITS[name]:
            raise ValueError(f"{name} must be at most {SEARCH_LIMITS[name]:,}, got {value!r}")


def _most_open_point(probe, P, directions):
    """Among the lattice points ``P`` (k, 3) outside the solid, the one farthest from the surface that is
    surrounded about some candidate axis (coordinate axes, principal axes, ``directions`` spread ones):
    ``(centre, unit axis)``, or None."""
    Vn = probe.V
    principal = np.linalg.eigh(np.cov((Vn - Vn.mean(0)).T))[1].T
    candidates = np.concatenate([np.eye(3), principal, _hemisphere(directions)])
    clearance = np.sqrt(probe.squared_distance(P))
    best = None
    for d in candidates:
        ok = probe.surrounded(P, d)
        if ok.any():
            k = int(np.argmax(np.where(ok, clearance, -1.0)))
            if best is None or clearance[k] > best[2]:  # ties keep the earlier axis (coordinate axes first)
                best = (P[k].copy(), d / np.linalg.norm(d), float(clearance[k]))
    return None if best is None else best[:2]


def _climb(probe, c, d, spacing):
    """In the plane of the loop: hill-climb the distance to the surface on shrinking 3 x 3 stencils."""
    u, v = plane_basis(d)
    offsets = np.array([(i, j) for i in (-1, 0, 1) for j in (-1, 0, 1)], dtype=np.float64)
    step = spacing
    for _ in range(6):
        step *= 0.5
        Q = c + step * (offsets[:, :1] * u + offsets[:, 1:] * v)
        c = Q[int(np.argmax(probe.squared_distance(Q)))].copy()
    return c


def _along(probe, c, d, lo, hi, grid):
    """The middle of the run of surrounded points outside the solid on the line through ``c`` along ``d``."""
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    reach = (corners - c) @ d
    t = np.linspace(reach.min(), reach.max(), 8 * grid)
    line = c + t[:, None] * d
    ok = probe.surrounded(line, d) & (np.abs(igl.fast_winding_number(probe.V, probe.F, line)) < 0.5)
    j = int(np.argmin(np.abs(t)))
    if not ok[j]:
        return c
    a = b = j
    while a > 0 and ok[a - 1]:
        a -= 1
    while b < len(t) - 1 and ok[b + 1]:
        b += 1
    return c + 0.5 * (t[a] + t[b]) * d


def _tilt(probe, c, d):
    """The loop's axis: the mean of the directions (a cone about ``d``) about which ``c`` is surrounded,
    snapped to a coordinate axis within :data:`_SNAP_DEGREES`."""
    u, v = plane_basis(d)
    theta = np.deg2rad(np.arange(3.0, 61.0, 3.0))[:, None]
    phi = (2 * np.pi * np.arange(16) / 16)[None, :]
    ring = (np.cos(theta)[..., None] * d + np.sin(theta)[..., None]
            * (np.cos(phi)[..., None] * u + np.sin(phi)[..., None] * v)).reshape(-1, 3)
    cone = [e for e in np.concatenate([d[None], ring]) if probe.surrounded(c[None], e)[0]]
    if not cone:
        return d
    m = np.mean(cone, axis=0)
    m = m / np.linalg.norm(m)
    k = int(np.argmax(np.abs(m)))
    if abs(m[k]) >= np.cos(np.deg2rad(_SNAP_DEGREES)):
        m = np.eye(3)[k] * np.sign(m[k])
    return m


def _refine(probe, centre, axis, lo, hi, grid):
    """Move the point to the middle of the opening and of the loop's plane, and turn the axis to the loop's."""
    spacing = float((hi - lo).max()) / (grid - 1)
    centre = _along(probe, _climb(probe, centre, axis, spacing), axis, lo, hi, grid)
    for _ in range(2):
        turned = _tilt(probe, centre, axis)
        if np.array_equal(turned, axis):
            break
        axis = turned
        centre = _along(probe, _climb(probe, centre, axis, spacing), axis, lo, hi, grid)
    return centre, axis


def find_opening(V, F, *, grid: int = 28, rays: int = 24, directions: int = 64):
    """The most open through-hole of a surface: a point outside its solid that the surface surrounds in a
    plane, like the middle of a teapot's handle, and the axis of that loop, in any orientation.

    Points of a ``grid^3`` lattice over the bounding box that lie outside the solid (generalised winding
    number below 1/2) are tested along candidate axes: the three coordinate axes, the three principal axes
    of the vertices, and ``directions`` directions spread evenly over the sphere (one per line, about 12
    degrees apart at 64). A point is *surrounded* about an axis if ``rays`` rays in the plane normal to it
    all but one hit the surface (libigl's AABB ray caster misses a hit now and then) and the two rays along
    it both miss (a bowl or a dent is surrounded in a plane but closed along the axis). Among surrounded
    points the one farthest from the surface wins. It is then refined in turn: moved in the plane to a
    local maximum of that distance (the middle of the opening), moved along the axis to the middle of the
    run of surrounded points through it (the plane of the loop), and the axis is replaced by the mean of
    the directions within 60 degrees about which the point is still surrounded (they form a cone about the
    loop's axis). An axis within 1 degree of a coordinate axis is snapped to it.

    A loop is found in any orientation if some candidate axis lies within its tilt tolerance, the angle by
    which the plane of rays can tilt and still meet the loop all round (about ``asin(tube radius / loop
    radius)``); at ``directions=64`` that holds for tolerances above about 12 degrees. Thinner loops are
    found near the coordinate and principal axes only; raise ``directions`` for them.

    Parameters
    ----------
    V : (n, 3) float tensor or array
    F : (m, 3) integer tensor or array
    grid : int
        Lattice points per side of the bounding box (at least 4).
    rays : int
        Rays in the plane normal to a candidate axis (at least 8).
    directions : int
        Candidate axes spread over the sphere, besides the coordinate and principal axes (at least 0).

    Returns
    -------
    (centre (3,) float64 array, axis (3,) float64 unit vector, clearance float): the point, the direction
    normal to the loop (its largest component positive), and the point's distance to the surface. ``None``
    if no point is surrounded (a surface without a hole, at this grid). Cost: ``grid^3`` winding numbers
    and distances, then two rays per outside point and candidate axis plus ``rays`` more for the points
    that pass the first test: 2.5 to 3 s at the defaults on the teapot (docs/shapes.md).

    Raises
    ------
    MeshError
        An invalid mesh (see :func:`meshmei.mesh.check_mesh`).
    ValueError
        ``grid`` below 4, ``rays`` below 8 or ``directions`` negative.
    """
    _check_search(grid, rays, directions)
    V, F = check_mesh(torch.as_tensor(V), torch.as_tensor(F))
    V, F = remove_unreferenced(V, F)  # a stray vertex widened the lattice until the opening fell between its points
    Vn = np.ascontiguousarray(V.detach().cpu().double().numpy())
    Fn = np.ascontiguousarray(F.cpu().numpy())
    # libigl's ray caster has absolute tolerances: on a mesh under about 1e-2 across it misses every hit, so
    # no opening was found. Search at about unit size: a power-of-two scale is exact, so a unit-size mesh
    # is searched exactly as before, and the results are scaled back.
    extent = Vn.max(0) - Vn.min(0)
    top = float(extent.max())  # the diagonal as top * |extent / top|: its square under- or overflowed beyond 1e154
    diag = top * float(np.linalg.norm(extent / top)) if top > 0 else 0.0
    unit = float(np.ldexp(1.0, int(np.round(np.log2(diag))))) if diag > 0 else 1.0
    Vn = Vn / unit
    lo, hi = Vn.min(0), Vn.max(0)
    axes = [np.linspace(lo[i], hi[i], grid) for i in range(3)]
    P = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)  # (grid^3, 3) lattice
    P = P[np.abs(igl.fast_winding_number(Vn, Fn, P)) < 0.5]
    if len(P) == 0:
        return None
    probe = _Probe(Vn, Fn, rays)
    found = _most_open_point(probe, P, directions)
    if found is None:
        return None
    centre, axis = _refine(probe, *found, lo, hi, grid)
    d = float(np.sqrt(probe.squared_distance(centre[None])[0]))
    return centre * unit, _canonical_axis(axis), d * unit


def _rotation_between(a, b):
    """The rotation matrix that turns unit vector ``a`` onto unit vector ``b`` about ``a x b`` (``a . b > 0``)."""
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    K = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + K + K @ K / (1.0 + c)


def opening_parts(opening):
    """Read and check an opening as :func:`find_opening` returns it.

    Parameters
    ----------
    opening : (centre, axis, clearance)
        ``centre`` and ``axis`` anything that reshapes to three floats, ``clearance`` a float.

    Returns
    -------
    centre : (3,) float64 array
    axis : (3,) float64 array
        Scaled to unit length.
    clearance : float

    Raises
    ------
    ValueError
        Anything but a triple of that form, a centre or axis that is not finite, or an axis of length 0.
    """
    try:
        centre, axis, clearance = opening
        centre = np.asarray(centre, dtype=np.float64).reshape(3)
        axis = np.asarray(axis, dtype=np.float64).reshape(3)
        clearance = float(clearance)
    except (TypeError, ValueError):
        raise ValueError(f"opening must be (centre, axis, clearance) as find_opening returns, "
                         f"got {opening!r}") from None
    norm = float(np.linalg.norm(axis))
    if not (np.isfinite(centre).all() and np.isfinite(axis).all() and norm > 0):
        raise ValueError(f"opening needs a finite centre and a finite non-zero axis, got {centre}, {axis}")
    return centre, axis / norm, clearance


def torus_through_opening(V, F, *, n_vertices: int = DEFAULT_N_VERTICES, dtype=torch.float32, opening=None):
    """The starting torus of :func:`meshmei.shapes.initial_mesh` placed with its hole through the most open
    through-hole of ``(V, F)`` (:func:`find_opening`, or ``opening`` as it returns, when already found): axis
    along the hole's axis, centred on it, scaled so that the hole's radius is twice the opening's clearance
    (the torus's tube then starts around the loop, not inside it).

    Parameters
    ----------
    V : (n, 3) float tensor or array
    F : (m, 3) integer tensor or array
        The target.
    n_vertices : int
        Vertex count of the torus (as :func:`meshmei.shapes.initial_mesh` takes it).
    dtype : torch float dtype of the returned vertices
    opening : (centre, axis, clearance), optional
        As :func:`find_opening` returns it (default: find it).

    Returns
    -------
    V : (k, 3) float tensor
        The placed torus's vertices, in ``dtype``.
    F : (l, 3) int64 tensor
        Its triangles, those of ``initial_mesh("torus", n_vertices=n_vertices)``.

    Raises
    ------
    MeshError
        ``(V, F)`` has no opening that :func:`find_opening` can see.
    ValueError
        ``opening`` is not ``(centre, axis, clearance)`` with a finite centre, a non-zero axis and a positive
        clearance.
    """
    dtype = float_dtype(dtype)  # before the search: an int dtype truncated the torus, a name failed in torch
    found = find_opening(V, F) if opening is None else opening
    if found is None:
        raise MeshError("the target has no through-hole that find_opening can see; start from a centred torus")
    centre, axis, clearance = opening_parts(found)
    if not (math.isfinite(clearance) and clearance > 0):
        raise ValueError(f"opening needs a positive clearance, got {clearance!r}")
    axis = _largest_positive(axis)  # the torus is the same either way; this keeps the turn below away from 180 degrees
    Vs, Fs = initial_mesh("torus", n_vertices=n_vertices, dtype=torch.float64)
    hole = TORUS_MAJOR_RADIUS - TORUS_MINOR_RADIUS  # hole radius at size 1
    scale = 2.0 * clearance / hole
    # the torus's axis is z: rotate the coordinates cyclically so that z lands on the coordinate axis
    # nearest the opening's axis, then turn that onto the axis itself
    k = int(np.argmax(np.abs(axis)))
    columns = {0: [2, 0, 1], 1: [1, 2, 0], 2: [0, 1, 2]}[k]
    Vs = Vs[:, columns]
    if not np.array_equal(axis, np.eye(3)[k]):
        Vs = Vs @ torch.from_numpy(_rotation_between(np.eye(3)[k], axis)).T
    Vs = Vs * scale + torch.from_numpy(centre)
    return Vs.to(dtype), Fs
