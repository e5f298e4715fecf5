"""Diverse 3D-MEIs: K meshes for one neuron, optimised together and pushed apart in image space.

The K members are the items of one batch (:class:`meshmei.mei.batch.BatchScene`, seeds 0 .. K-1 after the
first of ``settings.seeds``). Each member's loss is its usual one minus a diversity reward: the mean
distance between its preprocessed image and the others', as a share of the largest possible one (two
images of norm ``r`` are at most ``2 r`` apart), times the best member's response. A floor keeps every
member near the best: while the best response is positive, a member below ``floor`` times it pays
``10 * best * (floor - f / best)^2``. (An encoder that does not rescale its images, a lab's model with
``norm=None``, measures the distance as a share of the two images' norms summed.) The final iterate is kept
(a per-member best would break the set).
"""

from __future__ import annotations

import math
import numbers
import time
from dataclasses import dataclass, replace

import torch

from .._checks import SEED_RANGE, is_integral
from ..encoders import Encoder, frozen_encoder
from ..errors import MEIError
from ..optim import Budget, Schedule, Trace, make_optimizer, minimize
from .batch import BatchScene
from .optimize import check_neuron, initial, objective_weights, result_from_seeds, settings_for_encoder
from .scene import sheet_uv
from .settings import MEISettings

__all__ = ["DiverseMEIs", "diverse_meis", "MAX_MEMBERS"]

# The most members one call optimises: they form one batch, and the diversity reward compares every pair of
# images (k^2 distances); 10**400 from the command line grew a list of seeds until the machine ran out of memory
MAX_MEMBERS = 1024


@dataclass(frozen=True)
class DiverseMEIs:
    """K 3D-MEIs of one neuron.

    Attributes
    ----------
    results : list of MEIResult
        One per member, each a complete result (its ``seed`` is the member's).
    dissimilarity : (K, K) tensor
        Distances between the members' preprocessed images, as a share of the largest possible (0 .. 1).
    """

    results: list
    dissimilarity: torch.Tensor

    @property
    def responses(self) -> list[float]:
        return [r.activation for r in self.results]


def image_distances(encoder, z: torch.Tensor) -> torch.Tensor:
    """Distances ``(K, K)`` between the preprocessed images ``z (K, ...)`` as a share of the largest possible,
    in [0, 1]: two images ``a, b`` are at most ``|a| + |b|`` apart, ``2 r`` where the preprocessing rescales
    every image to norm ``r`` (the built-in encoders); an encoder without that rescaling (a lab's model
    with ``norm=None``) uses the images' own norms."""
    flat = z.reshape(z.shape[0], -1)
    d = torch.cdist(flat, flat)
    pre = encoder.preprocess
    if getattr(pre, "renorm", True):  # a lab's model made with norm=None has renorm False
        return d / (2 * float(pre.norm))
    size = flat.norm(dim=1)
    return d / (size[:, None] + size[None, :]).clamp_min(torch.finfo(d.dtype).tiny)


def _objective(encoder, neuron, F, scene: BatchScene, active, settings: MEISettings, weight: float, floor: float):
    def objective(point):
        V = scene.vertices()
        z, idx = encoder.inputs(scene.image(V, F), [neuron])
        f = encoder.respond(z, idx)[:, 0]
        K = f.shape[0]
        spread = image_distances(encoder, z).sum(1) / max(K - 1, 1)
        best = f.detach().max()
        scale = best.abs().clamp_min(1e-12)
        loss = -f - weight * scale * spread
        if floor > 0:  # a share of a positive best response; below zero there is no share to keep
            loss = loss + 10 * scale * torch.where(best > 0, torch.relu(floor - f / scale), torch.zeros_like(f)) ** 2
        record = {"response": f.detach().tolist(), "spread": spread.detach().tolist()}
        return loss + scene.penalties(V, F, active, settings, record), record

    return objective


def diverse_meis(encoder: Encoder, neuron: int, k: int = 4, init="sheet", settings: MEISettings | None = None, *,
                 diversity: float = 0.5, floor: float = 0.8, **overrides) -> DiverseMEIs:
    """K diverse 3D-MEIs of ``neuron`` (see the module's description for the objective).

    Parameters
    ----------
    k : int
        Members (2 to ``MAX_MEMBERS``, 1024).
    diversity : float
        Weight of the diversity reward (>= 0; 0 with ``floor`` 0: K independent runs, kept at their final
        iterate).
    floor : float
        Share of the best member's response that every member should keep, in [0, 1] (0: none); no bound
        while the best response is not positive.
    """
    settings = settings_for_encoder(MEISettings.with_overrides(settings, overrides), encoder)
    neuron = check_neuron(encoder, neuron)
    if not (is_integral(k) and 2 <= k <= MAX_MEMBERS):  # numpy's integers too
        raise MEIError(f"k must be an integer from 2 to {MAX_MEMBERS}, got {k!r}")
    k = int(k)
    if not all(isinstance(v, numbers.Real) and not isinstance(v, bool) for v in (diversity, floor)) or not (
            diversity >= 0 and math.isfinite(diversity) and 0 <= floor <= 1):
        raise MEIError(f"need diversity >= 0 and floor in [0, 1], got {diversity!r}, {floor!r}")
    if settings.robust_pose > 0 or settings.robust_light > 0:  # the batch renders one view per member
        raise MEIError("diverse 3D-MEIs take no robust objective (robust_pose, robust_light); make them "
                       "without it, or make robust 3D-MEIs one seed at a time")
    seeds = [settings.seeds[0] + i for i in range(k)]
    if seeds[-1] > SEED_RANGE[1]:  # 2**32 - 1 and 2**32 were one member twice (torch keeps a seed's low 32 bits)
        raise MEIError(f"the members' seeds {seeds[0]}..{seeds[-1]} (the first of seeds, then one more each) must lie "
                       f"in [{SEED_RANGE[0]}, {SEED_RANGE[1]}], the seeds of distinct runs; start from a seed of at "
                       f"most {SEED_RANGE[1] - k + 1}")
    V0, F, init_name = initial(init, settings, encoder.device)
    settings = settings.for_start(init_name)
    n_weights = settings.n_vertices if init_name != "custom" else V0.shape[0]
    t0 = time.perf_counter()
    with frozen_encoder(encoder):
        scene = BatchScene(V0, settings, seeds, sheet_uv(V0) if init_name == "sheet" else None, F, n_weights)
        trace = Trace()
        minimize(_objective(encoder, neuron, F, scene, objective_weights(settings, n_weights), settings, diversity,
                            floor),
                 make_optimizer("adam", scene.groups), Budget(steps=settings.steps),
                 schedule=Schedule("cosine", settings.lr_decay, endpoint=True), keep="last", trace=trace,
                 accept=scene.acceptor(), max_halvings=scene.max_halvings, states=scene.rbfs, error=MEIError,
                 where=f" (diverse MEIs of neuron {neuron})")
        with torch.no_grad():
            V = scene.vertices()
            images = scene.image(V, F, pose=True)
            z, idx = encoder.inputs(images, [neuron])
            acts = encoder.respond(z, idx)[:, 0].tolist()
            dissimilarity = image_distances(encoder, z).cpu()  # on the CPU, as the results
    wall = (time.perf_counter() - t0) / k
    runs = scene.item_runs(V, images, acts, trace.history, trace.history[-1]["loss"], [trace.step] * k, settings)
    # each member as it ran: its own seed, kept at the last iterate, and the set it belongs to (its run alone
    # would not give it back: the reward couples the members)
    results = []
    for i, (s, run) in enumerate(zip(seeds, runs)):
        res = result_from_seeds({s: run}, V0, F, replace(settings, seeds=(s,), keep="last"), neuron, encoder,
                                init_name, wall)
        results.append(replace(res, extra={**res.extra, "diverse": {"member": i, "k": k, "seeds": seeds,
                                                                     "diversity": float(diversity),
                                                                     "floor": float(floor)}}))
    return DiverseMEIs(results=results, dissimilarity=dissimilarity)
