"""Topology-only structures of a face array (unique edges, 1-ring adjacency), computed once and cached."""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from functools import cached_property

import torch

from .errors import MeshError

__all__ = ["MeshTopology", "mesh_topology"]


@dataclass(frozen=True, eq=False)
class MeshTopology:
    """Connectivity of a triangle mesh, independent of vertex positions.

    Attributes
    ----------
    n_vertices : int
    faces : (m, 3) int64 tensor
        The face array this was built from.
    edges : (E, 2) int64 tensor
        Unique undirected edges with ``edges[:, 0] < edges[:, 1]``, sorted lexicographically.
        Self-loops (a face repeating an index) are not edges and are left out.
    face_edges : (m, 3) int64 tensor
        ``face_edges[f, k]`` is the row of ``edges`` for the edge opposite corner ``k`` of face ``f``,
        i.e. between ``F[f, (k+1)%3]`` and ``F[f, (k+2)%3]``; -1 where that edge is a self-loop.
    nbr_ptr : (n + 1,) int64 tensor
        CSR row pointer of the 1-ring: the neighbours of vertex ``i`` are ``nbr_idx[nbr_ptr[i]:nbr_ptr[i+1]]``.
    nbr_src, nbr_idx : (2E,) int64 tensors
        Directed edges ``nbr_src[k] -> nbr_idx[k]``, sorted by source then target.
    degree : (n,) int64 tensor
        Number of distinct neighbours of each vertex (0 for unreferenced vertices).
    boundary_vertex : (n,) bool tensor
        True for vertices on an edge that only one face uses.
    """

    n_vertices: int
    faces: torch.Tensor
    edges: torch.Tensor
    face_edges: torch.Tensor
    nbr_ptr: torch.Tensor
    nbr_src: torch.Tensor
    nbr_idx: torch.Tensor
    degree: torch.Tensor
    boundary_vertex: torch.Tensor

    @property
    def n_edges(self) -> int:
        return int(self.edges.shape[0])

    @cached_property
    def cot_pattern(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Sparsity of the cotangent Laplacian: ``(indices (2, nnz), slot (12m,))``.

        ``indices`` are the coalesced (row-major sorted, unique) positions; ``slot`` sends the four
        contributions of each of the ``3m`` half-edges, in the order ``(a, b), (b, a), (a, a), (b, b)``
        blocked by kind, to their position, so assembly is one ``index_add`` with no sort per call.
        """
        F, n = self.faces, self.n_vertices
        a = F[:, [1, 2, 0]].reshape(-1)
        b = F[:, [2, 0, 1]].reshape(-1)
        rows = torch.cat([a, b, a, b])
        cols = torch.cat([b, a, a, b])
        uniq, slot = torch.unique(rows * n + cols, return_inverse=True)
        return torch.stack([uniq // n, uniq % n]), slot

    @cached_property
    def twins(self) -> torch.Tensor:
        """``(m, 3)`` int64: the half-edge ``3 g + l`` sharing edge ``(f, k)`` when exactly two faces do, else -1.

        Half-edge ``(f, k)`` is the edge opposite corner ``k``, from ``F[f, k+1]`` to ``F[f, k+2]``. The
        rasterizer finds the silhouette's edges with it.
        """
        fe = self.face_edges.reshape(-1)  # (3m,) edge id or -1
        E = self.n_edges
        key = torch.where(fe >= 0, fe, torch.full_like(fe, E))
        order = torch.argsort(key, stable=True)
        cnt = torch.bincount(key, minlength=E + 1)[:E]
        start = torch.cumsum(cnt, 0) - cnt
        two = (cnt == 2).nonzero().squeeze(1)
        h1, h2 = order[start[two]], order[start[two] + 1]
        twin = torch.full_like(fe, -1)
        twin[h1], twin[h2] = h2, h1
        return twin.view(-1, 3)

    @cached_property
    def corner_cycle(self) -> torch.Tensor:
        """``(m, 9)`` int64: each face's corners ``k``, then ``k + 1``, then ``k + 2`` (mod 3), ``k = 0, 1, 2``.

        Half-edge ``(f, k)`` runs from column ``3 + k`` to column ``6 + k``; the rasterizer gathers its
        per-corner screen coordinates in this order once instead of rolling them.
        """
        return self.faces[:, [0, 1, 2, 1, 2, 0, 2, 0, 1]].contiguous()

    @cached_property
    def edge_table(self) -> torch.Tensor:
        """``(m, 15)`` int64, five blocks of three columns, one per half-edge ``(f, k)``: its lower and higher
        vertex, the twin face's corner off the edge (the lower vertex where there is no twin), the twin
        face (-1 where none) and 1 where the half-edge runs from the higher vertex to the lower.

        What the rasterizer's silhouette pass needs of the topology, gathered with one row select per call.
        """
        F = self.faces
        a, b = F[:, [1, 2, 0]], F[:, [2, 0, 1]]
        lo, hi = torch.minimum(a, b), torch.maximum(a, b)
        twin = self.twins
        tf = torch.where(twin >= 0, twin // 3, torch.full_like(twin, -1))
        opp = torch.where(twin >= 0, F.reshape(-1)[twin.clamp_min(0)], lo)  # corner k of face f is half-edge 3 f + k's
        return torch.cat([lo, hi, opp, tf, (a > b).long()], 1).contiguous()

    def adjacency_list(self) -> list[list[int]]:
        """Sorted neighbour lists, one per vertex (as ``igl.adjacency_list`` gives them, up to order)."""
        ptr = self.nbr_ptr.tolist()
        idx = self.nbr_idx.tolist()
        return [idx[ptr[i]:ptr[i + 1]] for i in range(self.n_vertices)]


def _build(F: torch.Tensor, n: int) -> MeshTopology:
    device = F.device
    m = F.shape[0]
    # half-edge opposite corner k joins corners k+1 and k+2
    a = F[:, [1, 2, 0]].reshape(-1)  # (3m,)
    b = F[:, [2, 0, 1]].reshape(-1)
    lo, hi = torch.minimum(a, b), torch.maximum(a, b)
    key = lo * n + hi  # (3m,)
    valid = lo != hi
    uniq, inv = torch.unique(key[valid], return_inverse=True)  # sorted keys -> lexicographic edges
    edges = torch.stack([uniq // n, uniq % n], dim=1)
    face_edges = torch.full((3 * m,), -1, dtype=torch.int64, device=device)
    face_edges[valid] = inv
    face_edges = face_edges.view(m, 3)

    src = torch.cat([edges[:, 0], edges[:, 1]])
    dst = torch.cat([edges[:, 1], edges[:, 0]])
    order = torch.argsort(src * n + dst)
    src, dst = src[order], dst[order]
    degree = torch.bincount(src, minlength=n)
    ptr = torch.zeros(n + 1, dtype=torch.int64, device=device)
    ptr[1:] = torch.cumsum(degree, 0)
    uses = torch.bincount(inv, minlength=edges.shape[0])  # faces per edge
    boundary = torch.zeros(n, dtype=torch.bool, device=device)
    boundary[edges[uses == 1].reshape(-1)] = True
    return MeshTopology(n, F, edges, face_edges, ptr, src, dst, degree, boundary)


_CACHE: "OrderedDict[tuple, tuple[torch.Tensor, torch.Tensor, MeshTopology]]" = OrderedDict()
_CACHE_SIZE = 16


def same_faces(F: torch.Tensor, known: torch.Tensor) -> bool:
    """Whether ``F`` still holds the faces of ``known``, a copy taken when it was checked or cached.

    A face cache keyed by the tensor alone, or by torch's in-place version counter, misses an edit made
    through ``F.numpy()`` or ``F.data`` (which leave the counter alone) and would serve a stale topology
    (an IndexError or a silently wrong image later); comparing the values does not.
    """
    return torch.equal(F, known)  # False for another shape too


def mesh_topology(F: torch.Tensor, n_vertices: int | None = None) -> MeshTopology:
    """Topology of a face array, cached so optimisation loops build it once.

    The cache holds the face tensor itself and a copy of its values, so a hit means the very same tensor
    with the same faces, even when they were edited in place behind torch's version counter (through
    ``.numpy()`` or ``.data``); anything else is rebuilt (and at most 16 entries are kept). The comparison
    costs about 3 us for 1,000 faces and 26 us for 20,000.

    Parameters
    ----------
    F : (m, 3) int64 tensor
    n_vertices : int, optional
        Number of vertices (unreferenced trailing vertices count); defaults to ``F.max() + 1``.

    Raises
    ------
    MeshError
        ``F`` is not a non-empty ``(m, 3)`` int64 (or int32) tensor, or holds an index outside
        ``[0, n_vertices)``.
    """
    if not isinstance(F, torch.Tensor) or F.dtype not in (torch.int64, torch.int32):
        got = f"{F.dtype} tensor" if isinstance(F, torch.Tensor) else type(F).__name__
        raise MeshError(f"F must be an (m, 3) int64 tensor, got a {got}")
    if F.ndim != 2 or F.shape[1] != 3 or F.shape[0] == 0:
        raise MeshError(f"F must be a non-empty (m, 3) int64 tensor, got shape {tuple(F.shape)}")
    n = int(F.max()) + 1 if n_vertices is None else int(n_vertices)
    key = (id(F), n)
    hit = _CACHE.get(key)
    if hit is not None and hit[0] is F and same_faces(F, hit[1]):
        _CACHE.move_to_end(key)
        return hit[2]
    # checked on a miss only: a hit is the very tensor that passed, unmodified
    fmin, fmax = int(F.min()), (n - 1 if n_vertices is None else int(F.max()))
    if fmin < 0:
        raise MeshError(f"F holds a negative vertex index ({fmin}); indices must lie in [0, {n - 1}]")
    if fmax >= n:
        raise MeshError(f"F holds vertex index {fmax}, out of range for n_vertices={n}")
    topo = _build(F.long(), n)  # int32 faces: edge keys lo * n + hi overflow int32 from n = 46,341 on
    _CACHE[key] = (F, F.clone(), topo)
    _CACHE.move_to_end(key)
    while len(_CACHE) > _CACHE_SIZE:
        _CACHE.popitem(last=False)
    return topo
