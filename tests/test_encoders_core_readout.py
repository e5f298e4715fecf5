"""The core + Gaussian readout model: eval and training modes, the readout position, state_dict round trips."""

from __future__ import annotations

import math

import pytest
import torch

from meshmei.encoders import CoreReadoutModel


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


def test_images_of_another_dtype_than_the_weights_are_fed_in_the_models_dtype():
    """A float64 run with the (float32) demo model failed inside conv2d ("Input type (double) and bias type
    (float)"), then with meshmei's own error; dtype comes from the inputs (DESIGN), so the model now sees the
    images in its dtype and answers in theirs, gradient included, and a converted model runs as before."""
    from meshmei.mei import optimize_mei

    model = CoreReadoutModel(3).eval()
    x = torch.rand(2, 1, 32, 32, generator=torch.Generator().manual_seed(0))
    x64 = x.double().requires_grad_()
    out = model(x64)
    assert out.dtype == torch.float64
    torch.testing.assert_close(out, model(x).double(), rtol=1e-5, atol=1e-6)  # float32 inside (preprocessed in float64)
    out.sum().backward()
    assert x64.grad.dtype == torch.float64 and bool(torch.isfinite(x64.grad).all()) and float(x64.grad.abs().sum()) > 0
    for m in (model, model.double()):
        res = optimize_mei(m, 0, "sheet", steps=2, image_size=32, seeds=(0,), n_vertices=64, dtype="float64")
        assert res.V.dtype == torch.float64 and math.isfinite(res.activation)
        # the reported response is the model's for the returned render
        torch.testing.assert_close(m(res.render())[0, 0].double(), torch.tensor(res.activation, dtype=torch.float64),
                                   rtol=1e-5, atol=1e-6)
