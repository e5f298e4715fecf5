"""Every regularizer on every initial mesh, at rest and deformed: the table of ``meshmei regularizers``."""

from __future__ import annotations

import time

import torch

from ._checks import check_seed
from .operators import doublearea
from .regularizers import REGULARIZER_LABELS, REGULARIZERS
from .shapes import DEFAULT_N_VERTICES, initial_mesh

__all__ = ["tabulate_regularizers"]


def tabulate_regularizers(n_vertices: int = DEFAULT_N_VERTICES, seed: int = 0, out=print) -> dict:
    """Evaluate each regularizer on each initial mesh, at rest and after a smooth random bump.

    Returns ``{(kind, state, label): (value, seconds for forward+backward)}`` with the labels of
    :data:`~meshmei.regularizers.REGULARIZER_LABELS`, and prints a table.
    """
    g = torch.Generator().manual_seed(check_seed("seed", seed))  # SEED_RANGE: beyond it torch repeats these bumps
    rows = {}
    for kind in ("sheet", "sphere", "torus"):
        t = time.perf_counter()
        V0, F = initial_mesh(kind, n_vertices=n_vertices)
        build = time.perf_counter() - t
        # a smooth bump: a few Gaussian blobs of random displacement
        centres = V0[torch.randint(V0.shape[0], (4,), generator=g)]
        w = torch.exp(-torch.cdist(V0, centres) ** 2 / (2 * 0.15**2))  # (n, 4)
        bump = w @ (0.1 * torch.randn(4, 3, generator=g))
        out(f"{kind}: {V0.shape[0]} vertices, {F.shape[0]} faces, area {0.5 * doublearea(V0, F).sum():.4f}, built in {build:.2f} s")
        for state, V in (("rest", V0), ("bumped", V0 + bump)):
            for key, name in REGULARIZER_LABELS.items():
                X = V.clone().requires_grad_(True)
                t = time.perf_counter()
                val = REGULARIZERS[key](X, V0, F)
                val.backward()
                rows[(kind, state, name)] = (val.item(), time.perf_counter() - t)
    names = list(REGULARIZER_LABELS.values())
    out("")
    out(f"{'regularizer':24s}" + "".join(f"{k + ' ' + s:>17s}" for k in ("sheet", "sphere", "torus") for s in ("rest", "bumped")))
    for name in names:
        out(f"{name:24s}" + "".join(f"{rows[(k, s, name)][0]:17.3e}" for k in ("sheet", "sphere", "torus") for s in ("rest", "bumped")))
    total = sum(r[1] for r in rows.values())
    finite = all(torch.isfinite(torch.tensor(v)) for v, _ in rows.values())
    out(f"\nall {len(rows)} values finite: {finite}; {len(rows)} forward+backward passes took {total:.2f} s in all")
    return rows
