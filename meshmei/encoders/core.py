"""Image-computable model neurons that map grayscale images ``(B, 1, H, W)`` to responses ``(B, n_neurons)``.

Every encoder first applies the same preprocessing (:class:`Preprocess`): the image is standardised
with the mean and standard deviation of the encoder's training images, then rescaled to a fixed L2 norm
(25 by default, as in the energy-guided-diffusion V4 models). The response is computed from that
preprocessed image, so the stimulus energy is fixed and only the *pattern* of the image matters.

Three kinds of neuron:

- :class:`GaborSimpleCell`: the inner product of the preprocessed image with a zero-mean, unit-norm Gabor
  filter, divided by the image norm. By Cauchy-Schwarz the response lies in ``[-1, 1]`` and equals 1
  exactly when the preprocessed image is the filter (times the norm).
- :class:`GaborComplexCell`: the energy model over a quadrature pair made exactly orthonormal after mean
  removal; the response is the length of the projection onto the pair's plane, so it lies in ``[0, 1]``,
  equals 1 for a Gabor of *any* phase and is exactly phase-invariant.
- :class:`CoreReadoutModel`: a convolutional core followed by a per-neuron Gaussian readout and an
  ``ELU + 1`` output (Lurz et al. 2020), the model class used for macaque V4; it loads a trained
  ``state_dict`` and records the training mean and std it expects.

Image coordinates, used by the Gabor parameters and the readout positions: ``x`` runs from -1 at the left
edge to +1 at the right edge, ``y`` from -1 at the top to +1 at the bottom (``grid_sample``'s convention),
both over the full image, so a parameter set means the same at any resolution.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import torch
import torch.nn.functional as TF

from ..errors import EncoderError

__all__ = [
    "EncoderError",
    "Preprocess",
    "Encoder",
    "gabor_filters",
    "GaborSimpleCell",
    "GaborComplexCell",
    "DefaultCore",
    "GaussianReadout",
    "CoreReadoutModel",
    "DEFAULT_NORM",
    "DEMO_MODEL_PATH",
    "load_demo_model",
]

DEFAULT_NORM = 25.0
DEMO_MODEL_PATH = Path(__file__).resolve().parent.parent / "data" / "demo_model.pt"


def _check_images(x, name="images"):
    if not isinstance(x, torch.Tensor):
        raise EncoderError(f"{name} must be a torch tensor of shape (B, 1, H, W), got {type(x).__name__}")
    if x.ndim != 4 or x.shape[1] != 1 or x.shape[0] == 0 or x.shape[2] == 0 or x.shape[3] == 0:
        raise EncoderError(f"{name} must have shape (B, 1, H, W) with B, H, W >= 1, got {tuple(x.shape)}")
    if not x.is_floating_point():
        raise EncoderError(f"{name} must be a float tensor, got dtype {x.dtype}")


def _finite_float(name, value, *, positive=False):
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise EncoderError(f"{name} must be a real number, got {value!r}") from None
    if not math.isfinite(v) or (positive and v <= 0):
        raise EncoderError(f"{name} must be {'positive and ' if positive else ''}finite, got {value!r}")
    return v


class Preprocess(torch.nn.Module):
    """Standardise with the training mean / std, then rescale each image to L2 norm ``norm``.

    ``z = (x - mean) / std``, then ``z * norm / max(|z|, eps)`` with ``|z|`` the L2 norm of each image over
    all its pixels.

    Constant images: an image equal to the training mean everywhere standardises to exactly zero, whose
    direction is undefined. The ``max(|z|, eps)`` guard returns it as the zero image (every Gabor response
    is then 0) with finite gradients, instead of dividing 0 by 0. Any image whose standardised norm is at
    least ``eps`` is rescaled exactly. A constant image that differs from the mean is an ordinary image: it
    is rescaled to norm ``norm`` like any other (and, being uniform, is invisible to zero-mean filters).

    Parameters
    ----------
    mean, std : float
        Training mean and standard deviation (``std > 0``); stored as buffers so that they travel with a
        model's ``state_dict``.
    norm : float
        Target L2 norm of the preprocessed image (> 0).
    eps : float
        Floor on the standardised norm (> 0).
    """

    def __init__(self, mean: float = 0.0, std: float = 1.0, norm: float = DEFAULT_NORM, eps: float = 1e-6):
        super().__init__()
        mean = _finite_float("mean", mean)
        std = _finite_float("std", std, positive=True)
        self.norm = _finite_float("norm", norm, positive=True)
        self.eps = _finite_float("eps", eps, positive=True)
        self.register_buffer("mean", torch.tensor(mean, dtype=torch.float64))
        self.register_buffer("std", torch.tensor(std, dtype=torch.float64))

    def standardise(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean.to(x.dtype)) / self.std.to(x.dtype)

    def rescale(self, z: torch.Tensor) -> torch.Tensor:
        """Rescale standardised images ``(B, 1, H, W)`` to norm ``norm`` (the constant-image guard lives here)."""
        n = torch.linalg.vector_norm(z.flatten(1), dim=1).clamp_min(self.eps)  # (B,)
        return z * (self.norm / n).view(-1, 1, 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        _check_images(x)
        return self.rescale(self.standardise(x))

    def to_image(self, z: torch.Tensor, contrast: float = 1.0) -> torch.Tensor:
        """Map a preprocessed image back to pixel values: ``mean + contrast * std * z / norm * sqrt(H W)``.

        Preprocessing forgets the contrast, so any ``contrast > 0`` gives an image with the same
        preprocessed value; ``contrast=1`` gives pixels whose standardised RMS is 1.
        """
        hw = z.shape[-1] * z.shape[-2]
        return self.mean.to(z.dtype) + contrast * self.std.to(z.dtype) * z * (math.sqrt(hw) / self.norm)

    def extra_repr(self):
        return f"mean={float(self.mean):.4g}, std={float(self.std):.4g}, norm={self.norm:g}, eps={self.eps:g}"


class Encoder(torch.nn.Module):
    """Base class: ``forward(images, neurons=None, preprocessed=False) -> (B, len(neurons))``.

    Subclasses implement :meth:`respond` on preprocessed images for a given index tensor of neurons.

    Attributes
    ----------
    preprocess : Preprocess
    n_neurons : int
    upper_bound : float or None
        A response no image can exceed (1 for the Gabor cells), or None when unknown.
    """

    upper_bound: float | None = None

    def __init__(self, preprocess: Preprocess):
        super().__init__()
        self.preprocess = preprocess

    @property
    def n_neurons(self) -> int:
        raise NotImplementedError

    def neuron_index(self, neurons, device=None) -> torch.Tensor:
        """Validate a neuron selection (None, an int, or a sequence / 1-D tensor of ints) as an int64 tensor."""
        n = self.n_neurons
        if neurons is None:
            return torch.arange(n, device=device)
        if isinstance(neurons, bool):
            raise EncoderError(f"neurons must be None, an int or a sequence of ints, got {neurons!r}")
        idx = torch.as_tensor(neurons, device=device)
        if idx.numel() == 0:
            raise EncoderError("neurons is empty; ask for at least one neuron")
        if idx.is_floating_point() or idx.dtype == torch.bool or idx.is_complex():
            raise EncoderError(f"neuron indices must be integers, got dtype {idx.dtype}")
        idx = idx.reshape(-1).long()
        if int(idx.min()) < 0 or int(idx.max()) >= n:
            raise EncoderError(f"neuron index out of range for {n} neurons: got {idx.tolist()[:10]}")
        return idx

    def respond(self, z: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def forward(self, images: torch.Tensor, neurons=None, *, preprocessed: bool = False) -> torch.Tensor:
        """Responses of the selected neurons.

        Parameters
        ----------
        images : (B, 1, H, W) float tensor
            Raw images (pixel values), or already preprocessed ones with ``preprocessed=True``.
        neurons : None, int, or sequence of ints
            Which neurons to evaluate (all by default); only these are computed.

        Returns
        -------
        (B, k) tensor, k the number of neurons selected.
        """
        _check_images(images)
        idx = self.neuron_index(neurons, images.device)
        z = images if preprocessed else self.preprocess(images)
        return self.respond(z, idx)


def _broadcast_params(**params):
    ts = {}
    for k, v in params.items():
        t = torch.as_tensor(v, dtype=torch.float64).reshape(-1)
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
        return gabor_filters(H, W, **p)  # float64

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
        _check_images(images)
        idx = self.neuron_index(neuron, images.device)
        z = images if preprocessed else self.preprocess(images)
        ab = self._apply_filters(z, idx)[:, 0]  # (B, 2)
        return torch.atan2(ab[:, 1], ab[:, 0])


class DefaultCore(torch.nn.Module):
    """A small convolutional core: three ELU conv layers at full resolution, ``(B, 1, H, W) -> (B, C, H, W)``.

    Parameters
    ----------
    channels : int
        Feature channels ``C``.
    kernel_sizes : tuple of int
        Odd kernel sizes of the layers (the first is the largest: a V1-like front end).
    strides : tuple of int, optional
        Stride of each layer (default all 1); a stride of 2 in the first layer quarters the cost.
    """

    def __init__(self, channels: int = 16, kernel_sizes=(9, 5, 5), strides=None):
        super().__init__()
        if isinstance(channels, bool) or int(channels) != channels or channels < 1:
            raise EncoderError(f"channels must be a positive integer, got {channels!r}")
        strides = tuple(strides) if strides is not None else (1,) * len(kernel_sizes)
        if len(strides) != len(kernel_sizes) or any(int(s) != s or s < 1 for s in strides):
            raise EncoderError(f"strides must be positive integers, one per layer, got {strides!r}")
        layers, cin = [], 1
        for k, stride in zip(kernel_sizes, strides):
            if int(k) != k or k < 1 or k % 2 == 0:
                raise EncoderError(f"kernel sizes must be odd positive integers, got {kernel_sizes!r}")
            layers += [torch.nn.Conv2d(cin, channels, int(k), stride=int(stride), padding=int(k) // 2), torch.nn.ELU()]
            cin = channels
        self.net = torch.nn.Sequential(*layers)
        self.out_channels = int(channels)

    def forward(self, x):
        return self.net(x)


class GaussianReadout(torch.nn.Module):
    """Per-neuron Gaussian readout: sample the feature map at a learned position, weight the channels.

    For neuron ``n`` with position ``mu_n`` in ``[-1, 1]^2`` (``grid_sample`` convention: x right, y down,
    ``align_corners=True``), scale ``sigma_n``, channel weights ``w_n`` and bias ``b_n``, the output is
    ``ELU(w_n . phi(p_n) + b_n) + 1`` where ``phi(p)`` is the bilinearly sampled feature vector at ``p``.
    In training mode ``p_n = mu_n + sigma_n * noise`` (a fresh standard normal sample per image and
    neuron, the reparameterised Gaussian readout of Lurz et al. 2020); in eval mode ``p_n = mu_n``.
    Positions are clamped to ``[-1, 1]``.

    Parameters
    ----------
    n_neurons, in_channels : int
    init_mu_range : float
        Initial positions are uniform in ``[-init_mu_range, init_mu_range]^2``.
    init_sigma : float
        Initial scale.
    """

    def __init__(self, n_neurons: int, in_channels: int, *, init_mu_range: float = 0.5, init_sigma: float = 0.2):
        super().__init__()
        for name, v in (("n_neurons", n_neurons), ("in_channels", in_channels)):
            if isinstance(v, bool) or int(v) != v or v < 1:
                raise EncoderError(f"{name} must be a positive integer, got {v!r}")
        n, c = int(n_neurons), int(in_channels)
        self.mu = torch.nn.Parameter(torch.empty(n, 2).uniform_(-init_mu_range, init_mu_range))
        self.sigma = torch.nn.Parameter(torch.full((n,), float(init_sigma)))
        self.features = torch.nn.Parameter(torch.randn(n, c) / math.sqrt(c))
        self.bias = torch.nn.Parameter(torch.zeros(n))

    @property
    def n_neurons(self) -> int:
        return int(self.mu.shape[0])

    def forward(self, feats: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """Responses ``(B, len(idx))`` from a feature map ``(B, C, h, w)``."""
        B = feats.shape[0]
        mu = self.mu[idx].to(feats.dtype)  # (k, 2)
        grid = mu.unsqueeze(0).expand(B, -1, -1)
        if self.training:
            noise = torch.randn(B, mu.shape[0], 2, dtype=feats.dtype, device=feats.device)
            grid = grid + self.sigma[idx].to(feats.dtype).abs().view(1, -1, 1) * noise
        grid = grid.clamp(-1, 1).unsqueeze(2)  # (B, k, 1, 2)
        phi = TF.grid_sample(feats, grid, mode="bilinear", padding_mode="border", align_corners=True)
        phi = phi[..., 0]  # (B, C, k)
        y = torch.einsum("bck,kc->bk", phi, self.features[idx].to(feats.dtype)) + self.bias[idx].to(feats.dtype)
        return TF.elu(y) + 1.0


class CoreReadoutModel(Encoder):
    """A core + Gaussian readout model: ``(B, 1, H, W)`` images to ``(B, n_neurons)`` positive responses.

    Parameters
    ----------
    n_neurons : int
    core : torch.nn.Module, optional
        Maps ``(B, 1, H, W)`` preprocessed images to ``(B, C, h, w)`` features and has an ``out_channels``
        attribute (or give ``core_channels``). Default: :class:`DefaultCore`.
    core_channels : int, optional
        ``C`` for a custom core without ``out_channels``.
    mean, std : float
        Mean and standard deviation of the training images, recorded in the ``state_dict``
        (``preprocess.mean``, ``preprocess.std``).
    norm, eps : float
        See :class:`Preprocess`.

    Examples
    --------
    >>> model = CoreReadoutModel(3).eval()
    >>> model(torch.rand(2, 1, 32, 32), neurons=[2]).shape
    torch.Size([2, 1])
    """

    def __init__(self, n_neurons: int, core: torch.nn.Module | None = None, *, core_channels: int | None = None,
                 mean: float = 0.0, std: float = 1.0, norm: float = DEFAULT_NORM, eps: float = 1e-6,
                 readout_kwargs: dict | None = None):
        super().__init__(Preprocess(mean, std, norm, eps))
        self.core = core if core is not None else DefaultCore()
        channels = core_channels if core_channels is not None else getattr(self.core, "out_channels", None)
        if channels is None:
            raise EncoderError("a custom core needs an out_channels attribute or core_channels=...")
        self.readout = GaussianReadout(n_neurons, channels, **(readout_kwargs or {}))

    @property
    def n_neurons(self) -> int:
        return self.readout.n_neurons

    def respond(self, z, idx):
        return self.readout(self.core(z), idx)

    @classmethod
    def from_state_dict(cls, state: dict, core: torch.nn.Module | None = None, **kwargs) -> "CoreReadoutModel":
        """Build a model whose sizes fit ``state`` (a ``state_dict``, e.g. from ``torch.load``) and load it.

        ``n_neurons`` and the channel count come from the readout's tensors; training mean and std from
        ``preprocess.mean`` / ``preprocess.std``. Unknown or missing keys raise :class:`EncoderError`.
        """
        if not isinstance(state, dict) or "readout.features" not in state:
            keys = list(state)[:8] if isinstance(state, dict) else type(state).__name__
            raise EncoderError(f"not a CoreReadoutModel state_dict (no 'readout.features'); got keys {keys}")
        n, c = state["readout.features"].shape
        model = cls(int(n), core, core_channels=int(c), **kwargs)
        try:
            model.load_state_dict(state)
        except RuntimeError as err:
            raise EncoderError(f"state_dict does not fit the model: {err}") from None
        return model.eval()


def load_demo_model(path=None) -> CoreReadoutModel:
    """The shipped demo model: a core + Gaussian readout trained on simulated neurons (eval mode).

    It is a *digital twin of simulated neurons*, not of recorded V4 data: ``data_gen/make_demo_model.py``
    renders random deformed meshes under random poses and lights with meshmei's own renderer, computes the
    responses of a population of ground-truth model neurons (Gabor energy units, simple cells, curvature
    and shading units) and fits the model to them. The test-set correlation of each neuron and the
    ground-truth definitions are in ``demo_model.json`` beside the weights; see ``docs/encoders.md``.

    Parameters
    ----------
    path : str or Path, optional
        A file written by the same script (default: the one inside the package).
    """
    path = Path(path) if path is not None else DEMO_MODEL_PATH
    if not path.is_file():
        raise EncoderError(f"no demo model at {path}; run data_gen/make_demo_model.py to make it")
    blob = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(blob, dict) or "state_dict" not in blob or "core" not in blob:
        raise EncoderError(f"{path} is not a meshmei demo model file")
    core = DefaultCore(**json.loads(blob["core"]))
    model = CoreReadoutModel.from_state_dict(blob["state_dict"], core)
    model._meshmei_demo = True
    return model
