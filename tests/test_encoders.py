"""Encoders: preprocessing, the exact bounds of the Gabor cells, the core + readout model, the pixel-MEI baseline."""

from __future__ import annotations

import math

import pytest
import torch

from meshmei.encoders import (
    CoreReadoutModel,
    DefaultCore,
    EncoderError,
    GaborComplexCell,
    GaborSimpleCell,
    GaussianReadout,
    Preprocess,
    gabor_filters,
)
from meshmei.mei.pixel import gaussian_blur, pixel_mei

CELL_PARAMS = [
    {},
    dict(x0=0.2, y0=-0.1, orientation=1.1, frequency=6.0, sigma=0.2, aspect=1.5, phase=0.7),
]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_preprocess_standardises_and_rescales(dtype):
    pre = Preprocess(mean=0.3, std=2.0, norm=25.0)
    x = torch.rand(3, 1, 10, 12, dtype=dtype)
    z = pre(x)
    assert z.dtype == dtype
    torch.testing.assert_close(torch.linalg.vector_norm(z.flatten(1), dim=1), torch.full((3,), 25.0, dtype=dtype))
    # the direction is that of the standardised image; the std cancels
    ref = (x - 0.3) / torch.linalg.vector_norm((x - 0.3).flatten(1), dim=1).view(-1, 1, 1, 1) * 25
    torch.testing.assert_close(z, ref)
    # to_image inverts preprocessing up to contrast
    torch.testing.assert_close(pre(pre.to_image(z, contrast=0.3)), z)


def test_constant_image_is_finite_with_finite_gradient():
    for cell in (GaborSimpleCell(), GaborComplexCell(), CoreReadoutModel(2, mean=0.5).eval()):
        x = torch.full((2, 1, 16, 16), 0.5, requires_grad=True)  # equals the training mean: standardises to 0
        r = cell(x)
        r.sum().backward()
        assert torch.isfinite(r).all() and torch.isfinite(x.grad).all()
        if not isinstance(cell, CoreReadoutModel):
            assert torch.equal(r, torch.zeros_like(r))
    # a constant image away from the mean is an ordinary (uniform) image: zero-mean filters ignore it
    r = GaborSimpleCell()(torch.full((1, 1, 16, 16), 0.9))
    assert abs(float(r)) < 1e-6


@pytest.mark.parametrize("params", CELL_PARAMS)
@pytest.mark.parametrize("size", [(32, 32), (40, 56)])
def test_simple_cell_bound_reached_by_the_filter_itself(params, size):
    H, W = size
    cell = GaborSimpleCell(mean=0.0, std=1.0, **params)
    g = cell.filters(H, W)[0]  # (1, H, W) unit-norm, zero-mean
    torch.testing.assert_close(g.sum(), torch.tensor(0.0, dtype=torch.float64), atol=1e-12, rtol=0)
    torch.testing.assert_close(g.norm(), torch.tensor(1.0, dtype=torch.float64))
    r = cell(g.view(1, 1, H, W))
    assert abs(float(r) - 1.0) < 1e-12
    # any image of the form mean + c * filter reaches it under other statistics too
    cell = GaborSimpleCell(**params)
    assert abs(float(cell(cell.optimal_image(0, H, W, contrast=0.2))) - 1.0) < 1e-12
    # the negative filter gives exactly -1; random images stay inside [-1, 1]
    assert abs(float(cell(cell.optimal_image(0, H, W, contrast=-0.2))) + 1.0) < 1e-12
    r = cell(torch.rand(64, 1, H, W, dtype=torch.float64))
    assert r.abs().max() < 1


@pytest.mark.parametrize("params", CELL_PARAMS)
def test_complex_cell_quadrature_pair_and_phase_invariance(params):
    H = W = 48
    cell = GaborComplexCell(**params)
    G = cell.filters(H, W)[0].flatten(1)  # (2, H*W)
    torch.testing.assert_close(G @ G.T, torch.eye(2, dtype=torch.float64), atol=1e-12, rtol=0)
    torch.testing.assert_close(G.sum(1), torch.zeros(2, dtype=torch.float64), atol=1e-12, rtol=0)
    # exact optima for every phase
    for phi in torch.linspace(0, 2 * math.pi, 9):
        r = cell(cell.optimal_image(0, H, W, phase=float(phi)))
        assert abs(float(r) - 1.0) < 1e-12
        assert abs(math.remainder(float(cell.phase_of(cell.optimal_image(0, H, W, phase=float(phi)))) - float(phi),
                                  2 * math.pi)) < 1e-9
    # mean-free raw Gabors of any phase (same other parameters) give the same response: the pair spans them
    p = dict(x0=0.0, y0=0.0, orientation=0.0, frequency=4.0, sigma=0.35, aspect=1.0)
    p.update({k: v for k, v in params.items() if k != "phase"})
    raw = torch.stack([gabor_filters(H, W, phase=ph, **p)[0] for ph in (0.0, 0.4, 1.9, 3.0, 5.5)])
    imgs = 0.5 + 0.1 * (raw - raw.mean((1, 2), keepdim=True))
    r = cell(imgs.unsqueeze(1))
    assert float(r.max() - r.min()) < 1e-12
    assert abs(float(r.max()) - 1.0) < 1e-12
    # bounded on random images
    assert float(cell(torch.rand(64, 1, H, W, dtype=torch.float64)).max()) < 1


def test_gabor_bank_evaluates_only_requested_neurons():
    cell = GaborComplexCell(orientation=[0.0, 0.5, 1.0], frequency=[3.0, 4.0, 5.0])
    assert cell.n_neurons == 3
    x = torch.rand(4, 1, 32, 32)
    full = cell(x)
    torch.testing.assert_close(cell(x, neurons=[2, 0]), full[:, [2, 0]])
    torch.testing.assert_close(cell(x, neurons=1), full[:, [1]])


def test_orientation_convention():
    # orientation 0: wave vector along +x, vertical stripes (constant down each column)
    g = gabor_filters(16, 16, x0=0, y0=0, orientation=0.0, frequency=2.0, sigma=100.0, aspect=1.0, phase=0.0)[0]
    torch.testing.assert_close(g, g[:1].expand(16, 16), atol=1e-3, rtol=0)
    # orientation pi/2: horizontal stripes
    g = gabor_filters(16, 16, x0=0, y0=0, orientation=math.pi / 2, frequency=2.0, sigma=100.0, aspect=1.0, phase=0.0)[0]
    torch.testing.assert_close(g, g[:, :1].expand(16, 16), atol=1e-3, rtol=0)


def test_core_readout_model_eval_training_and_state_dict(tmp_path):
    torch.manual_seed(0)
    model = CoreReadoutModel(5, mean=0.4, std=0.2)
    x = torch.rand(3, 1, 32, 32)
    model.eval()
    r = model(x)
    assert r.shape == (3, 5) and bool((r > 0).all())  # ELU + 1 is positive
    torch.testing.assert_close(model(x), r)  # eval: deterministic
    torch.testing.assert_close(model(x, neurons=[4, 1]), r[:, [4, 1]])
    model.train()
    assert not torch.allclose(model(x), r)  # training: sampled positions
    model.eval()
    # eval mode samples exactly at mu: compare with a direct bilinear lookup at a pixel centre
    feats = model.core(model.preprocess(x))
    with torch.no_grad():
        model.readout.mu[0] = torch.tensor([-1.0, 1.0])  # bottom-left corner pixel (align_corners=True)
    y = feats[:, :, -1, 0] @ model.readout.features[0] + model.readout.bias[0]
    torch.testing.assert_close(model(x, neurons=0)[:, 0], torch.nn.functional.elu(y) + 1)
    # state dict round trip records the statistics
    path = tmp_path / "m.pt"
    torch.save(model.state_dict(), path)
    loaded = CoreReadoutModel.from_state_dict(torch.load(path))
    assert float(loaded.preprocess.mean) == pytest.approx(0.4) and float(loaded.preprocess.std) == pytest.approx(0.2)
    torch.testing.assert_close(loaded(x), model(x))
    # a custom core
    core = torch.nn.Sequential(torch.nn.Conv2d(1, 3, 3, padding=1), torch.nn.ReLU())
    m2 = CoreReadoutModel(2, core, core_channels=3).eval()
    assert m2(x).shape == (3, 2)


def test_bad_input_raises_encoder_error():
    cell = GaborSimpleCell()
    assert issubclass(EncoderError, ValueError)
    with pytest.raises(EncoderError, match=r"\(B, 1, H, W\)"):
        cell(torch.rand(2, 3, 8, 8))
    with pytest.raises(EncoderError, match="shape"):
        cell(torch.rand(8, 8))
    with pytest.raises(EncoderError, match="float"):
        cell(torch.ones(1, 1, 8, 8, dtype=torch.int64))
    with pytest.raises(EncoderError, match="out of range"):
        cell(torch.rand(1, 1, 8, 8), neurons=3)
    with pytest.raises(EncoderError, match="integers"):
        cell(torch.rand(1, 1, 8, 8), neurons=0.5)
    with pytest.raises(EncoderError, match="empty"):
        cell(torch.rand(1, 1, 8, 8), neurons=[])
    with pytest.raises(EncoderError, match="std"):
        Preprocess(std=0.0)
    with pytest.raises(EncoderError, match="frequency"):
        GaborSimpleCell(frequency=-1.0)
    with pytest.raises(EncoderError, match="1 or 3"):
        GaborSimpleCell(orientation=[0.0, 1.0, 2.0], frequency=[1.0, 2.0])
    with pytest.raises(EncoderError, match="finite"):
        GaborSimpleCell(sigma=float("nan"))
    with pytest.raises(EncoderError, match="n_neurons"):
        GaussianReadout(0, 4)
    with pytest.raises(EncoderError, match="channels"):
        DefaultCore(channels=0)
    with pytest.raises(EncoderError, match="state_dict"):
        CoreReadoutModel.from_state_dict({"a": torch.zeros(1)})
    with pytest.raises(EncoderError, match="fit"):
        sd = CoreReadoutModel(2).state_dict()
        sd["core.net.0.weight"] = torch.zeros(16, 1, 3, 3)
        CoreReadoutModel.from_state_dict(sd)
    with pytest.raises(EncoderError, match="constant"):
        GaborSimpleCell(sigma=1e-4)(torch.rand(1, 1, 8, 8))
    with pytest.raises(EncoderError, match="encoder"):
        pixel_mei(object(), 0)
    with pytest.raises(EncoderError, match="image_size"):
        pixel_mei(cell, 0, image_size=1)
    with pytest.raises(EncoderError, match="seeds"):
        pixel_mei(cell, 0, seeds=())


def test_gaussian_blur_preserves_constants_and_sum():
    x = torch.full((1, 1, 12, 10), 2.0, dtype=torch.float64)
    torch.testing.assert_close(gaussian_blur(x, 1.5), x)
    y = torch.zeros(1, 1, 21, 21, dtype=torch.float64)
    y[0, 0, 10, 10] = 1
    b = gaussian_blur(y, 1.0)
    torch.testing.assert_close(b.sum(), torch.tensor(1.0, dtype=torch.float64))
    torch.testing.assert_close(b[0, 0], b[0, 0].T)


@pytest.mark.parametrize("cls", [GaborSimpleCell, GaborComplexCell])
def test_pixel_mei_reaches_the_bound(cls):
    cell = cls(orientation=0.6, frequency=5.0, sigma=0.25, x0=0.1)
    res = pixel_mei(cell, 0, image_size=32, steps=60, seeds=(0, 1))
    assert res.activation >= 0.99
    assert abs(float(torch.linalg.vector_norm(res.image)) - 25.0) < 1e-3
    torch.testing.assert_close(cell(res.image, preprocessed=True)[0, 0], torch.tensor(res.activation))
    assert set(res.seed_activations) == {0, 1}


def test_pixel_mei_deterministic_and_restores_mode():
    model = CoreReadoutModel(2).train()
    a = pixel_mei(model, 1, image_size=16, steps=5, seeds=(3,))
    b = pixel_mei(model, 1, image_size=16, steps=5, seeds=(3,))
    assert model.training
    assert torch.equal(a.image, b.image) and a.history == b.history
    assert model.readout.mu.grad is None  # encoder parameters get no gradient
