"""Build a built-in encoder by name, and describe an encoder as JSON so that a saved run can rebuild it."""

from __future__ import annotations

import functools
import hashlib

from ..errors import EncoderError, MEIError
from .adapter import ModelEncoder, encoder_fingerprint, hash_state, load_model, model_fingerprint
from .base import Encoder
from .core_readout import is_demo_model, load_demo_model
from .gabor import GaborComplexCell, GaborSimpleCell

__all__ = ["make_encoder", "encoder_spec", "encoder_identity", "encoder_from_spec"]


def encoder_spec(encoder: Encoder) -> dict:
    """A JSON-able description of an encoder; :func:`make_encoder` rebuilds the built-in kinds from it."""
    pre = encoder.preprocess
    spec = {"class": type(encoder).__name__, "upper_bound": encoder.upper_bound, "n_neurons": encoder.n_neurons,
            "mean": float(pre.mean), "std": float(pre.std), "norm": pre.norm, "eps": pre.eps}
    if isinstance(encoder, (GaborSimpleCell, GaborComplexCell)):
        spec["kind"] = "gabor-simple" if isinstance(encoder, GaborSimpleCell) else "gabor-complex"
        spec["params"] = {k: v.tolist() for k, v in encoder.params.items()}
    elif is_demo_model(encoder):
        spec.update(kind="demo", weights=weights_hash(encoder))
    elif isinstance(encoder, ModelEncoder):
        spec.update(kind="model", source=encoder.source, image_size=list(encoder.image_size),
                    channels=encoder.channels, pixel_range=list(encoder.preprocess.pixel_range),
                    clip=encoder.preprocess.clip, renorm=encoder.preprocess.renorm,
                    forward_kwargs={k: v for k, v in encoder.forward_kwargs.items()
                                    if isinstance(v, (str, int, float, bool, type(None)))},
                    fingerprint=model_fingerprint(encoder))
    else:  # a user's own Encoder subclass: what it computes with, so that a changed one is not taken for it
        spec.update(kind="custom", fingerprint=encoder_fingerprint(encoder))
    return spec


def weights_hash(module) -> str:
    """A hash of a module's parameters and buffers (names, dtypes, shapes and values): a demo model loaded
    from another file, or changed in place, does not pass for the shipped one."""
    h = hashlib.sha256()
    hash_state(h, module)
    return h.hexdigest()[:16]


@functools.lru_cache(maxsize=1)
def _shipped_demo_weights() -> str:
    return weights_hash(load_demo_model())


def encoder_identity(encoder: Encoder) -> dict:
    """:func:`encoder_spec` without where a lab's model was loaded from (the spec as typed and the resolved
    path): what makes two encoders compute the same, for a configuration hash. The same model file reached by
    another path (another job's working directory) has the same identity; changed weights, code or options
    do not (its ``fingerprint`` and the file's ``sha256``). The shipped demo model's identity has no
    ``weights`` (as before they were recorded: its population folders resume); another demo model's has."""
    spec = encoder_spec(encoder)
    if spec.get("kind") == "demo" and spec["weights"] == _shipped_demo_weights():
        del spec["weights"]  # the shipped model: the identity it had before weights were recorded
    if isinstance(spec.get("source"), dict):
        spec["source"] = {k: v for k, v in spec["source"].items() if k not in ("spec", "path")}
    return spec


def make_encoder(kind: str, **params) -> Encoder:
    """A built-in encoder by name: ``"gabor-simple"``, ``"gabor-complex"`` (Gabor parameters as keywords),
    or ``"demo"`` (the shipped demo model, :func:`meshmei.encoders.load_demo_model`)."""
    if kind == "gabor-simple":
        return GaborSimpleCell(**params)
    if kind == "gabor-complex":
        return GaborComplexCell(**params)
    if kind == "demo":
        if set(params) - {"path"}:  # they were dropped without a word
            raise MEIError(f"the demo encoder takes no parameters but path=..., got {sorted(params)}")
        return load_demo_model(**params)
    raise MEIError(f"unknown encoder {kind!r}; expected 'gabor-simple', 'gabor-complex' or 'demo'")


def encoder_from_spec(spec: dict) -> Encoder:
    """Rebuild an encoder from its :func:`encoder_spec`: the built-in kinds, and a lab's model that was
    loaded from a file (:func:`~meshmei.encoders.load_model`: ``--model`` on the command line), which is
    loaded again from the same file with the same options and checked against the recorded neuron count.

    Raises
    ------
    MEIError
        The spec describes an encoder built in Python (pass the encoder itself to
        :func:`meshmei.mei.load_run`), or the model file is gone or no longer matches.
    """
    kind = spec.get("kind")
    if kind in ("gabor-simple", "gabor-complex"):
        return make_encoder(kind, **spec["params"], mean=spec["mean"], std=spec["std"], norm=spec["norm"],
                            eps=spec["eps"])
    if kind == "demo":
        enc = make_encoder("demo")
        if spec.get("weights") not in (None, weights_hash(enc)):  # runs saved before weights were recorded: None
            raise MEIError("the run's demo model had other weights than the shipped one (loaded from another "
                           "file, or changed after loading); load it yourself and pass encoder=... to load_run")
        return enc
    if kind == "model" and spec.get("source"):
        src = spec["source"]
        if src.get("unrecorded"):
            raise MEIError(f"the run's model was loaded with options that a run folder cannot record "
                           f"({', '.join(src['unrecorded'])}); load it yourself and pass encoder=... to load_run")
        try:
            enc = load_model(src["path"] + (f":{src['factory']}" if src.get("factory") else ""), **src["options"])
        except EncoderError as err:
            raise MEIError(f"cannot load the run's model again: {err}") from None
        if enc.n_neurons != spec["n_neurons"]:
            raise MEIError(f"the model at {src['path']} now has {enc.n_neurons} neurons; the run's had {spec['n_neurons']}")
        now = model_fingerprint(enc) if spec.get("fingerprint") else None
        if now is not None and now != spec["fingerprint"]:
            raise MEIError(f"the model at {src['path']} is not the run's any more (its weights or code changed: "
                           f"fingerprint {now}, the run's {spec['fingerprint']}); a factory must "
                           f"build the same model every time (load its weights, or seed its initialisation)")
        return enc
    raise MEIError(f"cannot rebuild a {spec.get('class')} encoder from a run directory; pass encoder=... to load_run")
