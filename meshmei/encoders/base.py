"""What every encoder shares: the preprocessing, the base class with its neuron selection, and eval mode.

Every encoder first applies the same preprocessing (:class:`Preprocess`): the image is standardised
with the mean and standard deviation of the encoder's training images, then rescaled to a fixed L2 norm
(25 by default, as in the energy-guided-diffusion V4 models). The response is computed from that
preprocessed image, so the stimulus energy is fixed and only the *pattern* of the image matters.
"""

from __future__ import annotations

import contextlib
import math

import torch

from ..errors import EncoderError

__all__ = [
    "EncoderError",
    "DEFAULT_NORM",
    "Preprocess",
    "Encoder",
    "eval_mode",
    "frozen_encoder",
]

DEFAULT_NORM = 25.0


def check_images(x, name="images"):
    """Raise :class:`EncoderError` unless ``x`` is a float tensor of shape ``(B, 1, H, W)`` with B, H, W >= 1."""
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
        """``(x - mean) / std`` of images ``(B, 1, H, W)``, in their dtype."""
        return (x - self.mean.to(x.dtype)) / self.std.to(x.dtype)

    def rescale(self, z: torch.Tensor) -> torch.Tensor:
        """Rescale standardised images ``(B, 1, H, W)`` to norm ``norm`` (the constant-image guard lives here)."""
        flat = z.flatten(1)
        n = torch.linalg.vector_norm(flat, dim=1)  # (B,)
        if bool(torch.isinf(n).any()):  # squares beyond the dtype (z of 1e20 in float32): n was inf, every image 0
            big = flat.detach().abs().amax(1, keepdim=True).clamp_min(1.0)  # exact rows keep their norm below
            n = torch.where(torch.isinf(n), big[:, 0] * torch.linalg.vector_norm(flat / big, dim=1), n)
        return z * (self.norm / n.clamp_min(self.eps)).view(-1, 1, 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Preprocessed images ``(B, 1, H, W)`` of raw images ``x`` ``(B, 1, H, W)``."""
        check_images(x)
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
    def device(self) -> torch.device:
        """Where the encoder computes: the device of its parameters, else of its buffers (``encoder.to(...)``
        moves both). A 3D-MEI renders and optimises on this device."""
        for p in self.parameters():
            return p.device
        for b in self.buffers():
            return b.device
        return torch.device("cpu")

    @property
    def n_neurons(self) -> int:
        """How many neurons the encoder models."""
        raise NotImplementedError

    def neuron_index(self, neurons, device=None) -> torch.Tensor:
        """Validate a neuron selection (None, an int, or a sequence / 1-D tensor of ints) as an int64 tensor on
        ``device`` (the CPU when None; the checks run there, without a device synchronisation)."""
        n = self.n_neurons
        device = torch.device("cpu") if device is None else device
        if neurons is None:
            return torch.arange(n, device=device)
        if isinstance(neurons, (bool, str, bytes)):
            raise EncoderError(f"a neuron must be an integer index (neurons: None, an int or a sequence of ints), "
                               f"got {neurons!r}")
        try:
            idx = torch.as_tensor(neurons, device="cpu")
        except (TypeError, ValueError, RuntimeError):  # strings in a list, objects, ragged nesting
            raise EncoderError(f"a neuron must be an integer index (neurons: None, an int or a sequence of ints), "
                               f"got {neurons!r}") from None
        if idx.numel() == 0:
            raise EncoderError("neurons is empty; ask for at least one neuron")
        if idx.is_floating_point() or idx.dtype == torch.bool or idx.is_complex():
            raise EncoderError(f"neuron indices must be integers, got dtype {idx.dtype}")
        idx = idx.reshape(-1).long()
        if int(idx.min()) < 0 or int(idx.max()) >= n:
            raise EncoderError(f"neuron index out of range for {n} neurons: got {idx.tolist()[:10]}")
        return idx.to(device)

    def respond(self, z: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """Responses ``(B, k)`` of the neurons ``idx`` ``(k,)`` to preprocessed images ``z`` ``(B, 1, H, W)``."""
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
        z, idx = self.inputs(images, neurons, preprocessed=preprocessed)
        return self.respond(z, idx)

    def inputs(self, images: torch.Tensor, neurons=None, *, preprocessed: bool = False) -> tuple:
        """Checked images and neuron selection: ``(z, idx)``, ``z`` the ``(B, 1, H, W)`` preprocessed images
        and ``idx`` the ``(k,)`` int64 neuron indices (see :meth:`forward` for the arguments)."""
        check_images(images)
        idx = self.neuron_index(neurons, images.device)
        z = images if preprocessed else self.preprocess(images)
        return z, idx


@contextlib.contextmanager
def eval_mode(module: torch.nn.Module):
    """Put ``module`` in eval mode (deterministic readout) for the block, then restore the mode of each of
    its submodules as it was (a model in eval mode stays in eval mode; a frozen batch norm inside a model in
    training mode stays frozen)."""
    modes = [(m, m.training) for m in module.modules()]  # parents before children
    module.eval()
    try:
        yield module
    finally:
        for m, was in modes:  # a parent's train() sets its children; each child is then set to its own
            m.train(was)


@contextlib.contextmanager
def frozen_encoder(encoder: torch.nn.Module):
    """Eval mode and no parameter gradients for the block; the encoder's mode and flags are restored after."""
    params = list(encoder.parameters())
    flags = [p.requires_grad for p in params]
    with eval_mode(encoder):
        for p in params:
            p.requires_grad_(False)
        try:
            yield encoder
        finally:
            for p, fl in zip(params, flags):
                p.requires_grad_(fl)
