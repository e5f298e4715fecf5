"""Reconstruction settings and results: what determines a run, per method and per stage, and what it returns."""

from __future__ import annotations

import math
import numbers
from dataclasses import asdict, dataclass, field, replace

import numpy as np
import torch

from .._checks import check_seed, is_integral, non_finite_entry
from ..contact import MAX_CONTACT_DISTANCE
from ..deform import MAX_LR_SCALE
from ..errors import ReconstructionError
from ..metrics import EVAL_SAMPLES, SurfaceMetrics
from ..optim import MAX_STEPS, OPTIMIZERS
from ..shapes.primitives import MAX_VERTICES
from ..validity import ValidityRules

__all__ = ["METHODS", "STAGE_FIELDS", "DEFAULTS", "DEFAULT_STEPS", "AUTO_EDGE_REFUSALS", "AUTO_EDGE_RAMP",
           "MIN_STAGE_VERTICES", "MAX_SAMPLES", "MAX_LR_SCALE",
           "ReconstructionSettings", "ReconstructionResult", "ReconstructionWarning"]


class ReconstructionWarning(RuntimeWarning):
    """A run that returned a result which is not what it looks like: a stage whose every step the step guard
    refused returned its start unchanged (also in ``ReconstructionResult.info["warnings"]``)."""

METHODS = ("rbf", "vertex", "largesteps")
# The step count of a run given neither steps nor a time budget. 1,000 since 2026-11-24 (it was 500): the
# CLI's default rbf run at 2,500 vertices (three levels, guarded, one torch thread) then ends at 1.18-1.25e-6
# on the bunny over seeds 0-5 (500 steps: 1.27-8.25e-6, 3 of 6 below 2e-6) and 1.87-1.92e-6 through the
# teapot's handle over seeds 0-2 (500: 2.13-2.40e-6), clean, in about 47 s against 25 s
# (docs/reconstruction.md, *How many steps*).
DEFAULT_STEPS = 1000

# The fewest vertices a stage may be remeshed to.
MIN_STAGE_VERTICES = 32
# The most samples n_samples, target_pool and eval_samples may ask for: 10**7 points and their distances take
# a few GB; 10**9 exhausted a 128 GB machine's memory after minutes
MAX_SAMPLES = 10_000_000

# contact_edges="auto": a stage turns edge-edge contact pairs on after this many candidates refused by the
# intersection rule (a stage that does not stall refuses 0-5 in all; a stall, hundreds)
AUTO_EDGE_REFUSALS = 5
# ... and in the run's last stage their weight grows from 1 / AUTO_EDGE_RAMP to 1 over this many steps: at full
# weight at once their barrier's gradient at the near-contact set the optimiser's one step divisor for the whole
# mesh, and a 10k teapot run went from 6.3e-7 to 3.2e-6 in 40 steps (docs/reconstruction.md, *The switch's kick*)
AUTO_EDGE_RAMP = 100
# The settings ReconstructionSettings.stage_overrides may change from one stage to the next.
STAGE_FIELDS = ("method", "lr", "lr_scale", "reg_decay", "w_laplacian", "w_edge", "w_arap", "optimizer", "lam",
                "sigma_factor", "r_cut", "centers", "coarse_ratio", "coarse_lr", "n_samples", "normal_match",
                "max_steps")

# Per-method defaults, tuned on sphere -> bunny and torus -> teapot at 2.5k and 10k vertices
# (see docs/reconstruction.md). Regularizer weights multiply losses in the units of a unit-diagonal
# target, for a 2,500-vertex result; reconstruct scales them to the run's final resolution
# (ReconstructionSettings.reg_ref_vertices).
DEFAULTS = {
    "rbf": dict(optimizer="uniform", lr=6e-3, reg_decay=True, lr_scale=0.0, w_laplacian=10.0, w_edge=0.0, w_arap=0.0,
                coarse_ratio=0, coarse_lr=3.0),
    "vertex": dict(optimizer="adam", reg_decay=False, lr=1e-3, lr_scale=0.0, w_laplacian=10.0, w_edge=0.0, w_arap=0.0,
                   coarse_ratio=0, coarse_lr=0.0),
    "largesteps": dict(optimizer="uniform", reg_decay=False, lr=5e-2, lr_scale=0.0, w_laplacian=0.0, w_edge=0.0,
                       w_arap=0.0, coarse_ratio=0, coarse_lr=0.0),
}


@dataclass(frozen=True)
class ReconstructionSettings:
    """Everything that determines a reconstruction run (recorded in its result and history JSON).

    A setting that only some runs use (``lr_scale``, ``sigma_factor``, ``r_cut``, ``centers``,
    ``coarse_ratio`` and ``coarse_lr`` rbf only, ``coarse_lr`` only with ``coarse_ratio``; ``lam`` large steps
    only; ``contact_distance`` and ``contact_edges=True`` only with ``w_contact > 0``; ``min_quality`` only
    with ``valid_steps``) must keep its default in a run, or a stage, that does not use it:
    :meth:`resolved` refuses it rather than record it as if applied.

    Attributes
    ----------
    method : {"rbf", "vertex", "largesteps"}
    steps : int or None
        Stop after this many optimisation steps (over all stages).
    time_budget : float or None
        Stop after this many seconds of optimisation wall time (metric evaluation not counted). With both
        ``steps`` and ``time_budget``, whichever ends first; the schedule (stages, learning-rate decay)
        follows the fraction of the budget used.
    lr : float
        Adam learning rate (offsets for rbf, vertex offsets for vertex, ``u`` for largesteps).
    lr_scale : float
        Learning rate of the RBF log-scales (0 freezes them), at most :data:`MAX_LR_SCALE` (10): a step moves
        a log-scale by up to ``lr_scale``. A run whose scales still leave the dtype's range (a kernel of
        infinite scale only translates the mesh) ends with a ``FloatingPointError``.
    lr_decay : float
        The learning rate decays geometrically to ``lr * lr_decay`` at the end of the run.
    reg_decay : bool
        Decay the regularizer weights by the same factor as the learning rate (strong smoothing while the
        shape moves far, less bias at the end).
    n_samples : int
        Points sampled on the current mesh per step, and target points drawn per step.
    target_pool : int
        Size of the fixed pool of target samples; the source-to-target direction uses all of it (through
        a KD-tree built once), so its resolution, not ``n_samples``, limits that direction. These two and
        ``eval_samples`` are at most ``MAX_SAMPLES`` (10,000,000).
    w_laplacian, w_edge, w_arap : float
        Weights of the uniform Laplacian, edge-length and direction-preserving ARAP regularizers, for a
        mesh of ``reg_ref_vertices`` vertices (see there).
    reg_ref_vertices : int or None
        The regularizer weights are stated for a mesh of this many vertices (default 2,500). A stage of
        ``n`` vertices multiplies the Laplacian weight by ``(n / reg_ref_vertices)^2`` and the edge and
        ARAP weights by ``n / reg_ref_vertices``: on an even mesh of edge length ``h ~ n^-1/2`` the
        uniform Laplacian loss (squared umbrella vectors, ``~ h^4`` times the squared mean curvature) falls
        like ``n^-2`` and the edge and direction terms (squared lengths) like ``n^-1``, so the scaled
        weights ask for the same smoothness at every resolution. The first stage takes the second stage's
        count instead of its own: it moves the shape farthest, and with its own count it folds the mesh
        (docs/reconstruction.md); with ``n/4`` vertices it is smoothed 16x more in surface terms. So the
        stages ``(n/4, n, n)`` all use ``n``, and ``(625, 2500, 10000, 10000)`` uses 2,500, 2,500,
        10,000, 10,000: a 10k run starts with the weights of a 2.5k run. Without ``stages``, the
        source's count. ``None``: weights used as given.
    optimizer : {"adam", "uniform"}
        ``torch.optim.Adam`` (per-coordinate step normalisation) or :class:`~meshmei.deform.largesteps.AdamUniform`
        (one normalisation per tensor, which keeps the smoothness of a preconditioned gradient).
    lam : float
        Smoothing weight of the large-steps parameterisation ``I + lam L``.
    sigma_factor, r_cut, centers : RBF kernel scale (in centre spacings), truncation radius (in scales) and
        number of kernels (None: all vertices).
    coarse_ratio : int
        rbf only (default 0, off: the paper's kernels alone). Above 0, add a second, coarse set of Gaussian kernels
        at ``n / coarse_ratio`` farthest points of each stage's mesh, each as wide as the spacing of those
        points (about ``sqrt(coarse_ratio)`` edges, 8 at 64), with offsets of their own. The map stays
        ``V0 + sum_k delta_k w_k`` over both sets. The coarse offsets are a separate tensor, so the uniform
        step normalises them on their own: they move the shape in smooth, wide steps while the fine
        kernels fit detail. Faster early on a compact target (the bunny), but the kernels are Euclidean:
        they tie together surface that is near in space and far along the surface, such as the two sides
        of a torus threaded through a teapot's handle, so they are off by default
        (docs/reconstruction.md, *Coarse kernels*). A stage where ``n / coarse_ratio`` rounds to fewer than 4
        (``deform.params.MIN_COARSE_KERNELS``) runs without coarse kernels, with a :class:`ReconstructionWarning`
        (its record says ``n_coarse_kernels`` 0): 10**6 on a 194-vertex mesh gave none, without a word.
    coarse_lr : float
        Learning rate of the coarse offsets as a multiple of ``lr`` (default 3).
    stages : tuple of int, "auto", "auto2", "auto3", "auto4", or None
        Vertex counts of coarse-to-fine stages; the source is remeshed to ``stages[0]`` at the start and the
        current shape to each next count between stages. None: one stage at the source's resolution.
        ``"auto"`` (in :func:`~meshmei.reconstruct.reconstruct`): the command line's default schedule,
        :func:`~meshmei.reconstruct.default_schedule` for the method and the source's vertex count (its
        stages, shares and overrides; ``stage_fractions`` and ``stage_overrides`` must then be unset);
        ``"auto2"``... force that many levels, as ``--stages`` does. On the 2.5k bunny the default run
        reaches Chamfer-L2 about 1.2e-6, one stage of the same method about 1e-4 (``reconstruct("sphere",
        "bunny")``, 2026-11-30).
        Under a time budget, a restart (a stage at the count of the one before, with the same settings)
        whose share is under twice the set-up time that stage took (remesh, guard, contact pairs: 2.3-2.7 s
        at 10k vertices) is not set up: the stage before runs on through its share, and its record in
        ``info["stages"]`` says ``merged_into``. A remesh lands near its count (5-7 % under in the default
        runs; each stage records ``n_vertices_asked`` beside ``n_vertices``); one that lands more than
        ``reconstruct.fit.STAGE_COUNT_TOLERANCE`` (1.25) times off gives its stage the regularizer weights
        of the count it got, with a warning (see ``reg_ref_vertices``).
    stage_fractions : tuple of float or None
        Share of the steps / budget of each stage (default equal shares).
    stage_overrides : tuple of (dict or None), or None
        Settings that differ in one stage (needs ``stages``; one entry per stage), e.g.
        ``({"w_laplacian": 0.0, "lr": 0.02}, None, None)`` or ``({"method": "largesteps"}, None)``. Keys
        are among :data:`STAGE_FIELDS`. A stage's settings are these overrides, then the values set
        explicitly for the run, then its method's defaults. The learning-rate decay and the regularizer
        scaling follow the whole run (the fraction of the budget used; the stage counts, see
        ``reg_ref_vertices``).
    seed : int
        Seed of all sampling (runs with ``steps`` are then bitwise repeatable); an integer from 0 to
        ``2**32 - 1`` (``meshmei._checks.SEED_RANGE``, the seeds of distinct runs: torch's CPU generator keeps a
        seed's low 32 bits, so 0, ``2**32`` and ``-2**63`` were one run; the metrics sample the target with
        ``seed + 1``).
    eval_every : int or None
        Evaluate :func:`surface_metrics` every this many steps (and always at the end).
    eval_times : tuple of float
        Also evaluate at the first step at or past each of these optimisation times (seconds).
    valid_steps : bool
        Accept only steps whose mesh is valid (default True; :class:`~meshmei.validity.ValidityRules` with
        ``turn_from="step"``: no new self-intersections, no face turned over in one step, no triangle
        below ``min_quality``); a refused step is halved until it passes. Remeshing between stages is
        checked too: a remesh that adds intersecting pairs is retried, and the stage keeps the mesh it
        has when no retry is clean. With the contact barrier (``w_contact``) the guard rarely has to
        refuse a step; without the barrier it stalls the fit at the first near-contact
        (docs/reconstruction.md, *Valid steps*). With the guard, a stage finer than ``reg_ref_vertices``
        takes the learning rate ``lr * sqrt(reg_ref_vertices / n)``, so that a step stays the same share
        of an edge (recorded per stage as ``lr`` in ``info["stages"]``).
    min_quality : float
        The triangle-quality bound of ``valid_steps``.
    w_contact : float
        Weight of the contact barrier (:class:`~meshmei.contact.ContactBarrier`), which pushes a vertex
        away from a face it is not part of once they come closer than ``contact_distance``; it keeps folds
        and self-contact from forming, so that the valid-steps guard has little to refuse. 0 turns it off.
    contact_distance : float
        The barrier's reach as a multiple of each stage's mean edge length at its start (default 0.25: on
        the bunny's default run, seeds 0 and 1, it ended at 1.9e-6 and 2.6e-6 against 5.8e-6 and 3.7e-6
        with 1/3; docs/reconstruction.md, *Valid steps*).
    contact_edges : bool or "auto"
        Also pair edges with edges (``ContactBarrier(edges=True)``), which ends the stalls where two edges
        cross at a near-contact the vertex-face pairs do not see. True: in every stage, at about 1.3 times
        the teapot's time at 2.5k vertices (the edge search); ``"auto"`` (default): in a stage from the step
        at which the guard has refused :data:`AUTO_EDGE_REFUSALS` candidates by the intersection rule (the
        sign of such a stall), so that stages that do not stall pay nothing, and in the run's last stage at a
        weight that grows to full over :data:`AUTO_EDGE_RAMP` steps; False: never (docs/reconstruction.md,
        *Stalls at edge contacts*, *The switch's kick*).
    w_facing : float
        Weight of the facing term: the mean over the Chamfer term's mesh samples of ``max(0, -n . n_t)``, the
        mesh normal ``n`` at a sample against the target normal ``n_t`` at the target sample nearest to it,
        so that only a surface turned away from the target pays. A fold lying on the target costs the
        Chamfer term almost nothing, and the guard will not let it pass through itself; this term unfolds
        it. 0 (default) leaves it out (docs/reconstruction.md, *Folds lying on the target*).
    normal_match : float
        Pair again each drawn target sample whose nearest mesh sample faces away from it (normals at more than
        90 degrees), with the mesh sample that minimises ``|q - p|^2 + (normal_match * D)^2 |n_q - n_p|^2``,
        ``D`` the target's bounding-box diagonal (approximate neighbours, scipy's ``eps=1``); the other pairs,
        and the mesh samples' nearest target samples, stay as they are, and the loss is the squared distance
        of the paired positions either way. By position alone the floor and walls of a cavity pull on the
        outside of the surface, across the wall, instead of on the surface over the opening, and a sphere
        never enters a cup; paired again, they pull on surface that faces their way. Only in a stage whose
        start encloses the target (99 % of 2,000 target samples inside it; the stage's record says
        ``start_encloses_target``): from a start that is not around the target, such pairs pull surface over
        from the far side, and the stage runs on plain pairs. 0 (default) is plain nearest neighbours;
        ``default_schedule`` sets 0.3 in rbf's first stage of three (docs/reconstruction.md, *Pairing by
        normal*). A stage setting.
    max_steps : int or None
        The most steps a stage takes (a stage setting; None, the default: no limit but its share). A stage
        that reaches it ends there, and what is left of its share of the budget goes to the stages after it,
        in their proportions (the stage's record says ``max_steps`` and ``ended_at_max_steps``); set for
        the last stage, or for a run without stages, the run ends there. ``default_schedule`` limits rbf's
        two coarse stages of three to the steps a default run of 1,000 gives them (150 and 250), and with four
        levels also the two stages at n/4 (350 and 250, what the 2,500-vertex default run gives its 2,500-vertex
        stages), so that a long time budget goes to the final resolution (docs/reconstruction.md, *Long
        budgets*, *The 2,500-vertex stages' limits*).
    surgery : bool
        Between stages, once the fit is close to the target elsewhere, change the mesh's topology where the
        target's differs (:func:`~meshmei.reconstruct.surgery.adapt_topology`): cut a hole through a thin
        sheet of the mesh that spans an opening of the target, and seal thin passages (and holes where the
        target has surface), filling the cavity they close where the target encloses it. Each change keeps
        the mesh closed, manifold and free of intersecting pairs; the stage's record says what was done
        (``surgery``). From the centred torus on the teapot, whose surface must otherwise span the handle
        and whose own hole has nowhere to go, the default run ends at 1.95e-6 against 2.76e-5 at 2.5k and
        8.7e-7 against 1.49e-5 at 10k (docs/reconstruction.md, *Topology surgery*). True (default) or False.
    eval_samples : int
        Samples per surface for the metrics (100,000 is the project's reported metric).
    """

    method: str = "rbf"
    steps: int | None = None
    time_budget: float | None = None
    lr: float | None = None
    lr_scale: float | None = None
    lr_decay: float = 0.1
    reg_decay: bool | None = None
    n_samples: int = 10_000
    target_pool: int = 200_000
    w_laplacian: float | None = None
    w_edge: float | None = None
    w_arap: float | None = None
    reg_ref_vertices: int | None = 2500
    optimizer: str | None = None
    lam: float = 19.0
    sigma_factor: float = 1.0
    r_cut: float = 4.0
    centers: int | None = None
    coarse_ratio: int | None = None
    coarse_lr: float | None = None
    stages: tuple | str | None = None
    stage_fractions: tuple | None = None
    stage_overrides: tuple | None = None
    seed: int = 0
    eval_every: int | None = None
    eval_times: tuple = ()
    eval_samples: int = EVAL_SAMPLES
    valid_steps: bool = True
    min_quality: float = 0.01
    w_contact: float = 100.0
    contact_distance: float = 0.25
    contact_edges: bool | str = "auto"
    w_facing: float = 0.0
    normal_match: float = 0.0
    max_steps: int | None = None
    surgery: bool = True

    def resolved(self) -> "ReconstructionSettings":
        """A copy with the per-method defaults filled in and every value checked.

        Raises
        ------
        ReconstructionError
            A value out of range, naming the setting and what arrived (a ``ValueError``).
        """
        if self.method not in METHODS:
            raise ReconstructionError(f"method must be one of {METHODS}, got {self.method!r}")
        s = replace(self, **{k: v for k, v in DEFAULTS[self.method].items() if getattr(self, k) is None})
        if s.steps is None and s.time_budget is None:
            s = replace(s, steps=DEFAULT_STEPS)
        s = _plain_numbers(s)
        _check_values(s)
        s = _resolve_stages(s)
        if _is_scalar(s.centers):  # 10.0 passed the check above, then the deformer refused it
            s = replace(s, centers=int(s.centers))
        if s.stage_overrides is not None:
            s = replace(s, stage_overrides=_check_overrides(s.stage_overrides, s.stages))
            self.stage_settings()  # every stage's own values are checked too, against its own method
        else:
            _check_used(s)
        return replace(s, eval_times=tuple(float(t) for t in s.eval_times))

    def validity_rules(self, max_step: float | None = None) -> ValidityRules:
        """The rules of ``valid_steps``: no new self-intersections, no face turned over in one step, and
        with the contact barrier no vertex moved farther than ``max_step`` in one step (reconstruction passes
        four times the barrier's ``d_hat``, the whole reach of its candidate search: one mean edge,
        :data:`~meshmei.reconstruct.fit.MAX_STEP_REACHES`)."""
        return ValidityRules(turn_from="step", min_quality=self.min_quality, max_step=max_step)

    def without_method_defaults(self) -> "ReconstructionSettings":
        """A copy with every value that equals its method's default unset (None), so that resolving it for
        another method fills in that method's defaults: resolved settings (a result's) hold their method's
        ``lr``, optimiser and weights, which a run of another method took as its own (a largesteps run at
        the vertex method's ``lr=1e-3``, Adam and Laplacian weight 10)."""
        if self.method not in DEFAULTS:
            return self
        return replace(self, **{k: None for k, v in DEFAULTS[self.method].items() if getattr(self, k) == v})

    def stage_settings(self) -> list:
        """The resolved settings of each stage (one entry when there are no ``stage_overrides``): for
        stage ``k``, ``stage_overrides[k]``, then the values set here, then the stage's method's defaults.
        Call it on the settings as given (unresolved), where unset values are still None."""
        if self.stage_overrides is None:
            return [self.resolved()]
        stages = []
        for k, o in enumerate(self.stage_overrides):
            method = (o or {}).get("method", self.method)
            # settings already resolved (a result's, replayed) hold the run method's defaults: a stage of
            # another method takes its own (they made a largesteps stage refuse rbf's coarse_lr, or run at rbf's lr)
            base = self.without_method_defaults() if method != self.method else self
            try:
                stages.append(replace(base, stage_overrides=None, **(o or {})).resolved())
            except ReconstructionError as err:
                raise ReconstructionError(f"stage {k}: {err}") from None
        return stages


def _is_real(x) -> bool:
    return isinstance(x, numbers.Real) and not isinstance(x, (bool, np.bool_))


def _is_scalar(x) -> bool:
    """A single value (a number, a bool, a string), not a sequence of them: ``centers`` as a count."""
    return isinstance(x, (numbers.Number, np.bool_, str))


def _sequence(x):
    """``x`` as a tuple, or None where it is not a sequence (a number, a string)."""
    if isinstance(x, (str, bytes)) or not hasattr(x, "__iter__"):
        return None
    return tuple(x)


# the settings that are numbers, and those that are whole numbers: checked for their kind first (a text '1'
# was a bare TypeError from a comparison below), then given to the run as Python's float and int (NumPy's
# float32 reached the run's JSON, and a NumPy seed torch's Generator)
_REALS = ("lr", "lr_scale", "lr_decay", "w_laplacian", "w_edge", "w_arap", "lam", "sigma_factor", "r_cut", "coarse_lr",
          "min_quality", "w_contact", "contact_distance", "w_facing", "normal_match", "time_budget")
_WHOLES = ("steps", "n_samples", "target_pool", "eval_samples", "max_steps", "seed", "coarse_ratio", "eval_every",
           "reg_ref_vertices")


MAX_NORMAL_MATCH = 1e6  # normals' weight against positions in the paired search (default 0.3 where used)


def _plain_numbers(s: ReconstructionSettings) -> ReconstructionSettings:
    """``s`` with its numbers as Python's (a one-element tensor taken as its value); ReconstructionError names a
    number setting holding anything else (text, a list, a complex number)."""
    out = {}
    for name in _REALS + _WHOLES:
        v = getattr(s, name)
        if isinstance(v, torch.Tensor) and v.numel() == 1 and not v.is_complex():
            v = v.item()
        if v is None or isinstance(v, (bool, np.bool_)):  # None: unset; a bool: refused by the checks as before
            continue
        if name in _WHOLES and not isinstance(v, numbers.Real):  # the count's own check names it
            continue
        if not isinstance(v, numbers.Real):
            raise ReconstructionError(f"{name} must be a number, got {v!r:.60}")
        if name in _REALS:
            out[name] = float(v)
        elif isinstance(v, numbers.Integral):  # a whole number given as 10.0 is left to its count's check
            out[name] = int(v)
    return replace(s, **out)


def _check_values(s: ReconstructionSettings) -> None:
    for name in ("valid_steps", "reg_decay", "surgery"):  # "no" or 0 would switch a feature on or off by truthiness
        if not isinstance(getattr(s, name), (bool, np.bool_)):
            raise ReconstructionError(f"{name} must be True or False, got {getattr(s, name)!r}")
    if s.steps is not None and not (is_integral(s.steps) and s.steps >= 1):  # inf: an OverflowError before
        raise ReconstructionError(f"steps must be a positive integer, got {s.steps!r}")
    if s.steps is not None and s.steps > MAX_STEPS:  # as the budget says it, before the target is loaded
        raise ReconstructionError(f"steps must be at most {MAX_STEPS:.0e}, got {s.steps!r}")
    tb = s.time_budget
    if tb is not None and not (_is_real(tb) and tb > 0 and math.isfinite(tb)):
        raise ReconstructionError(f"time_budget must be positive and finite, got {s.time_budget!r}")
    c = s.centers
    # a number of kernels (vertex indices, an array, are checked by the deformer); -5, 2.5 or True failed
    # after the target was loaded
    if _is_scalar(c) and not (is_integral(c) and c >= 1):
        raise ReconstructionError(f"centers must be None, a positive integer (a number of RBF kernels) or vertex "
                                  f"indices, got {c!r}")
    for name in ("lr", "r_cut", "sigma_factor", "contact_distance"):
        if not (getattr(s, name) > 0 and math.isfinite(getattr(s, name))):
            raise ReconstructionError(f"{name} must be positive and finite, got {getattr(s, name)!r}")
    if s.contact_distance > MAX_CONTACT_DISTANCE:
        raise ReconstructionError(f"contact_distance must be at most {MAX_CONTACT_DISTANCE:g} mean edge lengths, got "
                                  f"{s.contact_distance!r}")
    for name in ("n_samples", "target_pool", "eval_samples"):  # counts: refused here, not after the run
        n = getattr(s, name)
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise ReconstructionError(f"{name} must be a positive integer, got {n!r}")
        if n > MAX_SAMPLES:  # 10**9 ran out of memory after minutes, killed without a word
            raise ReconstructionError(f"{name} must be at most {MAX_SAMPLES:,} samples, got {n!r}")
    m = s.max_steps
    if m is not None and (isinstance(m, bool) or not isinstance(m, (int, np.integer)) or m < 1):
        raise ReconstructionError(f"max_steps must be a positive integer or None, got {m!r}")
    check_seed("seed", s.seed, error=ReconstructionError)  # SEED_RANGE: 0 and 2**32 were one run
    if not (isinstance(s.contact_edges, bool) or s.contact_edges == "auto"):
        raise ReconstructionError(f"contact_edges must be True, False or 'auto', got {s.contact_edges!r}")
    cr = s.coarse_ratio
    if isinstance(cr, bool) or not isinstance(cr, (int, np.integer)) or cr < 0 or cr == 1:
        raise ReconstructionError(f"coarse_ratio must be 0 (off) or an integer of at least 2, got {cr!r}")
    if cr and s.method == "rbf" and not s.coarse_lr > 0:  # other methods: refused by _check_used
        raise ReconstructionError(f"coarse_lr must be positive with coarse kernels, got {s.coarse_lr!r}")
    for name in ("lr_scale", "w_laplacian", "w_edge", "w_arap", "lam", "coarse_lr", "w_contact", "w_facing",
                 "normal_match"):
        if not (getattr(s, name) >= 0 and math.isfinite(getattr(s, name))):
            raise ReconstructionError(f"{name} must be non-negative and finite, got {getattr(s, name)!r}")
    if s.lr_scale > MAX_LR_SCALE:  # 1e10 overflowed every kernel scale at the first step, silently
        raise ReconstructionError(f"lr_scale must be at most {MAX_LR_SCALE:g} (a step may widen an RBF kernel "
                                  "e^lr_scale times; at 100 the first step overflowed every scale), "
                                  f"got {s.lr_scale!r}")
    if s.normal_match > MAX_NORMAL_MATCH:  # 1e160 made every 6-d distance inf: an IndexError inside the fit
        raise ReconstructionError(f"normal_match must be at most {MAX_NORMAL_MATCH:g}, got {s.normal_match!r}")
    ref = s.reg_ref_vertices
    if ref is not None and (isinstance(ref, bool) or not isinstance(ref, (int, np.integer)) or ref < 1):
        raise ReconstructionError(f"reg_ref_vertices must be a positive integer or None, got {s.reg_ref_vertices!r}")
    if s.optimizer not in OPTIMIZERS:
        raise ReconstructionError(f"optimizer must be 'adam' or 'uniform', got {s.optimizer!r}")
    if not 0 < s.lr_decay <= 1:
        raise ReconstructionError(f"lr_decay must lie in (0, 1], got {s.lr_decay!r}")
    if not 0 <= s.min_quality < 1:
        raise ReconstructionError(f"min_quality must lie in [0, 1), got {s.min_quality!r}")
    every = s.eval_every
    if every is not None and (isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 1):
        raise ReconstructionError(f"eval_every must be a positive integer or None, got {every!r}")
    try:  # a string is a sequence too: "10" ran as (1.0, 0.0)
        times = [math.nan] if isinstance(s.eval_times, (str, bytes)) else [float(t) for t in s.eval_times]
    except (TypeError, ValueError):
        times = [math.nan]
    if not all(t >= 0 and math.isfinite(t) for t in times):
        raise ReconstructionError(f"eval_times must be finite, non-negative seconds, got {s.eval_times!r}")


# Settings that only some runs use: (setting, what it needs, whether run s has that, what run s has). A value
# other than its default where the run would not use it is refused rather than recorded as if applied.
_RBF = ("method='rbf'", lambda s: s.method == "rbf", lambda s: f"method={s.method!r}")
_CONDITIONAL = (
    ("lr_scale", *_RBF), ("sigma_factor", *_RBF), ("r_cut", *_RBF), ("centers", *_RBF), ("coarse_ratio", *_RBF),
    ("coarse_lr", *_RBF),
    ("coarse_lr", "coarse_ratio > 0", lambda s: s.coarse_ratio > 0, lambda s: f"coarse_ratio={s.coarse_ratio!r}"),
    ("lam", "method='largesteps'", lambda s: s.method == "largesteps", lambda s: f"method={s.method!r}"),
    ("contact_distance", "w_contact > 0", lambda s: s.w_contact > 0, lambda s: f"w_contact={s.w_contact!r}"),
    ("min_quality", "valid_steps=True", lambda s: s.valid_steps, lambda s: f"valid_steps={s.valid_steps!r}"),
)


def _default(name: str, method: str):
    if name in DEFAULTS[method]:
        return DEFAULTS[method][name]
    return ReconstructionSettings.__dataclass_fields__[name].default


def _check_used(s: ReconstructionSettings) -> None:
    """Refuse a setting the run would ignore (one stage's settings, or a run without ``stage_overrides``)."""
    for name, needs, has, here in _CONDITIONAL:
        value, default = getattr(s, name), _default(name, s.method)
        given = value is not None if default is None else value != default
        if given and not has(s):
            shown = repr(value) if len(repr(value)) <= 40 else f"{repr(value)[:37]}..."
            raise ReconstructionError(f"{name}={shown} applies only with {needs}, not with {here(s)}; leave it at "
                                      f"its default ({default!r})")
    if s.contact_edges is True and not s.w_contact > 0:
        raise ReconstructionError(f"contact_edges=True applies only with w_contact > 0 (the contact barrier), not with "
                                  f"w_contact={s.w_contact!r}; leave contact_edges at 'auto'")


def _resolve_stages(s: ReconstructionSettings) -> ReconstructionSettings:
    if isinstance(s.stages, str):  # reconstruct() resolves a named schedule against the source it builds
        raise ReconstructionError(f"stages={s.stages!r} names a schedule of a source's vertex count: reconstruct() "
                                  f"resolves it; settings on their own need the counts (default_schedule(method, n))")
    if s.stages is None:
        if s.stage_fractions is not None:
            raise ReconstructionError("stage_fractions needs stages")
        return s
    # counts, each an integer (100.7 was truncated, inf an OverflowError, 500 alone a TypeError)
    counts = _sequence(s.stages)
    if not counts or not all(is_integral(x) and x >= MIN_STAGE_VERTICES for x in counts):
        raise ReconstructionError(f"stages must be integer vertex counts of at least {MIN_STAGE_VERTICES}, got "
                                  f"{s.stages!r} (stages=None runs one stage at the source's own size)")
    if max(counts) > MAX_VERTICES:
        raise ReconstructionError(f"stages must be vertex counts of at most {MAX_VERTICES:,}, got {s.stages!r}")
    stages = tuple(int(x) for x in counts)
    if s.centers is not None and not _is_scalar(s.centers):
        # indices of the source's vertices: a remeshed stage has other vertices (they were reused, silently)
        raise ReconstructionError("centers given as vertex indices name the source's vertices; with stages every "
                                  "stage is remeshed: give a number of kernels instead")
    if is_integral(s.centers) and s.centers > min(stages):  # the later stage failed after the earlier had run
        raise ReconstructionError(f"centers={s.centers!r} exceeds the smallest stage's {min(stages)} vertices; "
                                  f"a stage has at most one kernel per vertex")
    fr = _sequence(s.stage_fractions) if s.stage_fractions is not None else tuple(1.0 / len(stages) for _ in stages)
    if (fr is None or len(fr) != len(stages) or not all(_is_real(f) and f > 0 and math.isfinite(f) for f in fr)
            or not math.isfinite(float(sum(fr)))):  # (1e308, 1e308) summed to inf and became (0, 0)
        raise ReconstructionError(f"stage_fractions must give one positive, finite share per stage, "
                                  f"got {s.stage_fractions!r}")
    tot = float(sum(fr))
    fr = tuple(float(f) / tot for f in fr)
    if s.steps is not None and s.time_budget is None:
        _check_every_stage_steps(s.steps, stages, fr)
    return replace(s, stages=stages, stage_fractions=fr)


def _check_every_stage_steps(steps: int, stages: tuple, fractions: tuple) -> None:
    """Refuse a step budget that leaves a stage without a step: stage ``k`` runs from the first step ``i``
    with ``i / steps`` at or past its share's start while ``i / steps`` is under its end, as ``minimize``
    stops it (``--steps 3 --stages auto4`` ran four of five stages and ended on a 60-vertex mesh)."""
    bounds = np.cumsum((0.0,) + fractions)
    for k in range(len(stages)):
        end = 1.0 if k == len(stages) - 1 else float(bounds[k + 1])
        i = max(0, math.ceil(float(bounds[k]) * steps) - 1)
        while i / steps < float(bounds[k]):
            i += 1
        if not (i < steps and i / steps < end):
            raise ReconstructionError(f"steps={steps} gives stage {k} ({stages[k]} vertices) no step with "
                                      f"stage_fractions {tuple(round(f, 4) for f in fractions)}; give at least "
                                      f"{math.ceil(1.0 / min(fractions))} steps, or fewer stages")


def _check_overrides(overrides, stages) -> tuple:
    ov = tuple(overrides)
    if stages is None or len(ov) != len(stages):
        raise ReconstructionError(f"stage_overrides must give one entry per stage (stages={stages!r}), "
                                  f"got {overrides!r}")
    for o in ov:
        if o is not None and not isinstance(o, dict):
            raise ReconstructionError(f"each entry of stage_overrides must be a dict or None, got {o!r}")
        bad = sorted(set(o or {}) - set(STAGE_FIELDS))
        if bad:
            raise ReconstructionError(f"stage_overrides cannot set {bad[0]!r}; settable per stage: {STAGE_FIELDS}")
    return tuple(dict(o) if o else None for o in ov)


@dataclass(frozen=True)
class ReconstructionResult:
    """Output of :func:`reconstruct`.

    Attributes
    ----------
    V : (n, 3) float tensor, the reconstructed vertices (detached)
    F : (m, 3) int64 tensor
    history : list of dict
        One record per step: ``step``, ``stage``, ``time`` (optimisation seconds so far), ``loss``,
        ``chamfer`` (the sampled Chamfer term), ``lr``.
    metrics : list of dict
        One record per evaluation: ``step``, ``time``, ``n_vertices``, ``eval_seconds`` and the fields of
        :class:`~meshmei.metrics.SurfaceMetrics`.
    settings : ReconstructionSettings (resolved)
    final : SurfaceMetrics, the metrics of the returned mesh
    wall_time : float, optimisation seconds (remeshing between stages included, evaluation excluded)
    eval_time : float, seconds spent evaluating metrics
    info : dict, e.g. the regularizer weights used (``w_laplacian``, ``w_edge``, ``w_arap``, scaled to the
        resolution) and per stage (``info["stages"]``) its method, Laplacian weight, ``setup_seconds``, with
        the guard its ``steps`` and ``accepted_steps``, and for rbf the truncation error and pair counts (a
        restart merged into stage ``k``: ``n_vertices``, ``end_step``, ``steps`` 0, ``merged_into`` k), and
        after a checked remesh ``remesh_iterations`` and ``remesh_tries`` (every try refused:
        ``remesh_iterations`` None, ``remesh_refused_pairs``, ``remesh_refused_topology``, and
        ``remesh_out_of_time`` where a time budget stopped the tries, ``remesh_subdivided`` where the stage runs
        on its mesh split in four); ``warnings``: one line per stage whose every step the guard refused, whose
        remesh was refused or whose start has pairs in contact (each also a :class:`ReconstructionWarning`)
    """

    V: torch.Tensor
    F: torch.Tensor
    history: list
    metrics: list
    settings: ReconstructionSettings
    final: SurfaceMetrics
    wall_time: float
    eval_time: float
    info: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        """A JSON-serialisable dict of everything except the mesh (tensors and arrays, such as ``centers``
        given as vertex indices, as lists), whose numbers are all finite: standard JSON has no NaN or Infinity
        (Python's ``json`` writes them, strict readers refuse the file).

        Raises
        ------
        ReconstructionError
            A number of the result is NaN or Inf; the message names its key.
        """
        out = {
            "settings": _plain(asdict(self.settings)),
            "final": self.final.as_dict(),
            "wall_time": self.wall_time,
            "eval_time": self.eval_time,
            "n_vertices": int(self.V.shape[0]),
            "n_faces": int(self.F.shape[0]),
            "info": self.info,
            "history": self.history,
            "metrics": self.metrics,
        }
        bad = non_finite_entry(out)
        if bad is not None:  # info['target_frame']['scale'] inf was written to history.json as Infinity
            raise ReconstructionError(f"the result's {bad[0]} is {bad[1]}: JSON has no NaN or Infinity, so the "
                                      "result cannot be written as standard JSON")
        return out


def _plain(value):
    """``value`` with tensors, arrays and numpy scalars turned into lists and Python numbers, for JSON."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_plain(v) for v in value]
    if isinstance(value, tuple):
        return tuple(_plain(v) for v in value)
    if isinstance(value, (torch.Tensor, np.ndarray, np.generic)):
        return value.tolist()
    return value
