"""Parameterisations of a mesh's vertices behind one interface: RBF offsets and scales, raw vertex offsets,
and large steps. Each holds learnable tensors, maps them to vertex positions, and lists its parameter
groups (with learning rates) for the optimiser of :mod:`meshmei.optim`.
"""

from __future__ import annotations

import numbers

import torch

from .._checks import check_non_negative
from .largesteps import DifferentialSolver, system_matrix
from .rbf import RBFDeformer

__all__ = ["Parameterisation", "RBFParameterisation", "VertexParameterisation", "LargeStepsParameterisation",
           "PARAMETERISATIONS", "MIN_COARSE_KERNELS"]


class Parameterisation:
    """Learnable tensors that give vertex positions; the rest positions ``V0`` are where they start.

    Attributes
    ----------
    V0 : (n, 3) float tensor
        The rest (starting) vertices, detached.
    groups : list of dict
        Parameter groups ``{"params": [...], "lr": ...}`` for a torch optimiser.
    """

    def __init__(self, V0: torch.Tensor):
        self.V0 = V0.detach()
        self.groups = []

    def vertices(self) -> torch.Tensor:
        """The current vertices ``(n, 3)``, differentiable in the learnable tensors."""
        raise NotImplementedError

    def info(self) -> dict:
        """JSON-able facts about the parameterisation (sizes, truncation), for a run's record."""
        return {}

    def states(self) -> tuple:
        """Objects besides the parameters that the vertices depend on, with ``snapshot()`` and
        ``restore(saved)`` (an RBF deformer's pair list): :func:`meshmei.optim.minimize` puts them back with
        the parameters."""
        return ()


class VertexParameterisation(Parameterisation):
    """Free per-vertex offsets ``V = V0 + D`` (the classic "deform a sphere" recipe)."""

    def __init__(self, V0: torch.Tensor, *, lr: float):
        check_non_negative("lr", lr)  # as the RBF's: a negative lr climbed the loss
        super().__init__(V0)
        self.D = torch.zeros_like(self.V0, requires_grad=True)
        self.groups = [{"params": [self.D], "lr": lr}]

    def vertices(self) -> torch.Tensor:
        return self.V0 + self.D


START_TOLERANCE = 1e-3  # how far, as a share of the mesh's size, large steps may give the start back


class LargeStepsParameterisation(Parameterisation):
    """``V = (I + lam L)^{-1} u`` with ``u`` learnable (:mod:`meshmei.deform.largesteps`)."""

    def __init__(self, V0: torch.Tensor, F: torch.Tensor, *, lr: float, lam: float):
        check_non_negative("lr", lr)
        super().__init__(V0)
        self.solver = DifferentialSolver(system_matrix(F, V0.shape[0], lam))
        self.u = self.solver.to_differential(self.V0).requires_grad_(True)
        self._check_start(lam)
        self.groups = [{"params": [self.u], "lr": lr}]

    def vertices(self) -> torch.Tensor:
        return self.solver.solve(self.u)

    @torch.no_grad()
    def _check_start(self, lam: float) -> None:
        """ValueError when ``u`` in the run's dtype does not give back ``V0``: ``I + lam L`` magnifies the
        rounding of ``u`` by up to ``lam`` (float32, a 10k-vertex sphere: 1e-10 of its size at lam 19, 2e-4 at
        1e9, 0.2 at 1e12, 1e4 at 1e16, without a word; float64: 0.3 of its size at 1e16)."""
        extent = float((self.V0.amax(0) - self.V0.amin(0)).norm())
        off = float((self.vertices() - self.V0).abs().max())
        if not off <= START_TOLERANCE * extent:
            raise ValueError(f"lam {lam:g} is too large for {str(self.V0.dtype).removeprefix('torch.')}: the "
                             f"parameterisation gives the start back {off:.3g} off ({off / extent:.2g} of its size); "
                             "use a smaller lam or float64")


# The fewest coarse kernels RBFParameterisation adds (coarse_ratio): fewer would only translate the shape, and a
# ratio that gives fewer (n / coarse_ratio rounds below this) adds none
MIN_COARSE_KERNELS = 4


class RBFParameterisation(Parameterisation):
    """The paper's Gaussian RBF deformation (:class:`~meshmei.deform.rbf.RBFDeformer`), with an optional
    second, coarse set of kernels whose offsets are a group of their own.

    Parameters
    ----------
    V0 : (n, 3) float tensor
    lr : float
        Learning rate of the offsets.
    lr_scales : float
        Learning rate of the log-scales; 0 freezes them.
    centers, sigma_factor, r_cut
        See :class:`~meshmei.deform.rbf.RBFDeformer`.
    coarse_ratio : int
        Above 0, add ``round(n / coarse_ratio)`` coarse kernels (when that is at least
        :data:`MIN_COARSE_KERNELS`, 4; else none, and ``info()`` says ``n_coarse_kernels`` 0) with learning rate
        ``lr * coarse_lr``.
    coarse_lr : float
    """

    def __init__(self, V0: torch.Tensor, *, lr: float, lr_scales: float = 0.0, centers=None,
                 sigma_factor: float = 1.0, r_cut: float = 4.0, coarse_ratio: int = 0, coarse_lr: float = 0.0):
        for name, value in (("lr", lr), ("lr_scales", lr_scales), ("coarse_lr", coarse_lr)):
            check_non_negative(name, value)
        if isinstance(coarse_ratio, bool) or not isinstance(coarse_ratio, numbers.Integral) or coarse_ratio < 0:
            raise ValueError(f"coarse_ratio must be a non-negative integer (0: no coarse kernels), got {coarse_ratio!r}")
        if coarse_ratio and not coarse_lr > 0:  # the coarse kernels would never move
            raise ValueError(f"coarse kernels (coarse_ratio={coarse_ratio}) need coarse_lr > 0, got {coarse_lr!r}")
        super().__init__(V0)
        self.rbf = RBFDeformer(self.V0, centers, sigma_factor=sigma_factor, r_cut=r_cut,
                               learn_scales=lr_scales > 0)
        self.groups = [{"params": [self.rbf.offsets], "lr": lr}]
        if lr_scales > 0:
            self.groups.append({"params": [self.rbf.log_sigma], "lr": lr_scales})
        self._info = {"n_kernels": self.rbf.n_kernels, "n_pairs_initial": self.rbf.n_pairs}
        self.coarse = None
        k = round(V0.shape[0] / coarse_ratio) if coarse_ratio else 0
        if coarse_ratio and k < MIN_COARSE_KERNELS:  # said in the record (reconstruct warns)
            self._info.update(n_coarse_kernels=0)
        if k >= MIN_COARSE_KERNELS:
            self.coarse = RBFDeformer(self.V0, k, r_cut=r_cut, learn_scales=False)
            self.groups.append({"params": [self.coarse.offsets], "lr": lr * coarse_lr})
            self._info.update(n_coarse_kernels=k, n_coarse_pairs=self.coarse.n_pairs,
                              coarse_sigma=float(self.coarse.sigma[0]))

    def vertices(self) -> torch.Tensor:
        return self.rbf() if self.coarse is None else self.rbf() + self.coarse.displacement()

    def states(self) -> tuple:
        return (self.rbf,) if self.coarse is None else (self.rbf, self.coarse)

    def info(self) -> dict:
        trunc = self.rbf.truncation_error
        if self.coarse is not None:
            trunc = max(trunc, self.coarse.truncation_error)
        return dict(self._info, n_pairs_final=self.rbf.n_pairs, n_rebuilds=self.rbf.n_rebuilds,
                    truncation_error=trunc, sigma_median=float(self.rbf.sigma.detach().median()))


# method name -> class; reconstruct's settings pick one by name
PARAMETERISATIONS = {"rbf": RBFParameterisation, "vertex": VertexParameterisation,
                     "largesteps": LargeStepsParameterisation}
