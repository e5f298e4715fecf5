"""Large-steps parameterisation: the system matrix, the factorised solve and its gradient, uniform Adam."""

from __future__ import annotations

import re

import igl
import numpy as np
import pytest
import scipy.sparse.linalg
import torch

from meshmei.errors import MeshError
from meshmei.deform.largesteps import AdamUniform, DifferentialSolver, system_matrix

from conftest import icosphere


def test_system_matrix_is_identity_plus_graph_laplacian():
    V, F = icosphere(2)
    n = V.shape[0]
    M = system_matrix(F, n, lam=3.0)
    A = igl.adjacency_matrix(F.numpy()).astype(np.float64)
    L = scipy.sparse.diags(np.asarray(A.sum(1)).ravel()) - A
    ref = scipy.sparse.identity(n) + 3.0 * L
    assert abs(M - ref).max() == 0
    assert abs(M - M.T).max() == 0
    np.testing.assert_allclose(np.asarray(M.sum(1)).ravel(), np.ones(n))  # L annihilates constants
    # unreferenced trailing vertices get identity rows
    M2 = system_matrix(F, n + 2, lam=3.0)
    assert M2[n, n] == 1.0 and M2[n + 1].nnz == 1


def test_solve_round_trip_and_gradcheck():
    V, F = icosphere(1)
    solver = DifferentialSolver(system_matrix(F, V.shape[0], lam=5.0))
    u = solver.to_differential(V)
    torch.testing.assert_close(solver.from_differential(u), V)
    b = torch.randn(V.shape[0], 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(solver.solve, (b,))
    b1 = torch.randn(V.shape[0], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(solver.solve, (b1,))


def test_backward_reuses_the_forward_factorisation(monkeypatch):
    V, F = icosphere(1)
    M = system_matrix(F, V.shape[0], lam=19.0)
    calls = []
    real = scipy.sparse.linalg.splu
    monkeypatch.setattr(scipy.sparse.linalg, "splu", lambda *a, **k: calls.append(1) or real(*a, **k))
    solver = DifferentialSolver(M)
    u = solver.to_differential(V).requires_grad_(True)
    for _ in range(3):
        (solver.solve(u) ** 2).sum().backward()
    assert len(calls) == 1
    # the gradient is M^{-T} (2 V): check against a dense solve
    ref = np.linalg.solve(M.toarray().T, 2 * V.numpy())
    np.testing.assert_allclose(u.grad.numpy() / 3, ref, rtol=1e-10, atol=1e-12)


def test_solve_keeps_dtype_and_checks_shape():
    V, F = icosphere(0)
    solver = DifferentialSolver(system_matrix(F, V.shape[0]))
    assert solver.solve(V.float()).dtype == torch.float32
    with pytest.raises(ValueError, match="rows"):
        solver.solve(torch.zeros(3, 3))
    with pytest.raises(ValueError, match="lam"):
        system_matrix(F, V.shape[0], lam=-1.0)
    with pytest.raises(MeshError):
        system_matrix(np.zeros((0, 3), dtype=np.int64), 3)


def test_adam_uniform_step_uses_one_scale_per_tensor():
    p = torch.tensor([[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]], dtype=torch.float64, requires_grad=True)
    g = torch.tensor([[0.5, -2.0, 0.1], [0.0, 1.0, 0.0]], dtype=torch.float64)
    opt = AdamUniform([p], lr=0.1, eps=0.0)
    p.grad = g.clone()
    before = p.detach().clone()
    opt.step()
    # first step: m_hat = g, v_hat = g^2, so the step is lr * g / max|g| (direction kept, unlike Adam's sign(g))
    torch.testing.assert_close(p.detach(), before - 0.1 * g / g.abs().max())
    p.grad = g.clone()
    opt.step()
    torch.testing.assert_close(p.detach(), before - 0.2 * g / g.abs().max())
    with pytest.raises(ValueError, match="lr"):
        AdamUniform([p], lr=0.0)
    q = torch.ones(4, requires_grad=True)  # an all-zero gradient with eps 0: the step was 0 / 0, NaN parameters
    still = AdamUniform([q], lr=0.1, eps=0.0)
    (q * 0).sum().backward()
    still.step()
    assert torch.equal(q.detach(), torch.ones(4))


def test_adam_uniform_and_system_matrix_refuse_bad_arguments():
    """A negative lr climbed the loss, eps=-1 and betas=(0.9,) were accepted (the latter failing in step),
    and an out-of-range face index gave scipy's message."""
    p = torch.zeros(3, requires_grad=True)
    for kw, match in ((dict(lr=-0.5), "lr must be positive and finite"), (dict(lr=float("inf")), "lr must be"),
                      (dict(eps=-1.0), "eps must be"), (dict(betas=(0.9,)), "betas must be two numbers")):
        with pytest.raises(ValueError, match=match):
            AdamUniform([p], **kw)
    with pytest.raises(MeshError, match="vertex index 50, out of range for n_vertices=10"):
        system_matrix(torch.tensor([[0, 1, 50]]), 10)
    with pytest.raises(MeshError, match="integer dtype"):
        system_matrix(torch.tensor([[0.0, 1.5, 2.0]]), 10)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_lam_too_large_for_the_dtype_is_refused_not_a_start_far_from_v0(dtype):
    # u = (I + lam L) V0 rounded in the run's dtype came back as a start about 3 times the sphere's size off
    lam = 1e16
    from meshmei.deform.params import LargeStepsParameterisation

    V, F = icosphere(3)
    V = V.to(dtype)
    with pytest.raises(ValueError, match=re.escape(f"lam {lam:g} is too large for {str(dtype)[6:]}: ")):
        LargeStepsParameterisation(V, F, lr=0.1, lam=lam)
    p = LargeStepsParameterisation(V, F, lr=0.1, lam=19.0)  # the default: its start comes back to rounding
    with torch.no_grad():
        assert float((p.vertices() - V).abs().max()) < 1e-5
