"""Mesh validation and file I/O: the boundary where user meshes become checked torch tensors."""

from __future__ import annotations

import math
import os
import re
import uuid
from collections import OrderedDict
from pathlib import Path

import numpy as np
import torch

from ._checks import all_finite, float_dtype
from .errors import MeshError
from .topology import same_faces

__all__ = ["check_mesh", "check_rest_pose", "array_as_tensor", "as_faces", "numpy_mesh", "remove_unreferenced", "cast_vertices", "load_mesh", "save_mesh", "MESH_FORMATS"]

MESH_FORMATS = (".obj", ".ply", ".off", ".stl")


def array_as_tensor(x, name):
    """``x`` as a tensor: a tensor as it is, a NumPy array without a copy (one with negative strides copied),
    a nested list as a CPU tensor; MeshError naming ``name`` otherwise, and for a tensor on torch's "meta"
    device, which holds shapes and no values (every check below read one, and failed inside torch)."""
    if isinstance(x, torch.Tensor):
        if x.is_meta:
            raise MeshError(f"{name} is a meta tensor (shape {tuple(x.shape)}, {x.dtype}): torch's 'meta' device "
                            "holds no values; give the mesh on the CPU or a GPU")
        return x
    if isinstance(x, np.ndarray):
        # a view with negative strides (F[:, ::-1], the usual way to turn faces over) needs a copy
        return torch.from_numpy(x if all(st >= 0 for st in x.strides) else np.ascontiguousarray(x))
    if isinstance(x, (list, tuple)):
        try:
            return torch.as_tensor(np.asarray(x), device="cpu")
        except (ValueError, TypeError) as err:
            raise MeshError(f"{name} must be a rectangular array, got a ragged {type(x).__name__}: {err}") from None
    raise MeshError(f"{name} must be a torch tensor or numpy array, got {type(x).__name__}")


# unsigned dtypes whose reductions torch does not implement (uint8 works): faces in them are converted to int64
_WIDE_UNSIGNED = (torch.uint16, torch.uint32, torch.uint64)


def _signed_faces(F: torch.Tensor) -> torch.Tensor:
    """``F`` of a wide unsigned dtype as int64; uint64 indices of 2**63 or more do not fit and are refused."""
    F64 = F.to(torch.int64)  # uint64 values from 2**63 wrap to negative numbers
    if F.dtype == torch.uint64 and F64.numel() and int(F64.min()) < 0:
        raise MeshError(f"F holds vertex index {int(F64.min()) + 2 ** 64} ({F.dtype}), too large for any mesh")
    return F64


# face arrays that passed the checks: (the source array, a copy of its values, its int64 tensor); a hit is the
# very array with the same faces (edits through .numpy() or .data included), and skips the checks and the
# conversion in loops
_CHECKED_FACES: "OrderedDict[tuple, tuple[object, torch.Tensor, torch.Tensor]]" = OrderedDict()


def check_mesh(V, F, *, batched: bool | None = False):
    """Validate a triangle mesh and return it as torch tensors.

    Parameters
    ----------
    V : (n, 3) float tensor or array, or (B, n, 3) when ``batched``
        Vertex positions. float32 and float64 are kept as they are; other float types (float16, bfloat16)
        are kept too, and meshmei's steps that go through numpy (KD-trees, libigl) read them in float32
        or float64.
    F : (m, 3) integer tensor or array
        Triangle indices into the vertices (0-based). Any signed or unsigned integer dtype; uint16, uint32
        and uint64 are converted to int64 before the checks.
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
        NaN or Inf coordinates, a tensor on torch's "meta" device (no values). The message names the problem
        and what arrived.

    Examples
    --------
    >>> import torch
    >>> V, F = check_mesh(torch.eye(3, dtype=torch.float64), [[0, 1, 2]])
    >>> F.dtype
    torch.int64
    """
    V = array_as_tensor(V, "V")
    source, F = F, array_as_tensor(F, "F")
    if batched is None:
        batched = V.ndim == 3
    if not V.is_floating_point():
        raise MeshError(f"V must have a floating-point dtype, got {V.dtype} with shape {tuple(V.shape)}")
    want = "(B, n, 3)" if batched else "(n, 3)"
    if V.ndim != (3 if batched else 2) or V.shape[-1] != 3:
        raise MeshError(f"V must have shape {want}, got {tuple(V.shape)}")
    n = V.shape[-2]
    # a loop passes the same face array each call: checked and converted once, and the same int64 tensor
    # handed back, so that the topology cache (keyed by that tensor) hits for int32 and numpy faces too
    # (a new tensor each call rebuilt the topology every call: about 150 ms at 20,000 faces)
    key = (id(source), n, V.device)
    known = _CHECKED_FACES.get(key)
    # the int64 tensor handed out may have been edited in place since (its indices then unchecked): compared too
    if known is not None and known[0] is source and same_faces(F, known[1]) and same_faces(known[2], known[3]):
        _CHECKED_FACES.move_to_end(key)
        F = known[2]
    else:
        G = _checked_faces(F, n).to(device=V.device, dtype=torch.int64)
        if isinstance(source, (torch.Tensor, np.ndarray)):  # a list is built anew each call: nothing to reuse
            _CHECKED_FACES[key] = (source, F.clone(), G, G.clone())
            while len(_CHECKED_FACES) > 16:
                _CHECKED_FACES.popitem(last=False)
        F = G
    if batched and V.shape[0] == 0:
        raise MeshError(f"batch is empty: V has shape {tuple(V.shape)}")
    if not all_finite(V):
        bad = ~torch.isfinite(V)
        rows = bad.any(-1)
        first = tuple(rows.nonzero()[0].tolist())
        where = first[0] if len(first) == 1 else first
        kind = "NaN" if bool(torch.isnan(V).any()) else "Inf"
        raise MeshError(f"V holds {kind} coordinates ({int(rows.sum())} vertices, first at index {where})")
    return V, F


def check_rest_pose(V0, V: torch.Tensor, F: torch.Tensor) -> torch.Tensor:
    """The rest pose ``V0`` of a checked mesh ``(V, F)``, checked as :func:`check_mesh` checks ``V`` (same
    number of vertices; batched like ``V`` or shared by its batch), as a tensor; errors name ``V0``."""
    V0 = array_as_tensor(V0, "V0")
    if V0.shape[-2:] != V.shape[-2:] or (V0.ndim == 3 and V.ndim == 3 and V0.shape[0] != V.shape[0]):
        raise MeshError(f"rest pose V0 of shape {tuple(V0.shape)} does not match V of shape {tuple(V.shape)}")
    if V0.ndim == 3 and V.ndim == 2:
        raise MeshError(f"a batched rest pose {tuple(V0.shape)} needs a batched V, got {tuple(V.shape)}")
    try:
        V0, _ = check_mesh(V0, F, batched=None)
    except MeshError as err:  # check_mesh speaks of V
        raise MeshError("rest pose: " + re.sub(r"\bV\b", "V0", str(err))) from None
    return V0


def as_faces(F) -> torch.Tensor:
    """A face array on its own (no vertices to check it against) as an int64 tensor: a tensor, array or
    nested list of any integer dtype, shape ``(m, 3)`` with ``m > 0`` and no negative index; MeshError
    otherwise (a float or bool array was truncated to indices before)."""
    F = array_as_tensor(F, "F")
    if F.dtype == torch.bool or F.is_floating_point() or F.is_complex():
        raise MeshError(f"F must have an integer dtype, got {F.dtype} with shape {tuple(F.shape)}")
    if F.dtype in _WIDE_UNSIGNED:
        F = _signed_faces(F)
    if F.ndim != 2 or F.shape[1] != 3 or F.shape[0] == 0:
        raise MeshError(f"F must be a non-empty (m, 3) integer array, got shape {tuple(F.shape)}")
    if int(F.min()) < 0:
        raise MeshError(f"F holds a negative vertex index ({int(F.min())})")
    return F.long()


def _checked_faces(F: torch.Tensor, n: int) -> torch.Tensor:
    """``F`` checked against ``n`` vertices (dtype, shape, emptiness, index range), in a signed dtype."""
    if F.dtype == torch.bool or F.is_floating_point() or F.is_complex():
        raise MeshError(f"F must have an integer dtype, got {F.dtype} with shape {tuple(F.shape)}")
    if F.dtype in _WIDE_UNSIGNED:
        F = _signed_faces(F)
    if F.ndim != 2:
        raise MeshError(f"F must have shape (m, 3), got {tuple(F.shape)}")
    if F.shape[1] != 3:
        raise MeshError(f"F must hold triangles, shape (m, 3); got faces with {F.shape[1]} corners, shape {tuple(F.shape)}")
    if n == 0:
        raise MeshError("mesh is empty: V has no vertices")
    if F.shape[0] == 0:
        raise MeshError(f"mesh is empty: F has no faces, shape {tuple(F.shape)}")
    fmin, fmax = int(F.min()), int(F.max())
    if fmin < 0:
        raise MeshError(f"F holds a negative vertex index ({fmin}); indices must lie in [0, {n - 1}]")
    if fmax >= n:
        raise MeshError(f"F holds vertex index {fmax}, out of range for {n} vertices")
    return F


def numpy_mesh(V, F):
    """Validate a triangle mesh (see :func:`check_mesh`) and return it as contiguous numpy arrays for libigl.

    Returns
    -------
    V : (n, 3) float64 array
    F : (m, 3) int64 array
    """
    V, F = check_mesh(V, F)
    return np.ascontiguousarray(V.detach().cpu().double().numpy()), np.ascontiguousarray(F.cpu().numpy())


def remove_unreferenced(V, F):
    """Drop the vertices no face uses and renumber the faces (libigl's ``remove_unreferenced``).

    Parameters
    ----------
    V : (n, 3) float tensor or array
    F : (m, 3) integer tensor or array

    Returns
    -------
    V : (k, 3) float tensor
        The vertices ``F`` uses, in their order; ``V`` itself (as :func:`check_mesh` returns it) when all are.
    F : (m, 3) int64 tensor
        The same faces, indexing the kept vertices.

    Examples
    --------
    >>> V, F = remove_unreferenced(torch.eye(4, 3, dtype=torch.float64), [[3, 1, 2]])
    >>> V.shape[0], F.tolist()
    (3, [[2, 0, 1]])
    """
    V, F = check_mesh(V, F)
    used = torch.unique(F)  # (k,) sorted
    if used.numel() == V.shape[0]:
        return V, F
    new_index = torch.full((V.shape[0],), -1, dtype=torch.int64, device=F.device)
    new_index[used] = torch.arange(used.numel(), device=F.device)
    return V[used], new_index[F]


def load_mesh(path, *, dtype: torch.dtype = torch.float32, device=None):
    """Read a triangle mesh with trimesh (OBJ, PLY, OFF, STL and what else trimesh reads).

    Polygon faces are triangulated by trimesh. Vertices at exactly the same position are welded into one
    (the first in file order keeps its place, later copies are removed and the faces renumbered): an STL
    file stores every triangle's corners separately, and an OBJ with texture coordinates or normals
    repeats a vertex along every seam, so without welding a closed surface would read as loose triangles
    with coincident copies. Where welding would join surfaces that only touch at a point (a non-manifold,
    bow-tie vertex: the teapot's handle tip on its body), each fan of faces keeps its own vertex, so such a
    mesh reads back as it was written. Nothing else changes: faces keep their order and orientation, zero-area and
    duplicate faces stay, and vertices no face uses are kept (except in OBJ files, whose reader, trimesh's,
    drops them).

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
        The distinct vertex positions in file order, in ``dtype``.
    F : (m, 3) int64 tensor

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    MeshError
        The file is not a readable triangle mesh (a point cloud, say), the mesh in it is invalid (see
        ``check_mesh``), or its coordinates do not fit in ``dtype``.

    Examples
    --------
    >>> import tempfile, trimesh
    >>> path = os.path.join(tempfile.mkdtemp(), "box.stl")
    >>> _ = trimesh.creation.box().export(path)  # STL: 12 triangles, 36 corners
    >>> V, F = load_mesh(path)
    >>> tuple(V.shape), tuple(F.shape)
    ((8, 3), (12, 3))
    """
    import trimesh  # deferred: importing trimesh takes about 0.35 s and only file I/O needs it

    dtype = float_dtype(dtype, error=MeshError)
    path = Path(os.fspath(path)).expanduser()  # as save_mesh, and as trimesh would
    if not path.is_file():
        raise FileNotFoundError(f"mesh file not found: {path}")
    if path.suffix.lower() == ".obj":
        _check_obj_indices(path)
    try:
        mesh = trimesh.load(str(path), force="mesh", process=False)
    except Exception as err:  # trimesh raises many types for unreadable files
        raise MeshError(f"could not read a mesh from {path}: {type(err).__name__}: {err}") from None
    if not isinstance(mesh, trimesh.Trimesh):
        raise MeshError(f"{path} does not hold a triangle mesh (trimesh returned {type(mesh).__name__})")
    V = np.asarray(mesh.vertices, dtype=np.float64)
    F = np.asarray(mesh.faces, dtype=np.int64)
    if F.size == 0:
        n_points = len(V) or _point_count(path)
        if n_points:
            raise MeshError(f"{path} holds {n_points} points and no faces; a triangle mesh is needed")
        raise MeshError(f"{path} holds an empty mesh (0 vertices, 0 faces)")
    if V.ndim != 2 or V.shape[1] != 3:  # an OBJ of 2-D vertices: reshape's own ValueError before
        raise MeshError(f"{path}: vertices must have 3 coordinates, got an array of shape {V.shape}")
    try:
        V, F = check_mesh(V, F.reshape(-1, 3))
    except MeshError as err:
        raise MeshError(f"{path}: {err}") from None
    V, F = _weld(V, F)
    return cast_vertices(V, dtype, str(path)).to(device=device), F.to(device=device)


# a face corner with an index of 0 ("0", "0/2", "1/0/1", "1//0"): OBJ counts from 1 (negative: from the end)
_OBJ_ZERO_INDEX = re.compile(rb"^f[ \t](?:[^\n]*[ \t/])?0(?=[/ \t\r\n]|$)", re.MULTILINE)


def _check_obj_indices(path: Path) -> None:
    """Refuse an OBJ whose faces use index 0 (of a vertex, texture coordinate or normal). trimesh reads it as
    -1, the last one: a file written with 0-based indices (a common exporter slip) came back as another,
    degenerate mesh without a word, and a texture index 0 turned a face into one point."""
    try:
        data = path.read_bytes()
    except OSError:
        return  # trimesh names the unreadable file
    hit = _OBJ_ZERO_INDEX.search(data)
    if hit is not None:
        line = data.count(b"\n", 0, hit.start()) + 1
        raise MeshError(f"{path}, line {line}: a face uses index 0; OBJ indices count from 1 (was the file written "
                        "with 0-based indices?)")


def _point_count(path: Path) -> int:
    """The number of points in a file that trimesh reads as a point cloud (0 for anything else)."""
    import trimesh

    try:
        cloud = trimesh.load(str(path), process=False)
    except Exception:  # the forced read already succeeded; this one only words the error
        return 0
    return len(cloud.vertices) if isinstance(cloud, trimesh.PointCloud) else 0


def _weld(V: torch.Tensor, F: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Merge vertices of exactly equal coordinates, keeping the first copy's place; faces are renumbered.

    Where the merge would make a non-manifold vertex (two pieces, or two sheets of one surface, that touch at a
    point: the teapot's handle tip on its body), each fan of faces around it keeps a vertex of its own, the
    first copy it used in the file: a file of such a mesh reads back as it was written."""
    Vn, Fn = V.numpy(), F.numpy()
    _, first, inverse = np.unique(Vn, axis=0, return_index=True, return_inverse=True)
    if len(first) == V.shape[0]:
        return V, F
    import igl  # deferred, as trimesh: only file I/O needs it here

    group = inverse.reshape(-1)  # welded position of every file vertex
    Fw = group[Fn]
    merged = np.bincount(group, minlength=len(first)) > 1
    ok = np.asarray(igl.is_vertex_manifold(np.ascontiguousarray(Fw)), dtype=bool).reshape(-1)
    if len(ok) < len(first):  # positions no face uses: manifold
        ok = np.concatenate([ok, np.ones(len(first) - len(ok), dtype=bool)])
    # each corner's key: its welded position, and at a merge that breaks manifoldness, its fan there
    fan = np.zeros(Fn.shape, dtype=np.int64)
    for b in np.nonzero(merged & ~ok)[0]:
        faces, corners = np.nonzero(Fw == b)
        parent = list(range(len(faces)))

        def root(i):
            while parent[i] != i:
                parent[i] = parent[parent[i]]
                i = parent[i]
            return i

        by_edge = {}
        for k, (f, c) in enumerate(zip(faces, corners)):
            for other in (Fw[f, (c + 1) % 3], Fw[f, (c + 2) % 3]):  # faces sharing an edge at b: one fan
                if other in by_edge:
                    parent[root(k)] = root(by_edge[other])
                else:
                    by_edge[other] = k
        fan[faces, corners] = [root(k) for k in range(len(faces))]
    # a vertex per key, placed at the first file vertex that any of its corners used (file order kept)
    keys = Fw * (3 * Fn.shape[0] + 1) + fan
    unique_keys, corner_key = np.unique(keys.reshape(-1), return_inverse=True)
    rep = np.full(len(unique_keys), np.iinfo(np.int64).max)
    np.minimum.at(rep, corner_key, Fn.reshape(-1))
    # positions no face uses keep their first copy
    unused = np.setdiff1d(np.arange(len(first)), np.unique(Fw))
    reps = np.concatenate([rep, first[unused]])
    order = np.argsort(reps, kind="stable")
    new_index = np.empty(len(reps), dtype=np.int64)
    new_index[order] = np.arange(len(reps))
    F_new = new_index[corner_key].reshape(Fn.shape)
    return V[torch.from_numpy(reps[order])], torch.from_numpy(F_new)


def cast_vertices(V: torch.Tensor, dtype: torch.dtype, where: str) -> torch.Tensor:
    """``V`` (finite) in ``dtype``, or a MeshError naming ``where`` when a coordinate overflows ``dtype`` or the
    mesh's extent underflows it (a mesh 1e-300 across came back as every vertex at 0, without a word)."""
    out = V.to(dtype)
    if not bool(torch.isfinite(out).all()):
        raise MeshError(f"{where}: coordinates up to {float(V.abs().max()):.3g} do not fit in {dtype} (largest "
                        f"{torch.finfo(dtype).max:.3g}); rescale the mesh or use float64")
    if out.dtype != V.dtype and len(V):
        extent = float((V.max(0).values - V.min(0).values).max())
        kept = float((out.double().max(0).values - out.double().min(0).values).max())
        if extent > 0 and not kept > 0.5 * extent:
            raise MeshError(f"{where}: the mesh is {extent:.3g} across, {float(V.abs().max()):.3g} from the origin at "
                            f"most: in {dtype} its vertices collapse (smallest normal {torch.finfo(dtype).tiny:.3g}, "
                            f"{torch.finfo(dtype).eps:.3g} relative spacing); rescale or centre it, or use float64")
    return out


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
    # '~' expanded here, as trimesh expands it: the partial file was made at the literal path and trimesh wrote
    # to the home folder, so the rename failed and a stray partial file was left there
    path = Path(os.fspath(path)).expanduser()
    if path.suffix.lower() not in MESH_FORMATS:
        raise MeshError(f"unsupported mesh format {path.suffix!r} for {path}; use one of {', '.join(MESH_FORMATS)}")
    Vd = V.detach().cpu().double()
    if path.suffix.lower() in (".ply", ".stl"):  # binary float32 coordinates: refused here, not misread later
        cast_vertices(Vd, torch.float32, f"{path} ({path.suffix.lower()[1:].upper()} stores float32; OBJ and OFF "
                      "keep every digit)")
    mesh = trimesh.Trimesh(vertices=Vd.numpy(), faces=F.cpu().numpy(), process=False, validate=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    # written beside it and renamed into place: an interrupted write leaves the old file or none, never a
    # truncated one (trimesh reads a cut OBJ or OFF as a smaller mesh, without a word)
    tmp = path.with_name(f".{path.stem}.partial-{uuid.uuid4().hex[:8]}{path.suffix}")
    kwargs = {}
    if path.suffix.lower() in (".obj", ".off"):
        # text at a fixed count of decimals (trimesh: 8 for OBJ, 10 for OFF), as many more as the mesh is smaller
        # than 1 across: a mesh 1e-9 across was written as one point and read back as every face [0, 0, 0]
        extent = float(np.ptp(mesh.vertices, axis=0).max()) if len(mesh.vertices) else 0.0
        base = 8 if path.suffix.lower() == ".obj" else 10
        kwargs["digits"] = base + (max(0, -math.floor(math.log10(extent))) if extent > 0 else 0)
    try:
        mesh.export(str(tmp), **kwargs)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
