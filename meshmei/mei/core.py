"""MERGE: pieces awaiting their new homes from the helpers' branches (encoder registry -> encoders,
quality -> quality, REGULARIZERS -> regularizers, figures -> plots); deleted at merge."""

from __future__ import annotations

import math

import torch

from ..operators import doublearea
from ..regularizers import arap_direction_loss, arap_loss, area_loss, edge_loss, laplacian_loss

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
