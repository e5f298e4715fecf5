"""The core + Gaussian readout model: eval and training modes, the readout position, state_dict round trips."""

from __future__ import annotations

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
