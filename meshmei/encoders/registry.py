"""Build a built-in encoder by name, and describe an encoder as JSON so that a saved run can rebuild it."""

from __future__ import annotations

from ..errors import MEIError
from .base import Encoder
from .core_readout import is_demo_model, load_demo_model
from .gabor import GaborComplexCell, GaborSimpleCell

__all__ = ["make_encoder", "encoder_spec", "encoder_from_spec"]


def encoder_spec(encoder: Encoder) -> dict:
    """A JSON-able description of an encoder; :func:`make_encoder` rebuilds the built-in kinds from it."""
    pre = encoder.preprocess
    spec = {"class": type(encoder).__name__, "upper_bound": encoder.upper_bound, "n_neurons": encoder.n_neurons,
            "mean": float(pre.mean), "std": float(pre.std), "norm": pre.norm, "eps": pre.eps}
    if isinstance(encoder, (GaborSimpleCell, GaborComplexCell)):
        spec["kind"] = "gabor-simple" if isinstance(encoder, GaborSimpleCell) else "gabor-complex"
        spec["params"] = {k: v.tolist() for k, v in encoder.params.items()}
    elif is_demo_model(encoder):
        spec["kind"] = "demo"
    else:
        spec["kind"] = "custom"
    return spec


def make_encoder(kind: str, **params) -> Encoder:
    """A built-in encoder by name: ``"gabor-simple"``, ``"gabor-complex"`` (Gabor parameters as keywords),
    or ``"demo"`` (the shipped demo model, :func:`meshmei.encoders.load_demo_model`)."""
    if kind == "gabor-simple":
        return GaborSimpleCell(**params)
    if kind == "gabor-complex":
        return GaborComplexCell(**params)
    if kind == "demo":
        return load_demo_model()
    raise MEIError(f"unknown encoder {kind!r}; expected 'gabor-simple', 'gabor-complex' or 'demo'")


def encoder_from_spec(spec: dict) -> Encoder:
    """Rebuild an encoder from its :func:`encoder_spec`; only the built-in kinds can be rebuilt.

    Raises
    ------
    MEIError
        The spec describes a custom encoder (pass the encoder itself to :func:`meshmei.mei.load_run`).
    """
    kind = spec.get("kind")
    if kind in ("gabor-simple", "gabor-complex"):
        return make_encoder(kind, **spec["params"], mean=spec["mean"], std=spec["std"], norm=spec["norm"],
                            eps=spec["eps"])
    if kind == "demo":
        return make_encoder("demo")
    raise MEIError(f"cannot rebuild a {spec.get('class')} encoder from a run directory; pass encoder=... to load_run")
