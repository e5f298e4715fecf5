"""A lab's own model as a meshmei encoder: any module or callable that maps images ``(B, C, H, W)`` to
responses ``(B, N)``, with the training statistics in the model's own pixel units.

The renderer's intensities lie in ``[0, 1]`` (the background is 0.5). They reach the model by one rule:

1. fit to the model's ``image_size``: an image of another shape is first cropped about its centre to the
   model's aspect ratio (a square render for a 36 x 64 model keeps its middle rows: the view of a camera
   with a wider than tall sensor, never a stretched one), then resized (anti-aliased bilinear) when it is
   still of another size (meshmei renders a model's input at its longer side, so a crop alone fits it);
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

import functools
import hashlib
import importlib.util
import inspect
import json
import math
import numbers
import os
import sys
import types
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as nnf

from .._checks import all_finite, check_positive
from ..errors import EncoderError
from .base import DEFAULT_NORM, Encoder, Preprocess, check_images, eval_mode

__all__ = ["ModelEncoder", "PixelPreprocess", "encoder_from_model", "load_model", "model_source", "model_fingerprint",
           "aspect_crop", "fit_to_size"]


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


def one_line(err: BaseException, limit: int = 300) -> str:
    """``Type: message`` of an exception on one line, for an error that names what a model or factory raised:
    TorchScript's traceback is cut down to its last line (the error it ends with), line breaks are folded,
    and the text is cut at ``limit``."""
    text = str(err)
    head, sep, trace = text.partition("Traceback of TorchScript")
    if sep:
        lines = [line.strip() for line in trace.splitlines() if line.strip()]
        text = head + " " + (lines[-1] if lines else "")
    text = " ".join(text.split())
    if len(text) > limit:
        text = text[: limit - 4].rstrip() + " ..."
    return f"{type(err).__name__}: {text}" if text else type(err).__name__


def _held_modules(fn, depth: int = 2) -> list:
    """The ``torch.nn.Module`` objects a callable holds: a module itself, a ``functools.partial``'s function
    and arguments, a bound method's object, a function's closure cells and defaults, an object's attributes
    (``depth`` levels of such wrapping)."""
    if isinstance(fn, torch.nn.Module):
        return [fn]
    if depth == 0 or fn is None:
        return []
    if isinstance(fn, functools.partial):
        parts = [fn.func, *fn.args, *fn.keywords.values()]
    elif inspect.ismethod(fn):
        parts = [fn.__self__]
    elif inspect.isfunction(fn):
        parts = [c.cell_contents for c in (fn.__closure__ or ()) if _cell_full(c)]
        parts += list(fn.__defaults__ or ()) + [getattr(fn, "__wrapped__", None)]
    elif isinstance(fn, (list, tuple)):
        parts = list(fn)
    elif isinstance(fn, dict):
        parts = list(fn.values())
    else:
        parts = list(getattr(fn, "__dict__", {}).values())
    return [m for part in parts for m in _held_modules(part, depth - 1)]


def _cell_full(cell) -> bool:
    try:
        cell.cell_contents
    except ValueError:  # an empty cell (a name not yet bound)
        return False
    return True


def hash_state(h, module: torch.nn.Module) -> None:
    """Feed a module's parameters and buffers (names, dtypes, shapes and values) to the hash ``h``."""
    for name, t in module.state_dict().items():
        t = t.detach().contiguous().cpu().reshape(-1)
        h.update(f"{name}:{t.dtype}:{t.numel()}".encode())
        h.update(t.view(torch.uint8).numpy().tobytes())


_PLAIN = (str, int, float, bool, complex, type(None))


def _stable_const(c) -> bytes:
    """A code constant as bytes that are the same in every process: a nested code object (a lambda, an inner
    function, a comprehension) by its own code, not its ``repr`` (which holds its memory address); a
    frozenset (``x in {"a", "b"}``) with its items in sorted order (its own order follows the process's
    string hashing)."""
    if isinstance(c, types.CodeType):
        return b"code(" + _code_bytes(c) + b")"
    if isinstance(c, frozenset):
        return b"frozenset(" + b",".join(sorted(_stable_const(x) for x in c)) + b")"
    if isinstance(c, tuple):
        return b"(" + b",".join(_stable_const(x) for x in c) + b")"
    return repr(c).encode()


def _code_bytes(code: types.CodeType) -> bytes:
    """A function's code, constants and the names it reads (globals and attributes: ``x.relu()`` against
    ``x.sigmoid()`` is the same bytecode with another name) as bytes, the same in every process."""
    def unstable(c):
        return isinstance(c, (types.CodeType, frozenset)) or (isinstance(c, tuple) and any(unstable(x) for x in c))

    if not any(unstable(c) for c in code.co_consts):
        consts = repr(code.co_consts).encode()
    else:
        consts = b"consts:" + b";".join(_stable_const(c) for c in code.co_consts)
    return code.co_code + consts + b"names:" + ",".join(code.co_names).encode()


def _feed(h, value, depth: int = 4, seen: set | None = None) -> None:
    """Feed a value that a model computes with to the hash ``h``: numbers and strings by ``repr``, tensors and
    arrays by value, containers item by item, a function by its code and the values it holds (closure cells,
    defaults), a ``functools.partial`` by its function and arguments, other objects by their type and
    attributes, ``depth`` levels deep. Modules only leave a mark: their state is hashed where they are held."""
    seen = set() if seen is None else seen
    if isinstance(value, _PLAIN):
        h.update(f"{type(value).__name__}:{value!r};".encode())
        return
    if isinstance(value, torch.nn.Module):
        h.update(b"module;")
        return
    if depth < 0 or id(value) in seen:
        h.update(b"...;")
        return
    seen.add(id(value))
    if isinstance(value, torch.Tensor):
        t = value.detach().contiguous().cpu().reshape(-1)
        h.update(f"tensor:{t.dtype}:{tuple(value.shape)};".encode())
        h.update(t.view(torch.uint8).numpy().tobytes())
    elif isinstance(value, np.ndarray):
        h.update(f"array:{value.dtype}:{value.shape};".encode())
        h.update(np.ascontiguousarray(value).tobytes())
    elif isinstance(value, (list, tuple)):
        h.update(f"{type(value).__name__}:{len(value)};".encode())
        for v in value:
            _feed(h, v, depth - 1, seen)
    elif isinstance(value, dict):
        h.update(f"dict:{len(value)};".encode())
        for k in sorted(value, key=repr):
            _feed(h, k, depth - 1, seen)
            _feed(h, value[k], depth - 1, seen)
    elif isinstance(value, functools.partial):
        h.update(b"partial;")
        for v in (value.func, value.args, value.keywords):
            _feed(h, v, depth - 1, seen)
    elif inspect.ismethod(value):
        h.update(b"method;")
        _feed(h, value.__func__, depth - 1, seen)
        _feed(h, value.__self__, depth - 1, seen)
    elif inspect.isfunction(value):
        code = value.__code__
        h.update(f"function:{value.__qualname__};".encode() + _code_bytes(code))
        _feed(h, _held_values(value), depth - 1, seen)
    else:
        h.update(f"object:{type(value).__qualname__};".encode())
        _feed(h, _attributes(value), depth - 1, seen)


def _held_values(fn) -> list:
    """What a function holds beyond its code: its closure cells' contents and its defaults."""
    return ([c.cell_contents for c in (fn.__closure__ or ()) if _cell_full(c)] + list(fn.__defaults__ or ())
            + [fn.__kwdefaults__ or {}])


def _attributes(obj, keep=None) -> dict:
    """An object's own attributes, without private ones (``_name``: a counter or a cache belongs there) and a
    module's ``training`` flag; with ``keep``, only the values it accepts."""
    return {k: v for k, v in getattr(obj, "__dict__", {}).items()
            if not k.startswith("_") and k != "training" and (keep is None or keep(v))}


def _setting(v) -> bool:
    """A value that reads as a setting: a number, string, bool or None, or a tuple of them. Lists, dicts and
    tensors held as plain attributes of a module are left out: they are usually what a forward records
    (activations, a log), and would make the fingerprint change as the model runs."""
    return isinstance(v, _PLAIN) or (isinstance(v, tuple) and all(_setting(x) for x in v))


def _held(v) -> bool:
    """A value a callable computes with: a setting, a tensor or array (weights in a closure), a function or
    partial; not a list, dict or set (usually filled as it runs) or another object."""
    return (_setting(v) or isinstance(v, (torch.Tensor, np.ndarray, functools.partial)) or inspect.isfunction(v)
            or (isinstance(v, tuple) and all(_held(x) for x in v)))


def _hash_module(h, m: torch.nn.Module) -> None:
    """Feed a module to ``h``: its tree as printed, its parameters and buffers, and for each module class
    defined outside torch its source and its instances' plain attributes (``self.gain = 2.0``), which neither
    the print nor the state holds."""
    h.update(repr(m).encode())  # the module tree with each module's settings (kernel sizes, Gabor parameters)
    hash_state(h, m)
    # in the order the module tree meets them: a set of classes has another order in every process (ordered by
    # their addresses), which changed the fingerprint of a model with two classes of its own from run to run
    for cls in dict.fromkeys(type(sub) for sub in m.modules()):
        if not cls.__module__.startswith("torch."):
            h.update(cls.__qualname__.encode())
            try:
                h.update(inspect.getsource(cls).encode())
            except (OSError, TypeError):
                pass
    for sub in m.modules():
        attrs = _attributes(sub, _setting) if not type(sub).__module__.startswith("torch.") else None
        if attrs:  # fed only where there are some: the fingerprints of models without any stay as they were
            _feed(h, attrs)


def model_fingerprint(encoder: "ModelEncoder") -> str:
    """A hash of what a :class:`ModelEncoder` computes with: its modules' tree as printed (each module's
    settings), every parameter and buffer (names, dtypes, shapes and values), the source and plain attributes
    of module classes defined outside torch, the code of a plain callable and the values it holds (closure
    cells, defaults, a partial's arguments, a callable object's attributes), and the ``output`` and
    ``forward_kwargs`` options. Two encoders with the same fingerprint and options give the same responses;
    a changed weight, attribute, held value or forward gives another fingerprint (a population folder then
    refuses to mix them)."""
    h = hashlib.sha256()
    for m in (*encoder.models, *encoder.held):
        _hash_module(h, m)
    for c in encoder.callables:
        code = getattr(c, "__code__", None) or getattr(getattr(c, "func", None), "__code__", None)
        h.update(getattr(c, "__qualname__", type(c).__qualname__).encode())
        if code is not None:
            h.update(_code_bytes(code))
        held = _callable_values(c)
        if held:  # fed only where there are some, as above
            _feed(h, held)
    options = {"forward_kwargs": {k: v for k, v in encoder.forward_kwargs.items() if not isinstance(v, _PLAIN)}}
    if encoder.output is not None:
        options["output"] = encoder.output
    if options["forward_kwargs"] or "output" in options:  # plain keyword values are in the spec already
        _feed(h, options)
    return h.hexdigest()[:16]


def _callable_values(c) -> list:
    """The values a plain callable computes with besides its code and the modules it holds (hashed with
    those): a partial's arguments (keywords as ``(name, value)``), a function's closure cells and defaults, a
    callable object's or bound method's object's attributes."""
    if isinstance(c, functools.partial):
        values = [*c.args, *sorted(c.keywords.items()), *_callable_values(c.func)]
    elif inspect.ismethod(c):
        values = [] if isinstance(c.__self__, torch.nn.Module) else [_attributes(c.__self__, _held)]
    elif inspect.isfunction(c):
        values = [*_held_values(c)[:-1], *sorted((c.__kwdefaults__ or {}).items())]
    else:
        values = [_attributes(c, _held)]
    # modules are hashed as held; lists, dicts, sets and other objects are left out (see _held)
    return [v for v in values if (isinstance(v, dict) and v) or _held(v)]


def encoder_fingerprint(encoder: torch.nn.Module) -> str:
    """A hash of a user's own :class:`~meshmei.encoders.Encoder` subclass: as :func:`_hash_module` (its
    parameters and buffers, class source and plain attributes)."""
    h = hashlib.sha256()
    _hash_module(h, encoder)
    return h.hexdigest()[:16]


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
        # the modules a callable holds (a partial, a bound method, a closure): registered here too, so that
        # eval mode, frozen parameters and the device reach them
        own = {id(m) for m in self.models}
        held = {id(m): m for c in self.callables for m in _held_modules(c) if id(m) not in own}
        self.held = torch.nn.ModuleList(held.values())
        self._n, self._probed = int(n_neurons), False
        self.channels, self.image_size = int(channels), tuple(int(s) for s in image_size)
        self.forward_kwargs, self.output, self.source = dict(forward_kwargs), output, source

    @property
    def n_neurons(self) -> int:
        return self._n

    def inputs(self, images: torch.Tensor, neurons=None, *, preprocessed: bool = False) -> tuple:
        check_images(images)  # before the resize, whose own errors come from deep inside torch
        if tuple(images.shape[-2:]) != self.image_size:
            if preprocessed:
                raise EncoderError(f"preprocessed images must be {self.image_size[0]} x {self.image_size[1]}, "
                                   f"the model's size; got {tuple(images.shape[-2:])}")
            images = fit_to_size(images, self.image_size)
        if images.device != self.device:
            raise EncoderError(f"images are on {images.device} but the model is on {self.device}; render on the "
                               f"model's device or move the model")
        return super().inputs(images, neurons, preprocessed=preprocessed)

    def all_responses(self, z: torch.Tensor) -> torch.Tensor:
        """Every neuron's response ``(B, N)`` to preprocessed images ``z`` ``(B, 1, H, W)`` (the ensemble mean),
        in ``z``'s dtype. The models see the images in their own (floating) dtype: a float64 run feeds a float32
        model float32 images, and gets its responses back in float64 (with their gradient)."""
        dtype = self.model_dtype
        x = z if dtype is None or z.dtype == dtype else z.to(dtype)
        x = x.expand(-1, self.channels, -1, -1) if self.channels != 1 else x
        outs = []
        for i, m in enumerate((*self.models, *self.callables)):
            # each model its own copy: one that edits its input in place (x.sub_(mean), ReLU(inplace=True)) wrote
            # into the caller's images (a pixel MEI's leaf: "a leaf Variable ... in-place operation") and into the
            # next ensemble member's
            own = x.clone(memory_format=torch.contiguous_format)
            try:
                out = _pick(m(own, **self.forward_kwargs), self.output)
            except EncoderError:
                raise
            except Exception as err:  # the model's own failure, named with what it was given
                raise EncoderError(f"the model{self._member(i)} failed on images of shape {tuple(x.shape)} with "
                                   f"{self.forward_kwargs or 'no keyword arguments'}: {one_line(err)}") from err
            outs.append(self._checked(out, x, i))
        if len(outs) > 1 and len({o.shape for o in outs}) > 1:
            raise EncoderError(f"the ensemble's models return different shapes: {[tuple(o.shape) for o in outs]}")
        out = outs[0] if len(outs) == 1 else torch.stack(outs).mean(0)
        return out if out.dtype == z.dtype else out.to(z.dtype)

    @property
    def model_dtype(self) -> torch.dtype | None:
        """The dtype of the models' first floating parameter or buffer (None for a model without any): what
        the models are fed."""
        return _first_float_dtype((*self.models.parameters(), *self.held.parameters(), *self.models.buffers(),
                                   *self.held.buffers()))

    def _member(self, i: int) -> str:
        n = len(self.models) + len(self.callables)
        return f" (member {i} of the ensemble of {n})" if n > 1 else ""

    def _checked(self, out, x: torch.Tensor, i: int) -> torch.Tensor:
        """``out`` if it is a ``(B, N)`` float tensor for the ``B`` images ``x`` (``N`` the probed count once
        known), finite where ``x`` is, else EncoderError."""
        batch = x.shape[0]
        if not isinstance(out, torch.Tensor):
            raise EncoderError(f"the model{self._member(i)} returned a {type(out).__name__}, not a tensor of "
                               f"responses (B, N); pick the response with output=<index, key or callable>")
        if out.ndim != 2 or out.shape[0] != batch or out.shape[1] < 1 or (self._probed and out.shape[1] != self._n):
            want = f"({batch}, {self._n})" if self._probed else f"({batch}, N)"
            raise EncoderError(f"the model{self._member(i)} must return responses of shape (B, N); for a batch of "
                               f"{batch} it returned {tuple(out.shape)}, expected {want}")
        if out.layout != torch.strided:
            raise EncoderError(f"the model{self._member(i)} must return a dense tensor of responses, got layout "
                               f"{out.layout} (call .to_dense() on it)")
        if out.device != x.device:
            raise EncoderError(f"the model{self._member(i)} returned its responses on device {out.device}, its images "
                               f"were on {x.device}: responses must stay on the images' device")
        if not out.is_floating_point():
            raise EncoderError(f"the model must return float responses, got dtype {out.dtype}")
        if x.requires_grad and torch.is_grad_enabled() and not out.requires_grad:
            raise EncoderError(f"the model{self._member(i)}'s responses carry no gradient back to the image (an "
                               f"output that is detached, computed under no_grad, or does not depend on the input): "
                               f"a 3D-MEI and a pixel MEI climb that gradient")
        if not all_finite(out) and all_finite(x):
            bad = int((~torch.isfinite(out)).sum())
            raise EncoderError(f"the model{self._member(i)} returned non-finite responses to finite images of shape "
                               f"{tuple(x.shape)} ({bad} of {out.numel()} values NaN or Inf)")
        return out

    def respond(self, z: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        return self.all_responses(z).index_select(1, idx)

    def extra_repr(self):
        return (f"n_neurons={self._n}, models={len(self.models) + len(self.callables)}, channels={self.channels}, "
                f"image_size={self.image_size}, forward_kwargs={self.forward_kwargs!r}")


def aspect_crop(h: int, w: int, size) -> tuple:
    """The centred window ``(top, left, height, width)`` of an ``h x w`` image with the aspect ratio of
    ``size = (H, W)``, as large as fits (the whole image when the ratios agree to the pixel)."""
    H, W = size
    if h * W > w * H:  # taller than the model's aspect: keep the middle rows
        ch, cw = max(1, round(w * H / W)), w
    else:
        ch, cw = h, max(1, round(h * W / H))
    return (h - ch) // 2, (w - cw) // 2, ch, cw


def fit_to_size(images: torch.Tensor, size) -> torch.Tensor:
    """``(B, C, h, w)`` images as ``(B, C, H, W)`` for ``size = (H, W)``: cropped about the centre to the
    aspect ratio of ``size`` (:func:`aspect_crop`), then resized with anti-aliased bilinear interpolation
    if still of another size. Square pixels stay square: a square render for a wide model loses its top and
    bottom rows, it is not squeezed."""
    top, left, ch, cw = aspect_crop(images.shape[-2], images.shape[-1], size)
    images = images[..., top:top + ch, left:left + cw]
    if tuple(images.shape[-2:]) != tuple(size):
        images = nnf.interpolate(images, size=tuple(size), mode="bilinear", antialias=True, align_corners=False)
    return images


def _positive_int(name, value):
    check_positive(name, value, integer=True, error=EncoderError)
    return int(value)


def _first_float_dtype(tensors) -> torch.dtype | None:
    """The dtype of the first floating tensor of ``tensors`` (None without one)."""
    return next((t.dtype for t in tensors if t.is_floating_point()), None)


def _probe(encoder: ModelEncoder) -> int:
    """Run the model on gray images at its size, a batch of 2 and a batch of 1 (a 3D-MEI step renders one
    image): the neuron count, or EncoderError naming what arrived."""
    H, W = encoder.image_size
    try:
        x = torch.full((2, 1, H, W), 0.5, device=encoder.device)
        x[1, :, : H // 2] = 0.25  # two different images: a model that ignores its batch shows up as (1, N)
        pre = encoder.preprocess.to(encoder.device)
        with torch.no_grad():
            z = pre.rescale(pre.standardise(x))
            if not all_finite(z):  # before the model is blamed for it
                raise EncoderError(f"a gray image is not finite after preprocessing (mean "
                                   f"{pre.mean.flatten().tolist()}, std {pre.std.flatten().tolist()}, norm "
                                   f"{pre.norm}): the statistics do not fit in {z.dtype}; give them in the units of "
                                   "pixel_range")
            out = encoder.all_responses(z)
            encoder._n, encoder._probed = int(out.shape[1]), True
            one = encoder.all_responses(z[:1])  # the same count for a single image (a model ending in squeeze())
            other = encoder.all_responses(z[1:])  # the second image alone: its row of the batch, or a batch mix-up
    except (torch.OutOfMemoryError, RuntimeError) as err:
        if not isinstance(err, torch.OutOfMemoryError) and "allocate" not in str(err):
            raise
        raise EncoderError(f"two gray images of {H} x {W} pixels and {encoder.channels} channel(s), and the "
                           f"model's answer to them, do not fit in memory on {encoder.device}: check image_size "
                           f"and channels ({str(err).splitlines()[0][:160]})") from None
    if not bool(torch.isfinite(out).all() & torch.isfinite(one).all()):
        bad = int((~torch.isfinite(out)).sum())
        raise EncoderError(f"the model returned non-finite responses to a gray image ({bad} of {out.numel()} "
                           f"values NaN or Inf)")
    scale = float(out.abs().max()) + 1e-6
    for row, alone in ((0, one), (1, other)):
        if not torch.allclose(out[row:row + 1].double(), alone.double(), rtol=1e-3, atol=1e-4 * scale):
            # a model that answered every image of a batch with its first one's swept one value for every condition
            raise EncoderError(f"the model's responses to an image depend on the other images in its batch: image "
                               f"{row} of a batch of two got {out[row, :4].tolist()}..., alone "
                               f"{alone[0, :4].tolist()}...; meshmei scores images in batches (each row must be "
                               "that image's own response)")
    return encoder._n


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
    held = (_first_float_dtype((*m.parameters(), *m.buffers())) for m in models if isinstance(m, torch.nn.Module))
    member_dtypes = {str(d).removeprefix("torch.") for d in held if d is not None}
    if len(member_dtypes) > 1:  # all are fed the first one's dtype: torch's "expected ... but found ..." before
        raise EncoderError(f"the ensemble's members hold weights of different dtypes "
                           f"({', '.join(sorted(member_dtypes))}); convert them to one (model.float() or "
                           "model.double())")
    if isinstance(image_size, numbers.Integral) and not isinstance(image_size, (bool, np.bool_)):
        size = (int(image_size), int(image_size))  # NumPy's ints too (np.int64(16) was refused)
    else:
        size = image_size
    if isinstance(size, (str, bytes, dict, set, frozenset)):  # iterated: characters, keys, an order of its own
        raise EncoderError(f"image_size must be an int or (H, W), got {image_size!r}")
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
    if not isinstance(clip, (bool, np.bool_)):  # clip="no" clipped
        raise EncoderError(f"clip must be True or False, got {clip!r}")
    if isinstance(output, (bool, np.bool_)):  # output=True picked a tuple's element 1
        raise EncoderError(f"output must be None, an index, a key or a callable, got {output!r}")
    pre = PixelPreprocess(mean, std, norm, pixel_range, clip)
    enc = ModelEncoder(models, pre, n_neurons=1, channels=channels, image_size=size,
                       forward_kwargs=forward_kwargs or {}, output=output, source=source)
    devices = {p.device for p in enc.models.parameters()}
    if len(devices) > 1:
        raise EncoderError(f"the models' parameters are on several devices: {sorted(map(str, devices))}")
    enc.preprocess.to(enc.device)
    with eval_mode(enc):  # the probe runs as the optimisation will: in eval mode
        _probe(enc)
    return enc


def model_source(spec: str) -> tuple:
    """``(path, attribute)`` of a ``--model`` spec: ``file.py:factory`` or a TorchScript file (a str, or a
    path-like one: a Path was an AttributeError)."""
    if isinstance(spec, os.PathLike):
        spec = os.fspath(spec)
    if not isinstance(spec, str):
        raise EncoderError(f"a model spec is 'path/to/model.py:factory' or a TorchScript file, got {spec!r}")
    path, sep, attr = spec.rpartition(":")
    if sep and path.endswith(".py"):
        return Path(path), attr
    return Path(spec), None


_OPTIONS = tuple(inspect.signature(encoder_from_model).parameters)[1:]  # the adapter's keyword arguments


def load_model(spec: str, **adapter_options) -> ModelEncoder:
    """A :class:`ModelEncoder` from a ``--model`` spec.

    ``path/to/model.py:build``: ``build()`` returns an encoder made with :func:`encoder_from_model`, or a dict
    of its arguments (``{"model": m, "mean": 124.5, "std": 70.3, ...}``); ``adapter_options`` fill in what
    the dict leaves out, and an option the dict sets to another value is an error (``forward_kwargs`` are
    merged key by key). The factory's folder is on ``sys.path`` while it is imported and called, so it can
    import its neighbours; relative file paths inside it resolve against the working directory.
    ``model.ts`` (or ``.pt``): a TorchScript module, with its statistics in ``adapter_options`` (``mean`` and
    ``std`` are required; ``image_size`` is its input size, default 100). The spec is recorded as the
    encoder's ``source``, so a saved run can load the model again; options that are not JSON (a callable
    ``output``) are named there as unrecorded, and such a run cannot rebuild its model by itself.

    Raises
    ------
    EncoderError
        A missing file, a factory that fails or returns something else, an unknown or conflicting option,
        or a model the adapter refuses.
    """
    unknown = sorted(set(adapter_options) - set(_OPTIONS) - {"model"})
    if unknown:
        raise EncoderError(f"unknown adapter options {unknown}; encoder_from_model takes {list(_OPTIONS)}")
    path, attr = model_source(spec)
    if not path.is_file():
        raise EncoderError(f"no model file at {path}")
    options = dict(adapter_options)
    recorded, unrecorded = _jsonable(options)
    source = {"spec": str(spec), "path": str(path.resolve()), "factory": attr, "options": recorded,
              "sha256": _file_hash(path)}
    if unrecorded:
        source["unrecorded"] = unrecorded
    if attr is None:
        try:
            module = torch.jit.load(str(path), map_location="cpu")
        except Exception as err:
            raise EncoderError(f"{path} is not a TorchScript file ({one_line(err)}); for Python code "
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
    bad = sorted(set(built) - set(_OPTIONS) - {"model"})
    if bad:
        raise EncoderError(f"{spec} returned unknown keys {bad}; encoder_from_model takes 'model' and {list(_OPTIONS)}")
    kwargs = _merge(spec, built, options)
    missing = [k for k in ("mean", "std") if k not in kwargs]
    if missing:
        raise EncoderError(f"{spec} gave no {', '.join(missing)}; return them in the dict or pass them as options")
    return encoder_from_model(kwargs.pop("model"), source=source, **kwargs)


def _merge(spec: str, built: dict, options: dict) -> dict:
    """The factory's dict completed by the options; an option the dict sets otherwise is an error."""
    kwargs = dict(built)
    for k, v in options.items():
        if k == "forward_kwargs" and isinstance(built.get(k), dict) and isinstance(v, dict):
            clash = sorted(key for key in v if key in built[k] and built[k][key] != v[key])
            if clash:
                raise EncoderError(f"{spec} passes forward_kwargs {({c: built[k][c] for c in clash})} and the options "
                                   f"give {({c: v[c] for c in clash})}; set each in one place")
            kwargs[k] = {**built[k], **v}
        elif k in built and not _same(built[k], v):
            raise EncoderError(f"{spec} sets {k}={built[k]!r} and the options give {k}={v!r}; set it in one place")
        else:
            kwargs[k] = v
    return kwargs


def _same(a, b) -> bool:
    try:
        return bool(a == b) or (isinstance(a, (tuple, list)) and isinstance(b, (tuple, list)) and list(a) == list(b))
    except Exception:
        return False


def _file_hash(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]


def _call_factory(path: Path, attr: str):
    name = f"meshmei_user_model_{abs(hash(str(path.resolve())))}"
    folder = str(path.resolve().parent)
    sys.path.insert(0, folder)  # the factory may import modules beside it
    try:
        try:
            spec = importlib.util.spec_from_file_location(name, path)
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
        except Exception as err:
            raise EncoderError(f"importing {path} failed: {one_line(err)}") from None
        factory = getattr(module, attr, None)
        if not callable(factory):
            raise EncoderError(f"{path} has no callable {attr!r}")
        try:
            return factory()
        except Exception as err:
            raise EncoderError(f"{path}:{attr}() failed: {one_line(err)}") from None
    finally:
        sys.path.remove(folder)


def _jsonable(options: dict) -> tuple[dict, list]:
    """``(recorded, unrecorded)``: the options that survive JSON (tuples as lists), and the names of the rest."""
    out, left = {}, []
    for k, v in options.items():
        v = list(v) if isinstance(v, tuple) else v
        try:
            json.dumps(v, allow_nan=False)
        except (TypeError, ValueError):
            left.append(k)
            continue
        out[k] = v
    return out, left
