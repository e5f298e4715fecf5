"""Differentiable surface sampling and nearest neighbours: the per-step side of a Chamfer loss.

:func:`sample_points` draws area-uniform samples with gradients to the vertices; :func:`nearest_neighbors`,
:class:`PointIndex` (fast at any query distance) and :func:`chamfer_distance` find the pairs with scipy
KD-trees (no gradient) and measure them in torch. The float64 evaluation lives in :mod:`meshmei.metrics`.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial import cKDTree

from .errors import MeshError
from .mesh import check_mesh
from .operators import corners, cross_from_corners, safe_norm

__all__ = [
    "sample_points",
    "nearest_neighbors",
    "nn_spacing",
    "PointIndex",
    "spatial_order",
    "SORT_QUERIES_FROM",
    "chamfer_distance",
]


def _generator(generator, device):
    if generator is None or isinstance(generator, torch.Generator):
        return generator
    if isinstance(generator, (int, np.integer)) and not isinstance(generator, bool):
        if not -2**63 <= int(generator) < 2**64:  # torch's own "Overflow when unpacking long long" otherwise
            raise ValueError(f"an int generator is a seed in [-2**63, 2**64 - 1], got {int(generator)}")
        return torch.Generator(device=device).manual_seed(int(generator))
    raise TypeError(f"generator must be None, an int seed or a torch.Generator, got {type(generator).__name__}")


def sample_points(V, F, n: int, *, generator=None, return_normals: bool = False, return_faces: bool = False):
    """Points drawn uniformly by area on a triangle mesh, differentiable in the vertex positions.

    A face is drawn with probability proportional to its area (the choice carries no gradient), then a
    point uniformly inside it: ``(1 - sqrt(r1)) a + sqrt(r1) (1 - r2) b + sqrt(r1) r2 c``. The point is a
    fixed barycentric combination of its corners, so gradients flow to ``V``.

    Parameters
    ----------
    V : (n_v, 3) float tensor
    F : (m, 3) integer tensor
    n : int
        Number of samples (``0`` gives an empty ``(0, 3)`` tensor).
    generator : None, int or torch.Generator
        Source of randomness; an int seeds a fresh generator (same seed, same points).
    return_normals : bool
        Also return the unit normal of each sample's face, ``(n, 3)`` (differentiable).
    return_faces : bool
        Also return the face index of each sample, ``(n,)`` int64.

    Returns
    -------
    P : (n, 3) float tensor, dtype and device of ``V``; plus normals and/or face indices if asked.

    Raises
    ------
    MeshError
        Invalid mesh, or a mesh whose faces all have zero area.

    Examples
    --------
    >>> V = torch.tensor([[0., 0, 0], [1, 0, 0], [0, 1, 0]], requires_grad=True)
    >>> P = sample_points(V, torch.tensor([[0, 1, 2]]), 100, generator=0)
    >>> bool((P[:, 2] == 0).all()), bool((P[:, :2].sum(1) <= 1 + 1e-6).all())
    (True, True)
    """
    V, F = check_mesh(V, F)
    if isinstance(n, bool) or not isinstance(n, (int, float, np.integer, np.floating)) or not 0 <= n < math.inf \
            or int(n) != n:  # None or "10" failed inside int()
        raise ValueError(f"n must be a non-negative integer, got {n!r}")
    n = int(n)
    g = _generator(generator, V.device)
    T = corners(V, F)  # (m, 3, 3); index_select, whose backward (index_add) is deterministic
    cross = cross_from_corners(T)  # (m, 3)
    dbl = _row_norms(cross.detach())
    total = float(dbl.sum())
    if not total > 0:
        raise MeshError(f"cannot sample a mesh whose {F.shape[0]} faces all have zero area")
    if not math.isfinite(total):  # squared coordinates beyond the dtype's range (float32: about 1e19)
        raise MeshError(f"the face areas overflow {V.dtype} (largest coordinate {float(V.detach().abs().max()):.3g}, "
                        f"shape {tuple(V.shape)}); rescale the mesh or use float64")
    if n == 0:
        face = torch.zeros(0, dtype=torch.int64, device=V.device)
    else:
        face = torch.multinomial(dbl.double(), n, replacement=True, generator=g)
    r = torch.rand(n, 2, dtype=V.dtype, device=V.device, generator=g)
    s = r[:, :1].sqrt()
    w = torch.cat([1 - s, s * (1 - r[:, 1:]), s * r[:, 1:]], dim=1)  # (n, 3) barycentric
    P = (w.unsqueeze(-1) * T.index_select(0, face)).sum(1)
    out = [P]
    if return_normals:
        c = cross.index_select(0, face)
        out.append(c / _row_norms(c).unsqueeze(-1).clamp_min(torch.finfo(V.dtype).tiny))
    if return_faces:
        out.append(face)
    return out[0] if len(out) == 1 else tuple(out)


def _row_norms(x: torch.Tensor) -> torch.Tensor:
    """Row norms of ``(k, 3)`` vectors: torch's norm where the squares stay in the dtype's normal range (bit for
    bit as before), :func:`~meshmei.operators.safe_norm` where they do not. A cross product goes as the
    fourth power of the mesh's size: at 1e-10 in float32 its squares underflow, and the normals came out
    0.94 to 1.06 long, the faces drawn by wrong areas, and at 1e-11 every face had 'zero area'."""
    n = x.norm(dim=-1)
    fi = torch.finfo(x.dtype)
    off = ~((n > fi.tiny ** 0.5 * 4) & (n < fi.max ** 0.5 / 4)) & torch.isfinite(x).all(-1)  # inf stays inf
    return torch.where(off, safe_norm(x), n) if bool(off.any()) else n


def _check_points(P, name):
    if not isinstance(P, torch.Tensor) or P.ndim != 2 or P.shape[1] != 3 or not P.is_floating_point():
        got = f"{P.dtype} {tuple(P.shape)}" if isinstance(P, torch.Tensor) else type(P).__name__
        raise ValueError(f"{name} must be an (n, 3) float tensor, got {got}")
    if P.shape[0] == 0:
        raise ValueError(f"{name} is empty: shape {tuple(P.shape)}")
    bad = ~torch.isfinite(P).all(1)
    if bool(bad.any()):  # scipy's own message names neither argument
        raise ValueError(f"{name} holds NaN or Inf ({int(bad.sum())} of {P.shape[0]} points, first at index "
                         f"{int(bad.nonzero()[0, 0])})")


def nearest_neighbors(P: torch.Tensor, Q: torch.Tensor, *, tree=None, exact_within: float | None = None,
                      approx_eps: float = 1.0) -> torch.Tensor:
    """Index of the nearest point of ``Q`` for every point of ``P`` (scipy KD-tree, no gradient).

    A KD-tree query costs about ``(d / h)^2`` point visits for a query at distance ``d`` from a surface
    sampled at spacing ``h``: far from a dense target it is slow. With ``exact_within`` set, every query
    first gets a ``(1 + approx_eps)``-approximate neighbour (cheap at any distance); those closer than
    ``exact_within`` are then answered exactly, the farther ones keep the approximate neighbour (at most
    ``1 + approx_eps`` times farther than the nearest).

    Parameters
    ----------
    P : (n, 3) float tensor
    Q : (k, 3) float tensor
    tree : scipy.spatial.cKDTree, optional
        A tree already built on ``Q`` (reuse it when ``Q`` is fixed across calls).
    exact_within : float, optional
        Distance below which neighbours are exact; None (default): all exact.
    approx_eps : float
        Relative error allowed beyond ``exact_within``.

    Returns
    -------
    (n,) int64 tensor on the device of ``P``.
    """
    _check_points(P, "P")
    _check_points(Q, "Q")
    if tree is None:
        tree = cKDTree(_numpy_points(Q))
    elif tree.n != Q.shape[0]:
        raise ValueError(f"tree holds {tree.n} points but Q has {Q.shape[0]}")
    Pn = _numpy_points(P)
    if exact_within is None:
        _, idx = tree.query(Pn, k=1)
    else:
        d, idx = tree.query(Pn, k=1, eps=approx_eps, workers=-1)
        # the approximate distance exceeds the true one by up to (1 + approx_eps): a query truly within
        # exact_within may be reported beyond it, so the exact search takes every one that can be within
        near = np.flatnonzero(d < exact_within * (1.0 + approx_eps))
        if len(near):
            _, idx[near] = tree.query(Pn[near], k=1)
    return torch.from_numpy(np.asarray(idx, dtype=np.int64)).to(P.device)


def nn_spacing(X: np.ndarray, tree=None, sample: int | None = None) -> float:
    """Mean distance from each point of ``X`` (the first ``sample`` of them) to its nearest *distinct* point.

    Duplicated points (a mesh's seams, an STL file's vertices) would otherwise measure a spacing of 0.

    Parameters
    ----------
    X : (k, 3) float array
    tree : scipy.spatial.cKDTree, optional
        A tree already built on ``X``.
    sample : int, optional
        Measure from the first ``sample`` points only (all by default).

    Returns
    -------
    float
        The mean spacing; inf when ``X`` holds fewer than two distinct points.
    """
    head = X if sample is None else X[:sample]
    d, _ = (tree if tree is not None else cKDTree(X)).query(head, k=2)
    d = d[:, 1]
    if (d == 0).any():
        U = np.unique(X, axis=0)
        if len(U) < 2:
            return float("inf")
        d, _ = cKDTree(U).query(np.unique(head, axis=0), k=2)
        d = d[:, 1]
    return float(np.mean(d))


def _numpy_points(X: torch.Tensor) -> np.ndarray:
    """A point tensor as a numpy array (no gradient); half precision comes out in float32, since numpy has no
    bfloat16 and the KD-trees compute in float64 anyway."""
    X = X.detach().cpu()
    return (X.float() if X.is_floating_point() and X.element_size() < 4 else X).numpy()


def _point_array(X, name: str, shape: str = "(n, 3)", *, nonempty: bool = False) -> np.ndarray:
    """``X`` as a contiguous ``(k, 3)`` numpy array of finite points, or a ValueError naming ``name``."""
    Xn = np.ascontiguousarray(_numpy_points(X) if isinstance(X, torch.Tensor) else np.asarray(X))
    if Xn.ndim != 2 or Xn.shape[1] != 3 or (nonempty and len(Xn) == 0):
        raise ValueError(f"{name} must be {'a non-empty' if nonempty else 'an'} {shape} point array, "
                         f"got shape {Xn.shape}")
    bad = ~np.isfinite(Xn).all(1)
    if bad.any():
        raise ValueError(f"{name} holds NaN or Inf ({int(bad.sum())} of {len(Xn)} points, first at index "
                         f"{int(np.flatnonzero(bad)[0])})")
    return Xn


# PointIndex.query hands a large index its queries in Morton (Z-curve) order and puts the answers back in
# theirs: consecutive queries then walk the same branches of the tree, which stay in cache. The answers are the
# same (each query is searched on its own). Measured on two cores, 10,000 samples of a 10k-vertex fit of the
# teapot, 40 draws: into its 200,000-point pool 10.7 ms for 16.9 (two scipy threads; one: 15.8 for 22.2), the
# order's 1.3 ms included; into the 10,000 samples' own tree (which stays in cache anyway) 5.5 ms for 4.3, so
# the smaller indices keep the callers' order. In a whole run the gain is smaller: over a default 1,000-step
# bunny run at 2.5k the pool's queries took 10.9 and 12.3 s against 12.5 and 14.0, of 34-39 s
# (docs/reconstruction.md, *Query order*).
SORT_QUERIES_FROM = 50_000  # points in the index
_SORT_MIN_QUERIES = 512
_MORTON_BITS = 10


def _spread_bits(x: np.ndarray) -> np.ndarray:
    """The low 10 bits of each uint32 of ``x`` moved to every third bit (bit k to bit 3k)."""
    x = x & np.uint32(0x3FF)
    for shift, mask in ((16, 0x030000FF), (8, 0x0300F00F), (4, 0x030C30C3), (2, 0x09249249)):
        x = (x | (x << np.uint32(shift))) & np.uint32(mask)
    return x


def spatial_order(X: np.ndarray) -> np.ndarray:
    """A permutation of the points ``X`` ``(n, 3)`` (finite) along a Morton curve over their bounding box, 2^10
    cells a side: points near each other in space come near each other in the order (mostly)."""
    X = np.asarray(X)
    if len(X) == 0:
        return np.zeros(0, dtype=np.int64)
    lo = X.min(0)
    span = float((X.max(0) - lo).max())
    scale = (1 << _MORTON_BITS) / span if span > 0 else 0.0
    cell = np.minimum((X - lo) * scale, (1 << _MORTON_BITS) - 1).astype(np.uint32)
    code = _spread_bits(cell[:, 0]) | (_spread_bits(cell[:, 1]) << np.uint32(1)) | (_spread_bits(cell[:, 2])
                                                                                    << np.uint32(2))
    return np.argsort(code)


class PointIndex:
    """Nearest-neighbour queries into a fixed point set, fast at any query distance.

    A KD-tree query at distance ``d`` from points spaced ``h`` apart visits about ``(d / h)^2`` points,
    which makes queries far from a dense target slow, and a query from inside a closed surface, where
    every point is nearly equidistant, visits most of them. This index keeps KD-trees on nested prefixes of
    the (randomly ordered) points, each ``factor`` times smaller than the last. A query searches the
    coarsest level, then goes straight to the finest level where it is still cheap (its distance so far
    below ``exact_within * sqrt(n / n_level)``), and again from there, until no query can go finer. A query
    that reaches the finest level gets the true nearest point; the others get a point of a coarser prefix
    at most ``1 + far_eps`` times as far as that prefix's nearest, which exceeds the true distance by at
    most about the prefix's spacing.

    With ``near_first`` (by default when most of the previous call's queries lay within
    ``exact_within``, as in an optimisation that has closed in on its target), a call first searches the
    finest tree bounded at ``exact_within``: every query within ``exact_within`` of a point gets the true
    nearest in that one search, and the search gives up early on the others, which then go through the
    levels.

    Measured with 10,000 queries, one thread: into the bunny's 200,000-point pool, 7 to 9 ms for queries
    about 1e-3 from the surface (one full-tree search: 8 to 12 ms; one search per level, as this index
    did before: 30 ms) and 17 ms at 0.1 (full tree: 350 ms). From the bunny's samples into the samples of
    a sphere around it (the start of a reconstruction; index built per call, as there): 17 ms, 35 ms with
    ``near_first``, 85 ms with one search per level. Far answers are at most 1.5x the true distance in
    the tests (median 1.02x from the sphere into the pool).

    Parameters
    ----------
    Q : (k, 3) float tensor or array
        The points, in random order (e.g. from :func:`sample_points`), so that every prefix covers the
        surface evenly.
    exact_within : float
        Radius of exact answers, positive: with ``near_first``, every query within it of a point gets the
        true nearest; the level-by-level search answers exactly the queries whose distance found at a
        coarser level already falls below it, and may answer a query just inside it from a coarser prefix
        (up to about 1.2 times the true distance seen in a review). Which search runs follows the previous
        call (``near_first=None``), so the same query can get a different, equally valid, answer after a call
        of far queries; pass ``near_first=True`` for exact answers within the radius. Default: 10 times the
        mean spacing of ``Q`` estimated from its nearest-neighbour distances (to the nearest distinct point:
        duplicated points do not shrink it).
    factor : int
        Size ratio of consecutive levels.
    min_points : int
        Size of the coarsest level (at least this many points, fewer than ``factor`` times as many).
    far_eps : float
        Searches of the coarser levels (never of the finest) return a point at most ``1 + far_eps`` times
        as far as the nearest of that level (scipy's ``eps``). Those answers are approximate anyway; the
        slack makes the worst queries, from inside a closed surface, where every point is nearly
        equidistant, 2x cheaper.
    """

    def __init__(self, Q, *, exact_within: float | None = None, factor: int = 4, min_points: int = 500,
                 far_eps: float = 0.5):
        Qn = _point_array(Q, "Q", "(k, 3)", nonempty=True)
        if not far_eps >= 0:
            raise ValueError(f"far_eps must be non-negative, got {far_eps!r}")
        for name, value, least in (("factor", factor, 2), ("min_points", min_points, 1)):
            # factor 1 or min_points 0 would add levels forever
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
                raise ValueError(f"{name} must be an integer of at least {least}, got {value!r}")
        if exact_within is not None and not exact_within > 0:
            raise ValueError(f"exact_within must be positive, got {exact_within!r}")
        self.far_eps = float(far_eps)
        self.n = len(Qn)
        sizes = [self.n]
        while sizes[-1] // factor >= min_points:
            sizes.append(sizes[-1] // factor)
        self.sizes = sizes[::-1]  # coarse to fine
        self.trees = [cKDTree(Qn[:m]) for m in self.sizes]
        if exact_within is None:
            exact_within = 10.0 * nn_spacing(Qn, self.trees[-1], 2000) if self.n > 1 else np.inf
        self.exact_within = float(exact_within)
        # A query at distance d is cheap on level l when d < exact_within * sqrt(n_l / n) (spacing grows
        # with the square root of the thinning).
        self.cheap = [self.exact_within * np.sqrt(self.n / m) for m in self.sizes]
        self.far_share = 0.0  # share of the last call's queries farther than exact_within (picks the search)

    def query(self, P, *, near_first: bool | None = None, workers: int = 1) -> np.ndarray:
        """Index into ``Q`` of the (near-)nearest point for each row of ``P`` ``(n, 3)``; ``(n,)`` int64.

        ``near_first``: start with the bounded search of the finest tree (worth it when most queries are
        near the points); ``None`` decides from the previous call (:attr:`far_share` below one half). A
        caller that builds a new index for each batch can pass what the last index's ``far_share`` said.
        ``workers``: scipy's query threads (the answers are the same for any count). With one, scipy
        (1.17) keeps the GIL for the whole query, so a Python thread beside it waits: a pure-Python loop
        beside forty 10,000-point queries into 200,000 points took 0.80 s with the queries' 0.66 s, and
        ran alongside them (0.43 s in all) with two workers. Pass 2 or more where another thread has work
        during the query (:meth:`meshmei.contact.ContactBarrier.prefetch`); alone, one is as fast or
        faster on two cores. An index of at least :data:`SORT_QUERIES_FROM` points takes many queries in
        Morton order (:func:`spatial_order`) and answers in the order given.
        """
        Pn = _point_array(P, "P")
        if self.n >= SORT_QUERIES_FROM and len(Pn) >= _SORT_MIN_QUERIES:
            order = spatial_order(Pn)
            found = np.empty(len(Pn), dtype=np.int64)
            found[order] = self._query(np.ascontiguousarray(Pn[order]), near_first, workers)
            return found
        return self._query(Pn, near_first, workers)

    def _query(self, Pn: np.ndarray, near_first: bool | None, workers: int) -> np.ndarray:
        """:meth:`query` on checked points, in their order."""
        if near_first is None:
            near_first = self.far_share < 0.5
        if near_first:
            # most queries were near the points last time (a fit that is close): one search of the finest
            # tree bounded at exact_within answers those exactly and gives up early on the rest
            d, idx = self.trees[-1].query(Pn, k=1, distance_upper_bound=self.exact_within, workers=workers)
            idx = np.asarray(idx, dtype=np.int64)
            far = np.flatnonzero(~np.isfinite(d))
            if len(far):
                idx[far] = self._cascade(Pn[far], workers)[1]
            self.far_share = len(far) / max(len(Pn), 1)
            return idx
        d, idx = self._cascade(Pn, workers)
        self.far_share = float(np.mean(d >= self.exact_within)) if len(Pn) else 0.0
        return idx

    def _cascade(self, Pn, workers: int = 1):
        """Distances and indices, searching the coarsest level first and then, for each query, the finest
        level where it is still cheap (its nearest point there is no farther than the one found so far,
        since each level holds the coarser ones), until no query can go finer."""
        last = len(self.trees) - 1
        d, idx = self.trees[0].query(Pn, k=1, eps=self.far_eps if last > 0 else 0.0, workers=workers)
        idx = np.asarray(idx, dtype=np.int64)
        level = np.zeros(len(Pn), dtype=np.int64)
        cheap = np.asarray(self.cheap)
        while True:
            finest = (d[:, None] < cheap[None, :]).sum(1) - 1
            todo = np.flatnonzero(finest > level)
            if len(todo) == 0:
                return d, idx
            for lvl in np.unique(finest[todo]):
                sel = todo[finest[todo] == lvl]
                d[sel], idx[sel] = self.trees[lvl].query(Pn[sel], k=1, eps=self.far_eps if lvl < last else 0.0,
                                                         workers=workers)
                level[sel] = lvl


def chamfer_distance(P: torch.Tensor, Q: torch.Tensor, *, Q_tree=None, return_directions: bool = False):
    """Symmetric squared Chamfer distance ``mean_p min_q |p - q|^2 + mean_q min_p |q - p|^2``.

    The nearest neighbours come from scipy KD-trees and carry no gradient; the distances are computed in
    torch from the chosen pairs, so gradients flow to both point sets (this is the exact gradient almost
    everywhere, since the minimising index is locally constant).

    Parameters
    ----------
    P : (n, 3) float tensor
    Q : (k, 3) float tensor, same dtype
    Q_tree : scipy.spatial.cKDTree, optional
        A tree already built on ``Q`` (a fixed target); a tree on ``P`` is built per call.
    return_directions : bool
        Return the two directed terms ``(P -> Q, Q -> P)`` instead of their sum.

    Returns
    -------
    () float tensor, or a pair of them.

    Examples
    --------
    >>> P = torch.tensor([[0., 0, 0], [1, 0, 0]])
    >>> float(chamfer_distance(P, P + torch.tensor([0., 0, 0.5])))
    0.5
    """
    _check_points(P, "P")
    _check_points(Q, "Q")
    i_pq = nearest_neighbors(P, Q, tree=Q_tree)
    i_qp = nearest_neighbors(Q, P)
    # index_select: advanced indexing's backward (an accumulating index_put) adds in a thread-dependent order
    d_pq = ((P - Q.index_select(0, i_pq)) ** 2).sum(-1).mean()
    d_qp = ((Q - P.index_select(0, i_qp)) ** 2).sum(-1).mean()
    return (d_pq, d_qp) if return_directions else d_pq + d_qp
