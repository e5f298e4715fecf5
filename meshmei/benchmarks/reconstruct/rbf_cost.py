"""The cost of the truncated RBF map (pairs, memory, forward and backward time) against mesh size and truncation."""

from __future__ import annotations

import time

import torch

from ...deform import RBFDeformer
from ...shapes import initial_mesh, target_mesh
from .._report import machine_line, markdown_table, timeit, write_section

__all__ = ["rbf_cost"]


# What the table shows (under the section's first line).
_NOTE = (
    "All-vertex Gaussian kernels (`RBFDeformer(V0, sigma_factor=..., r_cut=...)`, headroom 1.25). "
    "`sigma` is `sigma_factor` times the mean centre spacing; pairs within `1.25 * r_cut * sigma` are kept, "
    "so the largest dropped weight is at most `exp(-r_cut^2 / 2)` (the column shows the value at build). "
    "Fixed scales (`learn_scales=False`, what `reconstruct` uses unless `lr_scale > 0`): the map is a "
    "constant sparse matrix, one CSR product forward and one with its transpose backward. Learnable scales: "
    "a gather and an `index_add` over the pairs, differentiable in the scales. Memory (fixed / learnable): "
    "pair indices and distances plus the two CSR matrices, or plus the per-pair temporaries of one forward "
    "and backward pass (float32). Time: one forward and backward pass, single thread, median of 5."
)


def _cost_row(kind, V0, sigma_factor, r_cut, quick):
    """One row of the table: the map on ``V0`` (n, 3) with fixed and with learnable scales."""
    t0 = time.perf_counter()
    rbf = RBFDeformer(V0, sigma_factor=sigma_factor, r_cut=r_cut)
    build = time.perf_counter() - t0
    fixed = RBFDeformer(V0, sigma_factor=sigma_factor, r_cut=r_cut, learn_scales=False)
    times = []
    for m in (fixed, rbf):
        with torch.no_grad():
            m.offsets.normal_(std=1e-3, generator=torch.Generator().manual_seed(0))

        def step(m=m):
            m.zero_grad(set_to_none=True)
            (m() ** 2).sum().backward()

        times.append(timeit(step, repeat=3 if quick else 5))
    # pair buffers (two int64 indices, a distance) plus, with fixed scales, W and W^T in CSR (int64
    # column index and a float32 value per pair each) or, with learnable scales, the per-pair
    # temporaries of one forward and backward pass (a weight, (P, 3) products forward and backward)
    mb_fixed = rbf.n_pairs * (8 + 8 + 4 + 2 * (8 + 4)) / 2**20
    mb_learn = rbf.n_pairs * (8 + 8 + 4 + 4 + 4 * 3 * 2) / 2**20
    return [f"{kind} {V0.shape[0]}", sigma_factor, r_cut, f"{rbf.truncation_error:.1e}", rbf.n_pairs,
            f"{rbf.n_pairs / V0.shape[0]:.0f}", f"{mb_fixed:.0f} / {mb_learn:.0f}", f"{build:.2f}",
            f"{1e3 * times[0]:.1f}", f"{1e3 * times[1]:.1f}", f"{times[1] / times[0]:.1f}"]


def rbf_cost(quick=False):
    """Pairs, memory and forward+backward time of the truncated RBF map against resolution, r_cut and scale;
    writes the section "reconstruction-rbf-cost" of ``docs/benchmarks.md``."""
    rows = []
    meshes = [("sphere", n) for n in ((500, 2000) if quick else (2500, 10000))]
    meshes.append(("bunny", None))
    for kind, n in meshes:
        V0 = target_mesh("bunny")[0] if kind == "bunny" else initial_mesh("sphere", n_vertices=n)[0]
        for sigma_factor, r_cut in ((1.0, 3.0), (1.0, 4.0), (1.0, 5.0), (2.0, 4.0)):
            rows.append(_cost_row(kind, V0, sigma_factor, r_cut, quick))
            print(rows[-1], flush=True)
    body = [
        "Written by `python -m meshmei.benchmarks.reconstruct --rbf-cost`. " + machine_line() + ".",
        "",
        _NOTE,
        "",
        markdown_table(["mesh", "sigma_factor", "r_cut", "max dropped weight", "pairs", "pairs / kernel",
                        "memory (MiB), fixed / learnable", "build (s)", "fwd+bwd fixed (ms)",
                        "fwd+bwd learnable (ms)", "ratio"], rows),
    ]
    write_section("reconstruction-rbf-cost", "\n".join(body))
