"""RBF deformation: truncated sparse map against the dense reference, gradients, rebuilds, centre choice."""

from __future__ import annotations

import math

import pytest
import torch

from meshmei.deform import RBFDeformer, farthest_point_sampling, rbf_dense
from meshmei.errors import MeshError

from conftest import icosphere


def _random_params(rbf, seed=0, spread=0.3):
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        rbf.offsets.copy_(0.1 * torch.randn(rbf.offsets.shape, generator=g, dtype=rbf.offsets.dtype))
        rbf.log_sigma.add_(spread * torch.randn(rbf.log_sigma.shape, generator=g, dtype=rbf.log_sigma.dtype))


def _dense_weights(rbf):
    C = rbf.V0[rbf.center_index]
    d2 = torch.cdist(rbf.V0, C) ** 2
    return torch.exp(-d2 / (2 * rbf.sigma.detach() ** 2))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_zero_offsets_give_rest_pose(dtype):
    V0, _ = icosphere(2, dtype=dtype)
    rbf = RBFDeformer(V0)
    out = rbf()
    assert out.dtype == dtype
    assert torch.equal(out, V0)


@pytest.mark.parametrize("r_cut", [2.0, 3.0, 4.0])
def test_truncated_equals_dense_to_the_reported_bound(r_cut):
    V0, _ = icosphere(2)  # 162 vertices
    rbf = RBFDeformer(V0, r_cut=r_cut, headroom=1.0, sigma_factor=2.0)
    _random_params(rbf)
    V = rbf()  # scales may have grown: the call rebuilds as needed
    err = rbf.truncation_error
    assert err <= math.exp(-r_cut**2 / 2) * (1 + 1e-12)
    # every weight the sparse map drops is at most the reported error
    Wd = _dense_weights(rbf)
    Ws = rbf.weights().detach().to_dense()
    dropped = Wd - Ws
    assert float(dropped.min()) >= -1e-12
    assert float(dropped.max()) <= err * (1 + 1e-9)
    # hence the displacement error is bounded by err times the summed offset norms
    Vd = rbf_dense(V0, V0[rbf.center_index], rbf.offsets.detach(), rbf.sigma.detach())
    bound = err * float(rbf.offsets.detach().norm(dim=1).sum())
    assert float((V.detach() - Vd).norm(dim=1).max()) <= bound
    # and the truncation is real at small r_cut (the test would not notice a dense fallback otherwise)
    assert rbf.n_pairs < V0.shape[0] * rbf.n_kernels


def test_gradients_match_dense_reference():
    V0, _ = icosphere(1)  # 42 vertices
    rbf = RBFDeformer(V0, r_cut=12.0, sigma_factor=1.5)  # dropped weights < 1e-31: exact in float64
    _random_params(rbf, seed=1)
    target = torch.randn(V0.shape, dtype=V0.dtype, generator=torch.Generator().manual_seed(2))
    loss = ((rbf() - target) ** 2).sum()
    g_off, g_ls = torch.autograd.grad(loss, [rbf.offsets, rbf.log_sigma])
    off = rbf.offsets.detach().clone().requires_grad_(True)
    ls = rbf.log_sigma.detach().clone().requires_grad_(True)
    loss_d = ((rbf_dense(V0, V0[rbf.center_index], off, torch.exp(ls)) - target) ** 2).sum()
    r_off, r_ls = torch.autograd.grad(loss_d, [off, ls])
    torch.testing.assert_close(g_off, r_off, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(g_ls, r_ls, rtol=1e-10, atol=1e-12)
    assert float(g_ls.abs().max()) > 0


def test_fixed_scales_use_a_cached_sparse_matrix_that_follows_the_scales():
    # With fixed scales the map is a constant CSR matrix (and its transpose for the backward pass); it must
    # give the same map and offset gradients as the differentiable path, and follow any change of scales.
    V0, _ = icosphere(3)  # 642 vertices
    fixed = RBFDeformer(V0, learn_scales=False, headroom=1.5)
    free = RBFDeformer(V0, learn_scales=True, headroom=1.5)
    target = torch.randn(V0.shape, dtype=V0.dtype, generator=torch.Generator().manual_seed(4))
    for step, change in enumerate([0.0, math.log(1.3), math.log(1.3), -math.log(2.0)]):
        with torch.no_grad():
            for rbf in (fixed, free):
                rbf.log_sigma.add_(change)  # 1.69x after the third: past the headroom, a rebuild
                rbf.offsets.copy_(0.05 * torch.randn(rbf.offsets.shape, generator=torch.Generator().manual_seed(step),
                                                     dtype=V0.dtype))
        outs = [rbf() for rbf in (fixed, free)]
        grads = [torch.autograd.grad(((o - target) ** 2).sum(), rbf.offsets)[0] for o, rbf in zip(outs, (fixed, free))]
        torch.testing.assert_close(outs[0], outs[1], rtol=0, atol=1e-13)
        torch.testing.assert_close(grads[0], grads[1], rtol=0, atol=1e-12)
        Vd = rbf_dense(V0, V0[fixed.center_index], fixed.offsets.detach(), fixed.sigma)
        bound = fixed.truncation_error * float(fixed.offsets.detach().norm(dim=1).sum())
        assert float((outs[0].detach() - Vd).norm(dim=1).max()) <= bound + 1e-14  # + float64 rounding
    assert fixed.n_rebuilds == free.n_rebuilds == 1
    off = fixed.offsets.detach()[:40].clone().requires_grad_(True)
    small = RBFDeformer(V0[:40], learn_scales=False)
    assert torch.autograd.gradcheck(lambda x: torch.func.functional_call(small, {"offsets": x}, ()), (off,))


def test_gradcheck_offsets_and_scales():
    V0, _ = icosphere(0)
    rbf = RBFDeformer(V0, r_cut=3.0)
    _random_params(rbf, seed=3, spread=0.1)
    rbf()  # settle the pair list so that gradcheck's perturbations do not rebuild it

    def f(off, ls):
        return torch.func.functional_call(rbf, {"offsets": off, "log_sigma": ls}, ())

    off = rbf.offsets.detach().clone().requires_grad_(True)
    ls = rbf.log_sigma.detach().clone().requires_grad_(True)
    assert torch.autograd.gradcheck(f, (off, ls))
    assert rbf.n_rebuilds == 0


def test_pair_list_rebuilt_only_when_a_scale_outgrows_it():
    V0, _ = icosphere(3)
    rbf = RBFDeformer(V0, headroom=1.5)
    assert rbf.n_rebuilds == 0
    n0 = rbf.n_pairs
    with torch.no_grad():
        rbf.log_sigma.add_(math.log(1.4))  # within the headroom
    rbf()
    assert rbf.n_rebuilds == 0
    with torch.no_grad():
        rbf.log_sigma[5] += math.log(1.2)  # one kernel now 1.68x its build scale: past the headroom
    rbf()
    assert rbf.n_rebuilds == 1
    assert rbf.n_pairs > n0
    assert rbf.truncation_error <= math.exp(-rbf.r_cut**2 / 2) * (1 + 1e-12)
    with torch.no_grad():
        rbf.log_sigma.sub_(math.log(3.0))  # shrinking never needs a rebuild
    rbf()
    assert rbf.n_rebuilds == 1


def test_a_scale_overflowed_to_inf_lists_every_pair_and_drops_nothing():
    """A huge learning rate on the scales (reconstruct's lr_scale=1e30) overflowed one to inf: the pair list then
    held every pair, and the truncation error was inf / inf, NaN, in the stage's record."""
    V0, _ = icosphere(3)
    rbf = RBFDeformer(V0.float(), learn_scales=True)  # a kernel at every vertex
    assert rbf.n_pairs < V0.shape[0] * rbf.n_kernels
    with torch.no_grad():
        rbf.log_sigma[3] = 1e5  # exp overflows: the kernel weighs 1 at every vertex
        rbf.offsets[3] = torch.tensor([0.5, -0.25, 1.0])
    moved = (rbf() - rbf.V0).detach()  # the other offsets are zero: every vertex moves by this kernel's offset
    assert torch.allclose(moved, rbf.offsets[3].detach().expand(V0.shape[0], 3), rtol=0, atol=1e-6)
    assert 0 < rbf.truncation_error <= math.exp(-rbf.r_cut**2 / 2) * (1 + 1e-6)  # the others' bound, not NaN
    with torch.no_grad():
        rbf.log_sigma.fill_(1e5)  # every scale: the list holds every pair and drops nothing
    assert torch.isfinite(rbf()).all() and rbf.truncation_error == 0.0


def test_pairs_grow_linearly_with_vertices():
    per_vertex = []
    for s in (3, 4):
        V0, _ = icosphere(s)
        rbf = RBFDeformer(V0)
        per_vertex.append(rbf.n_pairs / V0.shape[0])
    # a fixed scale in units of the spacing keeps the pairs per kernel constant as the mesh is refined
    assert per_vertex[1] == pytest.approx(per_vertex[0], rel=0.25)


@pytest.mark.slow
def test_all_vertex_kernels_on_the_bunny_fit_in_memory():
    from meshmei.shapes import target_mesh

    V0, _ = target_mesh("bunny")  # 28,088 vertices
    rbf = RBFDeformer(V0)
    assert rbf.n_kernels == V0.shape[0]
    assert rbf.n_pairs < 400 * V0.shape[0]  # about 8e6 pairs, versus 7.9e8 entries dense
    with torch.no_grad():
        rbf.offsets.normal_(std=1e-3)
    rbf().sum().backward()
    assert rbf.offsets.grad.shape == rbf.offsets.shape


def test_farthest_point_centres():
    V0, _ = icosphere(2)
    idx = farthest_point_sampling(V0, 12)
    assert len(set(idx.tolist())) == 12
    assert int(idx[0]) == 0
    # greedy property: each pick is a point farthest from those picked before it
    for i in range(1, 12):
        d = torch.cdist(V0, V0[idx[:i]]).min(dim=1).values
        assert float(d[idx[i]]) == pytest.approx(float(d.max()), rel=1e-12)
    # and the result is a 2-approximation of the best spread of 12 points (the icosahedron's)
    C = V0[idx]
    d = torch.cdist(C, C) + torch.eye(12, dtype=V0.dtype) * 10
    edge = 4 / math.sqrt(10 + 2 * math.sqrt(5))  # icosahedron edge on the unit sphere
    assert float(d.min()) >= edge / 2
    rbf = RBFDeformer(V0, 12)
    assert rbf.n_kernels == 12 and torch.equal(rbf.center_index, idx)
    rbf2 = RBFDeformer(V0, torch.tensor([0, 5, 7]))
    assert rbf2.offsets.shape == (3, 3)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(V0=torch.zeros(0, 3)), "empty"),
        (dict(V0=torch.zeros(4, 2)), r"\(n, 3\)"),
        (dict(V0=torch.tensor([[0.0, 0, 0], [float("nan"), 0, 0]])), "NaN"),
        (dict(V0=torch.rand(5, 3), r_cut=0.0), "r_cut"),
        (dict(V0=torch.rand(5, 3), centers=torch.tensor([0, 9])), "out of range"),
        (dict(V0=torch.rand(5, 3), centers=torch.tensor([0.5])), "integer"),
        (dict(V0=torch.rand(5, 3), sigma=-1.0), "sigma"),
        (dict(V0=torch.rand(5, 3), centers=9), "between 1 and 5"),
    ],
)
def test_bad_input_raises(kwargs, match):
    with pytest.raises(ValueError, match=match):
        RBFDeformer(**kwargs)


def test_bad_mesh_is_a_mesh_error():
    with pytest.raises(MeshError):
        RBFDeformer(torch.zeros(0, 3))


@pytest.mark.parametrize("spread", [0.0, 0.3])
def test_pair_list_is_every_pair_within_each_kernels_radius(spread):
    # All-vertex kernels (the default) list their pairs with one query_pairs call; given centres use a ball
    # query per kernel. Both must list exactly the (vertex, kernel) pairs within headroom * r_cut * sigma_k.
    V0, _ = icosphere(3)  # 642 vertices
    default = RBFDeformer(V0, r_cut=2.0)
    given = RBFDeformer(V0, torch.arange(V0.shape[0]), r_cut=2.0)
    for rbf in (default, given):
        _random_params(rbf, seed=3, spread=spread)
        rbf._build(rbf.sigma.detach())  # the pairs for these (possibly unequal) scales
    d = torch.cdist(V0, V0)  # (vertex, kernel) distances
    expected = d <= default._radius[None, :]
    # the brute-force set, up to pairs within rounding of a radius
    edge = (d - default._radius[None, :]).abs() < 1e-12
    for rbf in (default, given):
        got = torch.zeros_like(expected)
        got[rbf._rows, rbf._cols] = True
        assert rbf.n_pairs == int(got.sum())  # no pair listed twice
        assert torch.equal(got | edge, expected | edge)
        torch.testing.assert_close(rbf._d2, d[rbf._rows, rbf._cols] ** 2)
    assert 0 < default.n_pairs < V0.shape[0] ** 2
    assert (default._radius.min() < default._radius.max()) == (spread > 0)


def test_default_scale_ignores_duplicated_vertices():
    # a mesh with every vertex twice (seams, STL files) measured a spacing of 0 and was refused with
    # "sigma must be positive and finite, got 0.0", a sigma the caller never gave
    V, _ = icosphere(2)
    single = RBFDeformer(V)
    double = RBFDeformer(torch.cat([V, V]))
    torch.testing.assert_close(double.sigma, single.sigma.repeat(2))
    with torch.no_grad():
        double.offsets.normal_(generator=torch.Generator().manual_seed(0))
    out = double()
    assert torch.isfinite(out).all() and not torch.equal(out, double.V0)
    # all vertices at one point: the one-kernel rule (box diagonal, else 1)
    assert torch.equal(RBFDeformer(torch.zeros(4, 3, dtype=torch.float64)).sigma, torch.ones(4, dtype=torch.float64))


@pytest.mark.parametrize("learn_scales", [True, False])
def test_the_dense_path_of_a_small_mesh_is_the_sparse_map(monkeypatch, learn_scales):
    # a 3D-MEI's mesh (a few hundred vertices, wide kernels) keeps nearly every pair: the deformer then uses
    # one dense masked matrix; it must give the sparse list's displacement and gradients
    import meshmei.deform.rbf as rbf_module

    V0 = icosphere(2)[0].to(torch.float64)
    dense = RBFDeformer(V0, sigma_factor=3.0, learn_scales=learn_scales)
    monkeypatch.setattr(rbf_module, "DENSE_MAX_ENTRIES", 0)
    sparse = RBFDeformer(V0, sigma_factor=3.0, learn_scales=learn_scales)
    assert dense._dense_d2 is not None and sparse._dense_d2 is None
    for rbf in (dense, sparse):
        _random_params(rbf, seed=3, spread=0.1 if learn_scales else 0.0)
    Vd, Vs = dense(), sparse()
    torch.testing.assert_close(Vd, Vs, rtol=0, atol=1e-12)
    w = torch.randn(Vd.shape, dtype=Vd.dtype, generator=torch.Generator().manual_seed(4))
    (w * Vd).sum().backward()
    (w * Vs).sum().backward()
    torch.testing.assert_close(dense.offsets.grad, sparse.offsets.grad, rtol=0, atol=1e-12)
    if learn_scales:
        torch.testing.assert_close(dense.log_sigma.grad, sparse.log_sigma.grad, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_fixed_scales_in_half_precision_multiply_in_float32(dtype):
    # torch's CSR product has no half-precision kernel: a bfloat16 start failed in reconstruct's first step
    V0, _ = icosphere(3)  # 642 vertices: the sparse path
    rbf = RBFDeformer(V0.to(dtype), learn_scales=False)
    assert rbf.dense_pairs() is None
    _random_params(rbf, spread=0.0)
    V = rbf()
    assert V.dtype == dtype
    W = rbf.weights().detach().float()  # the same pairs and weights, in float32
    want = rbf.V0 + (W @ rbf.offsets.detach().float()).to(dtype)
    torch.testing.assert_close(V.detach(), want)
    (grad,) = torch.autograd.grad(V.float().sum(), rbf.offsets)
    torch.testing.assert_close(grad, (W.t() @ torch.ones(V.shape)).to(dtype))


def test_deformer_errors_name_what_arrived():
    V, _ = icosphere(1)
    with pytest.raises(MeshError, match="got a ndarray of dtype float64 and shape"):
        RBFDeformer(V.numpy())
    with pytest.raises(ValueError, match="sigma_factor must be positive and finite, got -1.0"):
        RBFDeformer(V, sigma_factor=-1.0)


def test_farthest_points_are_distinct_on_duplicated_points():
    """Once every remaining point lay on a chosen one, index 0 came back again: [0, 2, 0]."""
    X = torch.tensor([[0.0, 0, 0], [0, 0, 0], [1, 0, 0]])
    assert sorted(farthest_point_sampling(X, 3).tolist()) == [0, 1, 2]
    X = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 0, 0], [2, 0, 0]])
    assert sorted(farthest_point_sampling(X, 4).tolist()) == [0, 1, 2, 3]


def test_a_state_of_other_centres_is_refused_and_of_the_same_reproduces():
    """load_state_dict copied V0 and the centre indices but kept the old centres and pairs: another
    deformation (7.4 apart), silently."""
    V0 = torch.rand(200, 3, generator=torch.Generator().manual_seed(0))
    a = RBFDeformer(V0, 30)
    with torch.no_grad():
        a.offsets.normal_()
    with pytest.raises(ValueError, match="the state's center_index differs"):
        RBFDeformer(V0, torch.arange(30)).load_state_dict(a.state_dict())
    with pytest.raises(ValueError, match="the state's V0 differs"):
        RBFDeformer(2 * V0).load_state_dict(RBFDeformer(V0).state_dict())
    b = RBFDeformer(V0, a.center_index)
    b.load_state_dict(a.state_dict())
    assert torch.equal(b().detach(), a().detach())


def test_coarse_kernels_need_a_learning_rate():
    """coarse_ratio > 0 with the default coarse_lr 0 built kernels that never moved."""
    from meshmei.deform import RBFParameterisation

    V, _ = icosphere(2)
    with pytest.raises(ValueError, match=r"coarse kernels \(coarse_ratio=10\) need coarse_lr > 0"):
        RBFParameterisation(V.float(), lr=0.01, coarse_ratio=10)
    for kw, match in ((dict(lr_scales=-0.1), "lr_scales must be"), (dict(coarse_ratio=-10), "coarse_ratio must be")):
        with pytest.raises(ValueError, match=match):
            RBFParameterisation(V.float(), lr=0.01, **kw)


def test_learn_scales_must_be_a_boolean():
    V, _ = icosphere(1)
    with pytest.raises(ValueError, match="learn_scales must be True or False, got 'no'"):  # switched them on
        RBFDeformer(V, learn_scales="no")


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("batch", [None, 3])
def test_the_dense_map_with_its_mask_in_the_exponent_is_the_masked_product_bit_for_bit(dtype, batch):
    """dense_map folds the mask into the exponent (-inf off the pair list) and writes its backward: the
    displacement and both gradients equal autograd's through exp(-D2 inv) * mask @ offsets bit for bit, one
    mesh or a batch; scales whose inv is 0 or inf take the masked form (where -inf * 0 would be NaN)."""
    from meshmei.deform.rbf import dense_map, dense_negatives

    gen = torch.Generator().manual_seed(3)
    shape = () if batch is None else (batch,)
    n, K = 50, 40
    D2 = torch.rand(*shape, n, K, generator=gen, dtype=torch.float64).to(dtype) * 4.0
    mask = (torch.rand(*shape, n, K, generator=gen) < 0.5).to(dtype)
    D2 = D2 * mask  # zero off the pair list, as RBFDeformer keeps it
    D2[..., 0, 0], mask[..., 0, 0] = 0.0, 1.0  # a vertex at its own kernel's centre
    neg = dense_negatives(D2, mask)
    for log_sigma in (torch.randn(*shape, K, generator=gen, dtype=torch.float64).to(dtype) * 0.5,
                      torch.full((*shape, K), 80.0, dtype=dtype), torch.full((*shape, K), -400.0, dtype=dtype)):
        grads = []
        for use in (neg, None):
            ls = log_sigma.clone().requires_grad_()
            off = torch.randn(*shape, K, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64).to(dtype)
            off.requires_grad_()
            out = dense_map(0.5 * torch.exp(-2.0 * ls), off, D2, mask, use)
            (out * torch.linspace(-1.0, 2.0, out.numel(), dtype=dtype).reshape(out.shape)).sum().backward()
            grads.append((out.detach(), off.grad, ls.grad))
        for a, b in zip(*grads):
            assert torch.equal(a, b) or (a.isnan() == b.isnan()).all() and torch.equal(a.nan_to_num(), b.nan_to_num())
    assert bool(torch.isfinite(grads[0][0]).all()) is False  # inv = inf: NaN at the centre either way


def test_kernels_too_narrow_for_the_dtype_and_odd_arguments_are_refused():
    """sigma=1e-300 passed "positive and finite" and gave NaN vertices once the offsets moved; a string
    sigma, r_cut None and an infinite headroom (every pair kept) passed or failed inside Python."""
    V, _ = icosphere(1)
    V = V.float()
    for kw, says in [(dict(sigma=1e-300), "kernels are 1e-300 wide, too narrow for torch.float32"),
                     (dict(sigma=1e-20), "too narrow for torch.float32"),
                     (dict(sigma_factor=1e-300), "too narrow for torch.float32"),
                     (dict(sigma="1"), "sigma must be a positive number, got '1'"),
                     (dict(r_cut=None), "r_cut must be a positive number, got None"),
                     (dict(headroom=math.inf), "headroom must be a finite number of at least 1")]:
        with pytest.raises(ValueError, match=says):
            RBFDeformer(V, **kw)
    rbf = RBFDeformer(V.double(), sigma=1e-20)  # float64 holds 1 / sigma^2
    with torch.no_grad():
        rbf.offsets.fill_(1e-3)
    assert bool(torch.isfinite(rbf()).all())
