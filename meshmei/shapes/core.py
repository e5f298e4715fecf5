"""Starting meshes (sheet, sphere, torus) and reconstruction targets (Stanford bunny, Utah teapot)."""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .._checks import check_positive
from ..errors import MeshError

__all__ = ["initial_mesh", "target_mesh", "find_opening", "torus_through_opening", "membrane_floor", "MembraneFloor",
           "INITIAL_KINDS", "TARGET_NAMES", "bunny_path"]

INITIAL_KINDS = ("sheet", "sphere", "torus")
TARGET_NAMES = ("bunny", "teapot")

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

_DATA = Path(__file__).resolve().parent.parent / "data"
TEAPOT_FILE = _DATA / "utah_teapot_bezier.json"
# Part of each of the 32 teapot patches (from the data file's notes): 0 body (patches 0-11 rim and
# body, 28-31 bottom), 1 handle (12-15), 2 spout (16-19), 3 lid (20-27).
TEAPOT_PARTS = np.array([0] * 12 + [1] * 4 + [2] * 4 + [3] * 8 + [0] * 4)


def _area(kind):
    """Surface area of the ideal shape at size 1."""
    if kind == "sphere":
        return 4.0 * math.pi * SPHERE_RADIUS**2
    if kind == "torus":
        return 4.0 * math.pi**2 * TORUS_MAJOR_RADIUS * TORUS_MINOR_RADIUS
    return SHEET_SIDE**2


def _edge_for_count(kind, n):
    """Edge length (size 1) whose near-equilateral tiling of the surface has about ``n`` vertices.

    Each vertex owns two triangles on a closed mesh (F ~ 2V), so area ~ n * sqrt(3)/2 * h^2.
    """
    return math.sqrt(2.0 * _area(kind) / (math.sqrt(3.0) * n))


def _count_for_edge(kind, h):
    return 2.0 * _area(kind) / (math.sqrt(3.0) * h * h)


def _base_meshset(kind, h):
    """A pymeshlab primitive at size 1 whose edges are about ``h`` long (the icosphere level is capped at 7)."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    if kind == "sphere":
        # An icosphere with subdivision level s has 10 * 4^s + 2 vertices. Start at the first level at
        # least as fine as the target, so the remesher has to collapse towards it: from a coarser level
        # whose edges already lie within its [4/5, 4/3] tolerance it would leave the count where it was.
        n = _count_for_edge(kind, h)
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


def _compact(V, F):
    """Drop unreferenced vertices and renumber the faces."""
    used = np.unique(F)
    if len(used) == len(V):
        return V, F
    remap = np.full(len(V), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return V[used], remap[F]


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
    import pymeshlab

    ms = _base_meshset(kind, h)
    # create_grid(center=True) is off by half a cell in this pymeshlab, so the sheet is centred here,
    # by the base grid's bounding box (remeshing keeps the boundary, hence the box).
    base = ms.current_mesh().vertex_matrix()
    shift = -0.5 * (base.min(axis=0) + base.max(axis=0)) if kind == "sheet" else np.zeros(3)
    ms.meshing_isotropic_explicit_remeshing(
        targetlen=pymeshlab.PureValue(h),
        iterations=iterations,
        # Crease detection at 60 degrees keeps the sheet's four corners (90 degree turns of its
        # boundary) while the smooth primitives, whose facets meet at a few degrees, have no creases.
        featuredeg=60.0,
        reprojectflag=True,
    )
    ms.meshing_remove_unreferenced_vertices()
    m = ms.current_mesh()
    V = np.asarray(m.vertex_matrix(), dtype=np.float64)
    F = np.asarray(m.face_matrix(), dtype=np.int64)
    V, F = _compact(V, F)
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
        per vertex), then corrected once by ``sqrt(n_got / n)`` if the count misses by more than 10 %.
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
        or ``iterations``, or a request implying fewer than 32 or more than 5,000,000 vertices.

    Examples
    --------
    >>> V, F = initial_mesh("sphere", n_vertices=500)
    >>> V.shape[1], F.dtype, bool((V.norm(dim=1) - 0.5).abs().max() < 1e-6)
    (3, torch.int64, True)
    """
    if kind not in INITIAL_KINDS:
        raise ValueError(f"kind must be one of {INITIAL_KINDS}, got {kind!r}")
    check_positive("size", size)
    check_positive("iterations", iterations, integer=True)
    if target_edge_length is not None and n_vertices is not None:
        raise ValueError(
            f"give target_edge_length or n_vertices, not both (got {target_edge_length!r} and {n_vertices!r})"
        )
    if target_edge_length is not None:
        check_positive("target_edge_length", target_edge_length)
        h = float(target_edge_length) / float(size)
        implied = _count_for_edge(kind, h)
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
        h = _edge_for_count(kind, n)
        V, F = _remesh(kind, h, int(iterations))
        # The remesher leaves edges alone inside [4/5, 4/3] of the target, so a count can land far off
        # (e.g. on the icosphere level it started from). Rescale the target edge from the count reached,
        # up to three times, and keep the closest mesh.
        for _ in range(3):
            if abs(len(V) - n) <= 0.1 * n:
                break
            h = h * math.sqrt(len(V) / n)
            V2, F2 = _remesh(kind, h, int(iterations))
            if abs(len(V2) - n) < abs(len(V) - n):
                V, F = V2, F2
    V = torch.as_tensor(V * float(size), dtype=dtype, device=device)
    F = torch.as_tensor(F, dtype=torch.int64, device=device)
    return V, F


def bunny_path():
    """Path of the Stanford bunny shipped with pymeshlab (``tests/sample_meshes/bunny.obj``).

    Raises
    ------
    FileNotFoundError
        pymeshlab is installed without its sample meshes.
    """
    import pymeshlab

    path = Path(os.path.dirname(pymeshlab.__file__)) / "tests" / "sample_meshes" / "bunny.obj"
    if not path.is_file():
        raise FileNotFoundError(
            f"the Stanford bunny is looked up inside the installed pymeshlab package, but {path} does not "
            "exist; install a pymeshlab wheel that ships tests/sample_meshes"
        )
    return path


def _normalise(V):
    """Centre on the bounding-box centre and scale to unit bounding-box diagonal (float64)."""
    lo, hi = V.min(axis=0), V.max(axis=0)
    return (V - 0.5 * (lo + hi)) / np.linalg.norm(hi - lo)


def _bunny():
    import trimesh

    mesh = trimesh.load(bunny_path(), process=False, force="mesh")
    V = np.asarray(mesh.vertices, dtype=np.float64)
    F = np.asarray(mesh.faces, dtype=np.int64)
    return V, F


def _bernstein(t):
    """Cubic Bernstein basis at parameters ``t`` (k,) -> (k, 4)."""
    s = 1.0 - t
    return np.stack([s**3, 3 * t * s**2, 3 * t**2 * s, t**3], axis=1)


def _teapot_patches(resolution):
    """Tessellate the 32 Bezier patches; seams are not merged yet. Returns (V (32 (r+1)^2, 3), F)."""
    data = json.loads(TEAPOT_FILE.read_text())
    P = np.asarray(data["control_points"], dtype=np.float64)  # (306, 3)
    patches = np.asarray(data["patches"], dtype=np.int64)  # (32, 16)
    r = resolution
    B = _bernstein(np.linspace(0.0, 1.0, r + 1))  # (r+1, 4)
    nets = P[patches].reshape(len(patches), 4, 4, 3)  # (32, 4, 4, 3): net[i, j] row i, column j
    # S(u, v) = sum_ij B_i(u) B_j(v) P_ij
    V = np.einsum("ui,vj,pijc->puvc", B, B, nets).reshape(-1, 3)  # (32 (r+1)^2, 3)
    grid = np.arange((r + 1) ** 2).reshape(r + 1, r + 1)
    a, b = grid[:-1, :-1].ravel(), grid[:-1, 1:].ravel()  # corners (u, v), (u, v+1)
    c, d = grid[1:, 1:].ravel(), grid[1:, :-1].ravel()  # (u+1, v+1), (u+1, v)
    quad = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])  # (2 r^2, 3)
    offsets = (np.arange(len(patches)) * (r + 1) ** 2)[:, None, None]
    F = (quad[None] + offsets).reshape(-1, 3)
    return V, F


def _merge_close(V, F, tol, group):
    """Weld vertices closer than ``tol`` within the same ``group`` (n,); clusters keep their first vertex."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    n = len(V)
    # A fourth coordinate far apart per group keeps groups from welding to each other.
    far = 10.0 * (float(np.ptp(V, axis=0).max()) + 1.0)
    pairs = cKDTree(np.column_stack([V, far * group])).query_pairs(tol, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    # Renumber clusters in order of their first vertex so the result does not depend on scipy's labels.
    first = np.full(label.max() + 1, n, dtype=np.int64)
    np.minimum.at(first, label, np.arange(n))
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return V[first[order]], rank[label][F]


def _orient_teapot(V, F):
    """Orient faces consistently per connected piece, then outward by the winding number of the whole."""
    import igl

    F, comp = igl.bfs_orient(F)
    F = np.asarray(F, dtype=np.int64)
    comp = np.asarray(comp).ravel()
    N = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    C = V[F].mean(axis=1)
    # A point just in front of an outward face is outside the (nearly closed) teapot: winding number ~0.
    eps = 1e-3 * np.linalg.norm(V.max(0) - V.min(0))
    for k in np.unique(comp):
        sel = np.flatnonzero(comp == k)
        # A vote of about 64 evenly spread faces decides; probing every face would cost O(m^2).
        probe = sel[:: max(1, len(sel) // 64)]
        w = igl.fast_winding_number(V, F, C[probe] + eps * N[probe])
        if np.mean(w > 0.5) > 0.5:
            F[sel] = F[sel][:, ::-1]
    return F


def _teapot(resolution):
    V, F = _teapot_patches(resolution)
    lo, hi = V.min(axis=0), V.max(axis=0)
    # Weld seams within each part only: the handle's lower end touches the body at one point, and
    # welding it there would make a non-manifold (bow-tie) vertex.
    group = np.repeat(TEAPOT_PARTS, (resolution + 1) ** 2)
    V, F = _merge_close(V, F, 1e-8 * float(np.linalg.norm(hi - lo)), group)
    # Collapsed rows at the lid tip and bottom centre give faces with a repeated index.
    F = F[(F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 2] != F[:, 0])]
    dblA = np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    F = F[dblA > 0]
    # The same triangle twice (in either orientation) would make a non-manifold edge.
    _, keep = np.unique(np.sort(F, axis=1), axis=0, return_index=True)
    F = F[np.sort(keep)]
    V, F = _compact(V, F)
    F = _orient_teapot(V, F)
    return V, F


def target_mesh(name, *, resolution=16, dtype=torch.float32, device=None):
    """A reconstruction target, centred on its bounding-box centre and scaled to unit bounding-box diagonal.

    - ``"bunny"``: the Stanford bunny shipped inside pymeshlab (28,088 vertices, watertight, genus 0),
      kept as stored apart from the normalisation; y is up, as in the file.
    - ``"teapot"``: Newell's 32 bicubic Bezier patches (``meshmei/data/utah_teapot_bezier.json``), each
      sampled on a ``(resolution + 1)^2`` grid and split into ``2 resolution^2`` triangles; coincident seam
      vertices are welded (tolerance ``1e-8`` of the diagonal), faces with repeated indices, zero area or
      duplicates are dropped, unused vertices removed, and faces oriented outward. z is up, as in the
      data. The teapot is open (gaps at the lid, spout tip, and where the handle and spout meet the body)
      and self-intersecting where the handle and spout pass into the body.

    Parameters
    ----------
    name : str
        ``"bunny"`` or ``"teapot"``.
    resolution : int
        Samples per patch side for the teapot (ignored for the bunny).
    dtype : torch float dtype of the vertices
    device : torch device of the returned tensors

    Returns
    -------
    V : (n, 3) float tensor
    F : (m, 3) int64 tensor

    Raises
    ------
    ValueError
        Unknown ``name`` or non-positive ``resolution``.
    FileNotFoundError
        pymeshlab's copy of the bunny is missing.
    MeshError
        The bunny file holds no triangles.

    Examples
    --------
    >>> V, F = target_mesh("teapot", resolution=4)
    >>> round(float((V.max(0).values - V.min(0).values).norm()), 6)
    1.0
    """
    if name not in TARGET_NAMES:
        raise ValueError(f"name must be one of {TARGET_NAMES}, got {name!r}")
    check_positive("resolution", resolution, integer=True)
    if name == "bunny":
        V, F = _bunny()
        if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
            raise MeshError(f"{bunny_path()} should hold a triangle mesh, got faces of shape {F.shape}")
    else:
        V, F = _teapot(int(resolution))
    V = _normalise(V)
    return torch.as_tensor(V, dtype=dtype, device=device), torch.as_tensor(F, dtype=torch.int64, device=device)


def _hemisphere(n):
    """``n`` unit vectors spread evenly (equal area, golden-angle spiral) over the hemisphere ``z > 0``."""
    k = np.arange(n) + 0.5
    z = 1.0 - k / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def _plane_basis(d):
    """Two unit vectors orthogonal to the unit vector ``d`` and to each other."""
    a = np.zeros(3)
    a[int(np.argmin(np.abs(d)))] = 1.0
    u = np.cross(d, a)
    u /= np.linalg.norm(u)
    return u, np.cross(d, u)


def _canonical_axis(d):
    """The line's direction as a unit vector whose largest component is positive."""
    d = np.asarray(d, dtype=np.float64) / np.linalg.norm(d)
    return -d if d[int(np.argmax(np.abs(d)))] < 0 else d


# An axis found within this angle of a coordinate axis is taken to be that axis: models are usually built
# in an aligned frame, and ray-cast estimates of a symmetric loop's axis are off by a fraction of a degree.
_SNAP_DEGREES = 1.0


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
    import igl

    from ..mesh import check_mesh

    for name, value, least in (("grid", grid, 4), ("rays", rays, 8), ("directions", directions, 0)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
            raise ValueError(f"{name} must be an integer of at least {least}, got {value!r}")
    V, F = check_mesh(torch.as_tensor(V), torch.as_tensor(F))
    Vn = np.ascontiguousarray(V.detach().cpu().double().numpy())
    Fn = np.ascontiguousarray(F.cpu().numpy())
    # libigl's ray caster has absolute tolerances: on a mesh under about 1e-2 across it misses every hit, so
    # no opening was found. Search at about unit size: a power-of-two scale is exact, so a unit-size mesh
    # is searched exactly as before, and the results are scaled back.
    diag = float(np.linalg.norm(Vn.max(0) - Vn.min(0)))
    unit = float(np.ldexp(1.0, int(np.round(np.log2(diag))))) if diag > 0 else 1.0
    Vn = Vn / unit
    lo, hi = Vn.min(0), Vn.max(0)
    axes = [np.linspace(lo[i], hi[i], grid) for i in range(3)]
    P = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)  # (grid^3, 3) lattice
    P = P[np.abs(igl.fast_winding_number(Vn, Fn, P)) < 0.5]
    if len(P) == 0:
        return None
    tree = igl.AABB()
    tree.init(Vn, Fn)
    # ray angles in the plane, the first four a quarter turn apart so that most points fail early
    first = [0, rays // 2, rays // 4, (3 * rays) // 4]
    order = np.array(first + [k for k in range(rays) if k not in first])
    angle = 2 * np.pi * order / rays

    def hits(Q, D):
        I, _, _ = tree.intersect_ray_first(Vn, Fn, np.ascontiguousarray(Q), np.ascontiguousarray(D))
        return I >= 0

    def surrounded(Q, d):
        # open both ways along d, and surrounded (all rays but one hit) in the plane normal to it
        u, v = _plane_basis(d)
        n = len(Q)
        axial = hits(np.concatenate([Q, Q]), np.repeat(np.stack([d, -d]), n, 0)).reshape(2, n)
        idx = np.flatnonzero(~axial.any(0))
        misses = np.zeros(n, dtype=np.int64)
        for chunk in (angle[:4], angle[4:]):
            if len(idx) == 0:
                break
            D = np.cos(chunk)[:, None] * u + np.sin(chunk)[:, None] * v
            hit = hits(np.repeat(Q[idx], len(chunk), 0), np.tile(D, (len(idx), 1))).reshape(len(idx), len(chunk))
            misses[idx] += (~hit).sum(1)
            idx = idx[misses[idx] <= 1]
        out = np.zeros(n, dtype=bool)
        out[idx] = True
        return out

    principal = np.linalg.eigh(np.cov((Vn - Vn.mean(0)).T))[1].T
    candidates = np.concatenate([np.eye(3), principal, _hemisphere(directions)])
    clearance = np.sqrt(igl.point_mesh_squared_distance(P, Vn, Fn)[0])
    best = None
    for d in candidates:
        ok = surrounded(P, d)
        if ok.any():
            k = int(np.argmax(np.where(ok, clearance, -1.0)))
            if best is None or clearance[k] > best[2]:  # ties keep the earlier axis (coordinate axes first)
                best = (P[k].copy(), d / np.linalg.norm(d), float(clearance[k]))
    if best is None:
        return None
    centre, axis, _ = best
    spacing = float((hi - lo).max()) / (grid - 1)

    def climb(c, d):
        # in the plane of the loop: hill-climb the distance to the surface on shrinking 3 x 3 stencils
        u, v = _plane_basis(d)
        offsets = np.array([(i, j) for i in (-1, 0, 1) for j in (-1, 0, 1)], dtype=np.float64)
        step = spacing
        for _ in range(6):
            step *= 0.5
            Q = c + step * (offsets[:, :1] * u + offsets[:, 1:] * v)
            c = Q[int(np.argmax(igl.point_mesh_squared_distance(Q, Vn, Fn)[0]))].copy()
        return c

    def along(c, d):
        # the middle of the run of surrounded points outside the solid on the line through c along d
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        reach = (corners - c) @ d
        t = np.linspace(reach.min(), reach.max(), 8 * grid)
        line = c + t[:, None] * d
        ok = surrounded(line, d) & (np.abs(igl.fast_winding_number(Vn, Fn, line)) < 0.5)
        j = int(np.argmin(np.abs(t)))
        if not ok[j]:
            return c
        a = b = j
        while a > 0 and ok[a - 1]:
            a -= 1
        while b < len(t) - 1 and ok[b + 1]:
            b += 1
        return c + 0.5 * (t[a] + t[b]) * d

    def tilt(c, d):
        # the loop's axis: the mean of the directions (a cone about it) about which c is surrounded
        u, v = _plane_basis(d)
        theta = np.deg2rad(np.arange(3.0, 61.0, 3.0))[:, None]
        phi = (2 * np.pi * np.arange(16) / 16)[None, :]
        ring = (np.cos(theta)[..., None] * d + np.sin(theta)[..., None]
                * (np.cos(phi)[..., None] * u + np.sin(phi)[..., None] * v)).reshape(-1, 3)
        cone = [e for e in np.concatenate([d[None], ring]) if surrounded(c[None], e)[0]]
        if not cone:
            return d
        m = np.mean(cone, axis=0)
        m = m / np.linalg.norm(m)
        k = int(np.argmax(np.abs(m)))
        if abs(m[k]) >= np.cos(np.deg2rad(_SNAP_DEGREES)):
            m = np.eye(3)[k] * np.sign(m[k])
        return m

    centre = along(climb(centre, axis), axis)
    for _ in range(2):
        turned = tilt(centre, axis)
        if np.array_equal(turned, axis):
            break
        axis = turned
        centre = along(climb(centre, axis), axis)
    d = float(np.sqrt(igl.point_mesh_squared_distance(centre[None], Vn, Fn)[0][0]))
    return centre * unit, _canonical_axis(axis), d * unit


def _rotation_between(a, b):
    """The rotation matrix that turns unit vector ``a`` onto unit vector ``b`` about ``a x b`` (``a . b > 0``)."""
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    K = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + K + K @ K / (1.0 + c)


def _opening_parts(opening):
    """``(centre, unit axis, clearance)`` from an opening as :func:`find_opening` returns it; ``ValueError``
    for anything else, or for a centre or axis that is not finite, or an axis of length 0."""
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
    """The starting torus of :func:`initial_mesh` placed with its hole through the most open through-hole of
    ``(V, F)`` (:func:`find_opening`, or ``opening`` as it returns, when already found): axis along the
    hole's axis, centred on it, scaled so that the hole's radius is twice the opening's clearance (the
    torus's tube then starts around the loop, not inside it).

    Raises
    ------
    MeshError
        ``(V, F)`` has no opening that :func:`find_opening` can see.
    ValueError
        ``opening`` is not ``(centre, axis, clearance)`` with a finite centre, a non-zero axis and a positive
        clearance.
    """
    found = find_opening(V, F) if opening is None else opening
    if found is None:
        raise MeshError("the target has no through-hole that find_opening can see; start from a centred torus")
    centre, axis, clearance = _opening_parts(found)
    if not (math.isfinite(clearance) and clearance > 0):
        raise ValueError(f"opening needs a positive clearance, got {clearance!r}")
    if axis[int(np.argmax(np.abs(axis)))] < 0:
        axis = -axis  # the torus is the same either way; this keeps the turn below away from 180 degrees
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
        The opening (as :func:`find_opening` returns it).
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
    V, F : the target mesh (closed, so that inside and outside are defined).
    opening : (centre, axis, clearance) or None
        As :func:`find_opening` returns it (None: call it).
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
    import igl
    import scipy.ndimage as ndi

    from ..mesh import check_mesh

    V, F = check_mesh(torch.as_tensor(V), torch.as_tensor(F))
    Vn = np.ascontiguousarray(V.detach().cpu().double().numpy())
    Fn = np.ascontiguousarray(F.cpu().numpy())
    if opening is None:
        opening = find_opening(Vn, Fn)
        if opening is None:
            raise MeshError("the target has no through-hole that find_opening can see")
    centre, axis, clearance = _opening_parts(opening)
    diag = float(np.linalg.norm(Vn.max(0) - Vn.min(0)))
    h = diag / 400 if spacing is None else spacing
    if isinstance(h, bool) or not (isinstance(h, (int, float, np.floating)) and math.isfinite(h) and h > 0):
        raise ValueError(f"spacing must be a positive finite number, got {spacing!r}")
    h = float(h)
    u, w = _plane_basis(axis)
    rel = Vn - centre
    pu, pw, pa = rel @ u, rel @ w, rel @ axis
    a = np.arange(pu.min() - 2 * h, pu.max() + 2 * h, h)
    b = np.arange(pw.min() - 2 * h, pw.max() + 2 * h, h)
    if a.size * b.size > 4_000_000:
        raise ValueError(f"spacing {h:g} gives a grid of {a.size * b.size:,} cells (at most 4 million); raise it")
    ia, ib = int(np.argmin(np.abs(a))), int(np.argmin(np.abs(b)))
    a, b = a - a[ia], b - b[ib]  # put a cell centre on the opening's centre
    A, B = np.meshgrid(a, b, indexing="ij")
    P = centre + A[..., None] * u + B[..., None] * w
    outside = np.abs(igl.fast_winding_number(Vn, Fn, P.reshape(-1, 3))).reshape(A.shape) < 0.5
    labels, _ = ndi.label(outside)
    label = labels[ia, ib]
    if label == 0:
        raise MeshError("the opening's centre lies inside the target's solid")
    region = labels == label
    if region[0].any() or region[-1].any() or region[:, 0].any() or region[:, -1].any():
        raise MeshError("the region around the opening's centre is not enclosed by the target in its plane: "
                        "not an opening")
    cells = P[region]

    def along(c, t):
        """Distances to the target from the points ``c + t * axis``; ``t`` is (k,) or (len(c), k)."""
        t = np.broadcast_to(t, (len(c), t.shape[-1]))
        d2 = igl.point_mesh_squared_distance((c[:, None, :] + t[..., None] * axis).reshape(-1, 3), Vn, Fn)[0]
        return np.sqrt(d2).reshape(t.shape)

    ts = np.arange(pa.min(), pa.max() + h, h)
    lower = np.empty(len(cells))
    # h / 8 apart over the reach of the best coarse sample and its two neighbours, [-1.5 h, 1.5 h] about it
    fine = np.linspace(-1.5, 1.5, 25) * h
    for lo in range(0, len(cells), 2048):
        c = cells[lo:lo + 2048]
        D = along(c, ts)
        best = D.argmin(1)
        Df = along(c, ts[best][:, None] + fine[None, :])
        # 1-Lipschitz along the line: every t is within h/16 of a fine sample, or h/2 of a coarse one
        # that is not the best or beside it (those three are covered by the fine samples)
        near = np.abs(np.arange(len(ts))[None, :] - best[:, None]) <= 1
        lower[lo:lo + 2048] = np.minimum((Df - h / 16).min(1), np.where(near, np.inf, D - h / 2).min(1))
    # and 1-Lipschitz across the cell, whose points lie within h / sqrt(2) of its centre
    lower = np.maximum(lower - h * math.sqrt(0.5), 0.0)
    area = 0.5 * float(igl.doublearea(Vn, Fn).sum())
    return MembraneFloor(integral=float(2.0 * (lower**2).sum() * h * h), opening_area=float(region.sum() * h * h),
                         target_area=area, centre=centre, axis=axis, clearance=clearance, spacing=h)
