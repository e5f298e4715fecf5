"""What the reconstruction benchmark runs: its problems, resolutions, time budgets and method variants."""

from __future__ import annotations

from typing import NamedTuple

from ...reconstruct import default_schedule

__all__ = ["PROBLEMS", "BLOCKING", "RESOLUTIONS", "BUDGETS", "Variant", "VARIANTS", "variant_settings", "TARGETS",
           "COLORS"]

# name -> (target, start), the start resolved by meshmei.reconstruct.source_mesh for the target. "teapot"
# starts the torus with its hole through the teapot's handle (found by meshmei.reconstruct.openings.find_opening),
# as `meshmei reconstruct --init torus --target teapot` does: the torus is the start for the genus-1 teapot
# because its hole can become the handle's. "teapot-centred" starts it centred, its hole where the teapot
# has none: it shows what a start with the wrong hole costs (the membrane floor, membrane.py).
PROBLEMS = {"bunny": ("bunny", "sphere"), "teapot": ("teapot", "torus"),
            "teapot-centred": ("teapot", "torus-centred")}
BLOCKING = {"teapot-centred"}  # problems whose start blocks the target's opening (checked against membrane_floor)
RESOLUTIONS = (2500, 10000)
BUDGETS = (10.0, 30.0, 100.0)


class Variant(NamedTuple):
    """A method as the benchmark runs it: ``levels`` of coarse-to-fine stages from
    :func:`meshmei.reconstruct.default_schedule`, settings ``overrides`` on top, and the final vertex counts
    it runs at (``resolutions``; None: all)."""

    method: str
    levels: int | None  # None: as ``meshmei reconstruct --stages auto`` picks
    overrides: dict
    resolutions: tuple | None


# "rbf-nolap" (no Laplacian regularizer) shows the accuracy/health trade-off of the default weight;
# "largesteps-lr0.025" is large steps with the learning rate that suits 10k vertices better than the default
# (tuned at 2.5k); "rbf-coarse" adds the coarse kernel set (ReconstructionSettings.coarse_ratio). The
# "-3levels" variants have three levels: at 10k vertices, stages of 625, 2,500 and 10,000 vertices instead of
# 2,500 and 10,000; for rbf, default_schedule also sets the Laplacian weight of its two 10k stages to 2.5 (40
# after scaling, a quarter of the default 160): once the 625- and 2,500-vertex stages have moved the shape, the
# fine stages need less smoothing; and it draws half the Chamfer samples in the 625-vertex stage
# (RBF_THREE_LEVEL_OVERRIDES).
# The peers (free vertices and large steps) run as published: no step guard, no contact barrier and no
# topology surgery (UNGUARDED). "rbf" runs meshmei's defaults, which have the first two (issue 16) and, since
# 2026-11-30, the surgery, with the CLI's schedule (three levels at 2,000 vertices and more,
# RBF_THREE_LEVEL_OVERRIDES); "rbf-unguarded" is rbf with two levels without any of them, and the rbf
# ablations (nolap, coarse, 3levels) stay unguarded, as they were measured, so that they compare with
# "rbf-unguarded". Records of "rbf" made before the guard was the default were renamed
# "rbf-unguarded" in docs/reconstruction_benchmark.json.
UNGUARDED = {"valid_steps": False, "w_contact": 0.0, "surgery": False}
VARIANTS = {
    "rbf": Variant("rbf", None, {}, None),
    "rbf-unguarded": Variant("rbf", 2, UNGUARDED, None),
    "vertex": Variant("vertex", 2, UNGUARDED, None),
    "largesteps": Variant("largesteps", 2, UNGUARDED, None),
    "largesteps-lr0.025": Variant("largesteps", 2, {"lr": 0.025, **UNGUARDED}, (10000,)),
    "rbf-nolap": Variant("rbf", 2, {"w_laplacian": 0.0, "lr": 2e-3, **UNGUARDED}, (2500,)),
    "rbf-coarse": Variant("rbf", 2, {"coarse_ratio": 64, **UNGUARDED}, None),
    "rbf-3levels": Variant("rbf", 3, UNGUARDED, (10000,)),
    "largesteps-3levels": Variant("largesteps", 3, UNGUARDED, (10000,)),
}
TARGETS = {"bunny": 2e-6, "teapot": 5e-6, "teapot-centred": 5e-6}
COLORS = {"rbf": "tab:red", "rbf-unguarded": "tab:gray", "vertex": "tab:blue", "largesteps": "tab:orange", "largesteps-lr0.025": "tab:brown",
          "rbf-nolap": "tab:pink", "rbf-coarse": "tab:purple", "rbf-3levels": "tab:olive",
          "largesteps-3levels": "tab:green"}


def variant_settings(name: str, n_vertices: int) -> dict:
    """The keyword arguments of :func:`meshmei.reconstruct.reconstruct` for variant ``name`` at a final count of
    ``n_vertices``: its schedule (``stages``, ``stage_fractions``, ``stage_overrides``, from the same
    :func:`~meshmei.reconstruct.default_schedule` as ``meshmei reconstruct --stages auto2`` / ``auto3``) and
    its overrides."""
    variant = VARIANTS[name]
    stages, fractions, stage_overrides = default_schedule(variant.method, n_vertices, variant.levels)
    return dict(variant.overrides, stages=stages, stage_fractions=fractions, stage_overrides=stage_overrides)
