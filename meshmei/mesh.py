"""Mesh validation and file I/O: the boundary where user meshes become checked torch tensors."""

from __future__ import annotations

import os
from collections import OrderedDict
from pathlib import Path

import numpy as np
import torch

from .errors import MeshError

__all__ = ["check_mesh", "numpy_mesh", "load_mesh", "save_mesh", "MESH_FORMATS"]

MESH_FORMATS = (".obj", ".ply", ".off", ".stl")


def _as_tensor(x, name):
    if isinstance(x, torch.Tensor):
        return x
    if isinstance(x, np.ndarray):
        return torch.from_numpy(x)
    if isinstance(x, (list, tuple)):
        try:
            return torch.as_tensor(np.asarray(x))
        except (ValueError, TypeError) as err:
            raise MeshError(f"{name} must be a rectangular array, got a ragged {type(x).__name__}: {err}") from None
    raise MeshError(f"{name} must be a torch tensor or numpy array, got {type(x).__name__}")


# face tensors that passed the index checks, with their in-place version counter: a hit is the very
# tensor, unmodified, and skips two reductions per call in optimisation loops
_CHECKED_FACES: "OrderedDict[tuple, tuple[torch.Tensor, int]]" = OrderedDict()


def check_mesh(V, F, *, batched: bool | None = False):
    """Validate a triangle mesh and return it as torch tensors.

    Parameters
    ----------
    V : (n, 3) float tensor or array, or (B, n, 3) when ``batched``
        Vertex positions. float32 and float64 are kept as they are; other float types are kept too.
    F : (m, 3) integer tensor or array
        Triangle indices into the vertices (0-based).
    batched : bool or None
        Accept a leading batch dimension on ``V`` (all members share ``F``); None: batched exactly when
        ``V`` has three axes.

    Returns
    -------
    V : float tensor, same shape, dtype and device as given (numpy input becomes a tensor without copy)
    F : (m, 3) int64 tensor on the device of ``V``

    Raises
    ------
    MeshError
        Wrong shapes or dtypes, non-triangle faces, empty meshes, indices negative or out of range,
        NaN or Inf coordinates. The message names the problem and what arrived.

    Examples
    --------
    >>> import torch
    >>> V, F = check_mesh(torch.eye(3, dtype=torch.float64), [[0, 1, 2]])
    >>> F.dtype
    torch.int64
    """
    V = _as_tensor(V, "V")
    F = _as_tensor(F, "F")
    if batched is None:
        batched = V.ndim == 3
    if not V.is_floating_point():
        raise MeshError(f"V must have a floating-point dtype, got {V.dtype} with shape {tuple(V.shape)}")
    want = "(B, n, 3)" if batched else "(n, 3)"
    if V.ndim != (3 if batched else 2) or V.shape[-1] != 3:
        raise MeshError(f"V must have shape {want}, got {tuple(V.shape)}")
    if F.dtype == torch.bool or F.is_floating_point() or F.is_complex():
        raise MeshError(f"F must have an integer dtype, got {F.dtype} with shape {tuple(F.shape)}")
    if F.ndim != 2:
        raise MeshError(f"F must have shape (m, 3), got {tuple(F.shape)}")
    if F.shape[1] != 3:
        raise MeshError(f"F must hold triangles, shape (m, 3); got faces with {F.shape[1]} corners, shape {tuple(F.shape)}")
    n = V.shape[-2]
    if n == 0:
        raise MeshError(f"mesh is empty: V has no vertices, shape {tuple(V.shape)}")
    if F.shape[0] == 0:
        raise MeshError(f"mesh is empty: F has no faces, shape {tuple(F.shape)}")
    if batched and V.shape[0] == 0:
        raise MeshError(f"batch is empty: V has shape {tuple(V.shape)}")
    key = (id(F), n)
    known = _CHECKED_FACES.get(key)
    if known is None or known[0] is not F or known[1] != F._version:  # a loop's F is checked once
        fmin, fmax = int(F.min()), int(F.max())
        if fmin < 0:
            raise MeshError(f"F holds a negative vertex index ({fmin}); indices must lie in [0, {n - 1}]")
        if fmax >= n:
            raise MeshError(f"F holds vertex index {fmax}, out of range for {n} vertices")
        _CHECKED_FACES[key] = (F, F._version)
        while len(_CHECKED_FACES) > 16:
            _CHECKED_FACES.popitem(last=False)
    bad = ~torch.isfinite(V)
    if bool(bad.any()):
        rows = bad.any(-1)
        first = tuple(rows.nonzero()[0].tolist())
        where = first[0] if len(first) == 1 else first
        kind = "NaN" if bool(torch.isnan(V).any()) else "Inf"
        raise MeshError(f"V holds {kind} coordinates ({int(rows.sum())} vertices, first at index {where})")
    F = F.to(device=V.device, dtype=torch.int64)
    return V, F


def numpy_mesh(V, F):
    """Validate a triangle mesh (see :func:`check_mesh`) and return it as contiguous numpy arrays for libigl.

    Returns
    -------
    V : (n, 3) float64 array
    F : (m, 3) int64 array
    """
    V, F = check_mesh(V, F)
    return np.ascontiguousarray(V.detach().cpu().double().numpy()), np.ascontiguousarray(F.cpu().numpy())


def load_mesh(path, *, dtype: torch.dtype = torch.float32, device=None):
    """Read a triangle mesh with trimesh (OBJ, PLY, OFF, STL and what else trimesh reads).

    Polygon faces are triangulated by trimesh; vertices are kept as stored (no merging or reordering).

    Parameters
    ----------
    path : str or os.PathLike
    dtype : torch.dtype
        Float dtype of the returned vertices (float32 by default).
    device : torch.device, optional
        Device of both returned tensors.

    Returns
    -------
    V : (n, 3) float tensor
        The vertices as stored, in ``dtype``.
    F : (m, 3) int64 tensor

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    MeshError
        The file is not a readable triangle mesh, or the mesh in it is invalid (see ``check_mesh``).
    """
    import trimesh  # deferred: importing trimesh takes about 0.35 s and only file I/O needs it

    path = Path(os.fspath(path))
    if not path.is_file():
        raise FileNotFoundError(f"mesh file not found: {path}")
    try:
        mesh = trimesh.load(str(path), force="mesh", process=False)
    except Exception as err:  # trimesh raises many types for unreadable files
        raise MeshError(f"could not read a mesh from {path}: {type(err).__name__}: {err}") from None
    if not isinstance(mesh, trimesh.Trimesh):
        raise MeshError(f"{path} does not hold a triangle mesh (trimesh returned {type(mesh).__name__})")
    V = np.asarray(mesh.vertices, dtype=np.float64)
    F = np.asarray(mesh.faces, dtype=np.int64)
    if V.size == 0 or F.size == 0:
        raise MeshError(f"{path} holds an empty mesh ({len(V)} vertices, {len(F)} faces)")
    try:
        V, F = check_mesh(V.reshape(-1, 3), F.reshape(-1, 3))
    except MeshError as err:
        raise MeshError(f"{path}: {err}") from None
    return V.to(dtype=dtype, device=device), F.to(device=device)


def save_mesh(path, V, F) -> None:
    """Write a triangle mesh with trimesh; the format follows the extension (.obj, .ply, .off, .stl).

    Parameters
    ----------
    path : str or os.PathLike
    V : (n, 3) float tensor or array
    F : (m, 3) integer tensor or array
    """
    import trimesh  # deferred, as in load_mesh

    V, F = check_mesh(V, F)
    path = Path(os.fspath(path))
    if path.suffix.lower() not in MESH_FORMATS:
        raise MeshError(f"unsupported mesh format {path.suffix!r} for {path}; use one of {', '.join(MESH_FORMATS)}")
    mesh = trimesh.Trimesh(
        vertices=V.detach().cpu().double().numpy(), faces=F.cpu().numpy(), process=False, validate=False
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    mesh.export(str(path))
