"""Where a reconstruction starts and what it aims at: source meshes (named starts, files, pairs) and
target surfaces (named targets, files, pairs, normalised to unit diagonal)."""

from __future__ import annotations

import math
import os

import numpy as np
import torch

from ..errors import MeshError, ReconstructionError
from ..mesh import cast_vertices, load_mesh, remove_unreferenced
from ..operators import doublearea
from ..shapes import DEFAULT_N_VERTICES, TARGET_NAMES, initial_mesh, normalize_unit_diagonal, target_mesh
from .openings import find_opening, torus_through_opening

__all__ = ["SOURCE_NAMES", "source_mesh", "resolve_source", "target_surface"]

def target_surface(spec, *, dtype=torch.float32, normalize: bool = True, return_frame: bool = False):
    """Resolve a target: ``"bunny"``, ``"teapot"``, a mesh file path, or a ``(V, F)`` pair.

    Files and pairs keep only the vertices their faces use (an unused vertex has no surface, and would
    stretch the bounding box), and are centred and scaled to unit bounding-box diagonal
    (``normalize=True``), as the named targets are, so metrics are comparable across targets. They are
    read and normalised in float64 and cast to ``dtype`` after: in float32, a target 1e5 from the origin
    would lose its shape to rounding before it was centred.

    ``return_frame``: also return where the normalised target lies in the file's (or pair's) own
    coordinates, ``{"centre": [x, y, z], "scale": d}`` (a point ``p`` of the unit frame is ``p * d + centre``
    there), or None for a named target or ``normalize=False``.

    Raises
    ------
    FileNotFoundError
        A path that does not exist.
    MeshError
        A file that holds no mesh, an empty mesh, NaN coordinates, coordinates beyond ``dtype``'s range
        (after normalisation), or a mesh of zero area.
    """
    for name, flag in (("normalize", normalize), ("return_frame", return_frame)):
        if not isinstance(flag, (bool, np.bool_)):  # 'no' is a true string: the target was normalised
            raise ReconstructionError(f"{name} must be True or False, got {flag!r}")
    role = f"target {spec}" if isinstance(spec, (str, os.PathLike)) else "target"
    frame = None
    if isinstance(spec, str) and spec in TARGET_NAMES:
        V, F = target_mesh(spec, dtype=dtype)
    else:
        if isinstance(spec, (str, os.PathLike)):
            V, F = _load(spec, "target", torch.float64)
        else:
            V, F = _pair(spec, "target")
        if normalize:  # the frame measured as the normalisation measures: (hi - lo).norm() of a target 1e154
            try:       # across overflowed, and the result's scale was inf
                V, frame = normalize_unit_diagonal(V.double(), return_frame=True)
            except MeshError as err:
                raise MeshError(f"{role}: {err}") from None
        V = cast_vertices(V, dtype, role)
    _check_area(V, F, role)
    return (V, F, frame) if return_frame else (V, F)


SOURCE_NAMES = ("sheet", "sphere", "torus", "torus-centred", "torus-through-opening")


def source_mesh(spec, *, n_vertices: int = DEFAULT_N_VERTICES, dtype=torch.float32, target=None):
    """Resolve a starting mesh: a name in :data:`SOURCE_NAMES` (made with ``n_vertices``), a mesh file
    path (used as stored), or a ``(V, F)`` pair. A file or pair keeps only the vertices its faces use: an
    unused vertex would take part in the deformation (an RBF kernel of its own, which sets the kernel
    scale) without being part of the surface.

    ``"torus"`` is placed for the ``target`` when one is given (a ``(V, F)`` pair, used as it is, or a name or
    mesh file path, resolved by :func:`target_surface` as :func:`~meshmei.reconstruct.reconstruct` resolves
    it: normalised to unit diagonal): with its hole through the
    target's most open through-hole (:func:`meshmei.reconstruct.openings.torus_through_opening`) when
    :func:`~meshmei.reconstruct.openings.find_opening` sees one, as the teapot's handle, and centred otherwise (no
    target, or one without a hole, as the bunny). The torus is the start for genus-1 targets because its
    hole can become theirs; a torus whose hole misses the target's must block that hole with surface, which
    costs Chamfer accuracy no deformation can remove (:func:`meshmei.benchmarks.reconstruct.membrane_floor`; on the teapot,
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
            target = _target_pair(target)
            opening = find_opening(*target)
            if opening is None and spec == "torus-through-opening":
                raise MeshError("the target has no through-hole that find_opening can see; start from "
                                "'torus-centred'")
        if opening is not None:
            V, F = torus_through_opening(*target, n_vertices=n_vertices, dtype=dtype, opening=opening)
            placement = "through the target's opening (meshmei.reconstruct.openings.torus_through_opening)"
        else:
            kind = "torus" if spec.startswith("torus") else spec
            V, F = initial_mesh(kind, n_vertices=n_vertices, dtype=dtype)
            if kind == "torus":
                placement = "centred" + (" (the target has no through-hole that find_opening sees)"
                                         if spec == "torus" and target is not None else "")
    elif isinstance(spec, (str, os.PathLike)):
        V, F = _load(spec, "source", torch.float64)
        V = _cast_source(V, F, dtype, f"source {spec}")
    else:
        V, F = _pair(spec, "source")
    _check_area(V, F, f"source {spec}" if isinstance(spec, (str, os.PathLike)) else "source")
    return V, F, placement


def _target_pair(target):
    """The target a named torus is placed for, as ``(V, F)``: a name or a file resolved as :func:`reconstruct`
    resolves it (a name was unpacked as a pair: find_opening's TypeError, 'takes 2 positional arguments but 5
    were given'), a pair as it is."""
    if isinstance(target, (str, os.PathLike)):
        return target_surface(target)
    try:
        V, F = target
    except (TypeError, ValueError):
        raise ValueError(f"target must be a name, a mesh file path or a (V, F) pair, got {type(target).__name__}"
                         ) from None
    return V, F


def _load(path, role, dtype):
    try:
        return remove_unreferenced(*load_mesh(path, dtype=dtype))
    except FileNotFoundError:
        if os.path.splitext(str(path))[1]:
            raise
        names = ", ".join(SOURCE_NAMES if role == "source" else TARGET_NAMES)  # a mistyped name, not a file
        raise FileNotFoundError(f"{role} {path!s}: neither a built-in {role} ({names}) nor a mesh file") from None
    except MeshError as err:
        if str(path) in str(err):
            raise
        raise MeshError(f"{role} {path}: {err}") from None


def _cast_source(V, F, dtype, role):
    """A source read in float64, in ``dtype``; a MeshError when rounding to ``dtype`` collapses faces (a
    mesh far from the origin for its size: float32 keeps about 7 digits of each coordinate)."""
    out = cast_vertices(V, dtype, role)
    had = doublearea(V, F) > 0
    lost = int((had & ~(doublearea(out.double(), F) > 0)).sum())
    if lost:
        far = float(V.abs().max())
        raise MeshError(f"{role}: {lost} of {F.shape[0]} faces collapse to zero area in {dtype} (coordinates up to "
                        f"{far:.3g}, too far from the origin for that precision); centre the mesh near the origin")
    return out


def _pair(spec, role):
    try:
        V, F = spec
    except (TypeError, ValueError):
        raise ValueError(f"{role} must be a name, a mesh file path or a (V, F) pair, got {type(spec).__name__}") from None
    V, F = remove_unreferenced(V, F)
    return V.detach(), F


def _area(V, F) -> float:
    return 0.5 * float(doublearea(V.detach().double(), F).sum())


def _check_area(V, F, role):
    area = _area(V, F)
    # squared coordinates beyond the dtype's range (float32: about 1e19) would turn sampling, edge lengths
    # and the contact reach into Inf at the first step or stage; say so here, whatever the schedule (and
    # before the zero-area check: a float64 mesh at 1e155 has a NaN area, and was called "zero surface area")
    if not (math.isfinite(area) and math.isfinite(float(doublearea(V.detach(), F).sum()))):
        wider = " or use float64" if V.dtype != torch.float64 else ""
        raise MeshError(f"{role}: the face areas overflow {V.dtype} (largest coordinate "
                        f"{float(V.detach().abs().max()):.3g}); rescale the mesh{wider}")
    if not area > 0:
        raise MeshError(f"{role} mesh has zero surface area ({V.shape[0]} vertices, {F.shape[0]} faces)")
