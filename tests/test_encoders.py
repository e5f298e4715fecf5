"""Encoders as a whole: preprocessing, eval mode, constant images and bad input; the pixel-MEI baseline.

The Gabor cells are tested in test_encoders_gabor.py, the core + readout model in
test_encoders_core_readout.py, building encoders by name in test_encoders_registry.py.
"""

from __future__ import annotations

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
    eval_mode,
)
from meshmei.mei import gaussian_blur, pixel_mei


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


def test_eval_mode_restores_the_mode_even_after_an_error():
    model = CoreReadoutModel(2).train()
    with eval_mode(model) as m:
        assert m is model and not model.training
    assert model.training
    with pytest.raises(KeyError):
        with eval_mode(model):
            raise KeyError("inside")
    assert model.training
    model.eval()
    with eval_mode(model):
        pass
    assert not model.training


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


@pytest.mark.parametrize("kw", [dict(step_size=1e30), dict(init_std=1e30), dict(init_std=1e-30),
                                dict(blur_sigma=1e308)])
def test_pixel_mei_takes_any_finite_step_init_and_blur(kw):
    """Finite but extreme arguments: a step of 1e30 or a start of 1e30 overflowed the image's norm in float32
    and ended at an all-zero image with response 0; a start of 1e-30 underflowed it (an error blaming the
    objective); a blur of 1e308 raised OverflowError. Each now keeps the image on the norm sphere."""
    cell = GaborComplexCell()
    res = pixel_mei(cell, 0, image_size=24, steps=6, seeds=(0,), **kw)
    assert float(torch.linalg.vector_norm(res.image)) == pytest.approx(25.0, rel=1e-5)
    assert res.activation > 3 * res.history[0]  # it climbs (a complex cell: bound 1, the noise start 0.08)


def test_pixel_mei_of_a_model_without_norm_searches_the_renderable_images():
    """norm=None: the renders are standardised, not rescaled, so the pixel MEI's images are those whose
    intensities lie in [0, 1]; it searched the norm-25 sphere, so a linear neuron's 3D-MEI reached 3.5 times
    its pixel MEI. The box's optimum of a linear neuron is known: each pixel at the end its weight favours."""
    from meshmei.encoders import encoder_from_model

    w = torch.randn(1, 16 * 16, generator=torch.Generator().manual_seed(0))
    enc = encoder_from_model(lambda x: x.flatten(1) @ w.T, mean=0.5, std=0.05, norm=None, image_size=16)
    res = pixel_mei(enc, 0, steps=200, seeds=(0,), blur_sigma=0.0)  # white-noise weights: no blur
    lo, hi = (0.0 - 0.5) / 0.05, (1.0 - 0.5) / 0.05
    assert float(res.image.min()) >= lo - 1e-5 and float(res.image.max()) <= hi + 1e-5
    best = float(torch.where(w > 0, hi, lo).flatten() @ w.flatten())
    assert res.activation == pytest.approx(best, rel=1e-3)
    assert res.settings["space"] == "box"
    # every render lies in that box: the 3D-MEI cannot beat the pixel MEI
    image = torch.rand(1, 1, 16, 16)
    assert float(enc(image)[0, 0]) <= res.activation


@pytest.mark.parametrize("kw, match", [
    (dict(step_size=-0.2), "step_size must be positive and finite, got -0.2"),
    (dict(step_size=0.0), "step_size must be positive and finite, got 0.0"),
    (dict(step_size=float("nan")), "step_size must be positive and finite, got nan"),
    (dict(step_size=float("inf")), "step_size must be positive and finite, got inf"),
    (dict(blur_sigma=-3.0), "blur_sigma must be a finite non-negative number of pixels, got -3.0"),
    (dict(blur_sigma=float("nan")), "blur_sigma must be a finite non-negative number of pixels, got nan"),
    (dict(init_std=0.0), "init_std must be positive and finite, got 0.0"),
    (dict(init_std=float("inf")), "init_std must be positive and finite, got inf"),
    (dict(seeds=0), r"seeds must be a sequence of integers, e.g. \(0,\), got 0"),
    (dict(seeds=("a",)), r"seeds must be a sequence of integers, got \['a'\]"),
    (dict(seeds=(1, 0, 1)), r"seeds must be distinct; \[1\] repeated"),
    (dict(steps=None), "steps must be a positive integer, got None"),
    (dict(dtype="float32"), "dtype must be torch.float32 or torch.float64, got 'float32'"),
    (dict(dtype=torch.int64), "dtype must be torch.float32 or torch.float64, got torch.int64"),
    (dict(seeds=(2 ** 64,)), r"seeds must lie in \[0, 4294967295\], the seeds of distinct runs"),
    (dict(seeds=(0, 2 ** 32)), r"seeds must lie in \[0, 4294967295\], .*low 32 bits; 4294967296 gives the run of 0\)"),
    (dict(device="gpu"), "device 'gpu' cannot hold the image here"),
    (dict(device="meta"), "device 'meta' holds no values"),
    (dict(image_size=(16.7, 16)), r"image_size must be an int or a pair of integers \(H, W\), got \(16.7, 16\)"),
    (dict(image_size=10**6), r"image_size must be at most 8192 x 8192, got 1000000$"),  # the allocator's error
    (dict(image_size=(16, 8193)), r"image_size must be at most 8192 x 8192, got \(16, 8193\)$"),
])
def test_pixel_mei_refuses_bad_arguments_in_one_line(kw, match):
    # a negative step_size used to minimise the response; the others failed inside torch or ran a seed twice
    with pytest.raises(EncoderError, match=match) as err:
        pixel_mei(GaborSimpleCell(), 0, **{"image_size": 16, "steps": 2, "seeds": (0,), **kw})
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("neuron", [[3, 5], None, "0"])
def test_pixel_mei_takes_one_neuron_only(neuron):
    # [3, 5] used to run neuron 3 and None neuron 0, silently; "0" failed inside torch
    model = CoreReadoutModel(6)
    with pytest.raises(EncoderError, match="single index|must be an integer"):
        pixel_mei(model, neuron, image_size=16, steps=1, seeds=(0,))


def test_pixel_mei_refuses_a_non_finite_final_response():
    # a response that turns NaN at the last iterate, which minimize's guard (on the loss before each step)
    # never sees, must not come back as the seed's response (a step of 1e308 image norms once did this; such
    # steps are now taken as their direction)
    class LateNaN(GaborSimpleCell):
        calls = 0

        def respond(self, z, idx):
            LateNaN.calls += 1
            out = super().respond(z, idx)
            return out * float("nan") if LateNaN.calls > 1 else out

    with pytest.raises(EncoderError, match="the response became nan after the last step of seed 0"):
        pixel_mei(LateNaN(), 0, image_size=16, steps=1, seeds=(0,))


@pytest.mark.parametrize("neurons", ["0", ["0"], object()])
def test_a_neuron_that_is_not_an_integer_is_an_encoder_error(neurons):
    with pytest.raises(EncoderError, match="a neuron must be an integer index"):
        GaborSimpleCell().neuron_index(neurons)
