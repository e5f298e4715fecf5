"""Pixel-space MEI baseline: gradient ascent on the preprocessed image with blurred-gradient preconditioning.

The pixel MEI lives in the same image space as the 3D-MEI: the encoder's preprocessed images, whose L2
norm is fixed (25 by default). Each step takes the gradient of the neuron's response with respect to the
image, smooths it with a Gaussian blur (a preconditioner that favours smooth images early on; its width
decays to zero so the final iterate is an exact stationary point), moves along it, and projects the image
back to the norm sphere. Several random starts are run and the best kept.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass, field

import torch
import torch.nn.functional as TF

from ..encoders import Encoder, EncoderError

__all__ = ["PixelMEIResult", "pixel_mei", "gaussian_blur", "eval_mode"]


def gaussian_blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of images ``(B, C, H, W)`` with reflect padding; identity for ``sigma < 0.3``.

    The kernel is truncated at ``ceil(3 sigma)`` pixels (and at the image size) and normalised to sum 1.
    """
    sigma = float(sigma)
    if sigma < 0.3:
        return x
    H, W = x.shape[-2:]
    r = min(int(math.ceil(3 * sigma)), H - 1, W - 1)
    if r < 1:
        return x
    t = torch.arange(-r, r + 1, dtype=x.dtype, device=x.device)
    k = torch.exp(-t * t / (2 * sigma * sigma))
    k = k / k.sum()
    B, C = x.shape[:2]
    y = x.reshape(B * C, 1, H, W)
    y = TF.conv2d(TF.pad(y, (r, r, 0, 0), mode="reflect"), k.view(1, 1, 1, -1))
    y = TF.conv2d(TF.pad(y, (0, 0, r, r), mode="reflect"), k.view(1, 1, -1, 1))
    return y.view(B, C, H, W)


@contextlib.contextmanager
def eval_mode(module: torch.nn.Module):
    """Put ``module`` in eval mode (deterministic readout) for the block, then restore its mode."""
    was = module.training
    module.eval()
    try:
        yield module
    finally:
        module.train(was)


@dataclass(frozen=True)
class PixelMEIResult:
    """Outcome of :func:`pixel_mei`.

    Attributes
    ----------
    image : (1, 1, H, W) tensor
        The best preprocessed image (L2 norm ``encoder.preprocess.norm``); ``encoder.preprocess.to_image``
        maps it to pixel values.
    activation : float
        The neuron's response to ``image``.
    history : tuple of float
        Response at every step of the best seed.
    seed : int
        The seed that won.
    seed_activations : dict
        Final response per seed.
    settings : dict
        The arguments of the run.
    """

    image: torch.Tensor
    activation: float
    history: tuple
    seed: int
    seed_activations: dict = field(default_factory=dict)
    settings: dict = field(default_factory=dict)


def _check_size(image_size):
    if isinstance(image_size, int) and not isinstance(image_size, bool):
        image_size = (image_size, image_size)
    try:
        H, W = (int(s) for s in image_size)
    except (TypeError, ValueError):
        raise EncoderError(f"image_size must be an int or a pair (H, W), got {image_size!r}") from None
    if H < 2 or W < 2:
        raise EncoderError(f"image_size must be at least 2 x 2, got {image_size!r}")
    return H, W


def pixel_mei(encoder: Encoder, neuron: int, *, image_size=64, steps: int = 200, step_size: float = 0.2,
              blur_sigma: float = 2.0, seeds=(0, 1, 2), init_std: float = 1.0, dtype=torch.float32,
              device=None, progress: bool = False) -> PixelMEIResult:
    """Maximise one neuron's response over preprocessed images of fixed norm (the pixel-MEI baseline).

    Each step: ``g = blur(grad f(z), s_t)``, ``z <- z + eta_t * norm * g / |g|``, ``z <- norm * z / |z|``,
    with ``eta_t`` and the blur width ``s_t`` decaying from ``step_size`` and ``blur_sigma`` to zero on a
    cosine schedule. The encoder runs in eval mode (its mode is restored afterwards) and its parameters get
    no gradient.

    Parameters
    ----------
    encoder : Encoder
    neuron : int
    image_size : int or (H, W)
    steps : int
        Steps per seed (>= 1).
    step_size : float
        Initial step as a fraction of the image norm.
    blur_sigma : float
        Initial gradient blur in pixels (0 for plain gradient ascent).
    seeds : sequence of int
        One run per seed, from white noise with that seed; the highest final response wins.
    init_std : float
        Standard deviation of the initial noise before projection (only its direction matters).
    dtype, device : torch dtype and device of the image.
    progress : bool
        Show a tqdm progress bar.

    Returns
    -------
    PixelMEIResult
    """
    if not isinstance(encoder, Encoder):
        raise EncoderError(f"encoder must be a meshmei Encoder, got {type(encoder).__name__}")
    encoder.neuron_index(neuron)
    H, W = _check_size(image_size)
    if isinstance(steps, bool) or int(steps) != steps or steps < 1:
        raise EncoderError(f"steps must be a positive integer, got {steps!r}")
    seeds = [int(s) for s in seeds]
    if not seeds:
        raise EncoderError("seeds is empty; give at least one seed")
    norm = encoder.preprocess.norm
    best = None
    per_seed = {}
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(seeds) * int(steps), desc=f"pixel MEI neuron {neuron}")
    with eval_mode(encoder):
        for seed in seeds:
            g = torch.Generator().manual_seed(seed)
            z = (init_std * torch.randn(1, 1, H, W, generator=g, dtype=dtype)).to(device)
            z = norm * z / torch.linalg.vector_norm(z)
            hist = []
            for t in range(int(steps)):
                c = 0.5 * (1 + math.cos(math.pi * t / steps))  # 1 -> 0
                zt = z.detach().requires_grad_(True)
                f = encoder(zt, neuron, preprocessed=True)[0, 0]
                (grad,) = torch.autograd.grad(f, zt)
                hist.append(float(f.detach()))
                grad = gaussian_blur(grad, blur_sigma * c)
                gn = torch.linalg.vector_norm(grad)
                if float(gn) > 0:
                    z = z + (step_size * c + 1e-3) * norm * grad / gn
                z = norm * z / torch.linalg.vector_norm(z).clamp_min(torch.finfo(z.dtype).tiny)
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(act=f"{hist[-1]:.4f}")
            with torch.no_grad():
                final = float(encoder(z, neuron, preprocessed=True)[0, 0])
            hist.append(final)
            per_seed[seed] = final
            if best is None or final > best[1]:
                best = (z.detach(), final, tuple(hist), seed)
    if bar is not None:
        bar.close()
    settings = dict(image_size=[H, W], steps=int(steps), step_size=float(step_size), blur_sigma=float(blur_sigma),
                    seeds=seeds, init_std=float(init_std), dtype=str(dtype).replace("torch.", ""))
    return PixelMEIResult(best[0], best[1], best[2], best[3], per_seed, settings)
