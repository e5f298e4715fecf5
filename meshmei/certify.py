"""A proof, cheaper than the exact test, that a disc-shaped mesh does not intersect itself: it is the graph
of a function over a plane.

Project the mesh along a direction ``d`` onto the plane perpendicular to it. If

1. every face projects with positive orientation (its unit normal has ``n . d > 0``),
2. at every interior vertex the projected corner angles sum to one full turn (the fan wraps once), and at
   every boundary vertex to less than one,
3. the projected boundary loop is a simple polygon (boundary edges that share no vertex keep apart),

then the projection is a local homeomorphism of the disc that is one-to-one on its boundary, hence one-to-one
everywhere (the number of preimages of a point is the winding number of the boundary's image around it, 0
or 1). Two faces that shared a point other than their common vertices and edges would project to the same
point twice, so the mesh has no self-intersection, and libigl's exact test would find none.

Each rule is checked in float64 with a margin far above rounding (orientation ``n . d > 1e-9``, boundary
edges further apart than ``1e-9`` of the projected extent), so a case too close to call fails the
certificate and goes to the exact test. A failed certificate says nothing: the mesh may still be clean.

Cost: one projection, an angle per corner and the distances between pairs of boundary edges, O(m + b^2)
for b boundary edges (about 0.13 ms for the 3D-MEI's 400-vertex sheet, against about 1.5 ms for libigl's
test). :class:`~meshmei.validity.StepGuard` uses it for starts it applies to (the 3D-MEI's sheet) and
falls back to libigl when it fails.

:class:`StarCertificate` does the same for closed meshes by central projection onto a sphere about the
vertices' centroid ``c`` (the 3D-MEI's sphere start). If

1. every face has ``n . (a - c) > 0`` along a corner ``a`` (``c`` lies strictly inside every face's plane,
   so each face maps to a proper spherical triangle, orientation kept), and
2. at every vertex the spherical corner angles sum to one full turn,

then the radial map of the (connected, closed, consistently oriented) mesh onto the sphere is a local
homeomorphism, hence a covering of the sphere, hence one-to-one (the sphere is simply connected); two faces
that met elsewhere than at a shared vertex or edge would lie on one ray. The spherical corner angle at
``v`` between its neighbours ``a`` and ``b`` is the angle between ``a - v`` and ``b - v`` projected onto
the plane perpendicular to ``v - c`` (the directions of the great circles leaving ``v``), so both rules are
a few vector operations per face and corner.

:class:`SeparationCertificate` needs no particular shape: it proves a *step* clean from the last clean
mesh, the contact barrier's distances there and the step's length, and hands libigl only the faces it
cannot clear (see the class). It is what makes the guard affordable at 10k vertices, where libigl's test
costs 40 ms a check.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from . import native
from ._checks import all_finite
from .contact import pair_distance_bounds
from .errors import MeshError
from .mesh import array_as_tensor
from .metrics import face_components
from .quality import edge_use
from .topology import mesh_topology

__all__ = ["GraphCertificate", "StarCertificate", "SeparationCertificate"]

ORIENTATION_MARGIN = 1e-9  # smallest n . d of a face counted as facing along d
SEPARATION_MARGIN = 1e-9  # smallest distance of two boundary edges, as a share of the projected extent


class GraphCertificate:
    """Checks that a mesh with the faces ``F`` of a disc is the graph of a function over the plane
    perpendicular to ``direction`` (see the module docstring for the proof).

    Parameters
    ----------
    F : (m, 3) int64 tensor
        Faces of a topological disc, consistently oriented (use :meth:`for_start`, which checks).
    direction : (3,) float tensor
        The projection direction ``d``.
    n_vertices : int

    Attributes
    ----------
    direction : (3,) float64 tensor
        ``d``, unit length.
    """

    def __init__(self, F: torch.Tensor, direction: torch.Tensor, n_vertices: int):
        F = _faces(F)
        d = torch.as_tensor(direction, dtype=torch.float64, device="cpu")
        if d.shape != (3,) or not 0 < float(d.norm()) < math.inf:
            raise MeshError(f"direction must be a finite, non-zero 3-vector, got {d.tolist()}")  # NaN basis before
        d = d / d.norm()
        a = torch.tensor([1.0, 0.0, 0.0] if abs(float(d[0])) < 0.9 else [0.0, 1.0, 0.0], dtype=torch.float64,
                         device="cpu")
        u = a - (a @ d) * d
        u = u / u.norm()
        self.direction = d
        basis = torch.stack([u, torch.linalg.cross(d, u)])  # (2, 3): u x w = d, so n . d > 0 is counter-clockwise
        topo = mesh_topology(F, n_vertices)
        used = torch.zeros(n_vertices, dtype=torch.bool, device="cpu")
        used[F.reshape(-1)] = True
        seg = _boundary_segments(F, topo)  # (b, 2)
        i, j = torch.triu_indices(len(seg), len(seg), 1, device="cpu")
        apart = (seg[i][:, :, None] != seg[j][:, None, :]).all(-1).all(-1)  # share no vertex
        i, j = i[apart], j[apart]
        # numpy arrays for holds()
        self._d, self._basis_t = d.numpy(), basis.T.numpy()
        self._corner = F.reshape(-1).numpy()
        self._next, self._prev = F.roll(-1, 1).reshape(-1).numpy(), F.roll(1, 1).reshape(-1).numpy()
        self._interior, self._boundary = (used & ~topo.boundary_vertex).numpy(), (used & topo.boundary_vertex).numpy()
        sn = seg.numpy()
        self._pairs = tuple(np.ascontiguousarray(a, dtype=np.int64)
                            for a in (sn[i.numpy(), 0], sn[i.numpy(), 1], sn[j.numpy(), 0], sn[j.numpy(), 1]))
        # for the compiled check: faces, each vertex's kind (0 no face, 1 interior, 2 boundary), the basis rows
        self._F = np.ascontiguousarray(F.numpy(), dtype=np.int64)
        self._n_vertices = n_vertices
        self._kind = (self._interior.astype(np.uint8) + 2 * self._boundary.astype(np.uint8))
        self._u, self._w = np.ascontiguousarray(basis[0].numpy()), np.ascontiguousarray(basis[1].numpy())

    @classmethod
    def for_start(cls, V0: torch.Tensor, F: torch.Tensor, normals: torch.Tensor, *,
                  min_cos: float = 0.5) -> "GraphCertificate | None":
        """A certificate for the start ``(V0, F)`` with unit face ``normals``, or None when it does not apply:
        the mesh is not a consistently oriented topological disc (connected, one boundary loop, Euler
        characteristic 1, no edge used by more than two faces), or some face turns more than
        ``acos(min_cos)`` from the faces' mean normal, the projection direction."""
        V0, F, normals = _double(V0), _faces(F), _double(normals)
        n = V0.shape[0]
        boundary_edges, nonmanifold = edge_use(F)
        if nonmanifold or not boundary_edges:
            return None
        if not _consistently_oriented(F):
            return None
        topo = mesh_topology(F, n)
        used = int(torch.unique(F).numel())
        if used - topo.n_edges + F.shape[0] != 1 or not _one_boundary_loop(F, topo) or not _connected(F, n):
            return None
        d = normals.sum(0)
        if not float(d.norm()) > 0:
            return None
        d = d / d.norm()
        if float((normals.to(d.dtype) @ d).min()) < min_cos:
            return None
        return cls(F, d, n)

    def holds(self, V: torch.Tensor, normals: torch.Tensor, compiled: bool | None = None) -> bool:
        """Whether ``V`` ``(n, 3)`` with its unit face ``normals`` ``(m, 3)`` is proven free of
        self-intersections (False: not proven; the mesh may still be clean). Checked in float64 on the CPU,
        whatever the inputs' device: compiled where the kernels are built (``meshmei/_contact.c``, the same
        rules with rough angles at interior vertices: 0.08 against 0.17 ms a call on the 3D-MEI's sheet),
        else in NumPy (on arrays this size its per-operation cost is a fraction of torch's); pass float64
        normals, or the margins may fail on rounding."""
        normals, V = _double(normals), _double(V)
        if not _proper_input(V, normals, self._n_vertices, len(self._F), exact=True):
            return False
        if native.enabled() if compiled is None else compiled:
            Vn, Nn = np.ascontiguousarray(V.numpy()), np.ascontiguousarray(normals.numpy())
            work = np.empty(3 * len(Vn))
            a0, a1, b0, b1 = self._pairs
            return bool(native.library().graph_holds(
                len(Vn), Vn.ctypes.data, len(self._F), self._F.ctypes.data, Nn.ctypes.data, self._d.ctypes.data,
                self._u.ctypes.data, self._w.ctypes.data, self._kind.ctypes.data, len(a0), a0.ctypes.data,
                a1.ctypes.data, b0.ctypes.data, b1.ctypes.data, ORIENTATION_MARGIN, SEPARATION_MARGIN,
                work.ctypes.data))
        if float((normals.numpy() @ self._d).min()) <= ORIENTATION_MARGIN:
            return False
        P = V.numpy() @ self._basis_t  # (n, 2)
        x, y = np.ascontiguousarray(P[:, 0]), np.ascontiguousarray(P[:, 1])
        xc, yc = x[self._corner], y[self._corner]
        x1, y1, x2, y2 = x[self._next] - xc, y[self._next] - yc, x[self._prev] - xc, y[self._prev] - yc
        angle = np.arctan2(x1 * y2 - y1 * x2, x1 * x2 + y1 * y2)
        turn = np.bincount(self._corner, weights=angle, minlength=P.shape[0])
        if (np.abs(turn[self._interior] - 2 * math.pi) > 1e-6).any():
            return False  # an interior fan that wraps twice (or rounding we do not trust)
        if (turn[self._boundary] >= 2 * math.pi - 1e-9).any():
            return False
        if len(self._pairs[0]):
            tol = SEPARATION_MARGIN * float(np.hypot(x.max() - x.min(), y.max() - y.min()))
            if _segments_closer_than(x, y, *self._pairs, tol):
                return False
        return True


class StarCertificate:
    """Checks that a closed mesh is star-shaped about its vertices' centroid: its central projection onto a
    sphere is one-to-one (see the module docstring for the proof), so it does not intersect itself.

    Parameters
    ----------
    F : (m, 3) int64 tensor
        Faces of a connected, closed, consistently oriented mesh (use :meth:`for_start`, which checks).
    """

    def __init__(self, F: torch.Tensor):
        F = _faces(F)
        self._first = F[:, 0].numpy()
        self._corner = F.reshape(-1).numpy()
        self._next, self._prev = F.roll(-1, 1).reshape(-1).numpy(), F.roll(1, 1).reshape(-1).numpy()
        self._used = np.unique(self._corner)
        self._F = np.ascontiguousarray(F.numpy(), dtype=np.int64)  # for the compiled check
        self._least = int(self._used[-1]) + 1 if len(self._used) else 0  # rows V must have
        self._masks = {}  # the compiled check's used-vertex flags, by vertex count (made once: it runs every step)

    @classmethod
    def for_start(cls, V0: torch.Tensor, F: torch.Tensor, normals: torch.Tensor) -> "StarCertificate | None":
        """A certificate for the start ``(V0, F)`` with unit face ``normals``, or None when it does not apply:
        the mesh is not connected, closed (every edge used by two faces) and consistently oriented with
        outward normals, or the start itself is not star-shaped about its centroid."""
        V0, F, normals = _double(V0), _faces(F), _double(normals)
        boundary_edges, nonmanifold = edge_use(F)
        if boundary_edges or nonmanifold or not _consistently_oriented(F) or not _connected(F, V0.shape[0]):
            return None
        cert = cls(F)
        return cert if cert.holds(V0, normals) else None

    def holds(self, V: torch.Tensor, normals: torch.Tensor, compiled: bool | None = None) -> bool:
        """Whether ``V`` ``(n, 3)`` with its unit face ``normals`` ``(m, 3)`` is proven free of
        self-intersections (False: not proven; the mesh may still be clean). Checked in float64 on the CPU,
        whatever the inputs' device: compiled where the kernels are built (``meshmei/_contact.c``, the same
        rules with rough angles: 0.07 against 0.22 ms a call on the 3D-MEI's sphere), else coordinate by
        coordinate in NumPy."""
        V, normals = _double(V), _double(normals)
        if not _proper_input(V, normals, self._least, len(self._F)):
            return False
        Vn = V.numpy()
        if native.enabled() if compiled is None else compiled:
            Vn = np.ascontiguousarray(Vn)
            N = np.ascontiguousarray(normals.numpy())
            used = self._masks.get(len(Vn))
            if used is None:
                used = self._masks[len(Vn)] = np.zeros(len(Vn), dtype=np.uint8)
                used[self._used] = 1
            work = np.empty(4 * len(Vn))
            return bool(native.library().star_holds(len(Vn), Vn.ctypes.data, len(self._F), self._F.ctypes.data,
                                                    N.ctypes.data, used.ctypes.data, ORIENTATION_MARGIN,
                                                    work.ctypes.data))
        x, y, z = (np.ascontiguousarray(Vn[:, k] - Vn[self._used, k].mean()) for k in range(3))  # from c
        N = normals.numpy()
        f = self._first
        ax, ay, az = x[f], y[f], z[f]
        if not (N[:, 0] * ax + N[:, 1] * ay + N[:, 2] * az > ORIENTATION_MARGIN * np.sqrt(ax * ax + ay * ay + az * az)).all():
            return False  # c on or outside some face's plane
        c, nx, pv = self._corner, self._next, self._prev
        rx, ry, rz = x[c], y[c], z[c]
        x1, y1, z1 = x[nx] - rx, y[nx] - ry, z[nx] - rz
        x2, y2, z2 = x[pv] - rx, y[pv] - ry, z[pv] - rz
        # with r = (v - c) unscaled: the sine term scales by |r|, the cosine term's correction by |r|^2
        r2 = np.maximum(rx * rx + ry * ry + rz * rz, np.finfo(float).tiny)
        sine = (rx * (y1 * z2 - z1 * y2) + ry * (z1 * x2 - x1 * z2) + rz * (x1 * y2 - y1 * x2)) / np.sqrt(r2)
        cosine = x1 * x2 + y1 * y2 + z1 * z2 - (rx * x1 + ry * y1 + rz * z1) * (rx * x2 + ry * y2 + rz * z2) / r2
        turn = np.bincount(c, weights=np.arctan2(sine, cosine), minlength=len(x))
        return bool((np.abs(turn[self._used] - 2 * math.pi) <= 1e-6).all())


def _double(x) -> torch.Tensor:
    """Vertices or normals, a tensor or a NumPy array (an AttributeError before), as float64 on the CPU."""
    if not isinstance(x, (torch.Tensor, np.ndarray)):
        raise MeshError(f"vertices and normals must be tensors or NumPy arrays, got {type(x).__name__}")
    return array_as_tensor(x, "V").detach().cpu().double()


def _faces(F) -> torch.Tensor:
    if not isinstance(F, (torch.Tensor, np.ndarray)):
        raise MeshError(f"faces must be a tensor or a NumPy array, got {type(F).__name__}")
    return array_as_tensor(F, "F").cpu().long()


def _proper_input(V: torch.Tensor, normals: torch.Tensor, n: int, m: int, exact: bool = False) -> bool:
    """MeshError unless ``V`` is ``(n, 3)`` (at least ``n`` rows unless ``exact``) and ``normals`` ``(m, 3)``:
    the compiled checks index them by the certificate's faces, and a shorter array was read (and its work
    buffer written) past its end. False where either holds NaN or Inf: nothing is proven (every rule is
    'fail if above', which NaN never is)."""
    rows_ok = V.shape[0] == n if exact else V.shape[0] >= n
    if V.ndim != 2 or V.shape[1] != 3 or not rows_ok:
        raise MeshError(f"V must have shape ({n}{'' if exact else ' or more'}, 3) for the certificate's faces, got "
                        f"{tuple(V.shape)}")
    if tuple(normals.shape) != (m, 3):
        raise MeshError(f"normals must have shape ({m}, 3), one per face, got {tuple(normals.shape)}")
    return all_finite(V) and all_finite(normals)  # one reduction each: this runs at every guarded step


def _segments_closer_than(x: np.ndarray, y: np.ndarray, a0, a1, b0, b1, tol: float) -> bool:
    """Whether some pair of 2D segments ``(a0, a1)``, ``(b0, b1)`` (indices into the coordinates ``x, y``)
    crosses or comes within ``tol``. Pairs whose boxes are more than ``tol`` apart are dropped first."""
    xa0, xa1, xb0, xb1 = x[a0], x[a1], x[b0], x[b1]
    ya0, ya1, yb0, yb1 = y[a0], y[a1], y[b0], y[b1]
    near = ((np.minimum(xa0, xa1) <= np.maximum(xb0, xb1) + tol) & (np.minimum(xb0, xb1) <= np.maximum(xa0, xa1) + tol)
            & (np.minimum(ya0, ya1) <= np.maximum(yb0, yb1) + tol) & (np.minimum(yb0, yb1) <= np.maximum(ya0, ya1) + tol))
    if not near.any():
        return False
    A0 = np.stack([xa0[near], ya0[near]], 1)
    A1 = np.stack([xa1[near], ya1[near]], 1)
    B0 = np.stack([xb0[near], yb0[near]], 1)
    B1 = np.stack([xb1[near], yb1[near]], 1)

    def orient(p, q, r):
        return (q[:, 0] - p[:, 0]) * (r[:, 1] - p[:, 1]) - (q[:, 1] - p[:, 1]) * (r[:, 0] - p[:, 0])

    if ((orient(A0, A1, B0) * orient(A0, A1, B1) < 0) & (orient(B0, B1, A0) * orient(B0, B1, A1) < 0)).any():
        return True  # a proper crossing

    def point_segment_sq(p, q, r):  # from p to segment q r
        d = r - q
        t = np.clip(((p - q) * d).sum(1) / np.maximum((d * d).sum(1), np.finfo(float).tiny), 0.0, 1.0)
        e = q + d * t[:, None] - p
        return (e * e).sum(1)

    closest = min(point_segment_sq(A0, B0, B1).min(), point_segment_sq(A1, B0, B1).min(),
                  point_segment_sq(B0, A0, A1).min(), point_segment_sq(B1, A0, A1).min())
    return bool(closest <= tol * tol)


def _consistently_oriented(F: torch.Tensor) -> bool:
    """Whether no directed edge occurs twice (two faces sharing an edge run it in opposite directions)."""
    Fn = F.cpu().numpy().astype(np.int64)
    n = int(Fn.max(initial=-1)) + 1
    directed = (Fn * n + np.roll(Fn, -1, 1)).reshape(-1)  # one integer key per directed edge (dim=0 unique: slow)
    return len(np.unique(directed)) == len(directed)


def _boundary_segments(F: torch.Tensor, topo) -> torch.Tensor:
    """``(b, 2)``: the boundary edges as directed in their faces (half-edge ``(f, k)`` runs from
    ``F[f, k + 1]`` to ``F[f, k + 2]``)."""
    half = (topo.twins == -1).reshape(-1)
    return torch.stack([F.roll(-1, 1).reshape(-1), F.roll(1, 1).reshape(-1)], 1)[half]


def _one_boundary_loop(F: torch.Tensor, topo) -> bool:
    """Whether the boundary edges form a single cycle (every boundary vertex on exactly two of them)."""
    seg = _boundary_segments(F, topo)
    if not len(seg):
        return False
    deg = torch.bincount(seg.reshape(-1), minlength=topo.n_vertices)
    if bool((deg[deg > 0] != 2).any()):
        return False
    succ = dict(zip(seg[:, 0].tolist(), seg[:, 1].tolist()))  # consistently oriented: each vertex starts one edge
    if len(succ) != len(seg):
        return False
    start = next(iter(succ))
    v, steps = succ[start], 1
    while v != start and steps <= len(seg):
        v, steps = succ[v], steps + 1
    return steps == len(seg)


def _connected(F: torch.Tensor, n: int) -> bool:
    """Whether the faces form one connected piece (over shared vertices)."""
    labels = face_components(F, n)
    return len(labels) > 0 and int(labels.max()) == 0


class SeparationCertificate:
    """Proves a step clean from the last clean mesh, the contact barrier's distances and the step's length,
    leaving libigl's exact test only the faces it cannot clear (usually none).

    Let ``V0`` be the last accepted mesh (no intersecting pair) and ``V1`` the candidate, every vertex moved
    at most ``s``; every point of a face then moved at most ``s`` (a convex combination of its corners).

    1. Two faces sharing no vertex are disjoint in ``V0``, so their distance is the least of their six
       (vertex, face) and nine (edge, edge) distances. If that is more than ``2 s``, they are still apart
       in ``V1``. The contact barrier's last call, at ``V0`` (:meth:`~meshmei.contact.ContactBarrier.separation`),
       kept every such pair found within its search's reach and bounds the others (that reach less twice
       the farthest move since the search); a pair closer
       than ``2 s`` puts its faces (the face, and every face around the vertex; the faces of both edges) on
       the list for the exact test.
    2. Faces that share a vertex ``v`` both lie in ``v``'s star. Project the star onto the plane
       perpendicular to ``v``'s area-weighted normal: if every face projects with positive orientation and
       the corner angles at ``v`` sum to one turn (an interior vertex) or less (a boundary vertex), the star
       is a fan that wraps once, one-to-one in projection, so its faces meet only along their shared edges.
       A vertex where this fails puts its star on the list.

    The exact test then runs on the listed faces alone (libigl, the same vertices): together with 1 and 2 its
    verdict is the whole mesh's. Margins: the step's length and the distances in float64 with a relative
    1e-9, near-parallel edges counted as touching (:func:`~meshmei.contact.pair_distance_bounds`), the
    barrier's bound less 1e-5 of its reach; orientation ``n . N > 1e-9 |n| |N|``; the angle sums within
    1e-6 of one turn. It needs edge pairs in the barrier (two faces can pierce each other with every vertex
    far from the other's face) and a mesh whose every vertex has one fan of consistently oriented faces
    (:meth:`for_mesh`).

    Cost: the barrier's distances are already known; what is added is the handed-out pairs' distances
    again in float64, an angle per corner, and libigl's test on the listed faces (O(faces)).
    """

    def __init__(self, F: torch.Tensor, n_vertices: int):
        F = F.cpu()
        topo = mesh_topology(F, n_vertices)
        self.F = np.ascontiguousarray(F.numpy())
        self.E = np.ascontiguousarray(topo.edges.numpy())
        self._corner = F.reshape(-1).numpy()
        self._next, self._prev = F.roll(-1, 1).reshape(-1).numpy(), F.roll(1, 1).reshape(-1).numpy()
        self._face_of_corner = np.repeat(np.arange(len(self.F)), 3)
        used = np.zeros(n_vertices, dtype=bool)
        used[self._corner] = True
        self._interior = used & ~topo.boundary_vertex.numpy()
        self._boundary = used & topo.boundary_vertex.numpy()
        self._boundary_u8 = np.ascontiguousarray(self._boundary, dtype=np.uint8)
        self.n_vertices = n_vertices
        # each edge's faces (at most two)
        fe = topo.face_edges.numpy().reshape(-1)
        h = np.nonzero(fe >= 0)[0]
        order = np.argsort(fe[h], kind="stable")
        e, h = fe[h][order], h[order]
        first = np.ones(len(e), dtype=bool)
        first[1:] = e[1:] != e[:-1]
        self._edge_faces = np.full((len(self.E), 2), -1, dtype=np.int64)
        self._edge_faces[e[first], 0] = h[first] // 3
        self._edge_faces[e[~first], 1] = h[~first] // 3  # an edge-manifold mesh (for_mesh): at most two faces

    @classmethod
    def for_mesh(cls, F: torch.Tensor, n_vertices: int) -> "SeparationCertificate | None":
        """The certificate for faces ``F``, or None where it does not apply: faces not consistently oriented, an
        edge of more than two faces, or a vertex whose faces form more than one fan (two cones touching at
        their tips)."""
        F = F.cpu()
        if not _consistently_oriented(F):
            return None
        # no edge in more than two faces' sides (stricter than edge_use, which counts a degenerate face's
        # repeated side once: the edge-to-faces table holds two faces per edge)
        fe = mesh_topology(F, n_vertices).face_edges.reshape(-1)
        if bool((torch.bincount(fe[fe >= 0]) > 2).any()) or not _one_fan_per_vertex(F, n_vertices):
            return None
        return cls(F, n_vertices)

    def _star(self, vertices: np.ndarray) -> np.ndarray:
        """The faces around ``vertices``."""
        if not len(vertices):
            return np.zeros(0, dtype=np.int64)
        mask = np.zeros(self.n_vertices, dtype=bool)
        mask[vertices] = True
        return np.nonzero(mask[self.F].any(1))[0]

    def unfolded(self, V: np.ndarray, compiled: bool | None = None) -> np.ndarray:
        """``(n,)`` bool: the vertices whose star is proven a fan that wraps once (rule 2), float64 ``V``
        (compiled where the kernels are built: the same rule, about 20 times faster at 10k vertices)."""
        V = np.asarray(V.detach().cpu() if isinstance(V, torch.Tensor) else V, dtype=np.float64)
        if V.shape != (self.n_vertices, 3):  # the kernel reads n_vertices rows: a shorter V was read past its end
            raise MeshError(f"V must have shape ({self.n_vertices}, 3), the certificate's mesh; got {V.shape}")
        if not np.isfinite(V).all():
            return np.zeros(self.n_vertices, dtype=bool)  # nothing proven (NaN passes every 'fail if above')
        if native.enabled() if compiled is None else compiled:
            V = np.ascontiguousarray(V, dtype=np.float64)
            ok = np.empty(self.n_vertices, dtype=np.uint8)
            work = np.empty(4 * self.n_vertices)
            native.library().separation_fans(self.n_vertices, V.ctypes.data, len(self.F), self.F.ctypes.data,
                                             self._boundary_u8.ctypes.data, work.ctypes.data, ok.ctypes.data)
            return ok.astype(bool)
        A, B, C = V[self.F[:, 0]], V[self.F[:, 1]], V[self.F[:, 2]]
        N = np.cross(B - A, C - A)  # (m, 3), twice the area long
        n = np.stack([np.bincount(self._corner, weights=np.repeat(N[:, k], 3), minlength=self.n_vertices)
                      for k in range(3)], 1)
        nc = n[self._corner]  # (3m, 3): the vertex normal at each corner
        Nc = N[self._face_of_corner]
        nn = np.sqrt((nc * nc).sum(1))
        orient = (nc * Nc).sum(1)
        good = orient > ORIENTATION_MARGIN * nn * np.sqrt((Nc * Nc).sum(1))
        x1, x2 = V[self._next] - V[self._corner], V[self._prev] - V[self._corner]
        n2 = np.maximum(nn * nn, np.finfo(float).tiny)
        sine = orient / np.maximum(nn, np.finfo(float).tiny)
        cosine = (x1 * x2).sum(1) - (nc * x1).sum(1) * (nc * x2).sum(1) / n2
        turn = np.bincount(self._corner, weights=np.arctan2(sine, cosine), minlength=self.n_vertices)
        bad_corner = np.bincount(self._corner, weights=~good, minlength=self.n_vertices) > 0
        ok = ~bad_corner & ((n * n).sum(1) > 0)
        ok &= np.where(self._interior, np.abs(turn - 2 * math.pi) <= 1e-6, True)
        ok &= np.where(self._boundary, turn < 2 * math.pi - 1e-9, True)
        return ok | ~(self._interior | self._boundary)  # a vertex of no face has no star to fold

    def suspects(self, V1: torch.Tensor, V0: torch.Tensor, handed_out) -> np.ndarray | None:
        """The faces of ``V1`` that the exact test must still check (rules 1 and 2), from the last clean mesh
        ``V0`` and the pairs the contact barrier kept at ``V0`` (:meth:`~meshmei.contact.ContactBarrier.separation`);
        None where the barrier's bound does not cover twice the step (the whole mesh must be tested)."""
        vt, ft, ea, eb, unseen = handed_out
        X1, X0 = V1.detach().cpu().double().numpy(), V0.detach().cpu().double().numpy()
        step = float(np.sqrt(((X1 - X0) ** 2).sum(1)).max(initial=0.0))
        reach = 2.0 * step * (1.0 + 1e-9)
        if not unseen * (1.0 - 1e-9) > reach:
            return None
        dvf, dee = pair_distance_bounds(X0, self.F, vt, ft, self.E, ea, eb)
        close_vf, close_ee = dvf * (1.0 + 1e-9) <= reach, dee * (1.0 + 1e-9) <= reach
        faces = [ft[close_vf], self._star(np.unique(vt[close_vf])), self._edge_faces[ea[close_ee]].reshape(-1),
                 self._edge_faces[eb[close_ee]].reshape(-1), self._star(np.nonzero(~self.unfolded(X1))[0])]
        faces = np.unique(np.concatenate(faces))
        return faces[faces >= 0]


def _one_fan_per_vertex(F: torch.Tensor, n_vertices: int) -> bool:
    """Whether the faces around every vertex are one fan: its corners connected through the edges at it that
    two faces share (two cones touching at their tips have two). ``F`` consistently oriented
    (:func:`_consistently_oriented`)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    topo = mesh_topology(F, n_vertices)
    twin = topo.twins.reshape(-1).numpy()  # half-edge 3 f + k: from F[f, k + 1] to F[f, k + 2]
    h = np.nonzero(twin >= 0)[0]
    g = twin[h]
    f, k = h // 3, h % 3
    q, l = g // 3, g % 3
    # the twin runs the other way: F[f, k + 1] is corner l + 2 of face q, F[f, k + 2] is corner l + 1
    a = np.concatenate([3 * f + (k + 1) % 3, 3 * f + (k + 2) % 3])
    b = np.concatenate([3 * q + (l + 2) % 3, 3 * q + (l + 1) % 3])
    Fn = F.reshape(-1).numpy()
    m3 = 3 * F.shape[0]
    _, label = connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(m3, m3)), directed=False)
    lo = np.full(n_vertices, m3, dtype=np.int64)
    hi = np.full(n_vertices, -1, dtype=np.int64)
    np.minimum.at(lo, Fn, label)
    np.maximum.at(hi, Fn, label)
    used = hi >= 0
    return bool((lo[used] == hi[used]).all())
