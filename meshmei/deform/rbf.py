"""Gaussian radial-basis-function deformation of a mesh, as a sparse truncated linear map of learnable offsets.

The deformed vertices are ``V = V0 + sum_k delta_k * exp(-|V0 - c_k|^2 / (2 sigma_k^2))`` with kernel
centres ``c_k`` on the rest mesh (all vertices by default, as in the paper, or ``K`` farthest points).
Both ends of every kernel distance live on the rest mesh, so the distances never change: only (vertex,
kernel) pairs closer than ``r_cut * sigma_k`` are kept, found once with a KD-tree on the rest positions,
and the list is rebuilt only when a learnable scale grows past the radius the list covers. With fixed
scales (the default in reconstruction) the map is a constant sparse matrix ``W`` (vertices x kernels):
evaluation is one CSR product ``W @ offsets`` forward and one ``W^T @ grad`` backward, both cached until
the pair list or the scales change. With learnable scales it is one gather and one ``index_add`` over the
pairs, differentiable in the scales. Either way memory and time are linear in the number of pairs.
"""

from __future__ import annotations

import itertools
import math
import numbers
import warnings

import numpy as np
import torch
from scipy.spatial import cKDTree

from .._checks import check_positive
from ..errors import MeshError
from ..sampling import nn_spacing

__all__ = ["RBFDeformer", "NarrowKernelError", "farthest_point_sampling", "rbf_dense", "MAX_LR_SCALE"]


def farthest_point_sampling(X, k: int, *, start: int = 0) -> torch.Tensor:
    """Indices of ``k`` points of ``X`` chosen greedily, each farthest from those already chosen.

    Parameters
    ----------
    X : (n, 3) float tensor or array
    k : int
        Number of points, ``1 <= k <= n``.
    start : int
        Index of the first point.

    Returns
    -------
    (k,) int64 tensor, distinct indices in order of selection.

    Examples
    --------
    >>> farthest_point_sampling(torch.tensor([[0., 0, 0], [1, 0, 0], [0.1, 0, 0]]), 2).tolist()
    [0, 1]
    """
    X = torch.as_tensor(X)
    n = X.shape[0]
    if isinstance(k, bool) or int(k) != k or not 1 <= k <= n:
        raise ValueError(f"k must be an integer between 1 and {n} (the number of points), got {k!r}")
    if isinstance(start, bool) or not isinstance(start, (int, np.integer)) or not 0 <= start < n:
        raise ValueError(f"start must index one of the {n} points, got {start!r}")
    P = X.detach().double().cpu().numpy()
    idx = np.empty(int(k), dtype=np.int64)
    idx[0] = start
    d = ((P - P[start]) ** 2).sum(1)
    d[start] = -1.0  # chosen: never again, also when the rest lie on chosen points (duplicates)
    for i in range(1, int(k)):
        idx[i] = int(np.argmax(d))
        d = np.minimum(d, ((P - P[idx[i]]) ** 2).sum(1))  # chosen points stay at -1
        d[idx[i]] = -1.0
    return torch.from_numpy(idx).to(X.device)


def rbf_dense(V0: torch.Tensor, C: torch.Tensor, offsets: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """The untruncated RBF map with a dense ``(n, K)`` weight matrix: the reference for small meshes.

    Parameters
    ----------
    V0 : (n, 3) float tensor, rest positions
    C : (K, 3) float tensor, kernel centres
    offsets : (K, 3) float tensor
    sigma : (K,) float tensor, kernel scales

    Returns
    -------
    (n, 3) float tensor ``V0 + W @ offsets`` with ``W[i, k] = exp(-|V0_i - C_k|^2 / (2 sigma_k^2))``.
    """
    d2 = torch.cdist(V0, C) ** 2  # (n, K)
    W = torch.exp(-d2 / (2.0 * sigma * sigma))
    return V0 + W @ offsets


def _csr(rows: torch.Tensor, cols: torch.Tensor, values: torch.Tensor, shape: tuple) -> torch.Tensor:
    """A CSR matrix from (row, col, value) triples without duplicates, column indices sorted in each row."""
    # one int64 key per entry (row-major position; the pairs are unique, so any sort gives the same order)
    key = rows.cpu().numpy() * shape[1] + cols.cpu().numpy()
    order = torch.from_numpy(np.argsort(key)).to(rows.device)
    counts = torch.bincount(rows, minlength=shape[0])
    crow = torch.zeros(shape[0] + 1, dtype=torch.int64, device=rows.device)
    crow[1:] = torch.cumsum(counts, 0)
    with warnings.catch_warnings():  # torch flags every CSR tensor as a beta feature
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        warnings.filterwarnings("ignore", message="Sparse invariant checks are implicitly disabled")
        return torch.sparse_csr_tensor(crow, cols[order], values[order], shape, device=rows.device)


class _FixedMap(torch.autograd.Function):
    """``W @ x`` for a constant sparse ``W``, with ``W^T`` (also CSR) for the backward pass."""

    @staticmethod
    def forward(ctx, x, W, Wt):
        ctx.Wt = Wt
        return W @ x

    @staticmethod
    def backward(ctx, grad):
        return ctx.Wt @ grad.contiguous(), None, None


def _columns(X: torch.Tensor) -> torch.Tensor:
    """``X (..., K, 3)`` stored column by column (the same values, as the transpose of a contiguous ``(..., 3,
    K)``): CPU BLAS multiplies ``(n, K) @ (K, 3)`` about 3 times faster with the right factor in that layout
    (71 against 230 us at n = K = 409), and autograd's backward of an unbatched product then takes ``W^T @ g``
    as ``(g^T @ W)^T``, equally faster (76 against 268 us). Values change at rounding level only."""
    return X.transpose(-1, -2).contiguous().transpose(-1, -2)


class _DenseMap(torch.autograd.Function):
    """``exp(-D2 / (2 sigma^2)) @ offsets`` over a dense ``(..., n, K)`` pair matrix, with the mask folded into
    the exponent: ``neg_out`` is ``-D2`` with ``-inf`` off the pair list, whose exponential is exactly the
    masked weight (``+0``), and ``neg`` is ``-D2`` (``-0`` off the list) for the scales' gradient. The same
    operations as ``exp(-D2 * inv) * mask @ offsets`` under autograd, minus the negation and the mask's product
    forward and one product backward, so the values and both gradients are its bit for bit (tested); the
    caller keeps ``inv`` positive and finite (``-inf * 0`` would be NaN where the masked form gives 0)."""

    @staticmethod
    def forward(ctx, inv, offsets, neg_out, neg):
        W = (neg_out * inv.unsqueeze(-2)).exp_()
        ctx.save_for_backward(W, offsets)
        ctx.neg = neg
        return torch.matmul(W, _columns(offsets))

    @staticmethod
    def backward(ctx, grad):
        W, offsets = ctx.saved_tensors
        g_inv = g_off = None
        if ctx.needs_input_grad[0]:
            # autograd's order: the product's gradient, times the mask (here W's zeros), times exp's result,
            # times -D2, summed over the vertices
            gW = torch.matmul(grad, offsets.transpose(-1, -2))
            g_inv = gW.mul_(W).mul_(ctx.neg).sum(-2)
        if ctx.needs_input_grad[1]:
            if W.ndim == 2:  # autograd's order for a matrix product whose right factor is stored by columns
                g_off = torch.matmul(grad.transpose(-1, -2), W).transpose(-1, -2)
            else:  # and for a batched one
                g_off = torch.matmul(W.transpose(-1, -2), grad)
        return g_inv, g_off, None, None


def dense_map(inv: torch.Tensor, offsets: torch.Tensor, D2: torch.Tensor, mask: torch.Tensor, neg=None) -> torch.Tensor:
    """``(exp(-D2 * inv) * mask) @ offsets`` for ``D2, mask (..., n, K)``, ``inv (..., K)`` and ``offsets (..., K,
    3)``: by :class:`_DenseMap` where ``neg = (neg_out, -D2)`` is given, the dtypes agree and every ``inv`` is
    positive and finite, else as written (the same values and gradients either way)."""
    if neg is not None and offsets.dtype == D2.dtype:
        lo, hi = torch.aminmax(inv.detach())
        if 0.0 < float(lo) and float(hi) < math.inf:
            return _DenseMap.apply(inv, offsets, *neg)
    W = torch.exp(-D2 * inv.unsqueeze(-2)) * mask
    return torch.matmul(W.to(offsets.dtype), _columns(offsets))


def dense_negatives(D2: torch.Tensor, mask: torch.Tensor) -> tuple:
    """``(neg_out, neg)`` for :func:`dense_map`: ``-D2`` with ``-inf`` off the pair list, and ``-D2``."""
    neg = -D2
    return neg.masked_fill(mask == 0, -math.inf), neg


class NarrowKernelError(ValueError):
    """Kernels too narrow for the vertices' dtype: ``1 / sigma^2`` overflows and a kernel weighs its own
    centre ``0 * inf``, NaN vertices. Callers that chose sigma from their own settings name them."""


def _check_rest(V0, r_cut, headroom) -> None:
    if not isinstance(V0, torch.Tensor) or not V0.is_floating_point() or V0.ndim != 2 or V0.shape[1] != 3:
        got = (f"a {type(V0).__name__} of dtype {V0.dtype} and shape {tuple(V0.shape)}" if hasattr(V0, "shape")
               else f"a {type(V0).__name__}")
        raise MeshError(f"V0 must be an (n, 3) float torch tensor, got {got}")
    if V0.shape[0] == 0:
        raise MeshError("V0 is empty: shape (0, 3)")
    if not bool(torch.isfinite(V0).all()):
        raise MeshError(f"V0 holds NaN or Inf coordinates (shape {tuple(V0.shape)})")
    check_positive("r_cut", r_cut)  # None or "4" failed in the comparison
    if isinstance(headroom, bool) or not isinstance(headroom, numbers.Real) or not 1.0 <= headroom < math.inf:
        raise ValueError(f"headroom must be a finite number of at least 1, got {headroom!r}")  # inf: every pair


def _center_index(V0, centers) -> torch.Tensor:
    """The (K,) vertex index of the kernel centres: all vertices, ``K`` farthest points, or as given."""
    n = V0.shape[0]
    if centers is None:
        return torch.arange(n, device=V0.device)
    if isinstance(centers, (int, np.integer)) and not isinstance(centers, bool):
        if not 1 <= centers <= n:
            raise ValueError(f"centers (a kernel count) must lie between 1 and {n} (the vertices), got {centers}")
        return farthest_point_sampling(V0, int(centers))
    cidx = torch.as_tensor(centers, device=V0.device)
    if cidx.ndim != 1 or cidx.numel() == 0 or cidx.is_floating_point() or cidx.dtype == torch.bool:
        raise ValueError(f"centers must be None, an int, or a non-empty (K,) integer index, got {cidx.dtype} {tuple(cidx.shape)}")
    if int(cidx.min()) < 0 or int(cidx.max()) >= n:
        raise ValueError(f"centers index vertices in [{int(cidx.min())}, {int(cidx.max())}], out of range for {n} vertices")
    return cidx.long()


# The largest learning rate of RBF log-scales (reconstruction's lr_scale, the 3D-MEI's lr_scales). Adam and the
# uniform step move a parameter by up to its lr a step, so a step may widen a kernel e^lr_scale times: at 10,
# 22,000 times, from an edge to far
# past the unit-diagonal target. At 100 the first step overflowed float32 (e^88.7): every scale inf, every
# kernel weighing 1 at every vertex (all n^2 pairs listed), the map one translation, and the run went on
# without a word (sphere of 194 vertices to the bunny, 60 steps: sigma_median inf at 1e10 and 100, 2.5 at 10,
# 0.48 at 1, 0.14 at 0.1; the 3D-MEI's default lr_scales is 0.01). Below it, a scale that still overflows
# over many steps ends a reconstruction with a FloatingPointError (reconstruct.fit).
MAX_LR_SCALE = 10.0

# The pair list becomes a dense (n, K) matrix when it holds at least this share of all pairs and the
# matrix has at most this many entries (4 MB in float32): memory stays bounded and meshes that must scale
# keep the sparse list, whose cost grows with the pairs kept.
DENSE_MIN_FILL = 0.25
DENSE_MAX_ENTRIES = 1 << 20


class RBFDeformer(torch.nn.Module):
    """Learnable Gaussian RBF deformation of fixed rest positions (the paper's deformation model).

    Parameters
    ----------
    V0 : (n, 3) float tensor
        Rest vertex positions; the output has their dtype and device.
    centers : None, int, or (K,) int64 tensor
        Kernel centres: ``None`` for all vertices (the paper's default), an int ``K`` for ``K`` centres
        by farthest-point sampling, or explicit vertex indices.
    sigma : float, optional
        Initial scale of every kernel, in the units of ``V0``. Default ``sigma_factor`` times the mean
        distance from a centre to its nearest other centre at a different position (for all-vertex
        centres, about one edge); with one kernel, or all at one point, the diagonal of ``V0``'s box.
    sigma_factor : float
        See ``sigma``.
    r_cut : float
        Pairs farther apart than ``r_cut * sigma_k`` are dropped; the largest weight dropped is
        ``exp(-r_cut^2 / 2)`` (``3.4e-4`` at the default 4). Read it back from :attr:`truncation_error`.
    headroom : float
        When the pair list is (re)built it covers ``headroom * r_cut * sigma_k`` for each kernel, so the
        scales may grow by this factor before the next rebuild.
    learn_scales : bool
        Make the log-scales a learnable parameter (otherwise a buffer).

    Attributes
    ----------
    offsets : (K, 3) parameter, initialised to zero (so the initial output is ``V0``)
    log_sigma : (K,) parameter (or buffer), ``sigma = exp(log_sigma)``
    center_index : (K,) int64 buffer, the vertex each kernel sits on
    n_pairs : int, the number of (vertex, kernel) pairs kept
    n_rebuilds : int, how often the pair list has been rebuilt after construction

    Examples
    --------
    >>> V0 = torch.rand(50, 3, dtype=torch.float64)
    >>> rbf = RBFDeformer(V0)
    >>> bool(torch.equal(rbf(), V0))
    True
    >>> rbf.truncation_error <= math.exp(-4.0 ** 2 / 2)
    True
    """

    def __init__(
        self,
        V0: torch.Tensor,
        centers=None,
        *,
        sigma: float | None = None,
        sigma_factor: float = 1.0,
        r_cut: float = 4.0,
        headroom: float = 1.25,
        learn_scales: bool = True,
    ):
        super().__init__()
        _check_rest(V0, r_cut, headroom)
        V0 = V0.detach()
        cidx = _center_index(V0, centers)
        self.r_cut = float(r_cut)
        self.headroom = float(headroom)
        self.register_buffer("V0", V0)
        self.register_buffer("center_index", cidx)
        self._all_vertices = centers is None  # kernel k on vertex k (the default)
        self._v0_np = V0.double().cpu().numpy()
        self._c_np = self._v0_np[cidx.cpu().numpy()]
        self._tree = cKDTree(self._v0_np)
        K = cidx.numel()
        if sigma is None:
            # to the nearest distinct centre: duplicated vertices (seams, STL files) gave a spacing of 0
            spacing = nn_spacing(self._c_np) if K > 1 else math.inf
            if not math.isfinite(spacing):  # one kernel, or all at one point
                spacing = float(np.linalg.norm(self._v0_np.max(0) - self._v0_np.min(0))) or 1.0
            check_positive("sigma_factor", sigma_factor)
            sigma = sigma_factor * spacing
        check_positive("sigma", sigma)
        self.offsets = torch.nn.Parameter(torch.zeros(K, 3, dtype=V0.dtype, device=V0.device))
        log_sigma = torch.full((K,), math.log(sigma), dtype=V0.dtype, device=V0.device)
        if not bool(torch.isfinite(torch.exp(-2.0 * log_sigma)).all()):  # a kernel's own centre: 0 * inf, NaN
            raise NarrowKernelError(f"the RBF kernels are {sigma:.3g} wide, too narrow for {V0.dtype} arithmetic "
                                    "(1 / sigma^2 overflows)")
        if not isinstance(learn_scales, (bool, np.bool_)):  # "no" would switch them on
            raise ValueError(f"learn_scales must be True or False, got {learn_scales!r}")
        if learn_scales:
            self.log_sigma = torch.nn.Parameter(log_sigma)
        else:
            self.register_buffer("log_sigma", log_sigma)
        for name in ("_rows", "_cols", "_d2", "_radius", "_dense_d2", "_dense_mask"):
            self.register_buffer(name, None, persistent=False)
        self._dense_neg = None
        self.n_rebuilds = -1
        self._build(torch.exp(log_sigma))

    @property
    def sigma(self) -> torch.Tensor:
        """(K,) kernel scales."""
        return torch.exp(self.log_sigma)

    @property
    def n_kernels(self) -> int:
        return int(self.center_index.numel())

    @property
    def n_pairs(self) -> int:
        return int(self._rows.numel())

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """Load offsets and scales saved from a deformer of the same rest mesh and centres.

        The centres' positions, their KD-tree and the kernel pairs are built from ``V0`` and the centres
        when the deformer is made; loading another rest mesh or other centres would leave them behind and
        give the old deformation (silently). Build the deformer on the saved ones instead:
        ``RBFDeformer(state["V0"], centers=state["center_index"], ...)`` (as
        :func:`meshmei.mei.settings.rebuild_deformer` does).
        """
        for name in ("V0", "center_index"):
            saved = state_dict.get(name)
            mine = getattr(self, name)
            if saved is not None and (saved.shape != mine.shape or not torch.equal(saved.to(mine), mine)):
                raise ValueError(f"the state's {name} differs from this deformer's: build the deformer on it, "
                                 "RBFDeformer(state['V0'], centers=state['center_index']), then load the state")
        return super().load_state_dict(state_dict, strict=strict, assign=assign)

    @torch.no_grad()
    def _build(self, sigma: torch.Tensor) -> None:
        """Rebuild the (vertex, kernel) pair list to cover ``headroom * r_cut * sigma_k`` per kernel."""
        radius = self.headroom * self.r_cut * sigma.detach().double().cpu().numpy()  # (K,)
        if self._all_vertices:
            # Kernel k sits on vertex k: the pairs are the vertex pairs within the largest radius, both ways,
            # plus each vertex with its own kernel. One query_pairs call returns them as an array, 15x faster
            # than a ball query per kernel, which builds a Python list per kernel.
            ij = self._tree.query_pairs(float(radius.max()), output_type="ndarray")  # (p, 2), i < j
            i, j = ij[:, 0].astype(np.int64), ij[:, 1].astype(np.int64)
            d2 = ((self._v0_np[i] - self._v0_np[j]) ** 2).sum(1)
            own = np.arange(len(radius), dtype=np.int64)
            rows = np.concatenate([i, j, own])
            cols = np.concatenate([j, i, own])
            d2 = np.concatenate([d2, d2, np.zeros(len(own))])
            if radius.min() < radius.max():  # scales differ: keep each kernel's own radius
                keep = d2 <= radius[cols] ** 2
                rows, cols, d2 = rows[keep], cols[keep], d2[keep]
        else:
            lists = self._tree.query_ball_point(self._c_np, r=radius, return_sorted=False)
            counts = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(lists))
            rows = np.fromiter(itertools.chain.from_iterable(lists), dtype=np.int64, count=int(counts.sum()))
            cols = np.repeat(np.arange(len(lists), dtype=np.int64), counts)
            d2 = ((self._v0_np[rows] - self._c_np[cols]) ** 2).sum(1)
        dev, dt = self.V0.device, self.V0.dtype
        self._rows = torch.from_numpy(rows).to(dev)
        self._cols = torch.from_numpy(cols).to(dev)
        self._d2 = torch.from_numpy(d2).to(device=dev, dtype=dt)  # (P,) fixed squared kernel distances
        self._radius = torch.from_numpy(radius).to(device=dev, dtype=dt)  # (K,) radius each kernel's list covers
        self._dense_d2 = self._dense_mask = self._dense_neg = None
        n, K = self.V0.shape[0], len(radius)
        if n * K <= DENSE_MAX_ENTRIES and len(rows) >= DENSE_MIN_FILL * n * K:
            # nearly every pair is kept (a small mesh with wide kernels, as a 3D-MEI's): one dense (n, K)
            # matrix of squared distances, zero off the list, and its 0/1 mask, so W @ offsets runs as a
            # BLAS product instead of gathers and scatters (3x faster at 400 vertices), with the same pairs
            D2 = torch.zeros(n, K, dtype=dt, device=dev)
            D2[self._rows, self._cols] = self._d2
            mask = torch.zeros(n, K, dtype=dt, device=dev)
            mask[self._rows, self._cols] = 1.0
            self._dense_d2, self._dense_mask, self._dense_neg = D2, mask, dense_negatives(D2, mask)
        self.n_rebuilds += 1

    def _ensure_covered(self) -> None:
        self.cover(self.log_sigma)

    def snapshot(self) -> tuple:
        """The pair list as it is (references to its tensors: a rebuild replaces them, never edits them).

        The map depends on the list as well as on the parameters: a list rebuilt for wider scales keeps
        pairs beyond ``r_cut`` scales that a narrower one drops. An optimiser that puts the parameters back
        (a refused step undone, the best iterate restored) puts the list back with :meth:`restore`, so that
        the mesh is again the one it evaluated (and a step guard checked), not one no guard saw.
        """
        return (self._rows, self._cols, self._d2, self._radius, self._dense_d2, self._dense_mask, self._dense_neg)

    def restore(self, saved: tuple) -> None:
        """Put back a pair list taken by :meth:`snapshot` (counted as a rebuild when it differs)."""
        if saved[0] is self._rows:
            return
        self._rows, self._cols, self._d2, self._radius, self._dense_d2, self._dense_mask, self._dense_neg = saved
        self.n_rebuilds += 1  # cached matrices (and a batch's stacked dense maps) are keyed on the count

    def cover(self, log_sigma: torch.Tensor) -> None:
        """Rebuild the pair list if it no longer covers ``r_cut`` scales of the kernels ``exp(log_sigma)``."""
        with torch.no_grad():
            sigma = torch.exp(log_sigma)
            if bool((self.r_cut * sigma > self._radius).any()):
                self._build(sigma)

    def dense_pairs(self):
        """``(D2, mask)``, the ``(n, K)`` squared distances (zero off the pair list) and 0/1 mask when the map
        runs as one dense matrix (see :data:`DENSE_MIN_FILL`); None when it runs on the sparse pair list."""
        return None if self._dense_d2 is None else (self._dense_d2, self._dense_mask)

    @property
    def truncation_error(self) -> float:
        """Largest kernel weight dropped by the truncation at the current scales (``<= exp(-r_cut^2 / 2)``).

        Every weight of a dropped pair is below this, so the displacement error at any vertex is at most
        this times the sum of the offset norms of the kernels whose lists miss it.
        """
        with torch.no_grad():
            s = self.sigma.double()
            cover = torch.maximum(self._radius.double(), self.r_cut * s)
            # a scale past its cover would be rebuilt on the next call; report what that call would drop. An
            # infinite cover (a scale overflowed to inf by a huge lr on the scales) lists every pair: it drops
            # nothing (inf / inf made the error NaN)
            dropped = torch.exp(-(cover / s) ** 2 / 2)
            return float(torch.where(torch.isinf(cover), torch.zeros_like(dropped), dropped).max())

    def weights(self) -> torch.Tensor:
        """The truncated weight matrix as a sparse COO ``(n, K)`` tensor (differentiable in the scales)."""
        self._ensure_covered()
        w = self._pair_weights()
        n = self.V0.shape[0]
        return torch.sparse_coo_tensor(torch.stack([self._rows, self._cols]), w, (n, self.n_kernels),
                                       check_invariants=False, device=w.device)

    def _pair_weights(self) -> torch.Tensor:
        inv = 0.5 * torch.exp(-2.0 * self.log_sigma)  # (K,) 1 / (2 sigma^2)
        return torch.exp(-self._d2 * inv[self._cols])  # (P,)

    def _fixed_matrices(self, dtype: torch.dtype) -> tuple:
        """``W`` and ``W^T`` as CSR tensors in ``dtype`` at the current scales, cached until the pairs, the
        scales or the dtype change."""
        key = (self.n_rebuilds, self.log_sigma._version, self.log_sigma.data_ptr(), self._rows.data_ptr(), dtype)
        if getattr(self, "_fixed_key", None) != key:
            with torch.no_grad():
                w = self._pair_weights().to(dtype)
            n, K = self.V0.shape[0], self.n_kernels
            self._fixed = (_csr(self._rows, self._cols, w, (n, K)), _csr(self._cols, self._rows, w, (K, n)))
            self._fixed_key = key
        return self._fixed

    def displacement(self) -> torch.Tensor:
        """``sum_k delta_k w_k(V0)``, ``(n, 3)``."""
        self._ensure_covered()
        return self.displacement_with(self.offsets, self.log_sigma)

    def displacement_with(self, offsets: torch.Tensor, log_sigma: torch.Tensor) -> torch.Tensor:
        """The displacement for other parameters ``offsets (K, 3)`` and ``log_sigma (K,)`` on this deformer's
        pair list (call :meth:`cover` for ``log_sigma`` first); differentiable in both."""
        if self._dense_d2 is not None:  # (n, K) weights, zero off the pair list
            inv = 0.5 * torch.exp(-2.0 * log_sigma)  # (K,) 1 / (2 sigma^2)
            return dense_map(inv, offsets, self._dense_d2, self._dense_mask, self._dense_neg).to(self.V0.dtype)
        if not log_sigma.requires_grad and log_sigma is self.log_sigma:  # fixed scales: a constant sparse matrix
            # torch's CSR products have no float16 or bfloat16 kernels: half-precision offsets multiply in float32
            dtype = torch.float32 if offsets.element_size() < 4 else offsets.dtype
            W, Wt = self._fixed_matrices(dtype)
            return _FixedMap.apply(offsets.to(dtype), W, Wt).to(self.V0.dtype)
        inv = 0.5 * torch.exp(-2.0 * log_sigma)
        w = torch.exp(-self._d2 * inv[self._cols])  # (P,)
        contrib = w.unsqueeze(1) * offsets[self._cols]  # (P, 3)
        return torch.zeros_like(self.V0).index_add(0, self._rows, contrib.to(self.V0.dtype))

    def forward(self) -> torch.Tensor:
        """Deformed vertex positions, ``(n, 3)``."""
        return self.V0 + self.displacement()

    def extra_repr(self) -> str:
        return (f"n={self.V0.shape[0]}, K={self.n_kernels}, pairs={self.n_pairs}, r_cut={self.r_cut}, "
                f"truncation_error={self.truncation_error:.2e}")
