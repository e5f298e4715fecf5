"""Isotropic remeshing with pymeshlab, of the starting primitives and of any mesh (``remesh``).

pymeshlab comes from :mod:`meshmei.shapes._meshlab`, which says in which thread it is imported and why.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .._checks import check_positive
from ..errors import MeshError
from ..mesh import check_mesh
from ._meshlab import pymeshlab

__all__ = ["edge_length_for_count", "count_for_edge_length", "isotropic_parameters", "isotropic_remesh", "remesh",
           "mesh_arrays", "MAX_REMESH_GROWTH"]


def edge_length_for_count(area, n_vertices):
    """Edge length whose near-equilateral tiling of a surface of ``area`` has about ``n_vertices`` vertices.

    Each vertex owns two triangles on a closed mesh (F ~ 2V), so ``area ~ n * sqrt(3)/2 * h^2``, that is
    ``h = sqrt(2 area / (sqrt(3) n))``.

    Examples
    --------
    >>> round(edge_length_for_count(math.sqrt(3) / 2, 1), 12)
    1.0
    """
    return math.sqrt(2.0 * area / (math.sqrt(3.0) * n_vertices))


def count_for_edge_length(area, h):
    """The vertex count of :func:`edge_length_for_count` turned round: about ``2 area / (sqrt(3) h^2)``."""
    return 2.0 * area / (math.sqrt(3.0) * h * h)


def mesh_arrays(m):
    """The vertices and faces of the pymeshlab mesh ``m`` as C-ordered float64 and int64 arrays.

    pymeshlab hands its matrices out in Fortran order. A vertex tensor made from that has its rows
    strided, and ``index_select`` over rows, the gather behind every corner tensor, reads it about 18
    times slower (2.8 against 0.15 ms for the corners of a 10k-vertex mesh); a strided face array is
    copied by every ``reshape(-1)``.
    """
    V = np.ascontiguousarray(m.vertex_matrix(), dtype=np.float64)
    return V, np.ascontiguousarray(m.face_matrix(), dtype=np.int64)


def isotropic_parameters(targetlen, *, iterations: int, feature_degrees: float, check_distance: bool = True) -> dict:
    """Every parameter of pymeshlab's ``meshing_isotropic_explicit_remeshing``, named.

    pymeshlab keeps, for the whole process, the last value passed to each filter parameter and uses it as
    that parameter's default in later calls, on any ``MeshSet`` (a call with ``featuredeg=180`` made a
    later call that left it out remesh with 180 instead of 30). So a call that leaves a parameter out
    depends on what ran before it; every call in meshmei names them all. ``targetlen`` is a pymeshlab
    ``PureValue`` or ``PercentageValue``; ``check_distance`` is ``checksurfdist`` (refuse a collapse that
    leaves the input by more than 1 % of its bounding-box diagonal); the rest are pymeshlab's documented
    defaults.
    """
    return dict(iterations=int(iterations), adaptive=False, selectedonly=False, targetlen=targetlen,
                featuredeg=float(feature_degrees), checksurfdist=bool(check_distance),
                maxsurfdist=pymeshlab.PercentageValue(1.0),
                splitflag=True, collapseflag=True, swapflag=True, smoothflag=True, reprojectflag=True)


def isotropic_remesh(ms, h, *, iterations, feature_degrees, check_distance=True):
    """Remesh the current mesh of the pymeshlab ``MeshSet`` ``ms`` in place to edge length ``h`` and return it.

    ``meshing_isotropic_explicit_remeshing`` with reprojection onto the input, edges meeting at more than
    ``feature_degrees`` kept as creases, then unreferenced vertices removed.

    Parameters
    ----------
    ms : pymeshlab.MeshSet
        Holds the mesh to remesh as its current mesh.
    h : float
        Target edge length.
    iterations : int
        Iterations of the remesher.
    feature_degrees : float
        Crease angle; 180 keeps no creases.
    check_distance : bool
        Refuse collapses that leave the input surface (:func:`isotropic_parameters`).

    Returns
    -------
    V : (n, 3) float64 array
    F : (m, 3) int64 array
        Both C-ordered (:func:`mesh_arrays`).
    """
    ms.meshing_isotropic_explicit_remeshing(**isotropic_parameters(pymeshlab.PureValue(h), iterations=iterations,
                                                                   feature_degrees=feature_degrees,
                                                                   check_distance=check_distance))
    ms.meshing_remove_unreferenced_vertices()
    return mesh_arrays(ms.current_mesh())


# A remesh of a mesh of at least UNCHECKED_FROM vertices to at most 1/COARSENING of its count (the first stage of a
# coarse-to-fine schedule at 10k: n/16 or n/4 of the start) does not check its collapses against the input
# (pymeshlab's ``checksurfdist``), whose cost grows with the input: the 10k sphere and torus starts to 625
# vertices took 0.29-0.32 s with it and 0.08 s without, the sphere giving the same mesh either way. Smaller inputs
# keep it (0.07 s at 2,500): there it changes the coarse start (the 2,500-vertex sphere went to 159-171 vertices
# for 156 asked, 149-152 without), and so every default run, which stay as they were measured (without it the
# held-out dumbbell's default run failed, an outcome that turns on the start mesh: docs/reconstruction.md,
# *The first remesh*). The output is reprojected onto the input either way; refinements and restarts always
# keep the check.
COARSENING = 2
UNCHECKED_FROM = 8000
# A remesh that lands at more than this many times the count asked for (plus 100) has met parts thinner than its
# edge length, which it cannot coarsen, while it splits every long edge: a needle 1,000 long and 1e-3 thick
# asked for 160 vertices gave 108,102, and the checks that followed ran for minutes. remesh refuses it.
MAX_REMESH_GROWTH = 4
# iterations of pymeshlab's remesher a call may ask for: 1,000 take about 5 s on a small sphere, and the loop
# cannot be interrupted from Python (10**6 ran for over an hour)
MAX_REMESH_ITERATIONS = 1000


def check_iterations(iterations) -> int:
    """``iterations`` as an int, or a ValueError when it is not an integer in 1..MAX_REMESH_ITERATIONS."""
    check_positive("iterations", iterations, integer=True)
    if iterations > MAX_REMESH_ITERATIONS:
        raise ValueError(f"iterations must be at most {MAX_REMESH_ITERATIONS:,}, got {iterations!r}")
    return int(iterations)


def remesh(V, F, n_vertices: int, *, iterations: int = 5):
    """Isotropic remeshing (pymeshlab) to about ``n_vertices`` vertices, for coarse-to-fine stages.

    The target edge length is ``sqrt(2 A / (sqrt(3) n))`` for total area ``A`` (a near-equilateral closed
    mesh has two triangles per vertex). Returns float tensors in the dtype of ``V`` and int64 faces. Collapses
    are checked against the input's surface unless the input has at least :data:`UNCHECKED_FROM` vertices and
    ``n_vertices`` is at most 1/:data:`COARSENING` of them.

    Parameters
    ----------
    V : (n, 3) float tensor
    F : (m, 3) int64 tensor
    n_vertices : int
        Vertex count to aim for.
    iterations : int
        Iterations of the remesher.

    Returns
    -------
    V : (k, 3) float tensor
        In the dtype and on the device of ``V``.
    F : (l, 3) int64 tensor

    Raises
    ------
    ValueError
        ``n_vertices`` or ``iterations`` is not a positive integer, or ``iterations`` is above
        :data:`MAX_REMESH_ITERATIONS`.
    MeshError
        An invalid mesh, or one of zero area, or a result of more than :data:`MAX_REMESH_GROWTH` times
        ``n_vertices`` (plus 100) vertices: parts thinner than the edge length for that count.

    Examples
    --------
    >>> from meshmei.shapes import initial_mesh
    >>> V, F = remesh(*initial_mesh("sphere", n_vertices=300), 1000)
    >>> 800 < V.shape[0] < 1200, F.dtype
    (True, torch.int64)
    """
    check_positive("n_vertices", n_vertices, integer=True)
    check_iterations(iterations)
    V, F = check_mesh(V, F)
    Vn = V.detach().cpu().double().numpy()
    Fn = F.cpu().numpy().astype(np.int32)
    T = Vn[Fn]  # (m, 3, 3)
    area = 0.5 * np.linalg.norm(np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]), axis=1).sum()
    if not area > 0:  # pymeshlab would return an empty mesh
        raise MeshError(f"cannot remesh a mesh of zero surface area ({V.shape[0]} vertices, {F.shape[0]} faces)")
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=Vn, face_matrix=Fn))
    unchecked = V.shape[0] >= UNCHECKED_FROM and COARSENING * n_vertices <= V.shape[0]
    length = edge_length_for_count(area, n_vertices)
    V2, F2 = isotropic_remesh(ms, length, iterations=iterations, feature_degrees=180.0, check_distance=not unchecked)
    if len(V2) > MAX_REMESH_GROWTH * n_vertices + 100:
        raise MeshError(f"remeshing to about {n_vertices} vertices gave {len(V2)}: the mesh has parts thinner than "
                        f"the edge length for that count ({length:.3g}), which the remesher keeps while it splits "
                        "the long edges; thicken the thin parts, or remesh the mesh yourself")
    return check_mesh(torch.as_tensor(V2, dtype=V.dtype, device=V.device), torch.as_tensor(F2, device=V.device))
