"""Shape reconstruction by Chamfer minimisation: deform a starting mesh into a target surface.

:func:`reconstruct` fits a source mesh (a sphere, a torus, any mesh) to a target by minimising a sampled
Chamfer distance plus geometric regularizers with Adam, through one of three parameterisations:

- ``"rbf"``: the paper's Gaussian RBF deformation (:class:`meshmei.deform.RBFDeformer`), kernels at all
  vertices with learnable offsets and scales;
- ``"vertex"``: free per-vertex offsets (the classic pytorch3d "deform a sphere" recipe);
- ``"largesteps"``: ``u = (I + lambda L) V`` with a uniform Adam step (:mod:`meshmei.largesteps`).

Optional coarse-to-fine stages remesh the current shape isotropically (pymeshlab) to more vertices between
stages. The result carries the mesh, the history of loss and metrics against optimisation wall time
(metric evaluation is timed separately and not counted), and the settings. ``meshmei reconstruct`` is the
command-line front end.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from .._checks import check_positive
from ..errors import MeshError
from ..mesh import check_mesh, load_mesh, save_mesh
from ..operators import doublearea
from ..metrics import SurfaceMetrics, surface_metrics
from ..quality import mesh_health
from ..sampling import PointIndex, sample_points
from ..regularizers import arap_direction_loss, edge_loss, laplacian_loss

__all__ = [
    "reconstruct",
    "ReconstructionSettings",
    "ReconstructionResult",
    "METHODS",
    "STAGE_FIELDS",
    "DEFAULTS",
    "remesh",
    "source_mesh",
    "SOURCE_NAMES",
    "target_surface",
    "add_parser",
    "default_stages",
    "default_schedule",
    "RBF_THREE_LEVEL_OVERRIDES",
    "THREE_LEVEL_MIN_VERTICES",
    "plot_history",
]

METHODS = ("rbf", "vertex", "largesteps")
# The settings ReconstructionSettings.stage_overrides may change from one stage to the next.
STAGE_FIELDS = ("method", "lr", "lr_scale", "reg_decay", "w_laplacian", "w_edge", "w_arap", "optimizer", "lam",
                "sigma_factor", "r_cut", "centers", "coarse_ratio", "coarse_lr", "n_samples")

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
        Learning rate of the RBF log-scales (0 freezes them).
    lr_decay : float
        The learning rate decays geometrically to ``lr * lr_decay`` at the end of the run.
    reg_decay : bool
        Decay the regularizer weights by the same factor as the learning rate (strong smoothing while the
        shape moves far, less bias at the end).
    n_samples : int
        Points sampled on the current mesh per step, and target points drawn per step.
    target_pool : int
        Size of the fixed pool of target samples; the source-to-target direction uses all of it (through
        a KD-tree built once), so its resolution, not ``n_samples``, limits that direction.
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
        ``torch.optim.Adam`` (per-coordinate step normalisation) or :class:`~meshmei.largesteps.AdamUniform`
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
        (docs/reconstruction.md, *Coarse kernels*).
    coarse_lr : float
        Learning rate of the coarse offsets as a multiple of ``lr`` (default 3).
    stages : tuple of int, or None
        Vertex counts of coarse-to-fine stages; the source is remeshed to ``stages[0]`` at the start and the
        current shape to each next count between stages. None: one stage at the source's resolution.
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
        Seed of all sampling (runs with ``steps`` are then bitwise repeatable).
    eval_every : int or None
        Evaluate :func:`surface_metrics` every this many steps (and always at the end).
    eval_times : tuple of float
        Also evaluate at the first step at or past each of these optimisation times (seconds).
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
    stages: tuple | None = None
    stage_fractions: tuple | None = None
    stage_overrides: tuple | None = None
    seed: int = 0
    eval_every: int | None = None
    eval_times: tuple = ()
    eval_samples: int = 100_000

    def resolved(self) -> "ReconstructionSettings":
        """A copy with the per-method defaults filled in and every value checked."""
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {self.method!r}")
        s = replace(self, **{k: v for k, v in DEFAULTS[self.method].items() if getattr(self, k) is None})
        if s.steps is None and s.time_budget is None:
            s = replace(s, steps=500)
        if s.steps is not None and (isinstance(s.steps, bool) or int(s.steps) != s.steps or s.steps < 1):
            raise ValueError(f"steps must be a positive integer, got {s.steps!r}")
        if s.time_budget is not None and not (s.time_budget > 0 and math.isfinite(s.time_budget)):
            raise ValueError(f"time_budget must be positive and finite, got {s.time_budget!r}")
        for name in ("lr", "n_samples", "target_pool", "eval_samples", "r_cut", "sigma_factor"):
            if not getattr(s, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(s, name)!r}")
        cr = s.coarse_ratio
        if isinstance(cr, bool) or not isinstance(cr, (int, np.integer)) or cr < 0 or cr == 1:
            raise ValueError(f"coarse_ratio must be 0 (off) or an integer of at least 2, got {cr!r}")
        if cr and s.method != "rbf":
            raise ValueError(f"coarse_ratio applies to the rbf method only, not {s.method!r}; set it to 0")
        if cr and not s.coarse_lr > 0:
            raise ValueError(f"coarse_lr must be positive with coarse kernels, got {s.coarse_lr!r}")
        for name in ("lr_scale", "w_laplacian", "w_edge", "w_arap", "lam", "coarse_lr"):
            if not getattr(s, name) >= 0:
                raise ValueError(f"{name} must be non-negative, got {getattr(s, name)!r}")
        ref = s.reg_ref_vertices
        if ref is not None and (isinstance(ref, bool) or not isinstance(ref, (int, np.integer)) or ref < 1):
            raise ValueError(f"reg_ref_vertices must be a positive integer or None, got {s.reg_ref_vertices!r}")
        if s.optimizer not in ("adam", "uniform"):
            raise ValueError(f"optimizer must be 'adam' or 'uniform', got {s.optimizer!r}")
        if not 0 < s.lr_decay <= 1:
            raise ValueError(f"lr_decay must lie in (0, 1], got {s.lr_decay!r}")
        if s.eval_every is not None and not s.eval_every >= 1:
            raise ValueError(f"eval_every must be a positive integer or None, got {s.eval_every!r}")
        if s.stages is not None:
            stages = tuple(int(x) for x in s.stages)
            if not stages or min(stages) < 32:
                raise ValueError(f"stages must be vertex counts of at least 32, got {s.stages!r}")
            fr = s.stage_fractions or tuple(1.0 / len(stages) for _ in stages)
            if len(fr) != len(stages) or min(fr) <= 0:
                raise ValueError(f"stage_fractions must give one positive share per stage, got {s.stage_fractions!r}")
            tot = float(sum(fr))
            s = replace(s, stages=stages, stage_fractions=tuple(float(f) / tot for f in fr))
        elif s.stage_fractions is not None:
            raise ValueError("stage_fractions needs stages")
        if s.stage_overrides is not None:
            ov = tuple(s.stage_overrides)
            if s.stages is None or len(ov) != len(s.stages):
                raise ValueError(f"stage_overrides must give one entry per stage (stages={s.stages!r}), "
                                 f"got {s.stage_overrides!r}")
            for o in ov:
                if o is not None and not isinstance(o, dict):
                    raise ValueError(f"each entry of stage_overrides must be a dict or None, got {o!r}")
                bad = sorted(set(o or {}) - set(STAGE_FIELDS))
                if bad:
                    raise ValueError(f"stage_overrides cannot set {bad[0]!r}; settable per stage: {STAGE_FIELDS}")
            s = replace(s, stage_overrides=tuple(dict(o) if o else None for o in ov))
            self.stage_settings()  # every stage's own values are checked too
        return replace(s, eval_times=tuple(float(t) for t in s.eval_times))

    def stage_settings(self) -> list:
        """The resolved settings of each stage (one entry when there are no ``stage_overrides``): for
        stage ``k``, ``stage_overrides[k]``, then the values set here, then the stage's method's defaults.
        Call it on the settings as given (unresolved), where unset values are still None."""
        if self.stage_overrides is None:
            return [self.resolved()]
        return [replace(self, stage_overrides=None, **(o or {})).resolved() for o in self.stage_overrides]


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
        resolution) and per stage (``info["stages"]``) its method, Laplacian weight, and for rbf the
        truncation error and pair counts
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
        """A JSON-serialisable dict of everything except the mesh."""
        return {
            "settings": asdict(self.settings),
            "final": self.final.as_dict(),
            "wall_time": self.wall_time,
            "eval_time": self.eval_time,
            "n_vertices": int(self.V.shape[0]),
            "n_faces": int(self.F.shape[0]),
            "info": self.info,
            "history": self.history,
            "metrics": self.metrics,
        }


# ---------------------------------------------------------------------------------------------------------
# Meshes in and out


def _normalise(V: torch.Tensor) -> torch.Tensor:
    lo, hi = V.min(0).values, V.max(0).values
    diag = float((hi - lo).norm())
    if not diag > 0:
        raise MeshError(f"mesh has zero extent (all {V.shape[0]} vertices coincide); cannot normalise it")
    return (V - 0.5 * (lo + hi)) / diag


def target_surface(spec, *, dtype=torch.float32, normalize: bool = True):
    """Resolve a target: ``"bunny"``, ``"teapot"``, a mesh file path, or a ``(V, F)`` pair.

    Files and pairs are centred and scaled to unit bounding-box diagonal (``normalize=True``), as the
    named targets are, so metrics are comparable across targets.

    Raises
    ------
    FileNotFoundError
        A path that does not exist.
    MeshError
        A file that holds no mesh, an empty mesh, NaN coordinates, or a mesh of zero area.
    """
    from ..shapes import TARGET_NAMES, target_mesh

    if isinstance(spec, str) and spec in TARGET_NAMES:
        V, F = target_mesh(spec, dtype=dtype)
    else:
        if isinstance(spec, (str, os.PathLike)):
            V, F = _load(spec, "target", dtype)
        else:
            V, F = _pair(spec, "target")
            V = V.to(dtype)
        if normalize:
            V = _normalise(V)
    _check_area(V, F, f"target {spec}" if isinstance(spec, (str, os.PathLike)) else "target")
    return V, F


SOURCE_NAMES = ("sheet", "sphere", "torus", "torus-centred", "torus-through-opening")


def source_mesh(spec, *, n_vertices: int = 2500, dtype=torch.float32, target=None):
    """Resolve a starting mesh: a name in :data:`SOURCE_NAMES` (made with ``n_vertices``), a mesh file
    path (used as stored), or a ``(V, F)`` pair.

    ``"torus"`` is placed for the ``target`` ``(V, F)`` when one is given: with its hole through the
    target's most open through-hole (:func:`meshmei.shapes.torus_through_opening`) when
    :func:`~meshmei.shapes.find_opening` sees one, as the teapot's handle, and centred otherwise (no
    target, or one without a hole, as the bunny). The torus is the start for genus-1 targets because its
    hole can become theirs; a torus whose hole misses the target's must block that hole with surface, which
    costs Chamfer accuracy no deformation can remove (:func:`meshmei.shapes.membrane_floor`; on the teapot,
    at least 9.7e-6 at the teapot's area). Finding the opening takes one to three seconds.
    ``"torus-centred"`` is always the centred torus of ``initial_mesh("torus")``; ``"torus-through-opening"``
    always threads it and raises ``MeshError`` when the target has no opening.
    """
    V, F, _ = _resolve_source(spec, n_vertices, dtype, target)
    return V, F


def _resolve_source(spec, n_vertices, dtype, target):
    """``(V, F, placement)``: placement says how a named torus was placed (None for everything else)."""
    from ..shapes import find_opening, initial_mesh, torus_through_opening

    placement = None
    if isinstance(spec, str) and spec in SOURCE_NAMES:
        if spec == "torus-through-opening" and target is None:
            raise ValueError("source 'torus-through-opening' needs the target whose opening it threads")
        opening = None
        if spec in ("torus", "torus-through-opening") and target is not None:
            opening = find_opening(*target)
            if opening is None and spec == "torus-through-opening":
                raise MeshError("the target has no through-hole that find_opening can see; start from "
                                "'torus-centred'")
        if opening is not None:
            V, F = torus_through_opening(*target, n_vertices=n_vertices, dtype=dtype, opening=opening)
            placement = "through the target's opening (meshmei.shapes.torus_through_opening)"
        else:
            kind = "torus" if spec.startswith("torus") else spec
            V, F = initial_mesh(kind, n_vertices=n_vertices, dtype=dtype)
            if kind == "torus":
                placement = "centred" + (" (the target has no through-hole that find_opening sees)"
                                         if spec == "torus" and target is not None else "")
    elif isinstance(spec, (str, os.PathLike)):
        V, F = _load(spec, "source", dtype)
    else:
        V, F = _pair(spec, "source")
    _check_area(V, F, f"source {spec}" if isinstance(spec, (str, os.PathLike)) else "source")
    return V, F, placement


def _load(path, role, dtype):
    try:
        return load_mesh(path, dtype=dtype)
    except MeshError as err:
        if str(path) in str(err):
            raise
        raise MeshError(f"{role} {path}: {err}") from None


def _pair(spec, role):
    try:
        V, F = spec
    except (TypeError, ValueError):
        raise ValueError(f"{role} must be a name, a mesh file path or a (V, F) pair, got {type(spec).__name__}") from None
    V, F = check_mesh(V, F)
    return V.detach(), F


def _area(V, F) -> float:
    return 0.5 * float(doublearea(V.detach().double(), F).sum())


def _check_area(V, F, role):
    area = _area(V, F)
    if not area > 0:
        raise MeshError(f"{role} mesh has zero surface area ({V.shape[0]} vertices, {F.shape[0]} faces)")


# rbf with three levels (default_stages(n, levels=3)) in the benchmark (variant rbf-3levels) and the CLI's
# --stages auto3. The coarsest stage (625 vertices at 10k) draws 5,000 Chamfer samples a step instead of
# 10,000: a step there costs about what a 10k step does, mostly sampling and searching, so half the samples
# nearly doubles its steps, and eight samples per vertex are still plenty (at 10k it reached 5.6e-4 at 2 s
# where it was at 1.1e-3, before large steps' 7.6e-4; docs/reconstruction.md, *Fifth round*). Once the 625-
# and 2,500-vertex stages have moved the shape, the two fine stages need less smoothing, a quarter of the
# default Laplacian weight (2.5, that is 40 at 10k vertices against 160). Measured at 10k on three problems;
# 2.5 was the first value tried (*Coarse-to-fine*).
RBF_THREE_LEVEL_OVERRIDES = ({"n_samples": 5000}, None, {"w_laplacian": 2.5}, {"w_laplacian": 2.5})


def default_stages(n_vertices: int, levels: int = 2) -> tuple:
    """The coarse-to-fine schedule used by the benchmark and the CLI. Returns ``(stages, stage_fractions)``.

    ``levels=2`` (the default): ``(n/4, n, n)`` with shares ``(0.25, 0.45, 0.3)`` of the budget.
    ``levels=3``: ``(n/16, n/4, n, n)`` with shares ``(0.15, 0.25, 0.35, 0.25)``, so that a 10k run
    starts as a 2.5k run does (from 625 vertices, where the shape travels at little cost) and then refines.
    Either way the last stage restarts on a fresh isotropic remesh of the shape, which clears folds and
    slivers left by the one before. At 10k vertices three levels helped rbf on all three benchmark problems
    and large steps on the bunny, and hurt large steps through the teapot's handle (docs/reconstruction.md,
    *Coarse-to-fine*), so two is the default here; :func:`default_schedule` picks three for rbf from 8,000
    vertices.
    """
    n = int(n_vertices)
    if levels == 3:
        return (max(32, n // 16), max(32, n // 4), n, n), (0.15, 0.25, 0.35, 0.25)
    if levels == 2:
        return (max(32, n // 4), n, n), (0.25, 0.45, 0.3)
    raise ValueError(f"levels must be 2 or 3, got {levels!r}")


# The smallest final count at which meshmei reconstruct's --stages auto gives rbf three levels. They were
# measured at 10,000 (first stage 625, docs/reconstruction.md); the margin lets a mesh asked for at 10k
# that comes out a little smaller (a 10k torus has 9,465 vertices) have them too (first stage at least 500).
THREE_LEVEL_MIN_VERTICES = 8_000


def default_schedule(method: str, n_vertices: int, levels: int | None = None, *, n_samples: int = 10_000) -> tuple:
    """The coarse-to-fine schedule ``meshmei reconstruct --stages auto`` uses for ``method`` and a final
    count of ``n_vertices``. Returns ``(stages, stage_fractions, stage_overrides)``.

    ``levels`` 2 or 3 forces that many levels (``--stages auto2`` / ``auto3``); rbf with three levels
    always gets :data:`RBF_THREE_LEVEL_OVERRIDES`: half the run's Chamfer samples in the coarsest stage
    (``n_samples // 2``; 5,000 with the default 10,000) and the lighter fine stages. ``None``
    (``--stages auto``) picks as follows.

    rbf at ``THREE_LEVEL_MIN_VERTICES`` (8,000) vertices or more: three levels with those overrides
    (``default_stages(n, levels=3)``, the benchmark's rbf-3levels), measured against two levels at 10k on
    the three benchmark problems (docs/reconstruction.md, *Coarse-to-fine* and *Fifth round*). Otherwise
    two levels (``default_stages(n)``): three were measured at 10k only, and they hurt large steps
    through the teapot's handle.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if isinstance(n_samples, bool) or not isinstance(n_samples, (int, np.integer)) or n_samples < 2:
        raise ValueError(f"n_samples must be an integer of at least 2, got {n_samples!r}")
    n = int(n_vertices)
    if levels is None:
        levels = 3 if method == "rbf" and n >= THREE_LEVEL_MIN_VERTICES else 2
    stages, fractions = default_stages(n, levels)
    if method != "rbf" or levels != 3:
        return stages, fractions, None
    first = dict(RBF_THREE_LEVEL_OVERRIDES[0], n_samples=int(n_samples) // 2)
    return stages, fractions, (first,) + RBF_THREE_LEVEL_OVERRIDES[1:]


def remesh(V, F, n_vertices: int, *, iterations: int = 5):
    """Isotropic remeshing (pymeshlab) to about ``n_vertices`` vertices, for coarse-to-fine stages.

    The target edge length is ``sqrt(2 A / (sqrt(3) n))`` for total area ``A`` (a near-equilateral closed
    mesh has two triangles per vertex). Returns float tensors in the dtype of ``V`` and int64 faces.

    Raises
    ------
    ValueError
        ``n_vertices`` or ``iterations`` is not a positive integer.
    MeshError
        An invalid mesh, or one of zero area.
    """
    import pymeshlab

    check_positive("n_vertices", n_vertices, integer=True)
    check_positive("iterations", iterations, integer=True)
    V, F = check_mesh(V, F)
    Vn = V.detach().cpu().double().numpy()
    Fn = F.cpu().numpy().astype(np.int32)
    T = Vn[Fn]
    area = 0.5 * np.linalg.norm(np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]), axis=1).sum()
    if not area > 0:  # pymeshlab would return an empty mesh
        raise MeshError(f"cannot remesh a mesh of zero surface area ({V.shape[0]} vertices, {F.shape[0]} faces)")
    h = math.sqrt(2.0 * area / (math.sqrt(3.0) * n_vertices))
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=Vn, face_matrix=Fn))
    ms.meshing_isotropic_explicit_remeshing(targetlen=pymeshlab.PureValue(h), iterations=iterations,
                                            featuredeg=180.0, reprojectflag=True)
    ms.meshing_remove_unreferenced_vertices()
    m = ms.current_mesh()
    V2 = torch.as_tensor(np.asarray(m.vertex_matrix()), dtype=V.dtype, device=V.device)
    F2 = torch.as_tensor(np.asarray(m.face_matrix(), dtype=np.int64), device=V.device)
    return check_mesh(V2, F2)


# ---------------------------------------------------------------------------------------------------------
# Parameterisations: each maps learnable tensors to vertex positions


class _Param:
    def __init__(self, method, V0, F, s):
        self.method = method
        self.info = {}
        if method == "vertex":
            self.D = torch.zeros_like(V0, requires_grad=True)
            self.V0 = V0
            groups = [{"params": [self.D], "lr": s.lr}]
        elif method == "rbf":
            from ..deform import RBFDeformer

            self.rbf = RBFDeformer(V0, s.centers, sigma_factor=s.sigma_factor, r_cut=s.r_cut,
                                   learn_scales=s.lr_scale > 0)
            groups = [{"params": [self.rbf.offsets], "lr": s.lr}]
            if s.lr_scale > 0:
                groups.append({"params": [self.rbf.log_sigma], "lr": s.lr_scale})
            self.info = {"n_kernels": self.rbf.n_kernels, "n_pairs_initial": self.rbf.n_pairs}
            self.coarse = None
            k = round(V0.shape[0] / s.coarse_ratio) if s.coarse_ratio else 0
            if k >= 4:  # fewer coarse kernels than that would only translate the shape
                self.coarse = RBFDeformer(V0, k, r_cut=s.r_cut, learn_scales=False)
                groups.append({"params": [self.coarse.offsets], "lr": s.lr * s.coarse_lr})
                self.info.update(n_coarse_kernels=k, n_coarse_pairs=self.coarse.n_pairs,
                                 coarse_sigma=float(self.coarse.sigma[0]))
        else:
            from ..deform.largesteps import DifferentialSolver, system_matrix

            self.solver = DifferentialSolver(system_matrix(F, V0.shape[0], s.lam))
            self.u = self.solver.to_differential(V0).requires_grad_(True)
            groups = [{"params": [self.u], "lr": s.lr}]
        from ..deform.largesteps import AdamUniform

        self.opt = AdamUniform(groups) if s.optimizer == "uniform" else torch.optim.Adam(groups)
        for g in self.opt.param_groups:
            g["lr0"] = g["lr"]

    def vertices(self):
        if self.method == "vertex":
            return self.V0 + self.D
        if self.method == "rbf":
            return self.rbf() if self.coarse is None else self.rbf() + self.coarse.displacement()
        return self.solver.solve(self.u)

    def set_lr_factor(self, f):
        for g in self.opt.param_groups:
            g["lr"] = g["lr0"] * f

    def finish(self):
        if self.method == "rbf":
            trunc = self.rbf.truncation_error
            if self.coarse is not None:
                trunc = max(trunc, self.coarse.truncation_error)
            self.info.update(n_pairs_final=self.rbf.n_pairs, n_rebuilds=self.rbf.n_rebuilds,
                             truncation_error=trunc,
                             sigma_median=float(self.rbf.sigma.detach().median()))
        return self.info


# ---------------------------------------------------------------------------------------------------------


def reconstruct(source, target, method: str = "rbf", *, settings: ReconstructionSettings | None = None,
                progress: bool = False, callback=None, **kwargs) -> ReconstructionResult:
    """Deform ``source`` into ``target`` by minimising Chamfer distance plus regularizers with Adam.

    The loss per step is ``chamfer + w_laplacian * laplacian_loss + w_edge * edge_loss + w_arap *
    arap_direction_loss`` where ``chamfer`` is the mean squared distance from ``n_samples`` fresh
    area-uniform samples of the current mesh to their nearest points in a fixed pool of target samples,
    plus the mean squared distance from ``n_samples`` pool points to their nearest current samples.

    Parameters
    ----------
    source : (V, F) pair, a mesh file path, or a name in SOURCE_NAMES (2,500 vertices)
        Starting mesh, used as given (no normalisation). ``"torus"`` starts through the target's opening
        when it has one, as the teapot's handle (:func:`source_mesh`); ``"torus-centred"`` never does.
    target : (V, F) pair, a mesh file path, or "bunny" / "teapot"
        Target surface; paths and pairs are normalised to unit bounding-box diagonal and centred.
    method : {"rbf", "vertex", "largesteps"}
    settings : ReconstructionSettings, optional
        All other options (see its attributes); keyword arguments override its fields, e.g.
        ``reconstruct(src, "bunny", steps=300, lr=1e-3)``.
    progress : bool
        Show a tqdm progress bar (over steps, or seconds of the budget).
    callback : callable, optional
        ``callback(step, V, loss)`` after every step (``V`` detached).

    Returns
    -------
    ReconstructionResult

    Raises
    ------
    ValueError
        Unknown method or a bad setting. ``MeshError`` (a ``ValueError``) for an invalid source or target
        (empty, NaN coordinates, zero area); ``FileNotFoundError`` for a missing file. All before the
        first step.
    FloatingPointError
        The loss or the mesh became NaN or Inf during the run (a learning rate far too large).

    Examples
    --------
    >>> from meshmei.shapes import initial_mesh
    >>> res = reconstruct(initial_mesh("sphere", n_vertices=200), "bunny", "largesteps", steps=5,
    ...                   n_samples=500, target_pool=2000, eval_samples=1000)
    >>> len(res.history), res.V.shape[1], res.final.chamfer_l2 > 0
    (5, 3, True)
    """
    given = replace(settings or ReconstructionSettings(), method=method, **kwargs)
    s = given.resolved()
    per_stage = given.stage_settings() if s.stage_overrides else None  # each stage's own settings
    Vt, Ft = target_surface(target)
    V, F = source_mesh(source, target=(Vt, Ft))
    Vt = Vt.to(V.dtype)
    g = torch.Generator(device=V.device).manual_seed(s.seed)

    with torch.no_grad():
        pool = sample_points(Vt, Ft, s.target_pool, generator=g)  # (Np, 3) fixed target samples
    # Nearest neighbours are exact within 10 sample spacings of a surface and near-nearest beyond (where
    # exact KD-tree queries get slow and the neighbour's exact identity hardly matters).
    pool_index = PointIndex(pool)
    qp_far_share = 1.0  # share of target samples far from the current samples at the last step (a start is far)

    stages = s.stages or (None,)
    bounds = np.cumsum((0.0,) + (s.stage_fractions or (1.0,)))  # stage k covers [bounds[k], bounds[k+1])
    history, metrics, info = [], [], {"stages": []}
    opt_time, eval_time = 0.0, 0.0
    pending_times = sorted(s.eval_times)
    last_metrics = []

    def progress_fraction(step, t):
        f = 0.0
        if s.steps is not None:
            f = max(f, step / s.steps)
        if s.time_budget is not None:
            f = max(f, t / s.time_budget)
        return f

    def evaluate(step, Vc, Fc, health=False):
        nonlocal eval_time
        t0 = time.perf_counter()
        m = surface_metrics(Vc, Fc, Vt, Ft, n_samples=s.eval_samples, seed=s.seed, health=health)
        dt = time.perf_counter() - t0
        eval_time += dt
        rec = {"step": step, "time": opt_time, "n_vertices": int(Vc.shape[0]), "eval_seconds": dt}
        rec.update(m.as_dict())
        metrics.append(rec)
        last_metrics[:] = [m]
        return m

    bar = None
    if progress:
        from tqdm.auto import tqdm

        total = s.steps if s.time_budget is None else s.time_budget
        bar = tqdm(total=total, unit="step" if s.time_budget is None else "s", desc=f"reconstruct[{s.method}]",
                   bar_format=None if s.time_budget is None else "{l_bar}{bar}| {n:.1f}/{total:.0f} s {postfix}")

    n_final = s.stages[-1] if s.stages else V.shape[0]

    def weights(sk, k=None):
        # The weights are set for reg_ref_vertices vertices and scaled to the count each stage's weights
        # are stated for: its own, except the first stage, which takes the second's (see reg_ref_vertices).
        if s.reg_ref_vertices is None:
            return sk.w_laplacian, sk.w_edge, sk.w_arap
        n_k = n_final if k is None else max(s.stages[k], s.stages[min(1, len(s.stages) - 1)])
        ratio = n_k / s.reg_ref_vertices
        return sk.w_laplacian * ratio**2, sk.w_edge * ratio, sk.w_arap * ratio

    w_lap, w_edge, w_arap = weights(s)
    info.update(w_laplacian=w_lap, w_edge=w_edge, w_arap=w_arap)
    step = 0
    t_start = time.perf_counter()
    done = False
    last_eval_step = -1
    for k, n_stage in enumerate(stages):
        t0 = time.perf_counter()
        if n_stage is not None and (k > 0 or abs(V.shape[0] - n_stage) > 0.1 * n_stage):
            V, F = remesh(V, F, n_stage)
        sk = per_stage[k] if per_stage else s
        w_lap, w_edge, w_arap = weights(sk, k if n_stage is not None else None)
        param = _Param(sk.method, V.detach(), F, sk)
        opt_time += time.perf_counter() - t0
        last_stage = k == len(stages) - 1
        while True:
            f = progress_fraction(step, opt_time)
            if f >= 1.0 or (not last_stage and f >= bounds[k + 1]):
                done = f >= 1.0
                break
            t0 = time.perf_counter()
            decay = s.lr_decay ** f
            param.set_lr_factor(decay)
            wr = decay if sk.reg_decay else 1.0
            param.opt.zero_grad(set_to_none=True)
            Vc = param.vertices()
            try:
                P = sample_points(Vc, F, sk.n_samples, generator=g)
            except MeshError as err:
                if step == 0:
                    raise
                # the last step sent vertices to NaN or Inf, out of the dtype's range, or onto one point
                raise FloatingPointError(f"the mesh became unusable after step {step} ({err}); lower the learning "
                                         f"rate (lr={sk.lr})") from None
            sub = torch.randint(0, s.target_pool, (sk.n_samples,), generator=g, device=V.device)
            Q = pool[sub]
            i_pq = torch.from_numpy(pool_index.query(P))
            samples_index = PointIndex(P)
            i_qp = torch.from_numpy(samples_index.query(Q, near_first=qp_far_share < 0.5))
            qp_far_share = samples_index.far_share
            cd = ((P - pool[i_pq]) ** 2).sum(-1).mean() + ((Q - P[i_qp]) ** 2).sum(-1).mean()
            loss = cd
            if w_lap > 0:
                loss = loss + wr * w_lap * laplacian_loss(Vc, F)
            if w_edge > 0:
                loss = loss + wr * w_edge * edge_loss(Vc, F)
            if w_arap > 0:
                loss = loss + wr * w_arap * arap_direction_loss(Vc, _param_rest(param, V), F)
            loss.backward()
            param.opt.step()
            step += 1
            dt = time.perf_counter() - t0
            opt_time += dt
            lv = float(loss.detach())
            if not math.isfinite(lv):
                raise FloatingPointError(f"loss became {lv} at step {step}; lower the learning rate (lr={sk.lr})")
            history.append({"step": step, "stage": k, "time": opt_time, "loss": lv, "chamfer": float(cd.detach()),
                            "lr": param.opt.param_groups[0]["lr"]})
            if bar is not None:
                bar.update(1 if s.time_budget is None else dt)
                if step % 10 == 0:
                    bar.set_postfix(loss=f"{lv:.3e}", n=int(V.shape[0]))
            if callback is not None:
                callback(step, Vc.detach(), lv)
            due = s.eval_every is not None and step % s.eval_every == 0
            while pending_times and opt_time >= pending_times[0]:
                pending_times.pop(0)
                due = True
            if due:
                with torch.no_grad():
                    evaluate(step, param.vertices().detach(), F)
                last_eval_step = step
        with torch.no_grad():
            V = param.vertices().detach()
        info["stages"].append({"n_vertices": int(V.shape[0]), "end_step": step, "method": sk.method,
                               "w_laplacian": w_lap, "w_edge": w_edge, "w_arap": w_arap,
                               **param.finish()})
        if done:
            break
    if bar is not None:
        bar.close()
    if last_eval_step == step and metrics:
        # the last step was just evaluated: add the health check instead of sampling again
        t0 = time.perf_counter()
        si = mesh_health(V, F).self_intersections
        dt = time.perf_counter() - t0
        eval_time += dt
        metrics[-1].update(self_intersections=si, eval_seconds=metrics[-1]["eval_seconds"] + dt)
        final = replace(last_metrics[0], self_intersections=si)
    else:
        final = evaluate(step, V, F, health=True)
    info["total_seconds"] = time.perf_counter() - t_start
    return ReconstructionResult(V=V, F=F, history=history, metrics=metrics, settings=s, final=final,
                                wall_time=opt_time, eval_time=eval_time, info=info)


def _param_rest(param, V):
    # the rest pose of the direction-preserving ARAP term: the shape at the start of the stage
    return param.V0 if param.method == "vertex" else V


# ---------------------------------------------------------------------------------------------------------
# Output files and the command line


def plot_history(result: ReconstructionResult, out_dir) -> list[Path]:
    """Write ``loss.png`` (loss against time) and ``metrics.png`` (Chamfer-L2, F-score, normal consistency
    against time) into ``out_dir``; returns the paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    h = result.history
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.semilogy([r["time"] for r in h], [r["loss"] for r in h], lw=0.8)
    ax.set_xlabel("optimisation time (s)")
    ax.set_ylabel("loss")
    ax.set_title(f"{result.settings.method}: training loss")
    fig.tight_layout()
    p1 = out_dir / "loss.png"
    fig.savefig(p1, dpi=120)
    plt.close(fig)
    m = result.metrics
    fig, axs = plt.subplots(1, 3, figsize=(12, 3.5))
    t = [r["time"] for r in m]
    axs[0].semilogy(t, [r["chamfer_l2"] for r in m], "o-")
    axs[0].set_ylabel("Chamfer-L2")
    axs[1].plot(t, [r["fscore"] for r in m], "o-")
    axs[1].set_ylabel("F-score @ 1%")
    axs[2].plot(t, [r["normal_consistency"] for r in m], "o-")
    axs[2].set_ylabel("normal consistency")
    for a in axs:
        a.set_xlabel("optimisation time (s)")
    fig.tight_layout()
    p2 = out_dir / "metrics.png"
    fig.savefig(p2, dpi=120)
    plt.close(fig)
    return [p1, p2]


def add_parser(subparsers) -> None:
    """Add ``meshmei reconstruct`` to an argparse subparsers object."""
    p = subparsers.add_parser(
        "reconstruct",
        help="deform a sphere/torus/mesh into a target mesh by Chamfer minimisation",
        description="Deform a starting mesh into a target by Chamfer minimisation; writes mesh.obj, "
                    "history.json, loss.png and metrics.png to --out.",
    )
    p.add_argument("--init", default="sphere",
                   help="sphere, torus, sheet, torus-centred, torus-through-opening, or a mesh file (default "
                        "sphere). 'torus' starts with its hole through the target's most open through-hole when "
                        "it has one (a teapot's handle; meshmei.shapes.torus_through_opening), else centred; "
                        "'torus-centred' is always centred; 'torus-through-opening' fails without an opening")
    p.add_argument("--target", required=True, help="bunny, teapot, or a mesh file (normalised to unit diagonal)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--method", choices=METHODS, default="rbf")
    p.add_argument("--n-vertices", type=int, default=2500, help="vertices of a generated --init mesh")
    p.add_argument("--steps", type=int, default=None)
    p.add_argument("--time-budget", type=float, default=None, help="seconds of optimisation")
    p.add_argument("--lr", type=float, default=None)
    p.add_argument("--samples", type=int, default=10_000, help="Chamfer samples per step")
    p.add_argument("--stages", default="auto",
                   help="comma-separated vertex counts, e.g. 600,2500,2500 (equal shares); 'auto2': n/4,n,n; "
                        "'auto3': n/16,n/4,n,n (default_stages(n, levels=3); for rbf also half the --samples in "
                        "the first stage and a quarter of the Laplacian weight in the two fine stages, as the "
                        "benchmark's rbf-3levels); 'auto' (default): auto3 for rbf from 8,000 vertices, else auto2 "
                        "(default_schedule); 'none': one stage")
    p.add_argument("--eval-every", type=int, default=None)
    p.add_argument("--eval-samples", type=int, default=100_000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=_run_cli)


def _run_cli(args) -> int:
    # Resolve and check both meshes first: bad input fails before any optimisation starts.
    target = target_surface(args.target)
    V, F, placement = _resolve_source(args.init, args.n_vertices, torch.float32, target)
    source = (V, F)
    if placement is not None:
        print(f"{args.init}: {V.shape[0]} vertices, placed {placement}")
    stages, fractions, overrides = None, None, None
    n = source[0].shape[0]
    if args.stages in ("auto", "auto2", "auto3"):
        levels = {"auto": None, "auto2": 2, "auto3": 3}[args.stages]
        stages, fractions, overrides = default_schedule(args.method, n, levels, n_samples=args.samples)
    elif args.stages and args.stages != "none":
        try:
            stages = tuple(int(x) for x in args.stages.split(","))
        except ValueError:
            raise ValueError(f"--stages must be 'auto', 'auto2', 'auto3', 'none' or comma-separated integers, "
                             f"got {args.stages!r}") from None
    if args.steps is None and args.time_budget is None:
        args.steps = 500
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    res = reconstruct(source, target, args.method, steps=args.steps, time_budget=args.time_budget, lr=args.lr,
                      n_samples=args.samples, stages=stages, stage_fractions=fractions, stage_overrides=overrides,
                      eval_every=args.eval_every, eval_samples=args.eval_samples, seed=args.seed,
                      progress=not args.no_progress)
    save_mesh(out / "mesh.obj", res.V, res.F)
    record = res.to_json()
    record["init"], record["target"] = str(args.init), str(args.target)
    (out / "history.json").write_text(json.dumps(record, indent=1))
    plot_history(res, out)
    f = res.final
    print(f"{args.method}: {len(res.history)} steps in {res.wall_time:.1f} s; Chamfer-L2 {f.chamfer_l2:.3e}, "
          f"F-score {f.fscore:.3f}, normal consistency {f.normal_consistency:.3f}, area {f.area_ratio:.2f}x the "
          f"target's; wrote {out}")
    return 0
