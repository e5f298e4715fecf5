"""A contact barrier: an energy that keeps a surface from touching itself, so that a run whose steps are
checked (:mod:`meshmei.validity`) slides along a near-contact instead of stalling at it.

Every vertex is paired with the faces it does not belong to; a pair closer than ``distance`` (``d_hat``)
adds incremental potential contact's log barrier (Li et al. 2020)

    b(d) = -(d - d_hat)^2 log(d / d_hat),   0 < d < d_hat,

which is zero with zero slope at ``d_hat`` and grows without bound as ``d`` goes to zero. The energy is the
sum over pairs divided by the vertex count. A fold (two faces turned onto each other) and a self-contact
(two parts of the surface pressed together) both bring a vertex close to a face it is not part of; on a
well-shaped mesh the nearest such face lies about 0.87 edge lengths away, so ``distance`` at a quarter or
a third of the mean edge length leaves smooth parts alone (reconstruction uses a quarter).

With ``edges=True`` every two edges that share no vertex are paired too (the segment distance), as
incremental potential contact does: two edges crossing like an X come close while every vertex stays far
from the other's faces.

Cost. The candidate pairs are searched again only when some vertex has moved more than ``margin`` since the
last search (candidates are kept out to ``distance + 2 margin``, so no pair can come within ``distance``
unseen, with ``min_interval=1``, as reconstruction uses it). With a larger ``min_interval`` (the 3D-MEI's 4)
a search waits that many calls even when a vertex moved more than ``margin``, so a pair can come within
``distance`` unseen between two searches (at ten times the 3D-MEI's learning rate a review found 115-121 such
pairs over a run, the nearest at 0.2-0.3 ``distance``; none at the default rate): the barrier is then a
preference, and the step guard holds the guarantee. A search is a broad phase with the exact distances of
what it keeps. The broad phase is compiled (``_contact.c``, :mod:`meshmei.native`): a uniform grid
of cells over the vertices and the edges' midpoints, sized to the primitives and ``reach``, each face and
edge tested against the points of the cells its widened box overlaps with the same distance formulas in
C, which keep every pair within ``reach`` with a relative slack of 1e-6 (:data:`_SLACK`); O(n + pairs
tested). Where the kernels are not built, or within :func:`~meshmei.native.torch_reference`, the NumPy and
SciPy broad phase runs: KD-trees over the vertices and the face centroids (and the edges' midpoints),
whose pairs, most of them a vertex and the faces of its own ring or the next, are cut by a cheap lower
bound (the distance to the half-plane beyond the face's farthest edge), O(n log n), then the torch distances
decide. The compiled search keeps its own pairs and float64 distances: every pair the torch distance puts
within ``reach``, in the same order (by face then vertex, by first then second edge), and others only within
the slack, with distances equal to rounding (tested on hard meshes). The cached pairs are handed out with a
relative slack of :data:`_SLACK` over ``distance`` on either kind of distance.

Between searches a step hands out only the cached pairs that may have come within ``distance`` (a pair's
distance shrinks at most by how far its vertices moved since the search). The energy of those is compiled
too (``contact_energy`` in ``_contact.c``, :func:`_compiled_contact`): each pair measured once in float64,
its barrier and its gradient on the four corners written in the same pass, which the backward only scales:
O(pairs handed out). It replaced a pass of about sixty small torch operations and their backward: a 150-step
sphere 3D-MEI spent 3.8-3.9 ms a step in the energy's forward and 0.9-1.0 in the search and handout, then
1.0 in both (the search prefetched), and its backward lost about 1.3 ms (wrapped timers). Measured in float64
whatever the vertices' dtype, it is also the more accurate: on float32 meshes 1,000 units from the origin
the torch code's float32 gradients were off by more than their size, the compiled ones by 2e-8 (tests
against the float64 torch code on the same coordinates). Where the kernels are not built, for a non-finite
coordinate, and within :func:`~meshmei.native.torch_reference`, torch measures the pairs (without a graph,
then those within ``distance`` with one).

A larger ``margin`` would search less often, but beyond ``distance / 2`` (with ``distance`` a third of an
edge) the candidates reach the faces one ring away: at ``margin = distance`` a search of the 10k bunny keeps
103,000 pairs instead of 3,600 and costs 2.4 times as much, for 40 % fewer searches. Reconstruction starts
each step's search in a worker thread (:meth:`ContactBarrier.prefetch`) before its sampled Chamfer term, and
a 3D-MEI on a GPU before its render (on the CPU torch's threads take every core in the render, and a
3D-MEI searches in line: docs/mei.md, *The search in line*). For reconstruction, on two cores the 10k
bunny's default run took 3 to 14 % less time (162.0 s for 167.1 s, and 143.9 s for 168.2 s, in two A/B
pairs), the 2.5k run the same (96.6 s and 96.8 s, means of two runs each), with the same result bit for bit.
The two overlap only where the Chamfer term's KD-tree queries let go of the GIL, which scipy's do with two or
more query threads, not with one (:meth:`meshmei.sampling.PointIndex.query`): with two, the default 2.5k
bunny run went from 47 s to 38 s.
"""

from __future__ import annotations

import itertools
import os
import time
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch.autograd.function import once_differentiable

from . import native
from ._checks import all_finite, check_positive
from .errors import MeshError
from .mesh import as_faces, check_mesh
from .operators import edges as mesh_edges

__all__ = ["ContactBarrier", "contact_energies", "log_barrier", "point_triangle_sqdist", "segment_sqdist",
           "mean_edge_length", "pair_distance_bounds", "MAX_CONTACT_DISTANCE"]

# The widest contact reach the settings take, in mean edge lengths (the defaults are 0.25): the candidate
# pairs grow as the square of the reach, and 1e9 took a 4-step reconstruction from 0.7 s to 77 s
MAX_CONTACT_DISTANCE = 4.0


def _point_triangle(P, A, B, C):
    """Squared distances ``(k,)`` from ``P`` to triangles ``ABC``, and what gives the closest point's weights
    on the corners (:func:`_closest_weights`). Sums over the last axis of 3 are products with ones: torch's
    CPU ``sum(-1)`` over so short an axis costs several times more (7x in float64 at 1,000 rows)."""
    one = P.new_ones(3)
    ab, ac = B - A, C - A
    n = torch.linalg.cross(ab, ac)
    nn = (n * n) @ one
    tiny = torch.finfo(P.dtype).tiny
    ap = P - A
    # barycentric coordinates of the projection (Cramer's rule on the plane's normal), times nn: of B, of C
    u, v = ((torch.linalg.cross(torch.stack([ap, ab], -2), torch.stack([ac, ap], -2)) * n[..., None, :]) @ one).unbind(-1)
    inside = (u >= 0) & (v >= 0) & (u + v <= nn) & (nn > tiny)
    nn_c = nn.clamp_min(tiny)
    plane = ((ap * n) @ one).square() / nn_c
    # the edges AB, BC, CA: the closest point of each, at t along it
    D = torch.stack([ab, C - B, A - C], -2)  # (k, 3, 3)
    PX = P[..., None, :] - torch.stack([A, B, C], -2)
    t = (((PX * D) @ one) / ((D * D) @ one).clamp_min(tiny)).clamp(0, 1)
    edge, which = ((PX - D * t[..., None]).square() @ one).min(-1)
    return torch.where(inside, plane, edge), (inside, u / nn_c, v / nn_c, which, t)


def _closest_weights(inside, bu, bv, which, t):
    """The closest point's weights ``(k, 3)`` on ``A, B, C``: the projection's barycentrics inside, else
    ``(1 - t, t)`` on the nearest edge's ends (edges AB, BC, CA)."""
    tw = t.gather(-1, which[..., None])[..., 0]
    zero = torch.zeros_like(tw)
    wa = torch.where(which == 0, 1 - tw, torch.where(which == 2, tw, zero))
    wb = torch.where(which == 0, tw, torch.where(which == 1, 1 - tw, zero))
    wc = torch.where(which == 1, tw, torch.where(which == 2, 1 - tw, zero))
    return torch.where(inside[..., None], torch.stack([1 - bu - bv, bu, bv], -1), torch.stack([wa, wb, wc], -1))


class _PointTriangleSqDist(torch.autograd.Function):
    """:func:`point_triangle_sqdist` with the closed-form gradient: the squared distance to a convex set
    has gradient ``2 (P - Q)`` in ``P`` (``Q`` the closest point), and ``-2 w_X (P - Q)`` in the corner
    ``X`` with the closest point's weight ``w_X`` on it (Danskin's theorem), one graph node instead of
    about a hundred."""

    @staticmethod
    def forward(ctx, P, A, B, C):
        d2, closest = _point_triangle(P, A, B, C)
        ctx.save_for_backward(P, A, B, C, *closest)
        return d2

    @staticmethod
    @once_differentiable
    def backward(ctx, g):
        P, A, B, C, *closest = ctx.saved_tensors
        wa, wb, wc = _closest_weights(*closest).unsqueeze(-1).unbind(-2)
        gP = 2.0 * g[..., None] * (P - wa * A - wb * B - wc * C)
        return gP, -wa * gP, -wb * gP, -wc * gP


def point_triangle_sqdist(P: torch.Tensor, A: torch.Tensor, B: torch.Tensor, C: torch.Tensor) -> torch.Tensor:
    """Squared distances ``(k,)`` from points ``P`` to triangles ``ABC`` (all ``(k, 3)``), differentiable.

    The closest point is the projection onto the plane when it falls inside the triangle, else the closest
    point of the nearest edge. A degenerate triangle falls back to its edges. The gradient is written out
    (see :class:`_PointTriangleSqDist`).
    """
    if torch.is_grad_enabled() and any(x.requires_grad for x in (P, A, B, C)):
        return _PointTriangleSqDist.apply(P, A, B, C)
    return _point_triangle(P, A, B, C)[0]


def _segment_segment(P1, Q1, P2, Q2):
    """Squared distances ``(k,)`` between segments and the closest points' parameters ``s, t``."""
    d1, d2, r = Q1 - P1, Q2 - P2, P1 - P2
    a, e = (d1 * d1).sum(-1), (d2 * d2).sum(-1)
    b, c, f = (d1 * d2).sum(-1), (d1 * r).sum(-1), (d2 * r).sum(-1)
    tiny = torch.finfo(P1.dtype).tiny
    den = a * e - b * b
    skew = den > 1e-12 * a * e
    s = torch.where(skew, (b * f - c * e) / torch.where(skew, den, torch.ones_like(den)), torch.zeros_like(den))
    s = s.clamp(0, 1)
    t = (b * s + f) / e.clamp_min(tiny)
    # t outside [0, 1]: clamp it and take the best s for that end
    s = torch.where(t < 0, (-c / a.clamp_min(tiny)).clamp(0, 1), torch.where(t > 1, ((b - c) / a.clamp_min(tiny)).clamp(0, 1), s))
    t = t.clamp(0, 1)
    # the second segment a point (e = 0): t = 0 and the nearest s to it (above, s stayed at 0)
    point = e <= tiny
    s = torch.where(point, (-c / a.clamp_min(tiny)).clamp(0, 1), s)
    t = torch.where(point, torch.zeros_like(t), t)
    return (r + d1 * s[..., None] - d2 * t[..., None]).square().sum(-1), s, t


class _SegmentSqDist(torch.autograd.Function):
    """:func:`segment_sqdist` with the closed-form gradient at the closest points ``P1 + s d1`` and
    ``P2 + t d2`` (Danskin's theorem, as for :class:`_PointTriangleSqDist`)."""

    @staticmethod
    def forward(ctx, P1, Q1, P2, Q2):
        d2, s, t = _segment_segment(P1, Q1, P2, Q2)
        ctx.save_for_backward(P1, Q1, P2, Q2, s, t)
        return d2

    @staticmethod
    @once_differentiable
    def backward(ctx, g):
        P1, Q1, P2, Q2, s, t = ctx.saved_tensors
        s, t = s[..., None], t[..., None]
        gr = 2.0 * g[..., None] * ((1 - s) * P1 + s * Q1 - (1 - t) * P2 - t * Q2)
        return (1 - s) * gr, s * gr, -(1 - t) * gr, -t * gr


def segment_sqdist(P1: torch.Tensor, Q1: torch.Tensor, P2: torch.Tensor, Q2: torch.Tensor) -> torch.Tensor:
    """Squared distances ``(k,)`` between segments ``P1 Q1`` and ``P2 Q2`` (all ``(k, 3)``), differentiable.

    The closest parameters ``s, t`` in ``[0, 1]`` minimise over one segment with the other's clamped (as in
    Ericson's *Real-Time Collision Detection*, 5.1.9); parallel and zero-length segments fall back to an
    endpoint, with no division by zero. The gradient is written out (see :class:`_SegmentSqDist`).
    """
    if torch.is_grad_enabled() and any(x.requires_grad for x in (P1, Q1, P2, Q2)):
        return _SegmentSqDist.apply(P1, Q1, P2, Q2)
    return _segment_segment(P1, Q1, P2, Q2)[0]


def log_barrier(d: torch.Tensor, d_hat: float) -> torch.Tensor:
    """Incremental potential contact's barrier ``-(d - d_hat)^2 log(d / d_hat)`` for ``d < d_hat``, else 0,
    element by element: zero with zero slope at ``d_hat``, unbounded as ``d`` falls to 0 (``d <= 0`` is
    clamped to the smallest positive float, a very large but finite value).

    Outside the band the formula is never evaluated on ``d`` (it is on a stand-in of 1, and discarded), so
    an infinite ``d`` gets a zero, not a NaN, gradient; ``d_hat <= 0`` is an empty band: zero everywhere (a
    quality floor of 0, from a start with a collapsed triangle, gives one)."""
    inside = d < d_hat if d_hat > 0 else torch.zeros_like(d, dtype=torch.bool)
    dc = torch.where(inside, d.clamp_min(torch.finfo(d.dtype).tiny), torch.ones_like(d))
    return torch.where(inside, -(dc - d_hat).square() * torch.log(dc / d_hat), torch.zeros_like(d))


IN_CONTACT = 1e-3
"""Share of a barrier's ``distance`` below which a pair of a start counts as in contact
(:meth:`ContactBarrier.leave_out`)."""


def mean_edge_length(V: torch.Tensor, F: torch.Tensor) -> float:
    """The mean length of the faces' edges (each interior edge counted twice)."""
    T = V.detach()[F]
    return float((T - T.roll(1, dims=1)).norm(dim=-1).mean())


def _rowdot(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Row-wise dot products of two ``(k, 3)`` arrays."""
    return np.einsum("ij,ij->i", X, Y)


def _sqlen(X: np.ndarray) -> np.ndarray:
    """Row-wise squared lengths of a ``(k, 3)`` array."""
    return _rowdot(X, X)


def _halfplanes(A: np.ndarray, B: np.ndarray, C: np.ndarray) -> np.ndarray:
    """The four planes ``(m, 4, 4)`` that bound each triangle of the corner arrays ``A, B, C``: its own
    (unit normal and offset: signed distance ``n . p - n . a``) and, for each edge, the plane through the
    edge perpendicular to the triangle, its unit normal pointing into the (counter-clockwise) triangle. A
    face whose area is below ``1e-12`` of its squared edge lengths gets zero planes (a zero bound)."""
    n = np.cross(B - A, C - A)
    size = sum(_sqlen(Y - X) for X, Y in ((A, B), (B, C), (C, A)))
    length = np.sqrt(_sqlen(n))
    flat = length <= 1e-12 * size  # a (near-)collinear face: its rounded normal points anywhere
    n *= np.where(flat, 0.0, 1.0 / np.where(flat, 1.0, length))[:, None]
    planes = [(n, A)]
    for X, Y in ((A, B), (B, C), (C, A)):
        m = np.cross(n, Y - X)
        planes.append((m / np.maximum(np.sqrt(_sqlen(m)), np.finfo(m.dtype).tiny)[:, None], X))
    return np.stack([np.concatenate([u, -_rowdot(u, X)[:, None]], 1) for u, X in planes], 1)


def _halfplane_sqdist(P: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """A lower bound on the squared distance from each point ``P[k]`` to the triangle whose
    :func:`_halfplanes` are ``planes[k]``: the squared distance to the farthest of the three half-planes
    that hold the triangle (its plane, cut by the line through one edge), that is the squared distance to
    the plane plus the square of how far the point lies beyond the edge that puts it farthest."""
    s = np.einsum("kij,kj->ki", planes[:, :, :3], P) + planes[:, :, 3]  # (k, 4) signed distances
    beyond = np.maximum(-s[:, 1:].min(1), 0.0)
    return s[:, 0] ** 2 + beyond ** 2


def _ball_pairs(tree: cKDTree, centres: np.ndarray, radii: np.ndarray):
    """``(q, j)``: every tree point ``j`` within ``radii[q]`` of ``centres[q]``, as two index arrays."""
    lists = tree.query_ball_point(centres, radii)
    counts = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(lists))
    found = np.fromiter(itertools.chain.from_iterable(lists), dtype=np.int64, count=int(counts.sum()))
    return np.repeat(np.arange(len(lists)), counts), found


_WORKER = []
# a forked child has the executor but not its thread: work submitted there would wait forever
os.register_at_fork(after_in_child=_WORKER.clear)


# Up to this many cached pairs the contact energy measures them all rather than bound each first (the bounds
# cost about 9 ns a pair and 30 us a call in NumPy, the kernel about 45 ns a pair; a default 2.5k
# reconstruction keeps up to 110,000 pairs of which 12,000 are handed out, a 3D-MEI about a hundred).
_HAND_ALL = 1024


def _worker() -> ThreadPoolExecutor:
    """The one worker thread of :meth:`ContactBarrier.prefetch` (started on first use, and again in a forked
    child)."""
    if not _WORKER:
        _WORKER.append(ThreadPoolExecutor(max_workers=1, thread_name_prefix="meshmei-contact"))
    return _WORKER[0]


def _pair_keys(i: np.ndarray, j: np.ndarray, n: int) -> np.ndarray:
    """One int64 key per unordered pair of indices below ``n``."""
    return np.minimum(i, j).astype(np.int64) * n + np.maximum(i, j)


def _nearby(P: np.ndarray, C: np.ndarray, r: float):
    """All ``(i, j)`` with ``|P_i - C_j| <= r``, as two index arrays (two KD-trees traversed together, in C;
    built unbalanced, by midpoint splits, which halves their build for the same pairs)."""
    found = cKDTree(P, balanced_tree=False).sparse_distance_matrix(cKDTree(C, balanced_tree=False), r,
                                                                   output_type="ndarray")
    return found["i"].astype(np.int64), found["j"].astype(np.int64)


_SLACK = 1e-6
"""Relative slack on ``reach^2`` of the compiled broad phase (``_contact.c``): its own distances keep every
pair that the torch code measures within ``reach`` (the two differ by rounding, far below this); and on
``distance`` where cached pairs are handed out, on either kind of distance."""


def _compiled_pairs(kernel: str, Vn: np.ndarray, idx: np.ndarray, reach: float, *extra):
    """Run a broad-phase kernel of ``_contact.c`` (``contact_vertex_face`` or ``contact_edge_edge``) on the
    vertices ``Vn`` and faces or edges ``idx``; the pairs ``(a, b)`` as two int64 arrays and their squared
    distances by the kernel (every one below ``reach^2 (1 + _SLACK)``), or None where it cannot tell (a
    non-finite coordinate, no memory: the NumPy search runs instead)."""
    fn = getattr(native.library(), kernel)
    Vn, idx = np.ascontiguousarray(Vn, dtype=np.float64), np.ascontiguousarray(idx, dtype=np.int64)
    lim = reach * reach * (1.0 + _SLACK)
    cap = 16 * len(idx) + 64
    for _ in range(2):
        a, b, d2 = np.empty(cap, dtype=np.int64), np.empty(cap, dtype=np.int64), np.empty(cap)
        found = fn(len(Vn), Vn.ctypes.data, len(idx), idx.ctypes.data, *extra, lim, cap, a.ctypes.data, b.ctypes.data,
                   d2.ctypes.data)
        if found < 0:
            return None
        if found <= cap:
            return a[:found], b[:found], d2[:found]
        cap = found  # too little room: once more with room for all
    raise AssertionError("the contact search found more pairs on a second look at the same vertices")


def pair_distance_bounds(V: np.ndarray, F: np.ndarray, vt: np.ndarray, ft: np.ndarray, E: np.ndarray,
                         ea: np.ndarray, eb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lower bounds on the distances of (vertex, face) pairs ``(vt, ft)`` and (edge, edge) pairs ``(ea, eb)``
    of ``V`` (float64 arrays; the faces ``F`` and edges ``E``), as :class:`meshmei.certify.SeparationCertificate`
    needs them: the exact distances to rounding, and 0 for two edges within
    1e-4 radians of parallel, whose clamped closest points may miss the true ones (by the overlap times the
    angle). Compiled where the kernels are built, else in torch."""
    V = np.ascontiguousarray(V, dtype=np.float64)
    vt, ft, ea, eb = (np.ascontiguousarray(x, dtype=np.int64) for x in (vt, ft, ea, eb))
    if native.enabled():
        lib = native.library()
        dvf, dee = np.empty(len(vt)), np.empty(len(ea))
        F, E = np.ascontiguousarray(F, dtype=np.int64), np.ascontiguousarray(E, dtype=np.int64)
        if len(vt):
            lib.contact_vertex_face_distances(V.ctypes.data, F.ctypes.data, len(vt), vt.ctypes.data, ft.ctypes.data,
                                              dvf.ctypes.data)
        if len(ea):
            lib.contact_edge_edge_distances(V.ctypes.data, E.ctypes.data, len(ea), ea.ctypes.data, eb.ctypes.data,
                                            dee.ctypes.data)
        return dvf, dee
    Vt, Ft, Et = torch.from_numpy(V), torch.from_numpy(np.asarray(F)), torch.from_numpy(np.asarray(E))
    vt, ft, ea, eb = (torch.from_numpy(x) for x in (vt, ft, ea, eb))
    with torch.no_grad():
        dvf = point_triangle_sqdist(Vt[vt], Vt[Ft[ft, 0]], Vt[Ft[ft, 1]], Vt[Ft[ft, 2]]).sqrt()
        P1, Q1, P2, Q2 = Vt[Et[ea, 0]], Vt[Et[ea, 1]], Vt[Et[eb, 0]], Vt[Et[eb, 1]]
        d1, d2 = Q1 - P1, Q2 - P2
        a, e, b = (d1 * d1).sum(-1), (d2 * d2).sum(-1), (d1 * d2).sum(-1)
        dee = torch.where(a * e - b * b <= 1e-8 * a * e, torch.zeros_like(a), segment_sqdist(P1, Q1, P2, Q2).sqrt())
    return dvf.numpy(), dee.numpy()


class ContactBarrier:
    """The contact energy of one face list, with cached candidate pairs.

    Parameters
    ----------
    F : (m, 3) int64 tensor
    distance : float
        ``d_hat``: pairs closer than this add energy (e.g. a quarter of the mean edge length).
    margin : float, optional
        How far a vertex may move before the candidates are found again (default ``distance / 2``: the
        candidates then reach ``2 distance``, which on a well-shaped mesh still leaves out the faces one
        ring away).
    edges : bool
        Also pair every edge with the edges it shares no vertex with (incremental potential contact's
        edge-edge pairs): two edges crossing like an X come close with every vertex still far from the
        other's faces, which vertex-face pairs alone do not see (a reconstruction stalled at such a contact,
        every step refused by the intersection test; docs/reconstruction.md).
    min_interval : int
        Fewest calls between two searches (default 1: search whenever a vertex moved ``margin``). Above
        1, a pair may come within ``distance`` for up to that many calls before the barrier sees it; use it
        only where a :class:`~meshmei.validity.StepGuard` holds the guarantee and the barrier only steers
        (the 3D-MEI, whose steps are long against its edges, uses 4).

    Attributes
    ----------
    active : int
        Pairs within ``distance`` at the last call.
    rebuilds : int
        Candidate searches so far.
    seconds : float
        Time spent finding candidates (the searches, and handing out the cached pairs between them).
    edge_weight : float
        What the edge pairs' barrier is multiplied by in the energy (default 1). A reconstruction that turns
        edge pairs on in its last stage ramps it from near 0 to 1 over
        :data:`~meshmei.reconstruct.settings.AUTO_EDGE_RAMP` steps: at a near-contact their barrier's
        gradient, at full weight at once, sets the optimiser's one step divisor for the whole mesh
        (docs/reconstruction.md, *The switch's kick*).
    """

    def __init__(self, F: torch.Tensor, distance: float, margin: float | None = None, min_interval: int = 1,
                 edges: bool = False):
        check_positive("distance", distance)
        F = as_faces(F).cpu()  # the search and the energy run on the CPU (contact_energies)
        self.F = F
        self.Fn = np.ascontiguousarray(F.numpy())
        self._least_vertices = int(self.Fn.max()) + 1  # the vertex count the faces need (checked every call)
        self.distance = float(distance)
        if margin is not None:
            check_positive("margin", margin)
        self.margin = float(0.5 * distance if margin is None else margin)
        if isinstance(min_interval, bool) or not isinstance(min_interval, int) or min_interval < 1:
            raise ValueError(f"min_interval must be a positive integer, got {min_interval!r}")
        self.min_interval = min_interval
        self.E = self.En = None
        self.edge_energy = False  # edge pairs in the energy (use_edges), not only searched (track_edges)
        self.edge_weight = 1.0  # the edge pairs' share of the energy (a run ramps it up after a switch)
        self.active, self.rebuilds, self._since = 0, 0, 0
        self.seconds = 0.0
        self._built_at = None
        self._pairs = self._pairs_np = None  # the last search's pairs (tensors; the indices as arrays)
        self._out_vf = self._out_ee = None  # pairs left out (leave_out), as sorted keys
        self._pending = None  # (vertices, future) of a prefetch
        self._handout = None  # (vertices, pairs kept, bound on the others' distances) of the last call
        if edges:
            self.use_edges()

    def leave_out(self, V: torch.Tensor) -> int:
        """Leave out of the energy, from now on, every pair in contact in ``V`` (a start), closer than
        :data:`IN_CONTACT` times ``distance``: a vertex on a face it is not part of (a T-junction: an edge
        split on one side only, about 1e-6 of ``distance``), parts that touch. Pairs merely close (a remeshed
        stage of the bunny starts with pairs at 0.3 to 1 times ``distance`` in its ears) stay in.
        Their barrier is all but infinite from the first step, and an optimiser that scales every step by the
        largest gradient (:class:`~meshmei.deform.largesteps.AdamUniform`) then holds the whole mesh still: a
        sphere with one T-junction ended its fit of the bunny at 0.115 for 0.012. Edge pairs are found
        too, for the case that edges are switched on later. The pairs stay the step guard's business (an
        intersection is refused). Returns how many pairs are left out (0 for a clean, well-shaped mesh,
        whose nearest non-incident faces lie most of an edge away)."""
        Vn = V.detach().cpu().double().numpy()
        compiled = native.enabled()
        vt, ft, _, _, dvf, _ = self._candidates(Vn, compiled)
        close = (dvf < IN_CONTACT * self.distance).numpy()
        out_vf = np.unique(vt.numpy()[close] * len(self.Fn) + ft.numpy()[close])
        En = self.En if self.En is not None else mesh_edges(self.F).cpu().numpy()  # use_edges' list, same order
        ea, eb, dee = self._edge_candidates(Vn, self.distance + 2.0 * self.margin, En, compiled)
        close = (dee < IN_CONTACT * self.distance).numpy()
        out_ee = np.unique(_pair_keys(ea.numpy()[close], eb.numpy()[close], len(En)))
        self._out_vf, self._out_ee = out_vf, out_ee
        self._built_at = None  # searched again, without them
        return len(out_vf) + len(out_ee)

    def use_edges(self) -> None:
        """Pair edges with edges from the next call on (as ``edges=True``; the candidates are searched
        again then). A run that stalls at an edge contact turns them on where it needs them
        (:func:`meshmei.reconstruct.reconstruct`, ``contact_edges="auto"``)."""
        self.track_edges()
        if not self.edge_energy:
            self.edge_energy = True
            self._built_at = None

    def track_edges(self) -> None:
        """Search and hand out edge pairs without adding them to the energy (until :meth:`use_edges`): what a
        :class:`~meshmei.certify.SeparationCertificate` needs of the barrier (:meth:`separation`)."""
        if self.E is None:
            self.E = mesh_edges(self.F)  # (k, 2), i < j: the mesh's cached edge list
            self.En = self.E.cpu().numpy()
            self._built_at = None

    @classmethod
    def for_mesh(cls, V: torch.Tensor, F: torch.Tensor, factor: float = 1.0 / 3.0, **kwargs) -> "ContactBarrier":
        """A barrier whose ``distance`` is ``factor`` times the mesh's mean edge length (``kwargs``: the
        other parameters)."""
        V, F = check_mesh(V, F)
        return cls(F, factor * mean_edge_length(V, F), **kwargs)

    def _candidates(self, Vn: np.ndarray, compiled: bool = False):
        """(vertex, face) pairs, the vertex not in the face, within ``distance + 2 margin`` (by face, then
        vertex), then the edge pairs of :meth:`_edge_candidates`, then the two kinds' distances. ``compiled``:
        the broad phase by ``_contact.c``, whose own pairs and distances are kept (every pair the torch
        distance puts within reach, and others only within its slack); else the torch distances decide."""
        reach = self.distance + 2.0 * self.margin
        found = _compiled_pairs("contact_vertex_face", Vn, self.Fn, reach) if compiled else None
        if found is not None:  # the kernel's pairs and distances as they are (below reach, up to its slack)
            vi, fi, d2 = found
            near = np.ones(len(vi), dtype=bool)
        else:  # keep the pairs whose torch distance is within reach
            vi, fi = self._vertex_face_near(Vn, reach)
            Vd = torch.from_numpy(Vn)
            vt, ft, Fd = torch.from_numpy(vi), torch.from_numpy(fi), torch.from_numpy(self.Fn)
            d2 = point_triangle_sqdist(Vd[vt], Vd[Fd[ft, 0]], Vd[Fd[ft, 1]], Vd[Fd[ft, 2]]).numpy()
            near = d2 < reach * reach
        if self._out_vf is not None and len(self._out_vf):
            near &= ~np.isin(vi * len(self.Fn) + fi, self._out_vf)
        vi, fi, d2 = vi[near], fi[near], d2[near]
        order = np.lexsort((vi, fi))  # by face, then vertex: not the search's order
        ea, eb, de = self._edge_candidates(Vn, reach, compiled=compiled)
        return torch.from_numpy(vi[order]), torch.from_numpy(fi[order]), ea, eb, torch.from_numpy(d2[order]).sqrt(), de

    def _vertex_face_near(self, Vn: np.ndarray, reach: float):
        """The NumPy and SciPy broad phase of :meth:`_candidates`: (vertex, face) index arrays holding every
        pair within ``reach``, the vertex not in the face."""
        T = Vn[self.Fn]
        A, B, C = T[:, 0], T[:, 1], T[:, 2]
        cen = (A + B + C) / 3.0
        rad = np.sqrt(np.maximum.reduce([_sqlen(X - cen) for X in (A, B, C)]))  # each face lies in this ball
        # most faces: a KD-tree over centroids, searched to reach + the 98th-percentile radius; the few
        # faces larger than that (stretched while the shape moves) are searched with their own radius
        typical = float(np.quantile(rad, 0.98))
        big = rad > typical
        small = np.nonzero(~big)[0]
        vi, fi = [], []
        if len(small):
            vv, ff = _nearby(Vn, cen[small], reach + typical)
            vi.append(vv)
            fi.append(small[ff])
        if big.any():
            faces = np.nonzero(big)[0]
            q, found = _ball_pairs(cKDTree(Vn, balanced_tree=False), cen[faces], reach + rad[faces])
            vi.append(found)
            fi.append(faces[q])
        vi, fi = np.concatenate(vi), np.concatenate(fi)
        Fv = self.Fn[fi]
        keep = (Fv[:, 0] != vi) & (Fv[:, 1] != vi) & (Fv[:, 2] != vi)
        vi, fi = vi[keep], fi[keep]
        keep = _sqlen(Vn[vi] - cen[fi]) <= (reach + rad[fi]) ** 2
        vi, fi = vi[keep], fi[keep]
        # most pairs left lie an edge's height beside the face, in its plane (a smooth patch): drop those
        # whose distance to the half-plane beyond one of the face's edges is already beyond reach
        keep = _halfplane_sqdist(Vn[vi], _halfplanes(A, B, C)[fi]) < reach * reach
        return vi[keep], fi[keep]

    def _edge_candidates(self, Vn: np.ndarray, reach: float, En: np.ndarray | None = None, compiled: bool = False):
        """(edge, edge) pairs, sharing no vertex, within ``reach`` now (indices into :attr:`E`, by first
        edge, then second), and their distances; empty without ``edges``. ``En``: the edges to pair instead
        (with :attr:`E` unset). ``compiled``: the broad phase by ``_contact.c``, as in :meth:`_candidates`."""
        none = torch.zeros(0, dtype=torch.int64, device="cpu")
        En = self.En if En is None else En
        if En is None:
            return none, none, torch.zeros(0, dtype=torch.float64, device="cpu")
        A, B = Vn[En[:, 0]], Vn[En[:, 1]]
        mid, half = 0.5 * (A + B), 0.5 * np.sqrt(((B - A) ** 2).sum(1))
        typical = float(np.quantile(half, 0.98))
        big = half > typical
        # a pair is written (i, j), i < j, except that an edge longer than typical comes first when the other is
        # not: the NumPy search's order, which the compiled one keeps (its results are then the same bit for bit)
        first = np.ascontiguousarray(big, dtype=np.uint8)
        found = _compiled_pairs("contact_edge_edge", Vn, En, reach, first.ctypes.data) if compiled else None
        if found is not None:  # as in _candidates
            i, j, d2 = found
            near = np.ones(len(i), dtype=bool)
        else:
            i, j = self._edge_edge_near(mid, half, typical, big, En, reach)
            Vd, Et, it, jt = torch.from_numpy(Vn), torch.from_numpy(En), torch.from_numpy(i), torch.from_numpy(j)
            d2 = segment_sqdist(Vd[Et[it, 0]], Vd[Et[it, 1]], Vd[Et[jt, 0]], Vd[Et[jt, 1]]).numpy()
            near = d2 < reach * reach
        if self._out_ee is not None and len(self._out_ee):
            near &= ~np.isin(_pair_keys(i, j, len(En)), self._out_ee)
        i, j, d2 = i[near], j[near], d2[near]
        order = np.lexsort((j, i))
        return torch.from_numpy(i[order]), torch.from_numpy(j[order]), torch.from_numpy(d2[order]).sqrt()

    @staticmethod
    def _edge_edge_near(mid, half, typical, big, En, reach):
        """The NumPy and SciPy broad phase of :meth:`_edge_candidates`: (edge, edge) index arrays holding every
        pair within ``reach`` that shares no vertex."""
        tree = cKDTree(mid)
        ij = tree.query_pairs(reach + 2 * typical, output_type="ndarray")
        ij = ij[~(big[ij[:, 0]] | big[ij[:, 1]])]  # long edges: searched below with their own radius
        if big.any():
            b = np.nonzero(big)[0]
            q, other = _ball_pairs(tree, mid[b], reach + half[b] + half.max())
            first = b[q]
            once = ~big[other] | (first < other)  # a pair of two long edges is found from both
            ij = np.concatenate([ij, np.column_stack([first[once], other[once]])])
        i, j = ij[:, 0].astype(np.int64), ij[:, 1].astype(np.int64)
        a0, a1, b0, b1 = En[i, 0], En[i, 1], En[j, 0], En[j, 1]
        keep = (a0 != b0) & (a0 != b1) & (a1 != b0) & (a1 != b1)  # no shared vertex
        i, j = i[keep], j[keep]
        keep = ((mid[i] - mid[j]) ** 2).sum(1) <= (reach + half[i] + half[j]) ** 2
        return i[keep], j[keep]

    def prefetch(self, V: torch.Tensor) -> None:
        """Start :meth:`candidates` for ``V`` in a worker thread where it searches; the next call of
        :meth:`candidates` (or of the energy) with these vertices takes its result. The search is NumPy and
        SciPy work that mostly runs without the GIL, as do the KD-tree queries of a sampled Chamfer term with
        two or more scipy threads (one keeps the GIL), so the two overlap on two cores (reconstruction: the
        search starts before the Chamfer term and is taken after it), and so do the bounds of many cached pairs.
        A call that will not search (no vertex moved ``margin``, or fewer than ``min_interval`` calls since the
        last search) and whose last search kept at most :data:`_HAND_ALL` pairs is made here instead: the
        hand-off to the thread would cost more than the bookkeeping it moves, and the thread's Python would
        contend for the GIL with the caller's. The result is the one the call would have given: the same
        search on the same vertices, in the same order of calls. ``V`` must not be changed in place before it
        is taken."""
        self._take_pending()
        Vd = V.detach().cpu()
        compiled = native.enabled()
        moved = self._search_due(Vd)
        if moved is None or not self._few_kept():  # a search, or the bounds of many pairs: in the worker
            self._pending = (Vd, _worker().submit(self._prepare, Vd, compiled, moved))
            return
        done = Future()
        done.set_result(self._prepare(Vd, compiled, moved))
        self._pending = (Vd, done)

    def _take_pending(self, V: torch.Tensor | None = None):
        """The prefetched result if it was for ``V`` (None otherwise, or without a prefetch); a prefetch for
        other vertices is waited for and dropped (its search is done: the next search starts from it)."""
        pending, self._pending = self._pending, None
        if pending is None:
            return None
        Vp, future = pending
        result = future.result()  # the search's own error, raised here
        return result if V is not None and (Vp is V or torch.equal(Vp, V.detach())) else None

    def _prepared(self, V: torch.Tensor) -> tuple:
        """:meth:`_prepare` for ``V``, or the prefetched one when it was for ``V``."""
        if self._pending is not None:
            prepared = self._take_pending(V)
            if prepared is not None:
                return prepared
        return self._prepare(V, native.enabled())

    def _prepare(self, V: torch.Tensor, compiled: bool, moved: np.ndarray | None = None) -> tuple:
        """:meth:`_refresh` for ``V`` (``moved``: as there), then the pairs for its energy: ``(moved, pairs)``,
        ``pairs`` the int64 arrays ``(vt, ft, ea, eb)`` of :meth:`_energy_pairs`."""
        moved = self._refresh(V, compiled, moved)
        return moved, (self._pairs_np if self._few_kept() else self._filtered(moved))

    def _few_kept(self) -> bool:
        """Whether the last search kept at most :data:`_HAND_ALL` pairs (False before any search)."""
        return self._pairs_np is not None and len(self._pairs_np[0]) + len(self._pairs_np[2]) <= _HAND_ALL

    @torch.no_grad()
    def candidates(self, V: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """The candidate pairs for ``V`` that may lie within ``distance``: (vertex, face) and, with
        ``edges``, (edge, edge) index arrays, ``(vt, ft, ea, eb)``.

        The pairs within ``distance + 2 margin`` are searched again when some vertex has moved more than
        ``margin`` since the last search (and ``min_interval`` calls have passed). Between searches a
        cached pair is handed out only while it may lie within ``distance``: a pair's distance shrinks at
        most by how far its vertices moved since the search (the farthest of each side's), so a pair that
        was ``d`` apart then, and whose sides moved ``a`` and ``b`` since, is left out while
        ``d - a - b >= distance``."""
        moved, pairs = self._prepared(V)
        if pairs is self._pairs_np:  # all the search kept (few): bound them here; else the bounded ones already
            pairs = self._filtered(moved)
        return tuple(torch.from_numpy(x).to(V.device) for x in pairs)

    def _search_due(self, V: torch.Tensor):
        """None where the next call for ``V`` searches (or fails: the search raises then), else how far each
        vertex moved since the last search. A search is due at the first call, for another vertex count
        (another mesh on the same faces), and once a vertex moved more than ``margin`` with ``min_interval``
        calls since the last search."""
        if V.ndim != 2 or V.shape[1] != 3 or V.shape[0] < self._least_vertices or self._built_at is None:
            return None
        Vn = V.detach().cpu().double().numpy()
        if self._built_at.shape != Vn.shape:
            return None
        moved = np.sqrt(_sqlen(Vn - self._built_at))
        return None if self._since + 1 >= self.min_interval and moved.max() > self.margin else moved

    @torch.no_grad()
    def _refresh(self, V: torch.Tensor, compiled: bool, moved: np.ndarray | None = None) -> np.ndarray:
        """Search again for ``V`` where due (:meth:`_search_due`; the pairs within ``distance + 2 margin``, kept
        in ``_pairs``) and note what the last search kept and the bound on the others (:meth:`separation`);
        returns how far each vertex moved since the last search. ``compiled``: the broad phase by
        ``_contact.c`` (decided in the calling thread, where :func:`~meshmei.native.torch_reference` holds);
        ``moved``: what :meth:`_search_due` gave, where it was asked already."""
        t0 = time.perf_counter()
        if V.ndim != 2 or V.shape[1] != 3 or V.shape[0] < self._least_vertices:
            raise MeshError(f"the contact barrier's faces need vertices of shape (n, 3) with n >= "
                            f"{self._least_vertices}, got {tuple(V.shape)}")
        if moved is None:
            moved = self._search_due(V)
        self._since += 1
        if moved is None:
            Vn = V.detach().cpu().double().numpy()
            self._pairs = self._candidates(Vn, compiled)
            self._pairs_np = tuple(np.ascontiguousarray(x.numpy(), dtype=np.int64) for x in self._pairs[:4])
            self._built_at = Vn.copy()
            self.rebuilds += 1
            self._since = 0
            moved = np.zeros(len(Vn))
        # a pair not kept was beyond reach at the search and has come closer by at most twice the farthest move
        # since
        unseen = self.distance + 2.0 * self.margin - 2.0 * float(moved.max(initial=0.0))
        self._handout = (V.detach(), self._pairs[:4], unseen)
        self.seconds += time.perf_counter() - t0
        return moved

    def _filtered(self, moved: np.ndarray) -> tuple[np.ndarray, ...]:
        """The cached pairs that may lie within ``distance`` now that the vertices moved ``moved`` since the
        search, as int64 arrays: each pair's bound (NumPy: a few operations on arrays of a few thousand, where
        torch's dispatch would cost more than the work), with a relative slack far above the rounding of either
        kind of search distance (the kernel's or torch's)."""
        t0 = time.perf_counter()
        vt, ft, ea, eb, dvf, dee = self._pairs
        Fn, (vtn, ftn, ean, ebn) = self.Fn, self._pairs_np
        within = self.distance * (1.0 + _SLACK)
        # the farthest move of each face's and each edge's corners
        side = np.maximum(np.maximum(moved[Fn[:, 0]], moved[Fn[:, 1]]), moved[Fn[:, 2]])
        keep = dvf.numpy() - moved[vtn] - side[ftn] < within
        out = [vtn[keep], ftn[keep]]
        if len(ean):
            side = np.maximum(moved[self.En[:, 0]], moved[self.En[:, 1]])
            keep = dee.numpy() - side[ean] - side[ebn] < within
            out += [ean[keep], ebn[keep]]
        else:
            out += [ean, ebn]
        self.seconds += time.perf_counter() - t0
        return tuple(out)

    def _energy_pairs(self, V: torch.Tensor) -> tuple[np.ndarray, ...]:
        """The pairs for the energy of ``V`` (searched where due), as int64 arrays ``(vt, ft, ea, eb)``:
        :meth:`candidates`' pairs, or, where the last search kept at most :data:`_HAND_ALL` pairs, all of them,
        a superset that the energy's distance test (``d < distance``) cuts to the same pairs in the same order
        (the bounds cost more than measuring a few hundred pairs)."""
        return self._prepared(V)[1]

    def separation(self, V: torch.Tensor):
        """The pairs the last call's search kept, where the call was for the vertices ``V``:
        ``(vt, ft, ea, eb, unseen)``, the (vertex, face) and (edge, edge) pairs (int64 arrays; edges index
        :attr:`E`) found within ``distance + 2 margin`` at the last search, and a distance that every other
        such pair of ``V`` keeps: that reach less twice the farthest move since the search (less a margin over
        the torch distances' rounding). All the kept pairs, not only those handed out to the energy (those
        that may be within ``distance``): a certificate then covers steps up to half of that bound, not of
        ``distance``. None without edge pairs, with pairs left out (:meth:`leave_out`: they are never kept),
        or when the last call was for other vertices. For :class:`~meshmei.certify.SeparationCertificate`."""
        if self._handout is None or self.E is None:
            return None
        if (self._out_vf is not None and len(self._out_vf)) or (self._out_ee is not None and len(self._out_ee)):
            return None
        Vh, (vt, ft, ea, eb), unseen = self._handout
        if Vh.shape != V.shape or not torch.equal(Vh.to(V.dtype), V):
            return None
        # the torch segment distance of two near-parallel edges may exceed the true one by up to 1e-6 of an
        # edge (see pair_distance_bounds): the bound keeps a margin far above that
        unseen -= 1e-5 * (self.distance + 2.0 * self.margin)
        return vt.cpu().numpy(), ft.cpu().numpy(), ea.cpu().numpy(), eb.cpu().numpy(), unseen

    def __call__(self, V: torch.Tensor) -> torch.Tensor:
        """The contact energy of ``V`` (a scalar with a graph to ``V`` where some pair is within reach)."""
        if not isinstance(V, torch.Tensor):  # an array failed on its missing .device
            V = torch.as_tensor(np.asarray(V, dtype=np.float64))
        return contact_energies([self], V)


def contact_energies(barriers, V: torch.Tensor) -> torch.Tensor:
    """The contact energies ``(B,)`` of a batch of meshes ``V (B, n, 3)``, one :class:`ContactBarrier` per
    item (the same faces, ``distance`` and ``edges``): each item's candidates as its barrier keeps them, the
    pairs among them within ``distance`` counted. Compiled where the kernels take ``V`` (CPU, finite
    coordinates): ``_contact.c`` measures every candidate in float64 and writes the energy and its gradient in
    one pass (:func:`_compiled_contact`); else (and within :func:`~meshmei.native.torch_reference`) torch
    measures them, then those within ``distance`` again with a gradient (:func:`_torch_contact`).
    The two agree to rounding (float64 against ``V``'s dtype). Sets each barrier's ``active``.

    ``V`` on another device (a CUDA run): measured on a copy on the CPU, where the search runs, and the
    energies handed back on ``V``'s device with their gradient (a few thousand floats each way). One mesh ``V
    (n, 3)`` with one barrier gives its energy as a scalar."""
    if V.device.type != "cpu":
        return contact_energies(barriers, V.cpu()).to(V.device)
    X = V[None] if V.ndim == 2 else V  # (B, n, 3)
    B, n = X.shape[:2]
    F, E, dh = barriers[0].F, barriers[0].E, barriers[0].distance
    kinds_used = 2 if barriers[0].edge_energy else 1  # edge pairs searched for a certificate only: not in it
    # each item's pairs: all the last search kept, or those its bounds hand out (the distance test cuts either)
    found = [cb._energy_pairs(X[b] if V.ndim == 3 else V) for b, cb in enumerate(barriers)]
    if native.available(V) and all_finite(V):
        total, counts = _compiled_contact(V, barriers[0], found, kinds_used, dh)  # one mesh: a scalar
    else:
        Vf = X.reshape(-1, 3)
        kinds = []  # (corner indices (k, 4) into Vf, item (k,), distance function, weight) per kind of pair
        for first, second, rows_of, dist in ((0, 1, lambda a, b: torch.cat([a[:, None], F[b]], 1), point_triangle_sqdist),
                                             (2, 3, lambda a, b: torch.cat([E[a], E[b]], 1), segment_sqdist))[:kinds_used]:
            parts = [(torch.from_numpy(x[first]), torch.from_numpy(x[second])) for x in found]
            item = torch.cat([torch.full((len(a),), b, dtype=torch.long, device=V.device)
                              for b, (a, _) in enumerate(parts)])
            if len(item):
                rows = rows_of(torch.cat([a for a, _ in parts]), torch.cat([b for _, b in parts])) + (item * n)[:, None]
                kinds.append((rows, item, dist, 1.0 if first == 0 else barriers[0].edge_weight))
        total, counts = _torch_contact(X, Vf, kinds, dh)
        total = total[0] if V.ndim == 2 else total
    for cb, k in zip(barriers, counts.tolist()):
        cb.active = int(k)
    return total


def _torch_contact(V, Vf, kinds, dh):
    """:func:`contact_energies`' torch code: the energies ``(B,)`` and the counts of pairs within ``dh``. The
    pairs within ``dh`` are picked without a graph (most steps of a smooth mesh have none), and only those are
    measured again with one."""
    B, n = V.shape[:2]
    counts = torch.zeros(B, dtype=torch.long, device="cpu")
    total = V.sum((1, 2)) * 0.0  # zero, with a (zero) gradient, where no pair is near
    for rows, item, dist, weight in kinds:
        with torch.no_grad():
            near = dist(*(Vf[rows[:, k]] for k in range(4))) < dh * dh
        if not bool(near.any()):
            continue
        rows, item = rows[near], item[near]
        counts += torch.bincount(item.cpu(), minlength=B)
        # index_select: advanced indexing's backward (an accumulating index_put) adds in a thread-dependent order
        d = dist(*(Vf.index_select(0, rows[:, k]) for k in range(4))).clamp_min(torch.finfo(V.dtype).tiny).sqrt()
        b = log_barrier(d, dh)
        total = total.index_add(0, item, b if weight == 1.0 else weight * b)
    return total / n, counts


def _compiled_contact(V, barrier, found, kinds_used, dh):
    """:func:`contact_energies` by ``_contact.c``'s ``contact_energy``: the energies ``(B,)`` of ``V (B, n,
    3)`` (a scalar for one mesh ``(n, 3)``) and the counts of pairs within ``dh``. ``found``: each item's
    pairs, ``(vt, ft, ea, eb)`` int64 arrays into ``barrier``'s faces and edges; ``kinds_used``: 1
    (vertex-face pairs) or 2 (and edge pairs). Every pair handed out is measured in float64, item by item,
    vertex-face pairs first, and its gradient written in the same pass (:func:`~meshmei.native.with_gradient`:
    the backward only scales it); a pair at ``dh`` or beyond adds nothing."""
    Vd, energy, grad = native.kernel_buffers(V)  # (B, n, 3), indexed by the kernel as (B n, 3)
    B, n = Vd.shape[:2]
    counts = np.zeros(B, dtype=np.int64)
    tiny, lib = torch.finfo(V.dtype).tiny, native.library()
    tables = [None if t is None else np.ascontiguousarray(t, dtype=np.int64) for t in (barrier.Fn, barrier.En)]
    weight = barrier.edge_weight
    for b, pairs in enumerate(found):
        for kind in range(kinds_used):
            first, second = pairs[2 * kind:2 * kind + 2]  # contiguous int64 (ContactBarrier._energy_pairs)
            if not len(first):
                continue
            # edge pairs at a weight other than 1 (a ramp): written apart, then added in scaled
            apart = kind == 1 and weight != 1.0
            e_out = np.zeros_like(energy) if apart else energy
            g_out = np.zeros_like(grad) if apart and grad is not None else grad
            lib.contact_energy(len(first), Vd.ctypes.data, first.ctypes.data, second.ctypes.data,
                               tables[kind].ctypes.data, kind, b, n, dh, tiny, e_out.ctypes.data,
                               counts.ctypes.data, None if g_out is None else g_out.ctypes.data)
            if apart:
                energy += weight * e_out
                if grad is not None:
                    grad += weight * g_out
    return native.with_gradient(V, energy / n, None if grad is None else grad / n), torch.from_numpy(counts)
