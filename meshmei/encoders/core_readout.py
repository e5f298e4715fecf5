"""The model class used for macaque V4: a convolutional core, a per-neuron Gaussian readout, and the demo model.

:class:`CoreReadoutModel` is a convolutional core followed by a per-neuron Gaussian readout and an
``ELU + 1`` output (Lurz et al. 2020); it loads a trained ``state_dict`` and records the training mean and
std it expects. :func:`load_demo_model` loads the one shipped with the package.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import torch
import torch.nn.functional as TF

from ..errors import EncoderError
from .base import DEFAULT_NORM, Encoder, Preprocess

__all__ = [
    "DefaultCore",
    "GaussianReadout",
    "CoreReadoutModel",
    "DEMO_MODEL_PATH",
    "load_demo_model",
    "is_demo_model",
]

DEMO_MODEL_PATH = Path(__file__).resolve().parent.parent / "data" / "demo_model.pt"


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
        w = next(self.readout.parameters(), None)
        if w is not None and z.dtype != w.dtype:  # the model computes in its own dtype; responses in z's
            return self.readout(self.core(z.to(w.dtype)), idx).to(z.dtype)
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
    with torch.device("cpu"):  # on the CPU whatever torch's default device; .to(device) moves it
        core = DefaultCore(**json.loads(blob["core"]))
        model = CoreReadoutModel.from_state_dict(blob["state_dict"], core)
    model._meshmei_demo = True  # read by is_demo_model: a run records such a model as kind "demo"
    return model


def is_demo_model(encoder) -> bool:
    """Whether ``encoder`` was made by :func:`load_demo_model` (its responses are those of the shipped model)."""
    return bool(getattr(encoder, "_meshmei_demo", False))
