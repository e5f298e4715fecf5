"""Starting meshes: a square sheet, a sphere and a torus, made by pymeshlab and isotropically remeshed."""

from __future__ import annotations

import math

import numpy as np
import torch

from .._checks import check_positive, float_dtype
from ._meshlab import pymeshlab
from .remeshing import check_iterations, count_for_edge_length, edge_length_for_count, isotropic_remesh

__all__ = ["initial_mesh", "INITIAL_KINDS", "DEFAULT_N_VERTICES", "SPHERE_RADIUS", "TORUS_MAJOR_RADIUS",
           "TORUS_MINOR_RADIUS", "SHEET_SIDE"]

INITIAL_KINDS = ("sheet", "sphere", "torus")

# Geometry of the initial meshes at size 1 (all fit in the unit box [-0.5, 0.5]^3).
SPHERE_RADIUS = 0.5
TORUS_MAJOR_RADIUS = 0.35
TORUS_MINOR_RADIUS = 0.15
SHEET_SIDE = 1.0

DEFAULT_N_VERTICES = 2500
# Limits on the vertex count implied by the arguments: below the minimum a torus tube or sphere is no
# longer a recognisable surface; above the maximum remeshing takes minutes and gigabytes.
MIN_VERTICES = 32
MAX_VERTICES = 5_000_000


def _area(kind):
    """Surface area of the ideal shape at size 1."""
    if kind == "sphere":
        return 4.0 * math.pi * SPHERE_RADIUS**2
    if kind == "torus":
        return 4.0 * math.pi**2 * TORUS_MAJOR_RADIUS * TORUS_MINOR_RADIUS
    return SHEET_SIDE**2


def _base_meshset(kind, h):
    """A pymeshlab primitive at size 1 whose edges are about ``h`` long (the icosphere level is capped at 7)."""
    ms = pymeshlab.MeshSet()
    if kind == "sphere":
        # An icosphere with subdivision level s has 10 * 4^s + 2 vertices. Start at the first level at
        # least as fine as the target, so the remesher has to collapse towards it: from a coarser level
        # whose edges already lie within its [4/5, 4/3] tolerance it would leave the count where it was.
        n = count_for_edge_length(_area(kind), h)
        subdiv = int(np.clip(math.ceil(math.log(max(n, 12.0) / 10.0, 4)), 1, 7))
        ms.create_sphere(radius=SPHERE_RADIUS, subdiv=subdiv)
    elif kind == "torus":
        ms.create_torus(
            hradius=TORUS_MAJOR_RADIUS,
            vradius=TORUS_MINOR_RADIUS,
            hsubdiv=max(8, int(round(2 * math.pi * TORUS_MAJOR_RADIUS / h))),
            vsubdiv=max(4, int(round(2 * math.pi * TORUS_MINOR_RADIUS / h))),
        )
    else:
        k = max(2, int(round(SHEET_SIDE / h)) + 1)
        ms.create_grid(numvertx=k, numverty=k, absscalex=SHEET_SIDE, absscaley=SHEET_SIDE, center=False)
    return ms


def _project(kind, V):
    """Move vertices (size 1) exactly onto the ideal surface."""
    V = V.copy()
    if kind == "sphere":
        V *= SPHERE_RADIUS / np.linalg.norm(V, axis=1, keepdims=True)
    elif kind == "torus":
        rho = np.linalg.norm(V[:, :2], axis=1, keepdims=True)
        core = np.zeros_like(V)
        core[:, :2] = TORUS_MAJOR_RADIUS * V[:, :2] / rho
        d = V - core
        V = core + TORUS_MINOR_RADIUS * d / np.linalg.norm(d, axis=1, keepdims=True)
    else:
        V[:, 2] = 0.0
        # Boundary vertices slide along the square's sides; snap the round-off back onto them.
        half = 0.5 * SHEET_SIDE
        for c in (0, 1):
            near = np.abs(np.abs(V[:, c]) - half) < 1e-6 * SHEET_SIDE
            V[near, c] = np.sign(V[near, c]) * half
    return V


def _outward_sign(kind, V, F):
    """+1 if the faces point outward (sphere/torus) or up (sheet), -1 if inward, after a majority vote."""
    N = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])  # (m, 3) area-weighted normals
    C = V[F].mean(axis=1)  # (m, 3) centroids
    if kind == "sheet":
        out = np.array([0.0, 0.0, 1.0])
        return 1 if np.sum(N @ out > 0) * 2 > len(F) else -1
    if kind == "torus":
        rho = np.linalg.norm(C[:, :2], axis=1, keepdims=True)
        core = np.zeros_like(C)
        core[:, :2] = TORUS_MAJOR_RADIUS * C[:, :2] / rho
        C = C - core
    return 1 if np.sum(np.einsum("ij,ij->i", N, C) > 0) * 2 > len(F) else -1


def _remesh(kind, h, iterations):
    """Isotropically remesh the size-1 primitive to edge length ``h``; return float64 V, int64 F."""
    ms = _base_meshset(kind, h)
    # create_grid(center=True) is off by half a cell in this pymeshlab, so the sheet is centred here,
    # by the base grid's bounding box (remeshing keeps the boundary, hence the box).
    base = ms.current_mesh().vertex_matrix()
    shift = -0.5 * (base.min(axis=0) + base.max(axis=0)) if kind == "sheet" else np.zeros(3)
    # Crease detection at 60 degrees keeps the sheet's four corners (90 degree turns of its boundary)
    # while the smooth primitives, whose facets meet at a few degrees, have no creases.
    V, F = isotropic_remesh(ms, h, iterations=iterations, feature_degrees=60.0)
    V = _project(kind, V + shift)
    if _outward_sign(kind, V, F) < 0:
        F = F[:, ::-1].copy()
    return V, F


def initial_mesh(
    kind,
    *,
    target_edge_length=None,
    n_vertices=None,
    size=1.0,
    iterations=10,
    dtype=torch.float32,
    device=None,
):
    """A uniform starting mesh: a square sheet, a sphere or a torus, isotropically remeshed by pymeshlab.

    The primitive comes from pymeshlab (``create_grid``, ``create_sphere``, ``create_torus``) and is
    remeshed by ``meshing_isotropic_explicit_remeshing`` to one target edge length; the vertices are then
    projected exactly onto the ideal surface and the faces oriented outward (sphere, torus) or towards
    +z (sheet). The result is deterministic: the same call gives bitwise the same arrays.

    Geometry, all centred at the origin and scaled by ``size``:

    - ``"sphere"``: radius ``0.5 * size`` (unit diameter).
    - ``"torus"``: axis z, core circle of radius ``0.35 * size`` in the xy-plane, tube radius
      ``0.15 * size`` (so it spans ``size`` in x and y and ``0.3 * size`` in z).
    - ``"sheet"``: the square ``[-size/2, size/2]^2`` in the plane z = 0, normals +z; its boundary
      stays the square, corners included.

    Parameters
    ----------
    kind : str
        ``"sheet"``, ``"sphere"`` or ``"torus"``.
    target_edge_length : float, optional
        Edge length to remesh to, in the output's units. Give this or ``n_vertices``, not both.
    n_vertices : int, optional
        Approximate vertex count (usually within 10 %). The edge length is derived from the surface
        area ``A`` as ``h = sqrt(2 A / (sqrt(3) n))`` (a near-equilateral closed mesh has two triangles
        per vertex), then, if the count misses by more than 10 %, corrected by ``sqrt(n_got / n)`` until the
        count is bracketed and by bisection after (up to five more remeshes, the closest count kept).
        Default 2500 when neither argument is given.
    size : float
        Overall scale (see above).
    iterations : int
        Iterations of the isotropic remesher.
    dtype : torch float dtype of the vertices
    device : torch device of the returned tensors

    Returns
    -------
    V : (n, 3) float tensor
        Vertex positions, on the ideal surface up to floating-point round-off.
    F : (m, 3) int64 tensor
        Triangles; every vertex is referenced.

    Raises
    ------
    ValueError
        Unknown ``kind``, both or invalid ``target_edge_length`` / ``n_vertices``, non-positive ``size``
        or ``iterations`` (or ``iterations`` above ``MAX_REMESH_ITERATIONS``, 1,000), or a request implying
        fewer than 32 or more than 5,000,000 vertices.

    Examples
    --------
    >>> V, F = initial_mesh("sphere", n_vertices=500)
    >>> V.shape[1], F.dtype, bool((V.norm(dim=1) - 0.5).abs().max() < 1e-6)
    (3, torch.int64, True)
    """
    if kind not in INITIAL_KINDS:
        raise ValueError(f"kind must be one of {INITIAL_KINDS}, got {kind!r}")
    dtype = float_dtype(dtype)  # an int dtype truncated every vertex to 0
    check_positive("size", size)
    check_iterations(iterations)
    if target_edge_length is not None and n_vertices is not None:
        raise ValueError(
            f"give target_edge_length or n_vertices, not both (got {target_edge_length!r} and {n_vertices!r})"
        )
    if target_edge_length is not None:
        check_positive("target_edge_length", target_edge_length)
        h = float(target_edge_length) / float(size)
        implied = count_for_edge_length(_area(kind), h)
        if not MIN_VERTICES <= implied <= MAX_VERTICES:
            raise ValueError(
                f"target_edge_length={target_edge_length!r} at size={size!r} implies about {implied:.0f} "
                f"vertices for a {kind}; expected between {MIN_VERTICES} and {MAX_VERTICES}"
            )
        V, F = _remesh(kind, h, int(iterations))
    else:
        n = DEFAULT_N_VERTICES if n_vertices is None else n_vertices
        check_positive("n_vertices", n, integer=True)
        if not MIN_VERTICES <= n <= MAX_VERTICES:
            raise ValueError(f"n_vertices must lie between {MIN_VERTICES} and {MAX_VERTICES}, got {n!r}")
        h = edge_length_for_count(_area(kind), n)
        V, F = _remesh(kind, h, int(iterations))
        # The remesher leaves edges alone inside [4/5, 4/3] of the target, so a count can land far off
        # (e.g. on the icosphere level it started from), and jumps as the target edge moves. Rescale the
        # target edge from the count the last try reached until the count is bracketed, then bisect the
        # bracket (rescaling alone jumped over the count: 2,000 gave 2,404, then 1,556), up to five more
        # tries, and keep the closest mesh.
        reached, dense, sparse = len(V), 0.0, math.inf  # edges known to give too many, too few vertices
        for _ in range(5):
            if abs(len(V) - n) <= 0.1 * n:
                break
            if reached > n:
                dense = max(dense, h)
            else:
                sparse = min(sparse, h)
            h = math.sqrt(dense * sparse) if dense > 0 and sparse < math.inf else h * math.sqrt(reached / n)
            V2, F2 = _remesh(kind, h, int(iterations))
            reached = len(V2)
            if abs(reached - n) < abs(len(V) - n):
                V, F = V2, F2
    V = torch.as_tensor(V * float(size), dtype=dtype, device=device)
    F = torch.as_tensor(F, dtype=torch.int64, device=device)
    extent = (V.amax(0) - V.amin(0)).amax()
    if not (bool(torch.isfinite(V).all()) and float(extent) > 0):  # size 1e40 gave inf, 1e-50 zeros in float32
        raise ValueError(f"size={size!r} puts the {kind} out of {dtype}'s range (coordinates "
                         f"{'not finite' if not bool(torch.isfinite(V).all()) else 'all zero'})")
    return V, F
