"""Shape reconstruction by Chamfer minimisation: the objective and the coarse-to-fine stages of
:func:`reconstruct`, run by the one loop of :mod:`meshmei.optim`.

Each step samples the current mesh afresh, matches the samples to a fixed pool of target samples and back,
and adds the resolution-scaled regularizers. Between stages the current shape is remeshed
isotropically (pymeshlab) to the next stage's count and a fresh parameterisation starts from it.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import fields, replace

import igl
import numpy as np
import torch
from scipy.spatial import cKDTree

from ..contact import IN_CONTACT, ContactBarrier
from ..deform import MIN_COARSE_KERNELS, PARAMETERISATIONS, NarrowKernelError
from ..errors import MeshError, ReconstructionError
from ..metrics import surface_metrics
from ..optim import Budget, Lookahead, Progress, Schedule, Trace, checked_callbacks, make_optimizer, minimize
from ..mesh import numpy_mesh
from ..quality import self_intersecting_pairs, topology, triangle_quality
from ..regularizers import regularizer_values, scale_weights
from ..sampling import PointIndex, sample_points
from ..shapes import remesh
from ..validity import StepGuard
from .schedule import NAMED_SCHEDULES, schedule_from_text
from .settings import (AUTO_EDGE_RAMP, AUTO_EDGE_REFUSALS, ReconstructionResult, ReconstructionSettings,
                       ReconstructionWarning)
from .sources import source_mesh, target_surface
from .surgery import adapt_topology

__all__ = ["reconstruct"]

# scipy query threads of the sampled Chamfer term in a run with the contact barrier (PointIndex.query): its
# search runs in a worker thread beside the queries, and scipy's one-thread query keeps the GIL (the default
# 2.5k bunny: 47 s against 38 s, the same result bit for bit); without the barrier one thread is as fast on
# two cores (docs/reconstruction.md, *Valid steps*)
CONTACT_QUERY_WORKERS = 2
# ReconstructionSettings.normal_match: scipy's eps for the 6-d queries (an answer at most 1 + eps times as
# far as the nearest). Exact 6-d queries of 5,000 samples of the cup into 5,000 of a sphere around it took
# 120 ms, approximate 41 ms (all of them; only those whose nearest sample faces away are queried); they
# serve the coarse stage, where the shape travels far
NORMAL_MATCH_EPS = 1.0
# ... and only in a stage whose start encloses the target: at least this share of NORMAL_MATCH_PROBES target
# samples inside it (winding number above one half). A start around the target has surface facing the way
# of each target sample on the side its normal points to; one that is not around it (the torus through
# the teapot's handle) has that surface across the target, and pairing by normal pulled it over (the
# teapot's default run, seeds 0-2, with every target sample paired by normal: 2.18e-6, 3.37e-6, 2.29e-6
# against 1.96e-6, 2.05e-6, 1.78e-6; seed 1 with only those facing away paired again, 3.23e-6)
NORMAL_MATCH_ENCLOSED = 0.99
NORMAL_MATCH_PROBES = 2000


class _SampledChamfer:
    """The sampled Chamfer term: fresh samples of the current mesh against a fixed pool of target samples.

    Nearest neighbours are exact within 10 sample spacings of a surface and near-nearest beyond (where
    exact KD-tree queries get slow and the neighbour's exact identity hardly matters).
    """

    def __init__(self, Vt, Ft, pool_size: int, generator: torch.Generator, *, normals: bool = False,
                 facing: bool | None = None, workers: int = 1):
        self.workers = workers  # scipy's query threads (PointIndex.query): two beside the contact search
        with torch.no_grad():  # (Np, 3) fixed target samples, and their unit normals when asked for
            drawn = sample_points(Vt, Ft, pool_size, generator=generator, return_normals=normals)
        self.pool, self.pool_normals = drawn if normals else (drawn, None)
        self.index = PointIndex(self.pool)
        self.generator = generator
        self.far_share = 1.0  # share of target samples far from the current samples at the last step
        self.diagonal = float(torch.linalg.vector_norm(Vt.amax(0) - Vt.amin(0)))  # normal_match's length unit
        self.facing = normals if facing is None else facing  # return the facing term (it needs the normals)

    def __call__(self, Vc, F, n_samples: int, step: int, lr: float, normal_match: float = 0.0):
        """``(chamfer, facing)``: the sampled Chamfer term and, with target normals, the facing term (the
        mean of ``max(0, -n . n_t)`` over the mesh samples, ``n_t`` the normal of the nearest target sample;
        None without them or when not asked for). ``normal_match`` > 0 pairs again the target samples whose
        nearest mesh sample faces away (:attr:`ReconstructionSettings.normal_match`; it needs the normals)."""
        try:
            normals = self.pool_normals is not None
            drawn = sample_points(Vc, F, n_samples, generator=self.generator, return_normals=normals)
            P, N = drawn if normals else (drawn, None)
        except MeshError as err:
            if step == 0:
                raise
            # the last step sent vertices to NaN or Inf, out of the dtype's range, or onto one point
            raise FloatingPointError(f"the mesh became unusable after step {step} ({err}); lower the learning "
                                     f"rate (lr={lr})") from None
        sub = torch.randint(0, self.pool.shape[0], (n_samples,), generator=self.generator, device=Vc.device)
        Q = self.pool[sub]
        i_pq = torch.from_numpy(self.index.query(P, workers=self.workers))
        samples_index = PointIndex(P)
        i_qp = torch.from_numpy(samples_index.query(Q, near_first=self.far_share < 0.5, workers=self.workers))
        self.far_share = samples_index.far_share
        if normal_match > 0:
            self._pair_by_normal(P, N, sub, i_qp, normal_match)
        # index_select: advanced indexing's backward (an accumulating index_put) adds in a thread-dependent order
        cd = (((P - self.pool.index_select(0, i_pq)) ** 2).sum(-1).mean()
              + ((Q - P.index_select(0, i_qp)) ** 2).sum(-1).mean())
        if N is None or not self.facing:
            return cd, None
        return cd, torch.relu(-(N * self.pool_normals.index_select(0, i_pq)).sum(-1)).mean()

    def encloses(self, V, F) -> bool:
        """Whether the mesh ``(V, F)`` encloses the target (:data:`NORMAL_MATCH_ENCLOSED`)."""
        Vn, Fn = numpy_mesh(V, F)
        probes = _numpy(self.pool[:NORMAL_MATCH_PROBES])
        inside = np.abs(igl.fast_winding_number(Vn, Fn, probes)) > 0.5
        return bool(inside.mean() >= NORMAL_MATCH_ENCLOSED)

    def _pair_by_normal(self, P, N, sub, i_qp, normal_match: float):
        """Re-pair, in place, each drawn target sample ``pool[sub]`` whose nearest mesh sample ``P[i_qp]`` faces
        away from it with the (near-)nearest mesh sample by ``|q - p|^2 + (normal_match D)^2 |n_q - n_p|^2``
        (:data:`NORMAL_MATCH_EPS`)."""
        n_q = self.pool_normals[sub]
        away = torch.nonzero((n_q * N.index_select(0, i_qp)).sum(-1) < 0).flatten()
        if len(away) == 0:
            return
        scale = normal_match * self.diagonal
        P6 = np.hstack([_numpy(P), scale * _numpy(N)])
        Q6 = np.hstack([_numpy(self.pool[sub[away]]), scale * _numpy(n_q[away])])
        _, i = cKDTree(P6).query(Q6, eps=NORMAL_MATCH_EPS, workers=self.workers)
        i_qp[away] = torch.from_numpy(np.asarray(i, dtype=np.int64))


def _numpy(x: torch.Tensor) -> np.ndarray:
    return x.detach().cpu().numpy().astype(np.float64, copy=False)


class _Evaluation:
    """Surface metrics at chosen steps and times, timed apart from the optimisation."""

    def __init__(self, Vt, Ft, s: ReconstructionSettings, trace: Trace):
        self.Vt, self.Ft, self.s, self.trace = Vt, Ft, s, trace
        self.records, self.seconds, self.last, self.last_mesh = [], 0.0, None, None
        self.pending = sorted(s.eval_times)

    def __call__(self, V, F, *, health=False):
        t0 = time.perf_counter()
        m = surface_metrics(V, F, self.Vt, self.Ft, n_samples=self.s.eval_samples, seed=self.s.seed, health=health)
        dt = time.perf_counter() - t0
        self.seconds += dt
        self.records.append({"step": self.trace.step, "time": self.trace.seconds, "n_vertices": int(V.shape[0]),
                             "eval_seconds": dt, **m.as_dict()})
        self.last, self.last_mesh = m, (V, F)
        return m

    def due(self, step: int) -> bool:
        due = self.s.eval_every is not None and step % self.s.eval_every == 0
        while self.pending and self.trace.seconds >= self.pending[0]:
            self.pending.pop(0)
            due = True
        return due

    def final(self, V, F):
        """The returned mesh's metrics, with its health; the last evaluation is reused when it was of this
        very mesh (not when a remesh, or a step, came after it)."""
        if self.last_mesh is None or not all(torch.equal(a, b) for a, b in zip(self.last_mesh, (V, F))):
            return self(V, F, health=True)
        return self.last


# A remesh that lands this many times above or below the count its stage asked for (a stage of 32 vertices
# gave 93: the isotropic remesh of that shape at that edge length cannot go lower) is a different resolution:
# the stage's weights follow the count it got, with a warning. The default schedules land 5-7 % under their
# counts (and the teapot's first stage, whose weights are stated for the second's count, a third over).
STAGE_COUNT_TOLERANCE = 1.25


def stage_weights(s: ReconstructionSettings, sk: ReconstructionSettings, k: int | None, n_source: int,
                  n_mesh: int | None = None) -> tuple:
    """The Laplacian, edge and ARAP weights of stage ``k`` (None: a run without stages), scaled from
    ``reg_ref_vertices`` to the count the stage's weights are stated for: its own, except the first stage,
    which takes the second's (see :class:`ReconstructionSettings`); ``n_mesh``, when given, instead (a stage
    whose every remesh was refused runs on the mesh it had; one whose remesh landed more than
    :data:`STAGE_COUNT_TOLERANCE` times off its count runs on the count it got)."""
    if s.reg_ref_vertices is None:
        return sk.w_laplacian, sk.w_edge, sk.w_arap
    if n_mesh is not None:
        n_k = n_mesh
    elif k is None:
        n_k = s.stages[-1] if s.stages else n_source
    else:
        n_k = s.stages[1] if k == 0 and len(s.stages) > 1 else s.stages[k]  # (max of the two gave a later,
        # smaller stage the larger one's weights: (625, 2500, 1000) had 10, 10, 10 for 10, 10, 1.6)
    w = scale_weights({"laplacian": sk.w_laplacian, "edge": sk.w_edge, "arap": sk.w_arap}, n_k, s.reg_ref_vertices)
    return w["laplacian"], w["edge"], w["arap"]


def _parameterisation(sk: ReconstructionSettings, V0, F):
    kind = PARAMETERISATIONS[sk.method]
    if sk.method == "rbf":
        return kind(V0, lr=sk.lr, lr_scales=sk.lr_scale, centers=sk.centers, sigma_factor=sk.sigma_factor,
                    r_cut=sk.r_cut, coarse_ratio=sk.coarse_ratio, coarse_lr=sk.coarse_lr)
    if sk.method == "largesteps":
        return kind(V0, F, lr=sk.lr, lam=sk.lam)
    return kind(V0, lr=sk.lr)


def _check_scales(param, sk: ReconstructionSettings, k: int, step: int) -> None:
    """FloatingPointError when learnt RBF scales (``lr_scale > 0``) have left the dtype's range: a scale of
    inf weighs 1 at every vertex, so its kernel only translates the mesh, and the run went on without a word
    (every pair listed, ``sigma_median`` inf in its record)."""
    if not (sk.method == "rbf" and sk.lr_scale > 0):
        return
    log_sigma = param.rbf.log_sigma.detach()
    lo, hi = torch.aminmax(torch.exp(log_sigma))  # one reduction at every step (NaN propagates to both)
    if not (float(lo) > 0 and float(hi) < math.inf):
        far = float(log_sigma.abs().max())
        raise FloatingPointError(f"stage {k}: lr_scale={sk.lr_scale:g} took an RBF kernel's scale out of "
                                 f"{log_sigma.dtype}'s range by step {step} (a log-scale of {far:.3g}; an infinite "
                                 "scale weighs 1 at every vertex and only translates the mesh); lower lr_scale")


def _objective(param, vertices, F, sk, weights, chamfer, k, latest, contact):
    active = {name: w for name, w in zip(("laplacian", "edge", "arap"), weights) if w > 0}

    def objective(point):
        _check_scales(param, sk, k, point.step)
        Vc = vertices()
        latest[0] = Vc
        if contact is not None:  # its candidate search runs beside the Chamfer term's KD-tree queries
            contact.prefetch(Vc)
        cd, facing = chamfer(Vc, F, sk.n_samples, point.step, sk.lr, sk.normal_match)
        wr = point.factor if sk.reg_decay else 1.0
        loss = cd
        if facing is not None:
            loss = loss + sk.w_facing * facing
        # the direction ARAP's rest pose is the shape at the start of the stage
        for name, r in regularizer_values(Vc, param.V0, F, active).items():
            loss = loss + wr * active[name] * r
        record = {"stage": k, "chamfer": float(cd.detach())}
        if facing is not None:
            record["facing"] = float(facing.detach())
        if contact is not None:
            loss = loss + sk.w_contact * contact(Vc)
            record["contact_pairs"] = contact.active
        return loss, record

    return objective


def reconstruct(source, target, method: str | None = None, *, settings: ReconstructionSettings | None = None,
                progress: bool = False, callback=None, callbacks=(), **kwargs) -> ReconstructionResult:
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
        Target surface; paths and pairs are normalised to unit bounding-box diagonal and centred (where
        that frame lies in their own coordinates is ``result.info["target_frame"]``: ``{"centre", "scale"}``,
        a point ``p`` of the result is ``p * scale + centre`` there; also in ``history.json``).
    method : {"rbf", "vertex", "largesteps"}, optional
        Replaces ``settings.method`` when given; otherwise the settings' method (default ``"rbf"``) runs.
    settings : ReconstructionSettings, optional
        All other options (see its attributes); keyword arguments override its fields, e.g.
        ``reconstruct(src, "bunny", steps=300, lr=1e-3)``. Without ``stages`` the fit runs in one stage;
        ``stages="auto"`` runs the command line's coarse-to-fine schedule (:func:`default_schedule` for the
        method and the source's vertex count as built: its stages, shares and overrides; ``"auto2"``,
        ``"auto3"``, ``"auto4"`` force that many levels), two orders of magnitude lower Chamfer-L2 on the
        2.5k bunny. The result's settings hold the schedule it resolved to.
    progress : bool
        Show a tqdm progress bar (over steps, or seconds of the budget).
    callback : callable, optional
        ``callback(step, V, loss)`` after every step (``V`` detached, the vertices the loss was taken at).
    callbacks : callable or sequence of callables, optional
        Each called with every step's record, the dict the history keeps (``step``, ``loss``, ``chamfer``,
        ``stage``, ``time``, ...), as ``optimize_mei``'s ``callbacks`` are; their time, like ``callback``'s,
        is not counted in the run's times. A value that is not callable is refused before anything is built.

    Returns
    -------
    ReconstructionResult

    Raises
    ------
    ValueError
        Unknown method or a bad setting (``ReconstructionError``). ``MeshError`` (a ``ValueError``) for an
        invalid source or target (empty, NaN coordinates, zero area); ``FileNotFoundError`` for a missing
        file. All before the first step.
    ReconstructionError
        Also a start at a scale where the deformation gives NaN (an rbf start 1e-20 across), before its
        stage's first step.
    FloatingPointError
        The loss or the mesh became NaN or Inf during the run (a learning rate far too large), or learnt RBF
        scales left the dtype's range (``lr_scale`` too large).

    Warns
    -----
    ReconstructionWarning
        A stage whose every step the step guard refused (it returns its start; also in
        ``result.info["warnings"]``), and the other stage warnings there: a remesh refused, pairs of the start in
        contact, an rbf stage too small for its ``coarse_ratio`` (no coarse kernels), a time budget spent
        before the first step.

    Examples
    --------
    >>> from meshmei.shapes import initial_mesh
    >>> res = reconstruct(initial_mesh("sphere", n_vertices=200), "bunny", "largesteps", steps=5,
    ...                   n_samples=500, target_pool=2000, eval_samples=1000)
    >>> len(res.history), res.V.shape[1], res.final.chamfer_l2 > 0
    (5, 3, True)
    """
    callbacks = checked_callbacks(callbacks, ReconstructionError)
    if callback is not None and not callable(callback):
        raise ReconstructionError(f"callback must be callable, got {callback!r}")
    if method is not None:
        kwargs["method"] = method
    unknown = sorted(set(kwargs) - {f.name for f in fields(ReconstructionSettings)})
    if unknown:  # dataclasses' TypeError, which named __init__, not reconstruct's settings
        raise ReconstructionError(f"unknown ReconstructionSettings fields {unknown}")
    base = settings or ReconstructionSettings()
    if "method" in kwargs and kwargs["method"] != base.method:
        base = base.without_method_defaults()  # a result's resolved settings held the other method's lr, ...
    given = replace(base, **kwargs)
    named = _named_schedule(given)
    s = (replace(given, stages=None) if named else given).resolved()  # every other value checked before loading
    Vt, Ft, frame = target_surface(target, return_frame=True)
    V, F = source_mesh(source, target=(Vt, Ft))
    if named:  # the schedule of the source as built, as the command line counts it
        stages, fractions, overrides = schedule_from_text(named, s.method, V.shape[0], n_samples=s.n_samples)
        given = replace(given, stages=stages, stage_fractions=fractions, stage_overrides=overrides)
        s = given.resolved()
    per_stage = given.stage_settings() if s.stage_overrides else None  # each stage's own settings
    Vt = Vt.to(V.dtype)
    g = torch.Generator(device=V.device).manual_seed(s.seed)
    by_normal = any(sk.normal_match > 0 for sk in (per_stage or [s]))  # the target's normals are needed
    chamfer = _SampledChamfer(Vt, Ft, s.target_pool, g, normals=s.w_facing > 0 or by_normal, facing=s.w_facing > 0,
                              workers=CONTACT_QUERY_WORKERS if s.w_contact > 0 else 1)
    trace = Trace()
    evaluation = _Evaluation(Vt, Ft, s, trace)
    budget = Budget(s.steps, s.time_budget)
    bar = Progress(s.steps if s.time_budget is None else s.time_budget, f"reconstruct[{s.method}]",
                   unit="step" if s.time_budget is None else "s", every=10, enabled=progress,
                   postfix=lambda rec: {"loss": f"{rec['loss']:.3e}", "stage": rec["stage"]})
    w = stage_weights(s, s, None, V.shape[0])
    info = {"stages": [], "w_laplacian": w[0], "w_edge": w[1], "w_arap": w[2], "warnings": []}
    if frame is not None:  # a file's or pair's target is fitted in the unit frame: where that lies in its own
        info["target_frame"] = frame
    t_start = time.perf_counter()
    F_source = F
    try:
        V, F = _run_stages(V, F, s, per_stage, chamfer, evaluation, trace, budget, bar, callback, callbacks, info)
    finally:
        bar.close()
    final = evaluation.final(V, F)
    info["total_seconds"] = time.perf_counter() - t_start
    if not trace.history and s.time_budget is not None:  # said, not silently the start
        # remeshed or not by its faces (info['stages'] has a record whether or not the stage remeshed, and a run
        # without stages was said to be remeshed)
        remeshed = f" remeshed to {V.shape[0]} vertices" if not torch.equal(F, F_source) else " as given"
        info["warnings"].append(f"the time budget ({s.time_budget:g} s) ran out before the first step: the result "
                                f"is the start{remeshed}, not a fit")
    for message in info["warnings"]:
        warnings.warn(message, ReconstructionWarning, stacklevel=2)
    return ReconstructionResult(V=V, F=F, history=trace.history, metrics=evaluation.records, settings=s,
                                final=final, wall_time=trace.seconds, eval_time=evaluation.seconds, info=info)


def _guard_info(guard, records) -> dict:
    """What the guard did in a stage whose history ``records`` are given (a step of ``step_scale`` 0 was undone)."""
    if guard is None:
        return {}
    return {"checks": guard.checks, "refused": guard.failures, "check_seconds": guard.seconds, "certified": guard.certified,
            "separated": guard.separated, "refused_by": dict(guard.reasons), "steps": len(records),
            "accepted_steps": sum(1 for rec in records if rec["step_scale"] > 0)}


# The guard's step bound (ValidityRules.max_step) in barrier reaches: 4, one mean edge at the default reach of a
# quarter edge (contact_distance). A cheap refusal of runaway steps, before the exact test; the guarantee is
# the test's, not the bound's. It was 2 (half an edge) until 2026-11-29: the first Adam steps of a stage move
# vertices by up to about an edge, so a short run halved nearly every step of its coarse stages (a 10 s run
# at 10k vertices through the teapot's handle: 19 of 19 and 21 of 21 steps in its first two stages), and
# those runs ended near 5e-3 where runs with one edge ended at 1.9e-5 and 5.3e-5 (docs/reconstruction.md,
# *The step bound*).
MAX_STEP_REACHES = 4.0

# Why a guard refuses every step of a stage, by the rule that refused most candidates.
_STALL_CAUSES = {
    "step": "every step moved a vertex farther than the guard allows ({max_step:.3g}, one edge, which "
            "scales with the mesh), while lr={lr:g} is absolute; the stage's start is {size:.3g} across (the target: "
            "1): scale the source toward the target's size, or lower lr",
    "turn": "every step turned a face over; the start likely holds a sliver (a near-collinear face, minimum "
            "triangle quality {quality:.2g}), whose normal flips under any move: remesh or clean the source",
    "quality": "every step left a triangle below the quality floor (the start's minimum quality {quality:.2g})",
    "intersection": "every step added self-intersections",
    "non-finite": "every step gave non-finite vertices; lower lr",
}


def _stall_warning(k: int, stage: dict, V, F, max_step) -> str:
    """One line for a stage whose every step the guard refused: the mesh it returns is its start ``(V, F)``."""
    reasons = {r: n for r, n in stage["refused_by"].items() if n}
    cause = max(reasons, key=reasons.get) if reasons else "step"
    Vd = V.detach().double()
    hint = _STALL_CAUSES[cause].format(max_step=max_step or math.nan, lr=stage["lr"],
                                       size=float((Vd.max(0).values - Vd.min(0).values).norm()),
                                       quality=float(triangle_quality(Vd, F).min()))
    return (f"stage {k} ({stage['n_vertices']} vertices) accepted none of its {stage['steps']} steps: the step guard "
            f"refused {stage['refused']} of {stage['checks']} candidates {reasons}; {hint}. The stage returned its "
            f"start unchanged")


def _check_start(build, V, k: int, method: str):
    """The stage's parameterisation, ``build()``, which must reproduce its start: at a scale where its
    arithmetic under- or overflows (an rbf kernel 1e-20 wide) it gives NaN, which would otherwise surface at
    the first step, or its deformer refuses to be built."""
    try:
        param = build()
        with torch.no_grad():
            fails = not bool(torch.isfinite(param.vertices()).all())
        why = ""
    except NarrowKernelError as err:  # the deformer's own check: kernels too narrow for the dtype
        fails, why = True, f" ({err})"
    if fails:
        Vd = V.detach().double()
        size = float((Vd.max(0).values - Vd.min(0).values).norm())
        raise ReconstructionError(f"stage {k}: the {method} deformation gives non-finite vertices at its start, a mesh "
                                  f"{size:.3g} across (bounding-box diagonal, {V.dtype}), too small or too large for "
                                  f"its arithmetic{why}; scale the source toward the target's size (unit diagonal)")
    return param


def _guarded_step(s: ReconstructionSettings, sk: ReconstructionSettings, n_stage: int) -> ReconstructionSettings:
    """With the guard, a stage finer than ``reg_ref_vertices`` takes a learning rate scaled with its edge
    length, ``lr * sqrt(reg_ref / n)``: the guard and the barrier work at a fraction of an edge, and a step
    of the same absolute length carries vertices through faces at 10k vertices (about 1,200 refusals and
    5.2e-6 on the bunny, against 506 and 3.2e-6 at half the rate; docs/reconstruction.md)."""
    if not s.valid_steps or s.reg_ref_vertices is None or n_stage <= s.reg_ref_vertices:
        return sk
    return replace(sk, lr=sk.lr * (s.reg_ref_vertices / n_stage) ** 0.5)


def _contact_info(contact, edges_from) -> dict:
    if contact is None:
        return {}
    return {"contact_distance": contact.distance, "contact_rebuilds": contact.rebuilds,
            "contact_seconds": round(contact.seconds, 4),
            "contact_edges_from": edges_from}


def _new_intersections(V, F, old: np.ndarray, V2, F2) -> int:
    """Intersecting pairs a remesh ``(V2, F2)`` of ``(V, F)``, whose own pairs are ``old``
    (:func:`~meshmei.quality.self_intersecting_pairs`), added. Faces are renumbered by a remesh, so
    pairs are told apart by place: the excess over the old count, or, if more, the pairs of the new mesh with
    a face farther than two of its mean edge lengths from every intersecting face of the old one (a count
    alone let a remesh that cleared one place and crossed another through: review)."""
    new = self_intersecting_pairs(V2, F2)
    if len(new) == 0:
        return 0
    if len(old) == 0:
        return len(new)
    Vn, Fn = numpy_mesh(V, F)
    V2n, F2n = numpy_mesh(V2, F2)
    tree = cKDTree(Vn[Fn[np.unique(old)]].mean(1))  # centroids of the old mesh's intersecting faces
    reach = 2.0 * float(np.linalg.norm(V2n[F2n[:, 0]] - V2n[F2n[:, 1]], axis=1).mean())
    far_face = tree.query(V2n[F2n].mean(1), distance_upper_bound=reach)[0] == np.inf  # (m2,)
    elsewhere = int(far_face[new].any(axis=1).sum())
    return max(len(new) - len(old), elsewhere)  # at least the excess, and every pair away from the old ones


def _remesh_clean(V, F, n: int, clean: bool, seconds_left: float | None = None):
    """Remesh to ``n`` vertices; with ``clean``, retry (other iteration counts) when the remesh adds
    intersecting pairs (:func:`_new_intersections`) or changes the topology (:func:`~meshmei.quality.topology`:
    pieces welded at a vertex, a new non-manifold edge or vertex), and keep the mesh as it is when no try is
    clean; then, where that lands nearer ``n``, the mesh with every face split in four (:func:`_subdivided`,
    the same surface; ``remesh_subdivided`` in the record) if it passes the same checks. ``seconds_left``:
    under a time budget, the seconds left in the stage's share; no retry starts once what would be left after
    it, at the last try's duration, is under that duration (a refused 10k remesh and its checks take about a
    second: three tries spent a 10 s run's last share and ran it over budget).
    Returns ``(V, F, record)``; the record says how many tries were made (``remesh_tries``)."""
    t0 = time.perf_counter()
    try:
        V2, F2 = remesh(V, F, n)
    except MeshError as err:  # thin parts: a result many times the count (MAX_REMESH_GROWTH); no retry helps
        return V, F, {"remesh_iterations": None, "remesh_refused_count": str(err), "remesh_tries": 1}
    if not clean:
        return V2, F2, {}
    old, shape = self_intersecting_pairs(V, F), topology(F)  # the source's, once for every try
    tries, tried_at, out_of_time = 0, t0, False
    for iterations in (None, 10, 3):
        if iterations is not None:
            now = time.perf_counter()
            if seconds_left is not None and seconds_left - (now - t0) < 2.0 * (now - tried_at):
                out_of_time = True  # after one more try as long as the last, the stage would have less left
                break
            tried_at = now
            try:
                V2, F2 = remesh(V, F, n, iterations=iterations)
            except MeshError:  # this try landed far above the count (MAX_REMESH_GROWTH): refused as one
                tries += 1
                continue
        added = _new_intersections(V, F, old, V2, F2)
        changed = sorted(k for k, v in topology(F2).items() if v != shape[k])
        tries += 1
        if added == 0 and not changed:
            return V2, F2, {"remesh_iterations": iterations or 5, "remesh_tries": tries}
    record = {"remesh_iterations": None, "remesh_refused_pairs": added, "remesh_refused_topology": changed,
              "remesh_tries": tries, **({"remesh_out_of_time": True} if out_of_time else {})}
    # a stage that grows the mesh: split every face in four at its edges' midpoints (the same surface, about
    # four times the vertices) if that lands nearer the count asked for and passes the same checks
    if n > V.shape[0]:
        U, G = _subdivided(V, F)
        if abs(U.shape[0] - n) < abs(V.shape[0] - n) and _new_intersections(V, F, old, U, G) == 0 and \
                topology(G) == shape:
            return U, G, {**record, "remesh_subdivided": True}
    return V, F, record


def _subdivided(V, F):
    """``(V, F)`` with every face split in four at its edges' midpoints (libigl's ``upsample``), in ``V``'s
    dtype and on its device."""
    U, G = igl.upsample(*numpy_mesh(V, F), number_of_subdivs=1)
    return (torch.from_numpy(U).to(device=V.device, dtype=V.dtype),
            torch.from_numpy(np.asarray(G, dtype=np.int64)).to(F.device))


# A restart stage (the count of the stage before, the same settings) is run as part of the stage before it when
# its share of a time budget is under this many times the set-up that stage took (measured): a restart at
# 10k vertices sets up in 2.3-2.7 s (a remesh of 1.1-1.6 s, the guard, the contact pairs, the RBF lists),
# and a 10 s budget gives it 2.5 s, so it took 0-4 steps and ran over the budget (docs/reconstruction.md,
# *Restarts that cannot pay for themselves*).
RESTART_SETUP_MULTIPLE = 2.0


def _merged_restarts(k: int, stages, per_stage, bounds, budget, setup: float, merged_into: dict) -> int:
    """The last stage that stage ``k``, which took ``setup`` seconds to set up, runs through: ``k`` itself, or
    the restarts after it whose time share is under :data:`RESTART_SETUP_MULTIPLE` times ``setup``, which are
    marked in ``merged_into``. Only a time budget merges (a step budget is not spent by set-ups)."""
    end = k
    if budget.seconds is None:
        return end
    while (end + 1 < len(stages) and stages[end + 1] == stages[k]
           and (per_stage is None or per_stage[end + 1] == per_stage[k])
           and (bounds[end + 2] - bounds[end + 1]) * budget.seconds < RESTART_SETUP_MULTIPLE * setup):
        end += 1
        merged_into[end] = k
    return end


def _pass_on_share(bounds, k: int, f: float) -> None:
    """Stage ``k - 1`` ended at budget fraction ``f``, before its bound ``bounds[k]`` (its ``max_steps``): the
    stages from ``k`` on share what is left, ``[f, 1]``, in the proportions they had (``bounds`` in place)."""
    bounds[k:] = f + (bounds[k:] - bounds[k]) * (1.0 - f) / (1.0 - bounds[k])


def _stage_mesh(V, F, k: int, n_stage, s, sk, stages, left, n_source: int, info: dict, target):
    """Stage ``k``'s mesh and regularizer weights: ``(V, F, weights, remeshed)``. The mesh is ``(V, F)`` remeshed
    to ``n_stage`` vertices where the stage asks for a count (a first stage within a tenth of it runs on the
    source), and clean where ``s.valid_steps`` (:func:`_remesh_clean`, ``left`` seconds of its share); with
    ``s.surgery``, after the stage before it the mesh's topology is first adapted to the target ``target``
    (numpy arrays; :func:`_surgery`). ``remeshed`` is the remesh's record, with the surgery's under
    ``"surgery"``. What went wrong goes into ``info["warnings"]``."""
    remeshed = {}
    if n_stage is not None and k > 0 and s.surgery:
        V, F, remeshed = _surgery(V, F, n_stage, s.valid_steps, left, target)
    elif n_stage is not None and (k > 0 or abs(V.shape[0] - n_stage) > 0.1 * n_stage):
        V, F, remeshed = _remesh_clean(V, F, n_stage, s.valid_steps, left)
    # every remesh refused: the stage keeps the mesh it had and takes the weights of that mesh's count, not
    # of the count it asked for (a 9,917-vertex stage ran with the weights of 100 vertices; review)
    remesh_refused = remeshed.get("remesh_iterations", 0) is None
    refused = remesh_refused and not remeshed.get("remesh_subdivided")  # and the mesh kept as it was
    # a remesh far from its count: the weights a stage states for its own count follow the count it got (the
    # first stage of several states the second's)
    far = (n_stage is not None and not refused and not (k == 0 and len(stages) > 1)
           and not n_stage / STAGE_COUNT_TOLERANCE <= V.shape[0] <= n_stage * STAGE_COUNT_TOLERANCE)
    weights = stage_weights(s, sk, k if n_stage is not None else None, n_source,
                            V.shape[0] if refused or far else None)
    if far:
        info["warnings"].append(
            f"stage {k}: asked for {n_stage} vertices, the remesh gave {V.shape[0]} (more than "
            f"{STAGE_COUNT_TOLERANCE:g} times off); the stage runs with the weights for {V.shape[0]} vertices")
    if "remesh_refused_count" in remeshed:
        info["warnings"].append(f"stage {k}: {remeshed['remesh_refused_count']}; the stage runs on the mesh it "
                                f"had, {V.shape[0]} vertices, with the weights for that count")
    elif remesh_refused:
        tried = ("every remesh" if not remeshed.get("remesh_out_of_time") else
                 f"the remesh (tried {remeshed['remesh_tries']} of 3 times: the stage's share of the time budget "
                 "left no room for another)")
        runs_on = (f"the stage runs on the mesh it had, {V.shape[0]} vertices, with the weights for that count"
                   if refused else f"the stage runs on the mesh it had with every face split in four (the same "
                   f"surface), {V.shape[0]} vertices")
        info["warnings"].append(
            f"stage {k}: {tried} to {n_stage} vertices added self-intersections or changed the topology "
            f"({remeshed['remesh_refused_pairs']} new pairs; "
            f"{', '.join(remeshed['remesh_refused_topology']) or 'topology kept'}): {runs_on}")
    return V, F, weights, remeshed


def _surgery(V, F, n: int, clean: bool, left, target):
    """:func:`~meshmei.reconstruct.surgery.adapt_topology` of ``(V, F)`` to ``target``, then the remesh to ``n``
    vertices (:func:`_remesh_clean`): ``(V, F, record)``, the record the remesh's with the surgery's under
    ``"surgery"``. A sealed mesh (marching cubes, many times ``n`` vertices) whose remesh is refused is
    dropped, and the mesh as it was remeshed instead (``"dropped"`` in the surgery's record)."""
    t0 = time.perf_counter()
    Vn, Fn = numpy_mesh(V, F)
    V2, F2, surgery = adapt_topology(Vn, Fn, *target)
    if not (surgery["perforated"] or surgery["sealed"]):
        V2, F2, remeshed = _remesh_clean(V, F, n, clean, None if left is None else left - surgery["seconds"])
        return V2, F2, {**remeshed, "surgery": surgery}
    V2 = torch.from_numpy(np.ascontiguousarray(V2)).to(device=V.device, dtype=V.dtype)
    F2 = torch.from_numpy(np.ascontiguousarray(F2, dtype=np.int64)).to(F.device)
    spent = time.perf_counter() - t0
    U, G, remeshed = _remesh_clean(V2, F2, n, clean, None if left is None else left - spent)
    if surgery["sealed"] and remeshed.get("remesh_iterations", 0) is None and not remeshed.get("remesh_subdivided"):
        surgery["dropped"] = "its remesh was refused"
        U, G, remeshed = _remesh_clean(V, F, n, clean, None if left is None else left - spent)
    return U, G, {**remeshed, "surgery": surgery}


def _stage_parameterisation(V, F, k: int, s, sk, chamfer, info: dict):
    """Stage ``k``'s settings as it runs them on ``(V, F)`` and its parameterisation: ``(sk, param, pairing)``.
    ``pairing``: with ``normal_match``, whether the stage's start encloses the target (else None)."""
    sk = _guarded_step(s, sk, V.shape[0])
    pairing = None  # normal_match: whether the stage's start encloses the target (else plain pairs)
    if sk.normal_match > 0:
        pairing = chamfer.encloses(V, F)
        sk = sk if pairing else replace(sk, normal_match=0.0)
    if isinstance(sk.centers, int) and sk.centers > V.shape[0]:  # resolved: a count is an int
        # a kernel count at a stage's requested size: the remesh lands a few vertices off (300 gave 296),
        # and a stage has at most one kernel per vertex (the count it got is in the stage's n_kernels)
        sk = replace(sk, centers=V.shape[0])
    param = _check_start(lambda: _parameterisation(sk, V.detach(), F), V, k, sk.method)
    if sk.method == "rbf" and sk.coarse_ratio and param.coarse is None:  # it had none, without a word
        info["warnings"].append(
            f"stage {k} ({V.shape[0]} vertices): coarse_ratio={sk.coarse_ratio} gives "
            f"{round(V.shape[0] / sk.coarse_ratio)} coarse kernels, fewer than {MIN_COARSE_KERNELS} (which "
            "would only translate the shape): the stage runs without coarse kernels")
    return sk, param, pairing


def _stage_validity(V, F, k: int, s, info: dict):
    """Stage ``k``'s contact barrier and step guard on ``(V, F)`` (each None where the run has none):
    ``(contact, guard, left_out, max_step)``, ``left_out`` the start's pairs in contact that the barrier leaves
    out, ``max_step`` the guard's step bound."""
    contact = (ContactBarrier.for_mesh(V, F, s.contact_distance, edges=s.contact_edges is True)
               if s.w_contact > 0 else None)
    left_out = contact.leave_out(V) if contact is not None else 0  # pairs already in contact: locked the fit
    if left_out:
        info["warnings"].append(
            f"stage {k}: {left_out} vertex-face or edge pairs of the start are in contact (closer than "
            f"{IN_CONTACT:g} of the contact distance {contact.distance:.3g}): a T-junction (an edge split on one "
            "side only) or parts that touch; the contact barrier leaves them out (the step guard still refuses "
            "an intersection)")
    max_step = None if contact is None else MAX_STEP_REACHES * contact.distance  # one edge
    guard = StepGuard(V, F, s.validity_rules(max_step)) if s.valid_steps else None
    if guard is not None and contact is not None:
        # the barrier's distances at each accepted mesh clear most candidates of libigl's test; they need
        # its edge pairs, searched for that alone (not in the energy) unless the run pairs edges anyway
        contact.track_edges()
        guard.use_contact(contact)
    return contact, guard, left_out, max_step


def _named_schedule(given: ReconstructionSettings) -> str | None:
    """``stages`` when it names a schedule (:data:`~meshmei.reconstruct.schedule.NAMED_SCHEDULES`: ``"auto"``,
    ``"auto2"``, ...), which sets the shares and overrides too; None when it gives counts or nothing."""
    if not isinstance(given.stages, str):
        return None
    if given.stages not in NAMED_SCHEDULES:
        raise ReconstructionError(f"stages must be vertex counts, None or one of {NAMED_SCHEDULES}, "
                                  f"got {given.stages!r}")
    if given.stage_fractions is not None or given.stage_overrides is not None:
        raise ReconstructionError(f"stages={given.stages!r} sets the stages' shares and overrides itself; for other "
                                  f"ones pass the counts (default_schedule(method, n) gives all three to start from)")
    return given.stages


def _run_stages(V, F, s, per_stage, chamfer, evaluation, trace, budget, bar, callback, callbacks, info):
    stages = s.stages or (None,)
    bounds = np.cumsum((0.0,) + (s.stage_fractions or (1.0,)))  # stage k covers [bounds[k], bounds[k+1])
    schedule = Schedule("geometric", s.lr_decay)
    n_source = V.shape[0]
    merged_into = {}  # a restart stage run as part of the stage before it (_merged_restarts)
    target = numpy_mesh(evaluation.Vt, evaluation.Ft) if s.surgery else None
    for k, n_stage in enumerate(stages):
        if k in merged_into:  # run, and recorded, with the stage it was merged into
            continue
        t0 = time.perf_counter()
        left = None if budget.seconds is None else float(bounds[k + 1]) * budget.seconds - trace.seconds
        sk = per_stage[k] if per_stage else s
        V, F, weights, remeshed = _stage_mesh(V, F, k, n_stage, s, sk, stages, left, n_source, info, target)
        sk, param, pairing = _stage_parameterisation(V, F, k, s, sk, chamfer, info)
        contact, guard, left_out, max_step = _stage_validity(V, F, k, s, info)
        setup = time.perf_counter() - t0
        trace.seconds += setup
        end = _merged_restarts(k, stages, per_stage, bounds, budget, setup, merged_into)
        latest, edges_from = [None], [trace.step if s.contact_edges is True else None]

        last = end == len(stages) - 1

        def after_step(rec, param=param, F=F, latest=latest, contact=contact, guard=guard, last=last):
            if (s.contact_edges == "auto" and contact is not None and not contact.edge_energy and guard is not None
                    and guard.reasons["intersection"] >= AUTO_EDGE_REFUSALS):
                contact.use_edges()  # a stall at an edge contact: pair edges from here on
                edges_from[0] = rec["step"]
                if last:  # where the kick costs most: their weight ramped up (AUTO_EDGE_RAMP)
                    contact.edge_weight = 1.0 / AUTO_EDGE_RAMP
            elif contact is not None and contact.edge_weight < 1.0:
                contact.edge_weight = min(1.0, contact.edge_weight + 1.0 / AUTO_EDGE_RAMP)
            if callback is not None:
                callback(rec["step"], latest[0].detach(), rec["loss"])
            for cb in callbacks:
                cb(rec)
            if evaluation.due(rec["step"]):
                with torch.no_grad():
                    evaluation(param.vertices().detach(), F, health=True)

        n_before = len(trace.history)
        share_end = 1.0 if end == len(stages) - 1 else float(bounds[end + 1])  # where the stage's share ends
        stop_step = None if sk.max_steps is None else trace.step + sk.max_steps
        # a guarded step's check of the candidate and the next objective share one map of the parameters
        vertices = Lookahead(param.vertices, [p for g in param.groups for p in g["params"]])
        with torch.no_grad():
            V_first = param.vertices().detach()  # the parameterisation's own start (large steps' is V0 rounded)
        outcome = minimize(_objective(param, vertices, F, sk, weights, chamfer, k, latest, contact),
                           make_optimizer(sk.optimizer, param.groups), budget, schedule=schedule, trace=trace,
                           stop_at=share_end, stop_step=stop_step, progress=bar,
                           callbacks=[after_step], accept=None if guard is None else guard.acceptor(vertices.candidate),
                           max_halvings=0 if guard is None else guard.rules.max_halvings, states=param.states())
        _check_scales(param, sk, k, trace.step)  # the last step's, which no objective saw
        with torch.no_grad():
            V_start, V = V, param.vertices().detach()
        # ended by its max_steps before its share (a limit that the share reaches too cut nothing)
        f = budget.fraction(trace.step, trace.seconds)
        capped = stop_step is not None and trace.step >= stop_step and f < share_end
        if capped and end + 1 < len(stages):
            _pass_on_share(bounds, end + 1, f)
        stage = {"n_vertices": int(V.shape[0]), **({} if n_stage is None else {"n_vertices_asked": int(n_stage)}),
                 "end_step": trace.step, "method": sk.method, "lr": sk.lr,
                 **({} if pairing is None else {"normal_match": sk.normal_match, "start_encloses_target": pairing}),
                 **({} if sk.max_steps is None else {"max_steps": sk.max_steps, "ended_at_max_steps": capped}),
                 "w_laplacian": weights[0], "w_edge": weights[1], "w_arap": weights[2],
                 **_guard_info(guard, trace.history[n_before:]), **_contact_info(contact, edges_from[0]),
                 "contact_left_out": left_out, "setup_seconds": setup, **remeshed,
                 **param.info()}
        info["stages"].append(stage)
        info["stages"] += [{"n_vertices": stage["n_vertices"], "end_step": trace.step, "steps": 0, "merged_into": k}
                           for _ in range(k + 1, end + 1)]
        _stage_warnings(k, stage, guard, V_start, V, V_first, F, max_step, len(trace.history) - n_before,
                        weights, sk, info)
        if outcome.budget_spent:
            break
    return V, F


def _stage_warnings(k: int, stage: dict, guard, V_start, V, V_first, F, max_step, steps: int, weights, sk,
                    info: dict) -> None:
    """What a finished stage ``k`` says of itself: a guard that accepted none of its steps (the stage returned
    ``V_start``), or ``steps`` steps none of which moved the mesh from ``V_first``."""
    if guard is not None and stage["steps"] and not stage["accepted_steps"]:
        info["warnings"].append(_stall_warning(k, stage, V_start, F, max_step))
    elif steps > 0 and torch.equal(V, V_first):
        # w_edge=1e30: Adam's squared gradient overflowed, every step was 0, and the history showed steps
        # taken at the stage's lr
        info["warnings"].append(
            f"stage {k} ({stage['n_vertices']} vertices): none of its {steps} steps moved the mesh "
            f"(each step was zero: a weight so large that the optimiser's squared gradient overflows? "
            f"w_laplacian {weights[0]:g}, w_edge {weights[1]:g}, w_arap {weights[2]:g}, "
            f"w_contact {sk.w_contact:g}, w_facing {sk.w_facing:g}); the stage returned its start unchanged")
