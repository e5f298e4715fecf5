"""Laplacian-preconditioned mesh optimisation after Nicolet, Jacobson and Jakob, "Large Steps in Inverse
Rendering of Geometry" (SIGGRAPH Asia 2021), written here in torch and scipy.

Vertices ``V`` are optimised through ``u = (I + lambda L) V`` with ``L = D - A`` the combinatorial
(graph) Laplacian of the mesh. A gradient step on ``u`` maps back to ``V`` through the smoothing operator
``(I + lambda L)^{-1}``, so steps are smooth and large. The optimiser is Adam with one scalar second-moment
normalisation per parameter tensor (the largest per-entry root-mean-square gradient), which keeps the
direction of the preconditioned step instead of re-weighting it coordinate by coordinate.

Three public pieces: :func:`system_matrix`, :class:`DifferentialSolver` (factorise once, solve with a
gradient that reuses the factorisation) and :class:`AdamUniform`.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from .._checks import check_non_negative, check_positive
from ..errors import MeshError
from ..mesh import as_faces

__all__ = ["system_matrix", "DifferentialSolver", "AdamUniform"]


def system_matrix(F, n_vertices: int, lam: float = 19.0) -> sp.csc_matrix:
    """``I + lam * L`` with ``L = D - A`` the combinatorial Laplacian of ``F``, as scipy CSC ``(n, n)``.

    Parameters
    ----------
    F : (m, 3) integer tensor or array
    n_vertices : int
    lam : float
        Smoothing weight, ``>= 0``; the paper's experiments use 10-100.

    Returns
    -------
    scipy.sparse.csc_matrix (n, n), symmetric positive definite for ``lam >= 0``.
    """
    if not (lam >= 0 and np.isfinite(lam)):
        raise ValueError(f"lam must be non-negative and finite, got {lam!r}")
    F = as_faces(F).cpu().numpy()  # float faces are an error, not truncated
    n = int(n_vertices)
    if int(F.max()) >= n:
        raise MeshError(f"F holds vertex index {int(F.max())}, out of range for n_vertices={n}")
    i = F[:, [0, 1, 2]].ravel()
    j = F[:, [1, 2, 0]].ravel()
    A = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n)).tocsr()
    A = ((A + A.T) > 0).astype(np.float64)  # unique undirected edges, weight 1
    A.setdiag(0)
    A.eliminate_zeros()
    L = sp.diags(np.asarray(A.sum(1)).ravel()) - A
    return (sp.identity(n, format="csc") + lam * L).tocsc()


class _Solve(torch.autograd.Function):
    # x = M^{-1} b; the adjoint of a solve is a solve with M^T, so backward reuses the forward's factors.
    @staticmethod
    def forward(ctx, b, solver):
        ctx.solver = solver
        return solver._solve(b, transpose=False)

    @staticmethod
    def backward(ctx, grad):
        return ctx.solver._solve(grad, transpose=True), None


class DifferentialSolver:
    """A sparse LU factorisation of ``M`` (``scipy.sparse.linalg.splu``), computed once, with torch solves.

    Parameters
    ----------
    M : (n, n) scipy sparse matrix, square and non-singular (e.g. :func:`system_matrix`)

    Examples
    --------
    >>> F = torch.tensor([[0, 1, 2], [0, 2, 3]])
    >>> solver = DifferentialSolver(system_matrix(F, 4, lam=2.0))
    >>> V = torch.rand(4, 3, dtype=torch.float64)
    >>> torch.allclose(solver.solve(solver.to_differential(V)), V)
    True
    """

    def __init__(self, M):
        M = sp.csc_matrix(M, dtype=np.float64)
        if M.ndim != 2 or M.shape[0] != M.shape[1]:
            raise ValueError(f"M must be a square sparse matrix, got shape {M.shape}")
        self.M = M
        self._lu = spla.splu(M)

    @property
    def n(self) -> int:
        return self.M.shape[0]

    def _solve(self, b: torch.Tensor, transpose: bool) -> torch.Tensor:
        x = self._lu.solve(b.detach().cpu().double().numpy(), trans="T" if transpose else "N")
        return torch.from_numpy(np.ascontiguousarray(x)).to(device=b.device, dtype=b.dtype)

    def solve(self, b: torch.Tensor) -> torch.Tensor:
        """``M^{-1} b`` for ``b`` of shape ``(n,)`` or ``(n, d)``, differentiable in ``b``."""
        if b.shape[0] != self.n:
            raise ValueError(f"right-hand side must have {self.n} rows, got shape {tuple(b.shape)}")
        return _Solve.apply(b, self)

    def to_differential(self, V: torch.Tensor) -> torch.Tensor:
        """``u = M V``, ``(n, d)`` (no gradient; the starting point of the parameterisation)."""
        u = self.M @ V.detach().cpu().double().numpy()
        return torch.from_numpy(np.ascontiguousarray(u)).to(device=V.device, dtype=V.dtype)

    def from_differential(self, u: torch.Tensor) -> torch.Tensor:
        """``V = M^{-1} u`` (alias of :meth:`solve`)."""
        return self.solve(u)


class AdamUniform(torch.optim.Optimizer):
    """Adam whose step is normalised by one scalar per tensor: the largest bias-corrected RMS gradient.

    ``m_t`` and ``v_t`` are Adam's moment estimates; the update is
    ``p -= lr * m_hat / (sqrt(max_i v_hat_i) + eps)``. Plain Adam divides entry by entry, which undoes
    the smoothing that a Laplacian preconditioner put into the gradient; a single scale keeps it.

    Parameters
    ----------
    params : iterable of tensors or parameter groups
    lr : float
    betas : (float, float)
    eps : float
        Added to the denominator (guards an all-zero gradient).
    """

    elementwise = False  # one step size per tensor: the items of a batched loss would not step as if alone

    def __init__(self, params, lr: float = 1e-2, betas=(0.9, 0.999), eps: float = 1e-12):
        super().__init__(params, dict(lr=lr, betas=betas, eps=eps))

    def add_param_group(self, param_group: dict) -> None:
        """Each group's ``lr`` (positive, finite), ``betas`` (two values in [0, 1)) and ``eps``
        (non-negative, finite) are checked: a negative lr climbed the loss, silently."""
        super().add_param_group(param_group)
        g = self.param_groups[-1]
        lr, betas, eps = g["lr"], g["betas"], g["eps"]
        check_positive("lr", lr)
        try:
            betas = tuple(float(b) for b in betas)
        except (TypeError, ValueError):
            betas = ()
        if len(betas) != 2 or not all(0.0 <= b < 1.0 for b in betas):
            raise ValueError(f"betas must be two numbers in [0, 1), got {g['betas']!r}")
        check_non_negative("eps", eps)
        g["betas"] = betas

    @torch.no_grad()
    def step(self, closure=None):
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:
            b1, b2 = group["betas"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                state = self.state[p]
                if not state:
                    state["step"] = 0
                    state["m"] = torch.zeros_like(p)
                    state["v"] = torch.zeros_like(p)
                state["step"] += 1
                t = state["step"]
                state["m"].mul_(b1).add_(p.grad, alpha=1 - b1)
                state["v"].mul_(b2).addcmul_(p.grad, p.grad, value=1 - b2)
                m_hat = state["m"] / (1 - b1**t)
                denom = (state["v"].max() / (1 - b2**t)).sqrt() + group["eps"]
                if bool(denom > 0):  # 0 only for gradients all zero so far (or squared to 0): no step, not 0 / 0
                    p.sub_(group["lr"] * m_hat / denom)
        return loss
