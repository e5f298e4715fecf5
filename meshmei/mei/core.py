"""MERGE: pieces awaiting their new homes from the helpers' branches (encoder registry -> encoders,
quality -> quality, REGULARIZERS -> regularizers, figures -> plots); deleted at merge."""

from __future__ import annotations

import math

import torch

from ..encoders import Encoder, GaborComplexCell, GaborSimpleCell
from ..errors import MEIError
from ..operators import doublearea
from ..regularizers import arap_direction_loss, arap_loss, area_loss, edge_loss, laplacian_loss
from ..render import render
from .pixel import eval_mode  # noqa: F401

# name -> loss(V, V0, F); the paper's four first, then the two variants beyond it
REGULARIZERS = {
    "laplacian": lambda V, V0, F: laplacian_loss(V, F),
    "edge": lambda V, V0, F: edge_loss(V, F),
    "area": lambda V, V0, F: area_loss(V, F),
    "arap": lambda V, V0, F: arap_direction_loss(V, V0, F),
    "laplacian_cot": lambda V, V0, F: laplacian_loss(V, F, method="cotangent"),
    "arap_sorkine": lambda V, V0, F: arap_loss(V, V0, F),
}


# ---------------------------------------------------------------------------------------------- encoders

def encoder_spec(encoder: Encoder) -> dict:
    """A JSON-able description of an encoder; :func:`make_encoder` rebuilds the built-in kinds from it."""
    pre = encoder.preprocess
    spec = {"class": type(encoder).__name__, "upper_bound": encoder.upper_bound, "n_neurons": encoder.n_neurons,
            "mean": float(pre.mean), "std": float(pre.std), "norm": pre.norm, "eps": pre.eps}
    if isinstance(encoder, (GaborSimpleCell, GaborComplexCell)):
        spec["kind"] = "gabor-simple" if isinstance(encoder, GaborSimpleCell) else "gabor-complex"
        spec["params"] = {k: v.tolist() for k, v in encoder.params.items()}
    elif getattr(encoder, "_meshmei_demo", False):
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
        from ..encoders import load_demo_model

        return load_demo_model()
    raise MEIError(f"unknown encoder {kind!r}; expected 'gabor-simple', 'gabor-complex' or 'demo'")


def _encoder_from_spec(spec: dict) -> Encoder:
    kind = spec.get("kind")
    if kind in ("gabor-simple", "gabor-complex"):
        return make_encoder(kind, **spec["params"], mean=spec["mean"], std=spec["std"], norm=spec["norm"],
                            eps=spec["eps"])
    if kind == "demo":
        return make_encoder("demo")
    raise MEIError(f"cannot rebuild a {spec.get('class')} encoder from a run directory; pass encoder=... to load_run")


# ---------------------------------------------------------------------------------------------- quality

def triangle_quality(V: torch.Tensor, F: torch.Tensor) -> torch.Tensor:
    """Per-face quality ``4 sqrt(3) A / (l1^2 + l2^2 + l3^2)``: 1 for equilateral, 0 for degenerate, ``(m,)``."""
    T = V[F]  # (m, 3, 3)
    e = T.roll(-1, dims=1) - T  # edge vectors
    l2 = (e * e).sum((1, 2))
    return 2.0 * math.sqrt(3.0) * doublearea(V, F) / l2.clamp_min(torch.finfo(V.dtype).tiny)


def mesh_quality(V: torch.Tensor, F: torch.Tensor, *, self_intersections: bool = True) -> dict:
    """Minimum and mean triangle quality, and self-intersecting face pairs (libigl, exact predicates)."""
    q = triangle_quality(V.detach().double(), F)
    out = {"min_quality": float(q.min()), "mean_quality": float(q.mean()), "self_intersections": None}
    if self_intersections:
        import igl.predicates
        import numpy as np

        _, pairs, _ = igl.predicates.find_self_intersections(
            np.ascontiguousarray(V.detach().double().cpu().numpy()),
            np.ascontiguousarray(F.cpu().numpy().astype(np.int64)), False)
        out["self_intersections"] = int(len(pairs))
    return out


def _figures(result: MEIResult, out: Path):
    # the object-oriented API: no pyplot state, no backend switch in the caller's session
    import matplotlib.image
    from matplotlib.figure import Figure

    from ..render import camera_from_angles

    matplotlib.image.imsave(out / "render.png", result.image[0, 0].detach().cpu().numpy(), cmap="gray", vmin=0, vmax=1)
    views = []
    for az in (0.0, 45.0, 90.0):  # three more views of the mesh, turned about the vertical axis
        cam = camera_from_angles(az, 30.0, result.settings.camera_distance, fov_degrees=result.settings.fov_degrees)
        with torch.no_grad():
            img = render(result.V, result.F, camera=cam, settings=result.settings.render_settings())
        views.append(img[0, 0].cpu().numpy())
    fig = Figure(figsize=(12, 3.2))
    axes = fig.subplots(1, 4)
    axes[0].imshow(result.image[0, 0].detach().cpu().numpy(), cmap="gray", vmin=0, vmax=1)
    axes[0].set_title(f"MEI render, response {result.activation:.3f}")
    for ax, img, az in zip(axes[1:], views, (0, 45, 90)):
        ax.imshow(img, cmap="gray", vmin=0, vmax=1)
        ax.set_title(f"azimuth {az}, elevation 30")
    for ax in axes:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(out / "views.png", dpi=100)
    fig = Figure(figsize=(5, 3.2))
    ax = fig.subplots()
    ub = result.encoder.get("upper_bound")
    y = [h / ub for h in result.history] if ub else result.history
    ax.plot(range(1, len(y) + 1), y)
    ax.set_xlabel("step")
    ax.set_ylabel("fraction of upper bound" if ub else "response")
    ax.set_title(f"neuron {result.neuron}, seed {result.seed}")
    fig.tight_layout()
    fig.savefig(out / "activation.png", dpi=100)

