"""A lab's own model as a meshmei encoder: any module or callable that maps images ``(B, C, H, W)`` to
responses ``(B, N)``, with the training statistics in the model's own pixel units.

The renderer's intensities lie in ``[0, 1]`` (the background is 0.5). They reach the model by one rule:

1. resize to the model's ``image_size`` (area-weighted, anti-aliased) when the image arrives at another size
   (meshmei renders at the model's size where it can, so this is a fallback);
2. map to the model's pixel units, ``p = lo + (hi - lo) * intensity`` with ``pixel_range = (lo, hi)``
   (``(0, 255)`` for models trained on 8-bit images), optionally clipped to that range (``clip=True``);
3. standardise with the training ``mean`` and ``std`` (in the same units) and rescale each image to L2 norm
   ``norm`` (:class:`~meshmei.encoders.Preprocess`; ``norm=None`` skips the rescaling);
4. repeat the gray channel ``channels`` times (3 for an ImageNet-style core);
5. call the model (or each model of an ensemble, averaging their outputs as neuralpredictors'
   ``EnsembleModel`` does) with ``forward_kwargs`` (e.g. ``{"data_key": "all_sessions"}``) and pick the
   response with ``output`` when it returns a tuple or dict.

The model runs in eval mode with no parameter gradients whenever meshmei optimises against it
(:func:`~meshmei.encoders.frozen_encoder`); its mode and flags are restored afterwards.
"""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import torch
import torch.nn.functional as nnf

from .._checks import check_positive
from ..errors import EncoderError
from .base import DEFAULT_NORM, Encoder, Preprocess, eval_mode

__all__ = ["ModelEncoder", "PixelPreprocess", "encoder_from_model", "load_model", "model_source"]


class PixelPreprocess(Preprocess):
    """:class:`Preprocess` for statistics in the model's pixel units: intensities ``x`` in ``[0, 1]`` become
    ``lo + (hi - lo) x`` (clipped to ``[lo, hi]`` with ``clip``) before standardising; ``norm=None`` keeps
    the standardised image as it is."""

    def __init__(self, mean, std, norm=DEFAULT_NORM, pixel_range=(0.0, 1.0), clip=False, eps=1e-6):
        super().__init__(mean, std, DEFAULT_NORM if norm is None else norm, eps)
        self.renorm = norm is not None
        try:
            lo, hi = (float(v) for v in pixel_range)
        except (TypeError, ValueError):
            raise EncoderError(f"pixel_range must be two numbers (lo, hi), got {pixel_range!r}") from None
        if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
            raise EncoderError(f"pixel_range must be finite with hi > lo, got {pixel_range!r}")
        self.pixel_range, self.clip = (lo, hi), bool(clip)

    def to_pixels(self, x: torch.Tensor) -> torch.Tensor:
        lo, hi = self.pixel_range
        p = lo + (hi - lo) * x
        return p.clamp(lo, hi) if self.clip else p

    def standardise(self, x: torch.Tensor) -> torch.Tensor:
        return super().standardise(self.to_pixels(x))

    def rescale(self, z: torch.Tensor) -> torch.Tensor:
        return super().rescale(z) if self.renorm else z

    def to_image(self, z: torch.Tensor, contrast: float = 1.0) -> torch.Tensor:
        """Renderer intensities whose preprocessing gives back ``z``: with ``norm``, for any ``contrast``
        (see :meth:`Preprocess.to_image`); without, ``mean + contrast * std * z`` mapped back, exact at 1."""
        lo, hi = self.pixel_range
        if self.renorm:
            p = super().to_image(z, contrast)
        else:
            p = self.mean.to(z.dtype) + contrast * self.std.to(z.dtype) * z
        return (p - lo) / (hi - lo)

    def extra_repr(self):
        lo, hi = self.pixel_range
        return super().extra_repr() + f", pixel_range=({lo:g}, {hi:g}), clip={self.clip}, renorm={self.renorm}"


def _pick(out, output):
    """The response tensor of a model's output: ``output`` None (the output itself), an int (a tuple's
    element), a str (a dict's key) or a callable."""
    if output is None:
        return out
    if callable(output):
        return output(out)
    try:
        return out[output]
    except (KeyError, IndexError, TypeError) as err:
        raise EncoderError(f"output={output!r} cannot pick the response from a {type(out).__name__} "
                           f"({type(err).__name__}: {err})") from None


class ModelEncoder(Encoder):
    """A model (or an ensemble of models) behind meshmei's encoder interface; see the module docstring.

    Build it with :func:`encoder_from_model`, which also checks the model before any optimisation.

    Attributes
    ----------
    models : torch.nn.ModuleList
        The wrapped modules (a plain callable is held in ``callables`` instead).
    image_size : tuple of int
        ``(H, W)`` the model takes; meshmei renders at this size.
    channels : int
    forward_kwargs : dict
    source : dict or None
        How to load the model again (set by :func:`load_model`), recorded in a run's summary.
    """

    def __init__(self, models, preprocess: PixelPreprocess, *, n_neurons: int, channels: int, image_size,
                 forward_kwargs: dict, output=None, source: dict | None = None):
        super().__init__(preprocess)
        self.models = torch.nn.ModuleList([m for m in models if isinstance(m, torch.nn.Module)])
        self.callables = [m for m in models if not isinstance(m, torch.nn.Module)]
        self._n = int(n_neurons)
        self.channels, self.image_size = int(channels), tuple(int(s) for s in image_size)
        self.forward_kwargs, self.output, self.source = dict(forward_kwargs), output, source

    @property
    def n_neurons(self) -> int:
        return self._n

    @property
    def device(self) -> torch.device:
        """The device of the models' parameters (CPU for a model without parameters)."""
        for p in self.models.parameters():
            return p.device
        for b in self.models.buffers():
            return b.device
        return torch.device("cpu")

    def inputs(self, images: torch.Tensor, neurons=None, *, preprocessed: bool = False) -> tuple:
        if isinstance(images, torch.Tensor) and images.ndim == 4 and tuple(images.shape[-2:]) != self.image_size:
            if preprocessed:
                raise EncoderError(f"preprocessed images must be {self.image_size[0]} x {self.image_size[1]}, "
                                   f"the model's size; got {tuple(images.shape[-2:])}")
            images = nnf.interpolate(images, size=self.image_size, mode="bilinear", antialias=True,
                                     align_corners=False)
        if isinstance(images, torch.Tensor) and images.device != self.device:
            raise EncoderError(f"images are on {images.device} but the model is on {self.device}; render on the "
                               f"model's device or move the model")
        return super().inputs(images, neurons, preprocessed=preprocessed)

    def all_responses(self, z: torch.Tensor) -> torch.Tensor:
        """Every neuron's response ``(B, N)`` to preprocessed images ``z`` ``(B, 1, H, W)`` (the ensemble mean)."""
        x = z.expand(-1, self.channels, -1, -1) if self.channels != 1 else z
        outs = [_pick(m(x, **self.forward_kwargs), self.output) for m in (*self.models, *self.callables)]
        return outs[0] if len(outs) == 1 else torch.stack(outs).mean(0)

    def respond(self, z: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        return self.all_responses(z).index_select(1, idx)

    def extra_repr(self):
        return (f"n_neurons={self._n}, models={len(self.models) + len(self.callables)}, channels={self.channels}, "
                f"image_size={self.image_size}, forward_kwargs={self.forward_kwargs!r}")


def _positive_int(name, value):
    check_positive(name, value, integer=True, error=EncoderError)
    return int(value)


def _probe(encoder: ModelEncoder) -> int:
    """Run the model once on a gray image at its size; the neuron count, or EncoderError naming what arrived."""
    H, W = encoder.image_size
    x = torch.full((2, 1, H, W), 0.5, device=encoder.device)
    x[1, :, : H // 2] = 0.25  # two different images: a model that ignores its batch shows up as (1, N)
    pre = encoder.preprocess.to(encoder.device)
    try:
        with torch.no_grad():
            z = pre.rescale(pre.standardise(x))
            out = encoder.all_responses(z)
    except EncoderError:
        raise
    except Exception as err:
        raise EncoderError(f"the model failed on a batch of 2 gray images of shape (2, {encoder.channels}, {H}, {W}) "
                           f"with {encoder.forward_kwargs or 'no keyword arguments'}: {type(err).__name__}: {err}") from None
    if not isinstance(out, torch.Tensor):
        raise EncoderError(f"the model returned a {type(out).__name__}, not a tensor of responses (B, N); pick the "
                           f"response with output=<index, key or callable>")
    if out.ndim != 2 or out.shape[0] != 2 or out.shape[1] < 1:
        raise EncoderError(f"the model must return responses of shape (B, N); for a batch of 2 it returned "
                           f"{tuple(out.shape)}")
    if not bool(torch.isfinite(out).all()):
        raise EncoderError(f"the model returned non-finite responses to a gray image ({int((~torch.isfinite(out)).sum())} "
                           f"of {out.numel()} values NaN or Inf)")
    if not out.is_floating_point():
        raise EncoderError(f"the model must return float responses, got dtype {out.dtype}")
    return int(out.shape[1])


def encoder_from_model(model, *, mean: float, std: float, norm: float | None = DEFAULT_NORM, channels: int = 1,
                       image_size=100, forward_kwargs: dict | None = None, output=None, pixel_range=(0.0, 1.0),
                       clip: bool = False, source: dict | None = None) -> ModelEncoder:
    """Wrap a trained model (or a list of models, an ensemble) as a meshmei encoder.

    Parameters
    ----------
    model : torch.nn.Module, callable, or a list of them
        Maps ``(B, channels, H, W)`` preprocessed images to ``(B, N)`` responses (after ``output``). A list
        is an ensemble: the outputs are averaged.
    mean, std : float
        The training images' statistics, in the model's pixel units (``pixel_range``).
    norm : float or None
        L2 norm each standardised image is rescaled to (25, as in the energy-guided-diffusion V4 models);
        None keeps the standardised image.
    channels : int
        Channels the model takes; the gray image is repeated (3 for an ImageNet-style core).
    image_size : int or (H, W)
        The model's input size; meshmei renders at this size.
    forward_kwargs : dict, optional
        Passed to every call, e.g. ``{"data_key": "all_sessions"}`` or ``{"multiplex": False}``.
    output : None, int, str or callable
        Picks the response from a tuple (index), a dict (key) or anything else (``output(out)``).
    pixel_range : (lo, hi)
        The model's pixel units for the renderer's ``[0, 1]``: intensity ``x`` becomes ``lo + (hi - lo) x``.
    clip : bool
        Clip the mapped pixels to ``pixel_range`` (the training range).
    source : dict, optional
        How to load the model again (recorded in a run); :func:`load_model` sets it.

    Raises
    ------
    EncoderError
        Before any optimisation: a bad option, or a model that fails on a gray image, returns something
        other than ``(B, N)`` float responses, or returns NaN or Inf; the message names what arrived.
    """
    models = list(model) if isinstance(model, (list, tuple)) else [model]
    if not models:
        raise EncoderError("an ensemble needs at least one model")
    for m in models:
        if not callable(m):
            raise EncoderError(f"model must be a torch.nn.Module or a callable, got {type(m).__name__}")
    size = (image_size, image_size) if isinstance(image_size, int) and not isinstance(image_size, bool) else image_size
    try:
        size = tuple(_positive_int("image_size", s) for s in size)
    except TypeError:
        raise EncoderError(f"image_size must be an int or (H, W), got {image_size!r}") from None
    if len(size) != 2:
        raise EncoderError(f"image_size must be an int or (H, W), got {image_size!r}")
    channels = _positive_int("channels", channels)
    if norm is not None:
        check_positive("norm", norm, error=EncoderError)
    if forward_kwargs is not None and not isinstance(forward_kwargs, dict):
        raise EncoderError(f"forward_kwargs must be a dict, got {type(forward_kwargs).__name__}")
    pre = PixelPreprocess(mean, std, norm, pixel_range, clip)
    enc = ModelEncoder(models, pre, n_neurons=1, channels=channels, image_size=size,
                       forward_kwargs=forward_kwargs or {}, output=output, source=source)
    devices = {p.device for p in enc.models.parameters()}
    if len(devices) > 1:
        raise EncoderError(f"the models' parameters are on several devices: {sorted(map(str, devices))}")
    enc.preprocess.to(enc.device)
    with eval_mode(enc):  # the probe runs as the optimisation will: in eval mode
        enc._n = _probe(enc)
    return enc


def model_source(spec: str) -> tuple:
    """``(path, attribute)`` of a ``--model`` spec: ``file.py:factory`` or a TorchScript file."""
    path, sep, attr = spec.rpartition(":")
    if sep and path.endswith(".py"):
        return Path(path), attr
    return Path(spec), None


def load_model(spec: str, **adapter_options) -> ModelEncoder:
    """A :class:`ModelEncoder` from a ``--model`` spec.

    ``path/to/model.py:build``: ``build()`` returns an encoder made with :func:`encoder_from_model`, or a dict
    of its arguments (``{"model": m, "mean": 124.5, "std": 70.3, ...}``); ``adapter_options`` fill in what
    the dict leaves out. ``model.ts`` (or ``.pt``): a TorchScript module, with its statistics in
    ``adapter_options`` (``mean`` and ``std`` are required). The spec is recorded as the encoder's
    ``source``, so a saved run can load the model again.

    Raises
    ------
    EncoderError
        A missing file, a factory that fails or returns something else, or a model the adapter refuses.
    """
    path, attr = model_source(spec)
    if not path.is_file():
        raise EncoderError(f"no model file at {path}")
    options = {k: v for k, v in adapter_options.items() if v is not None}
    source = {"spec": str(spec), "path": str(path.resolve()), "factory": attr, "options": _jsonable(options)}
    if attr is None:
        try:
            module = torch.jit.load(str(path), map_location="cpu")
        except Exception as err:
            raise EncoderError(f"{path} is not a TorchScript file ({type(err).__name__}: {err}); for Python code "
                               f"pass path/to/model.py:factory") from None
        missing = [k for k in ("mean", "std") if k not in options]
        if missing:
            raise EncoderError(f"a TorchScript model needs its training statistics: give {', '.join(missing)}")
        return encoder_from_model(module, source=source, **options)
    built = _call_factory(path, attr)
    if isinstance(built, ModelEncoder):
        if options:
            raise EncoderError(f"{spec} returned a finished encoder, so {sorted(options)} cannot apply; return a dict "
                               f"of encoder_from_model's arguments instead, or leave the options out")
        built.source = source
        return built
    if isinstance(built, Encoder):
        raise EncoderError(f"{spec} returned a {type(built).__name__}; meshmei can use it from Python "
                           f"(optimize_mei(encoder, ...)), but --model needs encoder_from_model or a dict of its arguments")
    if not isinstance(built, dict) or "model" not in built:
        raise EncoderError(f"{spec} must return an encoder made with meshmei.encoder_from_model or a dict with "
                           f"'model', 'mean' and 'std'; it returned a {type(built).__name__}")
    kwargs = {**options, **built}
    missing = [k for k in ("mean", "std") if k not in kwargs]
    if missing:
        raise EncoderError(f"{spec} gave no {', '.join(missing)}; return them in the dict or pass them as options")
    return encoder_from_model(kwargs.pop("model"), source=source, **kwargs)


def _call_factory(path: Path, attr: str):
    name = f"meshmei_user_model_{abs(hash(str(path.resolve())))}"
    try:
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    except Exception as err:
        raise EncoderError(f"importing {path} failed: {type(err).__name__}: {err}") from None
    factory = getattr(module, attr, None)
    if not callable(factory):
        raise EncoderError(f"{path} has no callable {attr!r}")
    try:
        return factory()
    except Exception as err:
        raise EncoderError(f"{path}:{attr}() failed: {type(err).__name__}: {err}") from None


def _jsonable(options: dict) -> dict:
    out = {}
    for k, v in options.items():
        if isinstance(v, tuple):
            v = list(v)
        out[k] = v
    return out
