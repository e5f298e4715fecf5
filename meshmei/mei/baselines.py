"""Baselines a 3D-MEI is measured against: regularizer-weight grids, and responses to random smooth
deformations of the starting mesh in the same scene."""

from __future__ import annotations

import itertools
import numbers
from dataclasses import replace

import torch

from .._checks import check_seed
from ..encoders import Encoder, eval_mode
from ..errors import MEIError
from ..quality import health_report
from ..regularizers import REGULARIZERS
from ..render import render
from .optimize import check_neuron, initial, optimize_mei, settings_for_encoder
from .settings import MEISettings

__all__ = ["grid_search", "random_deformations", "random_mesh_responses"]


def grid_search(encoder: Encoder, neuron: int, init="sphere", grid: dict | None = None,
                settings: MEISettings | None = None, *, self_intersections: bool = True, progress: bool = False,
                **overrides) -> list[dict]:
    """Run :func:`optimize_mei` for every combination of regularizer weights in ``grid``.

    Parameters
    ----------
    grid : dict of str -> sequence of float
        Weights to try per regularizer (names of :data:`REGULARIZERS`); regularizers not named keep the
        weight of ``settings``. Default: Laplacian and edge weights in ``{0, 1, 10}``.

    Returns
    -------
    list of dict, one per setting: ``weights``, ``activation``, ``fraction_of_bound``, ``seconds``, and the
    result's :func:`~meshmei.quality.health_report` (``min_quality``, ``mean_quality``, ``self_intersections``
    (None with ``self_intersections=False``), ``flipped_faces`` against the start, ``watertight``, ...).
    """
    settings = MEISettings.with_overrides(settings, overrides)
    grid = grid if grid is not None else {"laplacian": [0.0, 1.0, 10.0], "edge": [0.0, 1.0, 10.0]}
    if not isinstance(grid, dict) or not grid:
        raise MEIError(f"grid must be a non-empty dict of regularizer name -> weights, got {grid!r}")
    for k, ws in grid.items():
        if k not in REGULARIZERS:
            raise MEIError(f"unknown regularizer {k!r} in grid; expected one of {sorted(REGULARIZERS)}")
        if isinstance(ws, (str, bytes)) or not hasattr(ws, "__iter__"):  # "10" ran weights 1 and 0
            raise MEIError(f"grid entry {k!r} must be a sequence of weights, got {ws!r}")
        if len(list(ws)) == 0:
            raise MEIError(f"grid entry {k!r} is empty")
    names = list(grid)
    rows = []
    for combo in itertools.product(*(list(grid[k]) for k in names)):
        w = dict(settings.weights)
        w.update(dict(zip(names, (float(x) for x in combo))))
        res = optimize_mei(encoder, neuron, init, replace(settings, weights=w), progress=progress)
        q = health_report(res.V, res.F, res.V0, self_intersections=self_intersections)
        rows.append({"weights": w, "activation": res.activation, "fraction_of_bound": res.fraction_of_bound,
                     **q, "seconds": res.wall_time})
    return rows


def random_deformations(V0: torch.Tensor, n: int, *, generator: torch.Generator | None = None, n_bumps: int = 4,
                        amplitude: float = 0.15, width=(0.1, 0.3)) -> torch.Tensor:
    """``n`` random smooth deformations of a mesh: sums of ``n_bumps`` Gaussian bumps of random displacement.

    Each bump sits on a random vertex, has a width drawn uniformly from ``width`` and a displacement drawn
    from ``N(0, amplitude^2 I)`` (world units; the initial meshes span 1).

    Returns
    -------
    (n, V0.shape[0], 3) tensor of deformed vertex positions (dtype and device of ``V0``).
    """
    g = generator if generator is not None else torch.Generator().manual_seed(0)
    dt, cpu = V0.dtype, dict(generator=g, device="cpu")  # drawn on the CPU (the generator's), then moved
    c = V0[torch.randint(V0.shape[0], (n, n_bumps), **cpu).to(V0.device)]  # (n, k, 3)
    w = (width[0] + (width[1] - width[0]) * torch.rand(n, 1, n_bumps, dtype=dt, **cpu)).to(V0.device)
    d = (amplitude * torch.randn(n, n_bumps, 3, dtype=dt, **cpu)).to(V0.device)
    K = torch.exp(-torch.cdist(V0.unsqueeze(0).expand(n, -1, -1), c) ** 2 / (2 * w * w))  # (n, nv, k)
    return V0 + K @ d


@torch.no_grad()
def random_mesh_responses(encoder: Encoder, neuron: int, init="sphere", n: int = 1000,
                          settings: MEISettings | None = None, *, seed: int = 0, batch: int = 50,
                          **deform_kw) -> torch.Tensor:
    """Responses ``(n,)`` of a neuron to ``n`` random deformations of the initial mesh, in the MEI's scene.

    The baseline a 3D-MEI has to beat: the same starting mesh, scene and preprocessing, with random smooth
    deformations (:func:`random_deformations`) instead of optimised ones. ``neuron`` is one neuron's index
    (``MEIError`` otherwise, as in :func:`optimize_mei`).
    """
    neuron = check_neuron(encoder, neuron)
    if isinstance(n, bool) or not isinstance(n, numbers.Integral) or n < 1:  # 0 failed in torch.cat, 2.5 in range
        raise MEIError(f"n must be a positive integer (deformations to draw), got {n!r}")
    seed = check_seed("seed", seed, error=MEIError)  # SEED_RANGE: beyond it torch repeats these draws
    settings = settings_for_encoder(MEISettings.with_overrides(settings, {}), encoder)  # the MEI's image size
    V0, F, _ = initial(init, settings, encoder.device)
    g = torch.Generator().manual_seed(seed)
    out = []
    with eval_mode(encoder):
        for start in range(0, n, batch):
            Vb = random_deformations(V0, min(batch, n - start), generator=g, **deform_kw)
            I = render(Vb, F, camera=settings.camera(),
                       light=None if settings.light is None else torch.tensor(settings.light, dtype=V0.dtype,
                                                                              device=V0.device),
                       settings=settings.render_settings())
            out.append(encoder(I, neuron)[:, 0])
    return torch.cat(out)
