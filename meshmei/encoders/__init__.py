"""Image-computable model neurons that map grayscale images ``(B, 1, H, W)`` to responses ``(B, n_neurons)``.

Every encoder first applies the same preprocessing (:class:`Preprocess`, in :mod:`.base`): standardise
with the training images' mean and std, then rescale to a fixed L2 norm, so only the *pattern* of an image
matters. Three kinds of neuron:

- :class:`GaborSimpleCell` (:mod:`.gabor`): the inner product of the preprocessed image with a zero-mean,
  unit-norm Gabor filter, divided by the image norm. By Cauchy-Schwarz the response lies in ``[-1, 1]``
  and equals 1 exactly when the preprocessed image is the filter (times the norm).
- :class:`GaborComplexCell` (:mod:`.gabor`): the energy model over a quadrature pair made exactly
  orthonormal after mean removal; the response lies in ``[0, 1]``, equals 1 for a Gabor of *any* phase
  and is exactly phase-invariant.
- :class:`CoreReadoutModel` (:mod:`.core_readout`): a convolutional core followed by a per-neuron Gaussian
  readout and an ``ELU + 1`` output (Lurz et al. 2020), the model class used for macaque V4.

- :class:`ModelEncoder` (:mod:`.adapter`): a lab's own trained model (any module or callable, an ensemble,
  a TorchScript file or a Python factory), made with :func:`encoder_from_model` or :func:`load_model`.

:mod:`.registry` builds the built-in encoders by name and describes any encoder as JSON.

Image coordinates, used by the Gabor parameters and the readout positions: ``x`` runs from -1 at the left
edge to +1 at the right edge, ``y`` from -1 at the top to +1 at the bottom (``grid_sample``'s convention),
both over the full image, so a parameter set means the same at any resolution.
"""

from .adapter import ModelEncoder, PixelPreprocess, aspect_crop, encoder_from_model, fit_to_size, load_model, model_fingerprint
from .base import DEFAULT_NORM, Encoder, EncoderError, Preprocess, eval_mode, frozen_encoder
from .core_readout import (
    DEMO_MODEL_PATH,
    CoreReadoutModel,
    DefaultCore,
    GaussianReadout,
    is_demo_model,
    load_demo_model,
)
from .gabor import GaborComplexCell, GaborSimpleCell, gabor_filters
from .registry import encoder_from_spec, encoder_identity, encoder_spec, make_encoder

__all__ = [
    "EncoderError",
    "Preprocess",
    "Encoder",
    "eval_mode",
    "frozen_encoder",
    "gabor_filters",
    "GaborSimpleCell",
    "GaborComplexCell",
    "DefaultCore",
    "GaussianReadout",
    "CoreReadoutModel",
    "DEFAULT_NORM",
    "DEMO_MODEL_PATH",
    "load_demo_model",
    "is_demo_model",
    "make_encoder",
    "encoder_spec",
    "encoder_identity",
    "encoder_from_spec",
    "ModelEncoder",
    "PixelPreprocess",
    "encoder_from_model",
    "load_model",
    "model_fingerprint",
    "aspect_crop",
    "fit_to_size",
]
