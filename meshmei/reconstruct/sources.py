"""Where a reconstruction starts and what it aims at: source meshes (named starts, files, pairs) and
target surfaces (named targets, files, pairs, normalised to unit diagonal)."""

from __future__ import annotations

import math
import os

import numpy as np
import torch

from .._checks import check_positive
from ..errors import MeshError
from ..mesh import check_mesh, load_mesh
from ..operators import doublearea
from ..shapes import TARGET_NAMES, find_opening, initial_mesh, target_mesh, torus_through_opening
from ..shapes.core import DEFAULT_N_VERTICES  # MERGE: meshmei.shapes

__all__ = ["SOURCE_NAMES", "source_mesh", "resolve_source", "target_surface", "remesh"]

def _normalise(V: torch.Tensor) -> torch.Tensor:
    lo, hi = V.min(0).values, V.max(0).values
    diag = float((hi - lo).norm())
    if not diag > 0:
        raise MeshError(f"mesh has zero extent (all {V.shape[0]} vertices coincide); cannot normalise it")
    return (V - 0.5 * (lo + hi)) / diag


def target_surface(spec, *, dtype=torch.float32, normalize: bool = True):
    """Resolve a target: ``"bunny"``, ``"teapot"``, a mesh file path, or a ``(V, F)`` pair.

    Files and pairs are centred and scaled to unit bounding-box diagonal (``normalize=True``), as the
    named targets are, so metrics are comparable across targets.

    Raises
    ------
    FileNotFoundError
        A path that does not exist.
    MeshError
        A file that holds no mesh, an empty mesh, NaN coordinates, or a mesh of zero area.
    """
    if isinstance(spec, str) and spec in TARGET_NAMES:
        V, F = target_mesh(spec, dtype=dtype)
    else:
        if isinstance(spec, (str, os.PathLike)):
            V, F = _load(spec, "target", dtype)
        else:
            V, F = _pair(spec, "target")
            V = V.to(dtype)
        if normalize:
            V = _normalise(V)
    _check_area(V, F, f"target {spec}" if isinstance(spec, (str, os.PathLike)) else "target")
    return V, F


SOURCE_NAMES = ("sheet", "sphere", "torus", "torus-centred", "torus-through-opening")


def source_mesh(spec, *, n_vertices: int = DEFAULT_N_VERTICES, dtype=torch.float32, target=None):
    """Resolve a starting mesh: a name in :data:`SOURCE_NAMES` (made with ``n_vertices``), a mesh file
    path (used as stored), or a ``(V, F)`` pair.

    ``"torus"`` is placed for the ``target`` ``(V, F)`` when one is given: with its hole through the
    target's most open through-hole (:func:`meshmei.shapes.torus_through_opening`) when
    :func:`~meshmei.shapes.find_opening` sees one, as the teapot's handle, and centred otherwise (no
    target, or one without a hole, as the bunny). The torus is the start for genus-1 targets because its
    hole can become theirs; a torus whose hole misses the target's must block that hole with surface, which
    costs Chamfer accuracy no deformation can remove (:func:`meshmei.shapes.membrane_floor`; on the teapot,
    at least 9.7e-6 at the teapot's area). Finding the opening takes one to three seconds.
    ``"torus-centred"`` is always the centred torus of ``initial_mesh("torus")``; ``"torus-through-opening"``
    always threads it and raises ``MeshError`` when the target has no opening.
    """
    V, F, _ = resolve_source(spec, n_vertices, dtype, target)
    return V, F


def resolve_source(spec, n_vertices, dtype, target):
    """``(V, F, placement)``: placement says how a named torus was placed (None for everything else)."""
    placement = None
    if isinstance(spec, str) and spec in SOURCE_NAMES:
        if spec == "torus-through-opening" and target is None:
            raise ValueError("source 'torus-through-opening' needs the target whose opening it threads")
        opening = None
        if spec in ("torus", "torus-through-opening") and target is not None:
            opening = find_opening(*target)
            if opening is None and spec == "torus-through-opening":
                raise MeshError("the target has no through-hole that find_opening can see; start from "
                                "'torus-centred'")
        if opening is not None:
            V, F = torus_through_opening(*target, n_vertices=n_vertices, dtype=dtype, opening=opening)
            placement = "through the target's opening (meshmei.shapes.torus_through_opening)"
        else:
            kind = "torus" if spec.startswith("torus") else spec
            V, F = initial_mesh(kind, n_vertices=n_vertices, dtype=dtype)
            if kind == "torus":
                placement = "centred" + (" (the target has no through-hole that find_opening sees)"
                                         if spec == "torus" and target is not None else "")
    elif isinstance(spec, (str, os.PathLike)):
        V, F = _load(spec, "source", dtype)
    else:
        V, F = _pair(spec, "source")
    _check_area(V, F, f"source {spec}" if isinstance(spec, (str, os.PathLike)) else "source")
    return V, F, placement


def _load(path, role, dtype):
    try:
        return load_mesh(path, dtype=dtype)
    except MeshError as err:
        if str(path) in str(err):
            raise
        raise MeshError(f"{role} {path}: {err}") from None


def _pair(spec, role):
    try:
        V, F = spec
    except (TypeError, ValueError):
        raise ValueError(f"{role} must be a name, a mesh file path or a (V, F) pair, got {type(spec).__name__}") from None
    V, F = check_mesh(V, F)
    return V.detach(), F


def _area(V, F) -> float:
    return 0.5 * float(doublearea(V.detach().double(), F).sum())


def _check_area(V, F, role):
    area = _area(V, F)
    if not area > 0:
        raise MeshError(f"{role} mesh has zero surface area ({V.shape[0]} vertices, {F.shape[0]} faces)")


def remesh(V, F, n_vertices: int, *, iterations: int = 5):
    """Isotropic remeshing (pymeshlab) to about ``n_vertices`` vertices, for coarse-to-fine stages.

    The target edge length is ``sqrt(2 A / (sqrt(3) n))`` for total area ``A`` (a near-equilateral closed
    mesh has two triangles per vertex). Returns float tensors in the dtype of ``V`` and int64 faces.

    Raises
    ------
    ValueError
        ``n_vertices`` or ``iterations`` is not a positive integer.
    MeshError
        An invalid mesh, or one of zero area.
    """
    import pymeshlab  # deferred: heavy, and only remeshing needs it

    check_positive("n_vertices", n_vertices, integer=True)
    check_positive("iterations", iterations, integer=True)
    V, F = check_mesh(V, F)
    Vn = V.detach().cpu().double().numpy()
    Fn = F.cpu().numpy().astype(np.int32)
    T = Vn[Fn]
    area = 0.5 * np.linalg.norm(np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]), axis=1).sum()
    if not area > 0:  # pymeshlab would return an empty mesh
        raise MeshError(f"cannot remesh a mesh of zero surface area ({V.shape[0]} vertices, {F.shape[0]} faces)")
    h = math.sqrt(2.0 * area / (math.sqrt(3.0) * n_vertices))
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=Vn, face_matrix=Fn))
    ms.meshing_isotropic_explicit_remeshing(targetlen=pymeshlab.PureValue(h), iterations=iterations,
                                            featuredeg=180.0, reprojectflag=True)
    ms.meshing_remove_unreferenced_vertices()
    m = ms.current_mesh()
    V2 = torch.as_tensor(np.asarray(m.vertex_matrix()), dtype=V.dtype, device=V.device)
    F2 = torch.as_tensor(np.asarray(m.face_matrix(), dtype=np.int64), device=V.device)
    return check_mesh(V2, F2)
