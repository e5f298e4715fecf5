"""Pixel-space MEI baseline: gradient ascent on the preprocessed image with blurred-gradient preconditioning.

The pixel MEI lives in the same image space as the 3D-MEI: the encoder's preprocessed images, whose L2
norm is fixed (25 by default). Each step takes the gradient of the neuron's response with respect to the
image, smooths it with a Gaussian blur (a preconditioner that favours smooth images early on; its width
decays to zero so the final iterate is an exact stationary point), moves along it, and projects the image
back to the norm sphere. Several random starts are run and the best kept.

A lab's model built with ``norm=None`` sees its renders standardised but not rescaled: their space is
every image whose intensities lie in the renderer's range ``[0, 1]``, a box in the preprocessed space,
``[(lo - mean) / std, (hi - mean) / std]`` per pixel. The pixel MEI searches that box instead (steps
measured against half its diagonal, each iterate clamped into it), so that the 3D-MEI's response over the
pixel MEI's compares two images of one space.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
import torch.nn.functional as TF

from .._checks import check_distinct_seeds, check_non_negative, check_positive, is_integral
from ..encoders import Encoder, EncoderError, frozen_encoder
from ..optim import Budget, Progress, Schedule, Trace, minimize
from ..render.settings import MAX_IMAGE_SIZE
from .optimize import check_neuron

__all__ = ["PixelMEIResult", "pixel_mei", "pixel_image_size", "gaussian_blur", "NormalizedAscent"]


def gaussian_blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of images ``(B, C, H, W)`` with reflect padding; identity for ``sigma < 0.3``.

    The kernel is truncated at ``ceil(3 sigma)`` pixels (and at the image size) and normalised to sum 1.
    """
    sigma = float(sigma)
    if sigma < 0.3:
        return x
    H, W = x.shape[-2:]
    r = min(H - 1, W - 1) if 3 * sigma >= min(H, W) else min(int(math.ceil(3 * sigma)), H - 1, W - 1)
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


@dataclass(frozen=True)
class PixelMEIResult:
    """Outcome of :func:`pixel_mei`.

    Attributes
    ----------
    image : (1, 1, H, W) tensor (on the CPU, whatever device the run used)
        The best preprocessed image (L2 norm ``encoder.preprocess.norm``; for a model with ``norm=None``,
        every pixel within the renderable range, see the module docstring); ``encoder.preprocess.to_image``
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
    square = isinstance(image_size, int) and not isinstance(image_size, bool)
    try:
        H, W = (image_size, image_size) if square else image_size
    except (TypeError, ValueError):
        raise EncoderError(f"image_size must be an int or a pair (H, W), got {image_size!r}") from None
    if not all(is_integral(s) for s in (H, W)):  # int() would cut (16.7, 16) to 16 x 16 without a word
        raise EncoderError(f"image_size must be an int or a pair of integers (H, W), got {image_size!r}")
    H, W = int(H), int(W)
    if H < 2 or W < 2:
        raise EncoderError(f"image_size must be at least 2 x 2, got {image_size!r}")
    if max(H, W) > MAX_IMAGE_SIZE:  # 10**6 went to the allocator and came back as its RuntimeError
        raise EncoderError(f"image_size must be at most {MAX_IMAGE_SIZE} x {MAX_IMAGE_SIZE}, got {image_size!r}")
    return H, W


def _on_sphere(z: torch.Tensor, norm: float) -> torch.Tensor:
    """``norm * z / |z|``, also where ``|z|`` overflows or underflows the dtype (``z`` of 1e30 or 1e-30 in
    float32): then ``z`` is first divided by its largest entry. ``z`` must have a non-zero finite entry."""
    n = torch.linalg.vector_norm(z)
    if not (math.isfinite(float(n)) and float(n) > 1e-30):
        z = z / z.abs().amax()
        n = torch.linalg.vector_norm(z)
    return norm * z / n.clamp_min(torch.finfo(z.dtype).tiny)


class NormalizedAscent(torch.optim.Optimizer):
    """The pixel MEI's step rule on images of fixed L2 norm, as a torch optimiser of the loss ``-f``.

    Each step: ``g = blur(-grad, blur_sigma * factor)``, ``z <- z + (lr + min_step) * norm * g / |g|``, then
    ``z <- norm * z / |z|``. ``factor`` is the schedule's factor, which :func:`meshmei.optim.minimize`
    stores in the group beside the scheduled ``lr``; ``min_step`` keeps the last steps from vanishing.
    A step too long for the dtype (``lr`` of 1e30) is taken as the direction it tends to, ``g / |g|``.

    With ``box = (a, b)`` the images are those with every pixel in ``[a, b]`` instead: the step is
    ``(lr + min_step) * r * g / |g|`` with ``r`` half the box's diagonal, then ``z <- clamp(z, a, b)``.
    """

    def __init__(self, params, *, lr: float, blur_sigma: float, norm: float, min_step: float = 1e-3, box=None):
        super().__init__(params, dict(lr=lr, blur_sigma=blur_sigma, norm=norm, min_step=min_step, factor=1.0,
                                      box=box))

    @torch.no_grad()
    def step(self, closure=None):
        for group in self.param_groups:
            norm, box = group["norm"], group["box"]
            for z in group["params"]:
                if z.grad is None:
                    continue
                grad = gaussian_blur(-z.grad, group["blur_sigma"] * group["factor"])
                gn = torch.linalg.vector_norm(grad)
                if not math.isfinite(float(gn)) or float(gn) > 1e30:  # a gradient too large to square
                    grad = grad / grad.abs().amax()
                    gn = torch.linalg.vector_norm(grad)
                if box is not None:
                    a, b = box
                    if float(gn) > 0:
                        radius = 0.5 * (b - a) * math.sqrt(z.numel())
                        z.add_(min(group["lr"] + group["min_step"], 1e6) * radius * grad / gn)
                    z.clamp_(a, b)
                    continue
                if float(gn) > 0:
                    step = (group["lr"] + group["min_step"]) * norm
                    moved = z + step * grad / gn
                    if not bool(torch.isfinite(moved).all()):  # the step overflows: its direction is g / |g|
                        moved = z / step + grad / gn
                    z.copy_(moved)
                z.copy_(_on_sphere(z, norm))


def _check_args(encoder, neuron, image_size, steps, seeds, step_size, blur_sigma, init_std, dtype, device=None):
    """The checked arguments of :func:`pixel_mei`: ``(neuron, H, W, steps, seeds)``; ``EncoderError`` names
    the first bad one."""
    neuron = check_neuron(encoder, neuron, error=EncoderError)
    H, W = _check_size(image_size)
    own = getattr(encoder, "image_size", None)
    if own is not None and tuple(own) != (H, W):  # it failed at the first step, as "preprocessed images must be ..."
        raise EncoderError(f"image_size must be the model's input size {tuple(own)} (or None for it), got "
                           f"{image_size!r}")
    if not is_integral(steps) or steps < 1:
        raise EncoderError(f"steps must be a positive integer, got {steps!r}")
    for name, v in (("step_size", step_size), ("init_std", init_std)):
        check_positive(name, v, error=EncoderError)
    check_non_negative("blur_sigma", blur_sigma, unit=" of pixels", error=EncoderError)
    if isinstance(seeds, (str, bytes)) or not hasattr(seeds, "__iter__"):
        raise EncoderError(f"seeds must be a sequence of integers, e.g. (0,), got {seeds!r}")
    seeds = [s.item() if isinstance(s, torch.Tensor) and s.numel() == 1 else s for s in seeds]
    if not all(is_integral(s) for s in seeds):
        raise EncoderError(f"seeds must be a sequence of integers, got {seeds!r}")
    seeds = [int(s) for s in seeds]
    if not seeds:
        raise EncoderError("seeds is empty; give at least one seed")
    check_distinct_seeds(seeds, error=EncoderError)
    if dtype not in (torch.float32, torch.float64):
        raise EncoderError(f"dtype must be torch.float32 or torch.float64, got {dtype!r}")
    if device is not None:
        try:
            dev = torch.device(device)
            torch.empty(0, device=dev)
        except (RuntimeError, TypeError, AssertionError) as err:
            raise EncoderError(f"device {device!r} cannot hold the image here: {str(err).splitlines()[0]}") from None
        if dev.type == "meta":
            raise EncoderError("device 'meta' holds no values; give a device that computes (cpu, cuda)")
    return neuron, H, W, int(steps), seeds


def pixel_image_size(encoder: Encoder, render_size):
    """The size of the pixel MEI that compares with a 3D-MEI rendered at ``render_size``: a lab's model's own
    input size, ``(H, W)``, which its renders are cropped to (a non-square model's renders are made square at
    the longer side first), else ``render_size``."""
    return getattr(encoder, "image_size", None) or render_size


def pixel_mei(encoder: Encoder, neuron: int, *, image_size=None, steps: int = 200, step_size: float = 0.2,
              blur_sigma: float = 2.0, seeds=(0, 1, 2), init_std: float = 1.0, dtype=torch.float32,
              device=None, progress: bool = False) -> PixelMEIResult:
    """Maximise one neuron's response over preprocessed images of fixed norm (the pixel-MEI baseline).

    Each step: ``g = blur(grad f(z), s_t)``, ``z <- z + eta_t * norm * g / |g|``, ``z <- norm * z / |z|``,
    with ``eta_t`` and the blur width ``s_t`` decaying from ``step_size`` and ``blur_sigma`` to zero on a
    cosine schedule (:class:`NormalizedAscent` run by :func:`meshmei.optim.minimize`). The encoder runs
    in eval mode (its mode is restored afterwards) and its parameters get no gradient.

    Parameters
    ----------
    encoder : Encoder
    neuron : int
        One neuron's index.
    image_size : int or (H, W), optional
        Default: the model's own size for a :class:`~meshmei.encoders.ModelEncoder`, else 64. Each side 2 to
        8192 (``MAX_IMAGE_SIZE``).
    steps : int
        Steps per seed (>= 1).
    step_size : float
        Initial step as a fraction of the image norm (finite, > 0).
    blur_sigma : float
        Initial gradient blur in pixels (finite, >= 0; 0 for plain gradient ascent).
    seeds : sequence of int
        One run per seed (distinct), from white noise with that seed; the highest final response wins.
    init_std : float
        Standard deviation of the initial noise before projection (finite, > 0; only its direction matters).
    dtype, device : torch dtype (``torch.float32`` or ``torch.float64``) and device of the image (the encoder's
        device when None).
    progress : bool
        Show a tqdm progress bar.

    Returns
    -------
    PixelMEIResult

    Raises
    ------
    EncoderError
        A bad argument (the message names it), or a seed whose final response is not finite.
    """
    if image_size is None:
        image_size = pixel_image_size(encoder, 64)
    neuron, H, W, steps, seeds = _check_args(encoder, neuron, image_size, steps, seeds, step_size, blur_sigma,
                                             init_std, dtype, device)
    device = encoder.device if device is None else torch.device(device)
    pre = encoder.preprocess
    norm = pre.norm
    box = None
    if not getattr(pre, "renorm", True):  # norm=None: the box of renderable images (module docstring)
        with torch.no_grad():
            ends = pre.standardise(torch.tensor([0.0, 1.0], dtype=torch.float64, device=device).view(1, 1, 1, 2))
            ends = ends.flatten()
        box = (float(ends.min()), float(ends.max()))
    best, per_seed = None, {}
    bar = Progress(len(seeds) * steps, f"pixel MEI neuron {neuron}", enabled=progress,
                   postfix=lambda rec: {"act": f"{rec['response']:.4f}"})
    with frozen_encoder(encoder):
        for seed in seeds:
            g = torch.Generator().manual_seed(seed)
            z = (init_std * torch.randn(1, 1, H, W, generator=g, dtype=dtype, device="cpu")).to(device)  # as on the CPU
            if box is None:
                z = _on_sphere(z, norm).requires_grad_(True)
            else:  # the box's centre plus the noise, its largest pixel a quarter of the box's width out
                a, b = box
                z = (0.5 * (a + b) + 0.25 * (b - a) * z / z.abs().amax()).requires_grad_(True)

            def objective(point, z=z):
                f = encoder(z, neuron, preprocessed=True)[0, 0]
                return -f, {"response": float(f.detach())}

            trace = Trace()
            minimize(objective, NormalizedAscent([z], lr=step_size, blur_sigma=blur_sigma, norm=norm, box=box), Budget(steps),
                     schedule=Schedule("cosine", 0.0), trace=trace, progress=bar, error=EncoderError,
                     where=f" of seed {seed}")
            with torch.no_grad():
                final = float(encoder(z, neuron, preprocessed=True)[0, 0])
            if not math.isfinite(final):  # the last step is not checked by minimize, whose loss precedes it
                raise EncoderError(f"the response became {final} after the last step of seed {seed}; lower "
                                   f"step_size (step_size={step_size:g})")
            per_seed[seed] = final
            if best is None or final > best[1]:
                best = (z.detach().cpu(), final, tuple(r["response"] for r in trace.history) + (final,), seed)
    bar.close()
    settings = dict(image_size=[H, W], steps=steps, step_size=float(step_size), blur_sigma=float(blur_sigma),
                    seeds=seeds, init_std=float(init_std), dtype=str(dtype).replace("torch.", ""),
                    space="sphere" if box is None else "box")
    return PixelMEIResult(best[0], best[1], best[2], best[3], per_seed, settings)
