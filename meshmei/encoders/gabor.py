"""Simulated V1 cells with exactly known optima: Gabor filters, simple cells and complex (energy) cells.

Image coordinates, used by the Gabor parameters: ``x`` runs from -1 at the left edge to +1 at the right
edge, ``y`` from -1 at the top to +1 at the bottom (``grid_sample``'s convention), both over the full
image, so a parameter set means the same at any resolution.
"""

from __future__ import annotations

import math

import torch

from ..errors import EncoderError
from .base import DEFAULT_NORM, Encoder, Preprocess

__all__ = ["gabor_filters", "GaborSimpleCell", "GaborComplexCell"]


def _broadcast_params(**params):
    ts = {}
    for k, v in params.items():
        t = torch.as_tensor(v, dtype=torch.float64, device="cpu").reshape(-1)
        if t.numel() == 0 or not bool(torch.isfinite(t).all()):
            raise EncoderError(f"Gabor parameter {k} must be finite and non-empty, got {v!r}")
        ts[k] = t
    n = max(t.numel() for t in ts.values())
    for k, t in ts.items():
        if t.numel() not in (1, n):
            raise EncoderError(f"Gabor parameter {k} has {t.numel()} values; expected 1 or {n} (one per neuron)")
        ts[k] = t.expand(n).clone()
    for k in ("frequency", "sigma", "aspect"):
        if bool((ts[k] <= 0).any()):
            raise EncoderError(f"Gabor parameter {k} must be positive, got {ts[k].tolist()}")
    return ts


def gabor_filters(height: int, width: int, *, x0, y0, orientation, frequency, sigma, aspect, phase,
                  dtype=torch.float64, device=None) -> torch.Tensor:
    """Raw (not normalised) Gabor filters on an ``height x width`` pixel grid, one per neuron.

    ``g(x, y) = exp(-(u^2 + aspect^2 v^2) / (2 sigma^2)) * cos(2 pi frequency u / 2 + phase)`` with
    ``u = (x - x0) cos(orientation) + (y0 - y) sin(orientation)`` along the carrier's wave vector and
    ``v`` across it, in the image coordinates of the module docstring (``y0 - y`` so that a positive
    orientation turns counter-clockwise as seen on screen). ``frequency`` is in cycles per image width,
    ``sigma`` in units of half the image width (the ``[-1, 1]`` span is 2), angles in radians.

    Returns
    -------
    (N, height, width) tensor
    """
    p = _broadcast_params(x0=x0, y0=y0, orientation=orientation, frequency=frequency, sigma=sigma,
                          aspect=aspect, phase=phase)
    p = {k: v.to(device).view(-1, 1, 1) for k, v in p.items()}
    xs = (torch.arange(width, dtype=torch.float64, device=device) + 0.5) / width * 2 - 1
    ys = (torch.arange(height, dtype=torch.float64, device=device) + 0.5) / height * 2 - 1
    # non-square images keep square pixels: y is scaled like x (the width spans [-1, 1])
    ys = ys * (height / width)
    Y, X = torch.meshgrid(ys, xs, indexing="ij")
    dx, dy = X - p["x0"], p["y0"] - Y
    c, s = torch.cos(p["orientation"]), torch.sin(p["orientation"])
    u = dx * c + dy * s
    v = -dx * s + dy * c
    env = torch.exp(-(u**2 + (p["aspect"] * v) ** 2) / (2 * p["sigma"] ** 2))
    g = env * torch.cos(math.pi * p["frequency"] * u + p["phase"])
    return g.to(dtype)


class _GaborBank(Encoder):
    """Shared parameter handling and filter caching of the Gabor cells."""

    upper_bound = 1.0

    def __init__(self, *, x0=0.0, y0=0.0, orientation=0.0, frequency=4.0, sigma=0.35, aspect=1.0, phase=0.0,
                 mean=0.5, std=0.2, norm=DEFAULT_NORM, eps=1e-6):
        super().__init__(Preprocess(mean, std, norm, eps))
        self.params = _broadcast_params(x0=x0, y0=y0, orientation=orientation, frequency=frequency,
                                        sigma=sigma, aspect=aspect, phase=phase)
        self._cache = {}

    @property
    def n_neurons(self) -> int:
        return int(self.params["x0"].numel())

    def _raw(self, H, W, phase_shift=0.0):
        p = dict(self.params)
        p["phase"] = p["phase"] + phase_shift
        return gabor_filters(H, W, **p, device="cpu")  # float64, moved to the images' device by filters()

    def filters(self, height: int, width: int, dtype=torch.float64, device=None) -> torch.Tensor:
        """The unit-norm, zero-mean filters ``(N, k, height, width)`` (k = 1 simple, 2 complex); cached."""
        key = (int(height), int(width), dtype, str(device))
        if key not in self._cache:
            self._cache[key] = self._build(int(height), int(width)).to(dtype=dtype, device=device)
        return self._cache[key]

    def _apply_filters(self, z, idx):
        B, _, H, W = z.shape
        G = self.filters(H, W, z.dtype, z.device)[idx]  # (k_neurons, k, H, W)
        r = torch.einsum("bp,nkp->bnk", z.flatten(1), G.flatten(2))  # (B, n, k)
        return r / self.preprocess.norm

    def optimal_image(self, neuron: int, height: int, width: int, *, phase: float = 0.0, contrast: float = 1.0,
                      dtype=torch.float64) -> torch.Tensor:
        """A raw image ``(1, 1, H, W)`` whose response is the upper bound 1: ``mean + std * filter`` (scaled).

        For the complex cell, ``phase`` picks the member of the optimal family.
        """
        idx = self.neuron_index(neuron)
        G = self.filters(height, width)[idx[0]]  # (k, H, W) float64
        g = G[0] if G.shape[0] == 1 else math.cos(phase) * G[0] + math.sin(phase) * G[1]
        z = g * self.preprocess.norm
        return self.preprocess.to_image(z.view(1, 1, height, width), contrast).to(dtype)

    def extra_repr(self):
        keys = ("x0", "y0", "orientation", "frequency", "sigma", "aspect", "phase")
        return f"n_neurons={self.n_neurons}, " + ", ".join(f"{k}={self.params[k].tolist()}" for k in keys)


def _zero_mean_unit(g: torch.Tensor) -> torch.Tensor:
    g = g - g.mean(dim=(-2, -1), keepdim=True)
    n = torch.linalg.vector_norm(g.flatten(-2), dim=-1)
    if bool((n <= 1e-12).any()):
        raise EncoderError("a Gabor filter is constant on this pixel grid (sigma or frequency too small for the "
                           "image size); choose a larger sigma or lower frequency")
    return g / n[..., None, None]


class GaborSimpleCell(_GaborBank):
    """Simulated simple cells: the normalised inner product with a zero-mean, unit-norm Gabor filter.

    ``r = <P(x), g> / norm`` where ``P`` is the preprocessing (norm ``norm``) and ``g`` the filter after
    removing its mean and scaling to unit L2 norm on the image's pixel grid. By Cauchy-Schwarz ``|r| <= 1``,
    with equality exactly when ``P(x) = norm * g``, i.e. when the raw image is ``mean + c * g`` for any
    ``c > 0`` (:meth:`optimal_image`).

    Parameters (each a float, or a sequence with one value per neuron; they broadcast)
    ----------
    x0, y0 : float
        Centre, in image coordinates (``[-1, 1]``, y down).
    orientation : float
        Direction of the carrier's wave vector in radians, counter-clockwise from +x as seen on screen
        (0: vertical stripes).
    frequency : float
        Cycles per image width.
    sigma : float
        Envelope standard deviation in half image widths.
    aspect : float
        Envelope aspect ratio (``> 1`` shortens the envelope along the stripes).
    phase : float
        Carrier phase in radians (0: bright centre stripe).
    mean, std : float
        The "training" statistics the preprocessing standardises with. The defaults (0.5 and 0.2) match the
        renderer's gray background and the spread of its shades, so empty space is neutral.
    norm : float
        Image norm after preprocessing.
    eps : float
        Constant-image guard of :class:`Preprocess`.

    Examples
    --------
    >>> cell = GaborSimpleCell(orientation=0.3)
    >>> x = cell.optimal_image(0, 32, 32)
    >>> round(float(cell(x)), 6)
    1.0
    """

    def _build(self, H, W):
        return _zero_mean_unit(self._raw(H, W)).unsqueeze(1)  # (N, 1, H, W)

    def respond(self, z, idx):
        return self._apply_filters(z, idx)[..., 0]


class GaborComplexCell(_GaborBank):
    """Simulated complex cells: the energy model over an exactly orthonormal quadrature pair.

    The even (``phase``) and odd (``phase + pi/2``) Gabors are made zero-mean on the pixel grid, then
    orthonormalised (Gram-Schmidt: the even one normalised, the odd one stripped of its component along it
    and normalised), so both have unit norm and are exactly orthogonal. The response is
    ``r = sqrt(<P(x), g1>^2 + <P(x), g2>^2) / norm``, the length of the projection of the preprocessed image
    onto the pair's plane divided by its norm, so ``0 <= r <= 1`` and ``r = 1`` exactly for
    ``P(x) = norm * (cos(phi) g1 + sin(phi) g2)``, any phase ``phi``. A Gabor of any phase (same other
    parameters) lies in that plane after mean removal, so the response to it does not depend on its phase.

    At ``r = 0`` the square root's gradient would be infinite; there the response is exactly 0 with a zero
    gradient instead.

    Parameters are those of :class:`GaborSimpleCell`.

    Examples
    --------
    >>> cell = GaborComplexCell(orientation=0.3)
    >>> [round(float(cell(cell.optimal_image(0, 32, 32, phase=p))), 6) for p in (0.0, 1.0, 2.5)]
    [1.0, 1.0, 1.0]
    """

    def _build(self, H, W):
        even = _zero_mean_unit(self._raw(H, W))
        odd = self._raw(H, W, math.pi / 2)
        odd = odd - odd.mean(dim=(-2, -1), keepdim=True)
        odd = odd - (odd * even).sum((-2, -1), keepdim=True) * even
        odd = _zero_mean_unit(odd)
        return torch.stack([even, odd], dim=1)  # (N, 2, H, W)

    def respond(self, z, idx):
        ab = self._apply_filters(z, idx)  # (B, n, 2)
        e = (ab * ab).sum(-1)
        ok = e > 0
        return torch.where(ok, torch.where(ok, e, torch.ones_like(e)).sqrt(), torch.zeros_like(e))

    def phase_of(self, images: torch.Tensor, neuron: int = 0, *, preprocessed: bool = False) -> torch.Tensor:
        """Phase ``atan2(<P(x), g2>, <P(x), g1>)`` of images ``(B, 1, H, W)`` against the quadrature pair, ``(B,)``."""
        z, idx = self.inputs(images, neuron, preprocessed=preprocessed)
        ab = self._apply_filters(z, idx)[:, 0]  # (B, 2)
        return torch.atan2(ab[:, 1], ab[:, 0])
