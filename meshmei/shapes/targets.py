"""Reconstruction targets at unit diagonal: the Stanford bunny, the Utah teapot (from its Bezier patches), and
three targets with thin parts (implicit surfaces meshed by pymeshlab)."""

from __future__ import annotations

import functools
import json
import math
import os
from pathlib import Path

import igl
import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .._checks import check_positive, float_dtype
from ..errors import MeshError
from ..quality import in_range, range_exponent, signed_volume
from ._meshlab import pymeshlab
from .remeshing import isotropic_parameters, mesh_arrays

__all__ = ["target_mesh", "bunny_path", "normalize_unit_diagonal", "TARGET_NAMES", "TEAPOT_FILE", "THIN_TARGETS"]

# Targets with thin parts (issue 16): implicit surfaces (muparser expressions, negative inside) meshed by
# pymeshlab's marching cubes at voxel 0.015 on [-1, 1]^3, then remeshed isotropically (edges 1 % of the
# diagonal). None of them was used to choose a setting before normal_match (2026-11-29), whose weight and
# form were chosen on the cup and the dumbbell; the fin, and the bowl added then, were used to choose nothing.
THIN_TARGETS = {
    # two balls (radius 0.35) joined by a rod of radius 0.05
    "dumbbell": "min(min(sqrt((x-0.6)^2+y^2+z^2)-0.35, sqrt((x+0.6)^2+y^2+z^2)-0.35), "
                "max(sqrt(y^2+z^2)-0.05, abs(x)-0.7))",
    # a ball (radius 0.45) with a disc 0.06 thick and 1.7 across through its equator
    "fin": "min(sqrt(x^2+y^2+z^2)-0.45, max(abs(z)-0.03, sqrt(x^2+y^2)-0.85))",
    # a cup: a cylinder with a wall and a bottom 0.05 thick, open at the top
    "cup": "max(max(sqrt(x^2+y^2)-0.5, abs(z)-0.5), -max(sqrt(x^2+y^2)-0.45, -(z+0.45)))",
    # a bowl: a spherical shell (radii 0.45 and 0.5) below the plane z = 0.15, open at the top
    "bowl": "max(abs(sqrt(x^2+y^2+z^2)-0.475)-0.025, z-0.15)",
}
TARGET_NAMES = ("bunny", "teapot") + tuple(THIN_TARGETS)

_DATA = Path(__file__).resolve().parent.parent / "data"
TEAPOT_FILE = _DATA / "utah_teapot_bezier.json"
# Part of each of the 32 teapot patches (from the data file's notes): 0 body (patches 0-11 rim and
# body, 28-31 bottom), 1 handle (12-15), 2 spout (16-19), 3 lid (20-27).
TEAPOT_PARTS = np.array([0] * 12 + [1] * 4 + [2] * 4 + [3] * 8 + [0] * 4)


def bunny_path():
    """Path of the Stanford bunny shipped with pymeshlab (``tests/sample_meshes/bunny.obj``).

    Raises
    ------
    FileNotFoundError
        pymeshlab is installed without its sample meshes.
    """
    path = Path(os.path.dirname(pymeshlab.__file__)) / "tests" / "sample_meshes" / "bunny.obj"
    if not path.is_file():
        raise FileNotFoundError(
            f"the Stanford bunny is looked up inside the installed pymeshlab package, but {path} does not "
            "exist; install a pymeshlab wheel that ships tests/sample_meshes"
        )
    return path


def normalize_unit_diagonal(V, *, return_frame: bool = False):
    """Centre ``V`` on its bounding-box centre and scale it to unit bounding-box diagonal.

    Every row of ``V`` sets the box: drop the vertices no face uses first
    (:func:`meshmei.mesh.remove_unreferenced`, as :func:`meshmei.reconstruct.target_surface` does).

    Parameters
    ----------
    V : (n, 3) float tensor
    return_frame : bool
        Also return where the result lies in ``V``'s coordinates: ``{"centre": [x, y, z], "scale": d}``, the
        box's centre and diagonal, so that a point ``p`` of the result is ``p * d + centre`` there.

    Returns
    -------
    (n, 3) float tensor
        A new tensor in the dtype and on the device of ``V``, computed in float64 (a float32 mesh
        1e-30 or 1e30 across has a diagonal whose squared length under- or overflows float32); with
        ``return_frame``, ``(tensor, frame)``.

    Raises
    ------
    MeshError
        All vertices coincide (zero extent), so there is no scale to divide by; with ``return_frame``, a
        diagonal beyond float64's range (the frame's scale would be inf).

    Examples
    --------
    >>> normalize_unit_diagonal(torch.tensor([[0.0, 0.0, 0.0], [3.0, 4.0, 0.0]]))
    tensor([[-0.3000, -0.4000,  0.0000],
            [ 0.3000,  0.4000,  0.0000]])
    """
    if not isinstance(V, torch.Tensor) or not V.is_floating_point() or V.ndim != 2 or V.shape[1] != 3 or not len(V):
        got = f"{V.dtype} of shape {tuple(V.shape)}" if isinstance(V, torch.Tensor) else type(V).__name__
        raise MeshError(f"V must be a non-empty (n, 3) float tensor, got {got}")
    if not isinstance(return_frame, (bool, np.bool_)):
        raise MeshError(f"return_frame must be True or False, got {return_frame!r}")
    if not bool(torch.isfinite(V).all()):  # Inf gave NaN vertices, NaN a 'coincide' error
        raise MeshError("V holds NaN or Inf coordinates; cannot normalise it")
    Vd = V.double()
    W = in_range(Vd)  # V itself when it is float64; beyond 1e50 scaled by a power of two, exactly (at
    lo, hi = W.min(0).values, W.max(0).values  # 1e155 the squared diagonal overflowed: inf, and a zero mesh)
    diag = float((hi - lo).norm())
    if not diag > 0:
        raise MeshError(f"mesh has zero extent (all {V.shape[0]} vertices coincide); cannot normalise it")
    out = ((W - 0.5 * (lo + hi)) / diag).to(V.dtype)
    if not return_frame:
        return out
    # the frame in V's own units: the diagonal and centre measured on W, scaled back by the same power of two
    # (exact); measured on V, the diagonal of a mesh 1e154 across overflowed to inf
    e = range_exponent(Vd)
    try:
        scale = math.ldexp(diag, -e)
    except OverflowError:
        raise MeshError(f"the mesh's bounding-box diagonal, {diag:.6g} * 2**{-e}, is beyond float64's range "
                        f"({torch.finfo(torch.float64).max:.3g}); rescale it") from None
    centre = [math.ldexp(c, -e) for c in (0.5 * (lo + hi)).tolist()]
    return out, {"centre": centre, "scale": scale}


def _bunny():
    """The bunny's vertices and faces as stored in pymeshlab's copy: float64 (n, 3), int64 (m, 3) arrays."""
    import trimesh  # deferred on purpose: it takes over half a second to import, and only the bunny needs it

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


def _compact(V, F):
    """Drop unreferenced vertices and renumber the faces."""
    used = np.unique(F)
    if len(used) == len(V):
        return V, F
    remap = np.full(len(V), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return V[used], remap[F]


def _teapot(resolution):
    """The teapot's patches tessellated, seams welded, degenerate and duplicate faces dropped, faces oriented."""
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


@functools.lru_cache(maxsize=None)
def _implicit(name):
    """A :data:`THIN_TARGETS` surface: watertight, outward, no self-intersection (checked in the tests)."""
    ms = pymeshlab.MeshSet()
    ms.create_implicit_surface(voxelsize=0.015, minx=-1, miny=-1, minz=-1, maxx=1, maxy=1, maxz=1,
                               expr=THIN_TARGETS[name])
    ms.meshing_isotropic_explicit_remeshing(**isotropic_parameters(pymeshlab.PercentageValue(1.0), iterations=5,
                                                                   feature_degrees=30.0))
    V, F = mesh_arrays(ms.current_mesh())
    if signed_volume(V, F) < 0:
        F = F[:, ::-1].copy()
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
    - ``"dumbbell"``, ``"fin"``, ``"cup"``, ``"bowl"`` (:data:`THIN_TARGETS`): watertight surfaces with thin
      parts (a rod of radius 0.05 between two balls; a disc 0.06 thick through a ball; a cup with walls 0.05
      thick; a bowl, a spherical shell 0.05 thick cut above its equator), from
      implicit expressions meshed by pymeshlab, z up.

    Parameters
    ----------
    name : str
        One of :data:`TARGET_NAMES`.
    resolution : int
        Samples per patch side for the teapot, at least 2 (at 1 the welded patches share an edge among three
        faces); the other targets have one mesh each and take only the default.
    dtype : torch float dtype of the vertices
    device : torch device of the returned tensors

    Returns
    -------
    V : (n, 3) float tensor
        Centred on the bounding-box centre, at unit bounding-box diagonal.
    F : (m, 3) int64 tensor
        Triangles, oriented outward; every vertex is referenced.

    Raises
    ------
    ValueError
        Unknown ``name``, a ``resolution`` below 2 or given for a target other than the teapot, or a
        ``dtype`` that is not a floating-point one.
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
    if resolution < 2:
        raise ValueError(f"resolution must be at least 2 (at 1 the teapot's welded patches are not edge-manifold), "
                         f"got {resolution!r}")
    if name != "teapot" and resolution != 16:
        raise ValueError(f"resolution applies to the teapot only; the {name} has one mesh (got {resolution!r})")
    dtype = float_dtype(dtype)  # an int dtype zeroed every vertex
    if name == "bunny":
        V, F = _bunny()
        if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
            raise MeshError(f"{bunny_path()} should hold a triangle mesh, got faces of shape {F.shape}")
    elif name in THIN_TARGETS:
        V, F = (x.copy() for x in _implicit(name))
    else:
        V, F = _teapot(int(resolution))
    V = normalize_unit_diagonal(torch.from_numpy(V))
    return V.to(dtype=dtype, device=device), torch.as_tensor(F, dtype=torch.int64, device=device)
