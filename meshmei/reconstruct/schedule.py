"""Coarse-to-fine schedules of a reconstruction: the stage counts, shares and per-stage settings that the
CLI's ``--stages auto`` and the benchmark's variants both take from here."""

from __future__ import annotations

import numpy as np

from ..errors import ReconstructionError
from .settings import MAX_SAMPLES, METHODS, MIN_STAGE_VERTICES

__all__ = ["RBF_THREE_LEVEL_OVERRIDES", "RBF_FOUR_LEVEL_OVERRIDES", "THREE_LEVEL_MIN_VERTICES",
           "FOUR_LEVEL_MIN_VERTICES", "NAMED_SCHEDULES", "default_stages", "default_schedule", "schedule_from_text"]

# The schedules named by text, in reconstruct(stages=...) and the CLI's --stages: the levels they force (None:
# default_schedule's pick)
_LEVELS = {"auto": None, "auto2": 2, "auto3": 3, "auto4": 4}
NAMED_SCHEDULES = tuple(_LEVELS)

# rbf with three levels (default_stages(n, levels=3)) in the benchmark (variant rbf-3levels) and the CLI's
# --stages auto3. The coarsest stage (625 vertices at 10k) draws 5,000 Chamfer samples a step instead of
# 10,000: a step there costs about what a 10k step does, mostly sampling and searching, so half the samples
# nearly doubles its steps, and eight samples per vertex are still plenty (at 10k it reached 5.6e-4 at 2 s
# where it was at 1.1e-3, before large steps' 7.6e-4; docs/reconstruction.md, *Fifth round*). Once the 625-
# and 2,500-vertex stages have moved the shape, the two fine stages need less smoothing, a quarter of the
# default Laplacian weight (2.5, that is 40 at 10k vertices against 160). Measured at 10k on three problems;
# 2.5 was the first value tried (*Coarse-to-fine*).
#
# In the coarsest stage a target sample whose nearest mesh sample faces away is paired by position and
# normal (normal_match, 0.3 of the target's diagonal): a sphere then enters a cavity (the cup: 5.8e-7
# against 1.6e-3), where by position alone the cavity's floor pulls on the outside of the surface across the
# wall (docs/reconstruction.md, *Pairing by normal*).
#
# The two coarse stages take at most the steps that the CLI's default run of 1,000 steps gives them (150 and
# 250, its shares 0.15 and 0.25), whatever the budget: the settings were chosen on runs of that length and the
# coarse shapes settle within them, so a longer budget goes to the final resolution. The bunny's 100 s run at
# 10k vertices in the reconstruction benchmark: 1.4e-5 at 10 s and 1.7e-6 at 30 s, where the shares alone gave
# 2.7e-4 and 8.3e-6 (the 625-vertex stage held 15 s, 560 steps), against large steps' 1.7e-4 and 3.8e-6. A
# 1,000-step run (the CLI's default), every 10 s run and the 30 s runs at 10k are as before
# (docs/reconstruction.md, *Long budgets*).
#
# The last stage at four levels' lighter weight (0.5, below) gained in the 2,500-vertex default runs of 1,000
# steps but stalled in longer ones (the teapot at 4e-6 from 50 s on, against 1.5e-6) and lost on three of
# four thin targets: tried and reverted (docs/reconstruction.md, *The last stage's smoothing at 2,500
# vertices: tried, not taken*).
#
# The first of the two fine stages takes at most the 350 steps that the default run gives it, too, so that a long
# budget goes to the last one. The mesh is checked for topology surgery only where a stage begins, and the
# centred teapot at 2,500 vertices often keeps the handle's membrane through the first fine stage; in a 100 s
# run that stage held it for about 2,000 steps, to 55-62 s (1.8e-5 to 2.1e-5 at 30 and 50 s, against large
# steps' 1.6e-5 and 1.1e-5; two of three runs on 2026-12-01). With the limit the next stage, and its seal,
# comes after about 750 steps, 15-20 s: two such runs were at 3.4e-6 and 3.2e-6 at 30 s, and the teapot and
# the bunny ended as before (1.35e-6 and 1.08e-6; docs/reconstruction.md, *The first fine stage's limit*).
RBF_THREE_LEVEL_OVERRIDES = ({"n_samples": 5000, "normal_match": 0.3, "max_steps": 150}, {"max_steps": 250},
                             {"w_laplacian": 2.5, "max_steps": 350}, {"w_laplacian": 2.5})

# rbf with four levels (default_stages(n, levels=4): what three levels give a run at n/4, then one stage at n)
# takes the three-level settings for its first four stages, and the last stage a fifth of the fine stages'
# Laplacian weight (0.5, that is 8 at 10k vertices, below). The stages at n/4 have the regularizer weights of
# a run at n/4 (reg_ref_vertices scales them by stage count), so up to the last stage a 10k run is a 2.5k
# run; the last stage starts from an even remesh of that 2.5k result. At 10k a 10 s run got to 6.2e-7 on the
# bunny where three levels ended at 3.5e-5 (their two 10k stages ran 60 steps after 2.3 s of remeshing and
# setting up), and 1.8e-6 through the teapot's handle against 2.7e-6 (docs/reconstruction.md, *Four levels
# at 10k*).
#
# The two stages at n/4 also take at most the steps that the 2,500-vertex default run gives its two
# 2,500-vertex stages (350 and 250), as the coarse stages do theirs: a long budget then goes to the stage at
# n instead of polishing the n/4 shape. The CLI's default 1,000-step run at 10k gives them 300 and 200 steps,
# so it, every 10 s and 30 s run and the 50 s runs measured are unchanged. In the 100 s runs at 10k the
# last stage got 58 s instead of 28 s: the teapot through the handle 9.9e-7 against 1.18e-6 (seed 0) and
# the bunny 4.7e-7 against 4.9e-7, both clean (docs/reconstruction.md, *The 2,500-vertex stages' limits*).
#
# The last stage starts from the 2,500-vertex shape, which has arrived: it needs little smoothing, and the
# step guard and the contact barrier keep it clean. Its Laplacian weight was 2.5 (40 at 10k), the fine stages'
# of three levels, until 2026-11-30; at 0.5 the teapot through the handle at 10k ended at 7.8e-7 in 70 s
# against 1.12e-6 (1.0: 8.5e-7; 0.25: 7.7e-7 with the smallest triangle quality 0.18 against 0.24), 9.8e-7 in
# 30 s against 1.36e-6, and the bunny at 3.1e-7 in 70 s against 5.0e-7, all clean
# (docs/reconstruction.md, *The last stage's smoothing*).
#
# The last stage draws twice the run's Chamfer samples (default_schedule: 20,000 with the default 10,000, two
# a vertex at 10k). With one a vertex its sampled term's noise set the level it stayed at for a given
# learning rate: the teapot through the handle at 10k (100 s, benchmark settings, 2026-12-01) was at 9.7e-7
# to 1.0e-6 at 50 s and ended at 6.7e-7 to 7.2e-7 in the runs without an excursion, with twice the samples
# at 7.6e-7 to 9.2e-7 and 5.1e-7 to 6.3e-7, for 10 to 20 % fewer steps (docs/reconstruction.md, *The
# last stage's samples*); four times the samples halved the steps for no further gain.
RBF_FOUR_LEVEL_OVERRIDES = (*RBF_THREE_LEVEL_OVERRIDES[:3], {**RBF_THREE_LEVEL_OVERRIDES[3], "max_steps": 250},
                            {"w_laplacian": 0.5, "n_samples": 20_000})


def _vertex_count(n_vertices) -> int:
    """``n_vertices`` as an int: a positive integer (NumPy's too, not a bool), else ReconstructionError naming it
    (NaN was Python's 'cannot convert float NaN to integer', inf an OverflowError, 100.7 ran as 100 and
    '100' as 100, without a word)."""
    if isinstance(n_vertices, (bool, np.bool_)) or not isinstance(n_vertices, (int, np.integer)) or n_vertices < 1:
        raise ReconstructionError(f"n_vertices must be a positive integer, got {n_vertices!r}")
    return int(n_vertices)


def default_stages(n_vertices: int, levels: int = 2) -> tuple:
    """The coarse-to-fine schedule used by the benchmark and the CLI. Returns ``(stages, stage_fractions)``.

    ``levels=2`` (the default): ``(n/4, n, n)`` with shares ``(0.25, 0.45, 0.3)`` of the budget.
    ``levels=3``: ``(n/16, n/4, n, n)`` with shares ``(0.15, 0.25, 0.35, 0.25)``, so that a 10k run
    starts as a 2.5k run does (from 625 vertices, where the shape travels at little cost) and then refines.
    ``levels=4``: three levels' schedule for ``n/4``, then one stage at ``n``: ``(n/64, n/16, n/4, n/4, n)``
    with shares ``(0.1, 0.15, 0.3, 0.2, 0.25)``, so that a 10k run is a 2.5k run until its last quarter.
    Either way the last stage restarts on a fresh isotropic remesh of the shape, which clears folds and
    slivers left by the one before. At 10k vertices three levels helped rbf on all three benchmark problems
    and large steps on the bunny, and hurt large steps through the teapot's handle (docs/reconstruction.md,
    *Coarse-to-fine*), so two is the default here; :func:`default_schedule` picks three for rbf from 2,000
    vertices and four from 8,000. No stage has fewer than
    :data:`~meshmei.reconstruct.settings.MIN_STAGE_VERTICES` (32) vertices, so ``n_vertices`` must be an integer
    of at least that many.
    """
    n = _vertex_count(n_vertices)
    if n < MIN_STAGE_VERTICES:
        raise ReconstructionError(f"a coarse-to-fine schedule needs at least {MIN_STAGE_VERTICES} vertices, got "
                                  f"{n_vertices!r}; run one stage at the mesh's own size (stages=None)")
    if levels == 3:
        return (max(MIN_STAGE_VERTICES, n // 16), max(MIN_STAGE_VERTICES, n // 4), n, n), (0.15, 0.25, 0.35, 0.25)
    if levels == 4:
        return tuple(max(MIN_STAGE_VERTICES, n // d) for d in (64, 16, 4, 4, 1)), (0.1, 0.15, 0.3, 0.2, 0.25)
    if levels == 2:
        return (max(MIN_STAGE_VERTICES, n // 4), n, n), (0.25, 0.45, 0.3)
    raise ReconstructionError(f"levels must be 2, 3 or 4, got {levels!r}")


# The smallest final count at which meshmei reconstruct's --stages auto gives rbf three levels. Measured at
# 10,000 (first stage 625) and at the CLI's default 2,500 (first stage about 150; guarded, seeds 0-2: bunny
# 1.59e-6, 2.78e-6, 1.30e-6 against 1.82e-6, 2.30e-6 for seeds 0-1 with two levels; teapot through the handle
# 2.00e-6, 2.13e-6, 2.19e-6 against 3.68e-6, 3.79e-6; docs/reconstruction.md). Below 2,000 the first stage
# would fall under 125 vertices, where nothing was measured.
THREE_LEVEL_MIN_VERTICES = 2_000

# The smallest final count at which --stages auto gives rbf four levels: from here the run at n/4 that they
# begin with is itself a three-level run. Measured at 10,000, and at the CLI's default 2,500, where four
# levels were worse in a 1,000-step run (seeds 0-2, guarded: bunny 1.29e-6, 1.32e-6, 1.28e-6 against three
# levels' 1.22e-6, 1.18e-6, 1.09e-6; teapot through the handle 2.50e-6, 2.13e-6, 1.97e-6 against 1.96e-6,
# 2.05e-6, 1.78e-6; docs/reconstruction.md, *Four levels at 10k*). Below 8,000 rbf keeps three.
FOUR_LEVEL_MIN_VERTICES = 4 * THREE_LEVEL_MIN_VERTICES


def default_schedule(method: str, n_vertices: int, levels: int | None = None, *, n_samples: int = 10_000) -> tuple:
    """The coarse-to-fine schedule ``meshmei reconstruct --stages auto`` uses for ``method`` and a final
    count of ``n_vertices``. Returns ``(stages, stage_fractions, stage_overrides)``.

    ``levels`` 2, 3 or 4 forces that many levels (``--stages auto2`` / ``auto3`` / ``auto4``); rbf with three
    levels always gets :data:`RBF_THREE_LEVEL_OVERRIDES` (with four, :data:`RBF_FOUR_LEVEL_OVERRIDES`, the same
    and a lighter last stage): half the run's Chamfer samples in the coarsest stage (``n_samples // 2``; 5,000
    with the default 10,000) and the lighter fine stages; with four, twice the run's samples in the last stage
    (``2 n_samples``, at most ``MAX_SAMPLES``). ``None`` (``--stages auto``) picks as follows.

    rbf at ``FOUR_LEVEL_MIN_VERTICES`` (8,000) vertices or more: four levels
    (``default_stages(n, levels=4)``), measured against three at 10k on the bunny and the teapot
    (docs/reconstruction.md, *Four levels at 10k*). rbf at ``THREE_LEVEL_MIN_VERTICES`` (2,000) vertices or
    more: three levels (``default_stages(n, levels=3)``, the benchmark's rbf-3levels), measured against two
    levels at 10k on the three benchmark problems (*Coarse-to-fine* and *Fifth round*) and at the CLI's
    default 2,500 on the bunny and the teapot (guarded). Otherwise two levels (``default_stages(n)``); large
    steps and vertex always get two: three hurt large steps through the teapot's handle.

    A start of fewer than ``MIN_STAGE_VERTICES`` (32) vertices has no coarser level to start from: it
    runs in one stage at its own size, ``(None, None, None)``, whatever ``levels`` says. ``n_vertices`` must be a
    positive integer (NumPy's too; not a bool, a float or a string).
    """
    if method not in METHODS:
        raise ReconstructionError(f"method must be one of {METHODS}, got {method!r}")
    if isinstance(n_samples, bool) or not isinstance(n_samples, (int, np.integer)) or n_samples < 2:
        raise ReconstructionError(f"n_samples must be an integer of at least 2, got {n_samples!r}")
    n = _vertex_count(n_vertices)
    if n < MIN_STAGE_VERTICES:
        return None, None, None
    if levels is None:
        levels = 2
        if method == "rbf":
            levels = 4 if n >= FOUR_LEVEL_MIN_VERTICES else 3 if n >= THREE_LEVEL_MIN_VERTICES else 2
    stages, fractions = default_stages(n, levels)
    if method != "rbf" or levels == 2:
        return stages, fractions, None
    overrides = RBF_FOUR_LEVEL_OVERRIDES if levels == 4 else RBF_THREE_LEVEL_OVERRIDES
    first = dict(overrides[0], n_samples=int(n_samples) // 2)
    if levels == 3:
        return stages, fractions, (first,) + overrides[1:]
    last = dict(overrides[-1], n_samples=min(2 * int(n_samples), MAX_SAMPLES))
    return stages, fractions, (first,) + overrides[1:-1] + (last,)


def schedule_from_text(spec: str, method: str, n_vertices: int, *, n_samples: int = 10_000) -> tuple:
    """``(stages, stage_fractions, stage_overrides)`` from the CLI's ``--stages`` text: ``"auto"``
    (:func:`default_schedule`'s pick), ``"auto2"`` / ``"auto3"`` / ``"auto4"`` (that many levels), ``"none"``
    (one stage), or comma-separated vertex counts with equal shares (``"600,2500,2500"``), each at least
    ``MIN_STAGE_VERTICES`` (32). ``n_vertices`` is the start's count, a positive integer."""
    _vertex_count(n_vertices)
    if spec in _LEVELS:
        return default_schedule(method, n_vertices, _LEVELS[spec], n_samples=n_samples)
    if not spec or spec == "none":
        return None, None, None
    try:
        stages = tuple(int(x) for x in spec.split(","))
    except ValueError:
        raise ReconstructionError(f"--stages must be 'auto', 'auto2', 'auto3', 'auto4', 'none' or comma-separated "
                                  f"integers, got {spec!r}") from None
    if min(stages) < MIN_STAGE_VERTICES:
        raise ReconstructionError(f"--stages {spec}: every stage needs at least {MIN_STAGE_VERTICES} vertices (the "
                                  f"start has {int(n_vertices)}); '--stages none' runs one stage at the start's size")
    return stages, None, None
