"""The benchmark's figures: Chamfer-L2, F-score and normal consistency against time, one file per problem."""

from __future__ import annotations

from .problems import COLORS, PROBLEMS, TARGETS
from .records import Case, Records, ordered

__all__ = ["plot"]

_FIELDS = ("chamfer_l2", "fscore", "normal_consistency")


def plot(results, floors, out):
    """Write ``out / "reconstruction_<problem>.png"`` for each problem with results: a row per vertex count, a
    column per metric, a curve per variant, the decimation floor and the issue's target as lines.

    ``results`` and ``floors`` as stored in ``docs/reconstruction_benchmark.json``.
    """
    import matplotlib  # deferred on purpose: a heavy optional dependency, needed for the figures only

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    records = Records.from_json({"results": results, "floors": floors})
    for prob in PROBLEMS:
        mine = {key: r for key, r in records.results.items() if key.problem == prob}
        if not mine:
            continue
        ns = sorted({key.n_vertices for key in mine})
        fig, axs = plt.subplots(len(ns), 3, figsize=(14, 3.6 * len(ns)), squeeze=False)
        for row, n in enumerate(ns):
            _plot_row(axs[row], prob, n, mine, records.floors.get(Case(prob, n)))
        fig.tight_layout()
        fig.savefig(out / f"reconstruction_{prob}.png", dpi=110)
        plt.close(fig)


def _plot_row(axs, prob, n, results, floor):
    """The three panels of problem ``prob`` at ``n`` vertices: every variant's evaluations against time."""
    for key, r in ordered(results):
        if key.n_vertices != n:
            continue
        t = [x["time"] for x in r["metrics"]]
        for col, field in enumerate(_FIELDS):
            axs[col].plot(t, [x[field] for x in r["metrics"]], "o-", ms=3, label=key.variant,
                          color=COLORS.get(key.variant))
    for col, field in enumerate(_FIELDS):
        ax = axs[col]
        # a target with fewer faces than the result is its own floor (Chamfer 0): no line on a log axis
        if floor and (field != "chamfer_l2" or floor[field] > 1e-15):
            ax.axhline(floor[field], color="k", ls="--", lw=0.8, label="decimation floor")
        ax.set_xscale("log")
        if field == "chamfer_l2":
            ax.set_yscale("log")
            if prob in TARGETS:
                ax.axhline(TARGETS[prob], color="r", ls=":", lw=0.8, label="target")
        ax.set_title(f"{prob}, {n} vertices: {field}")
        ax.set_xlabel("optimisation time (s)")
    axs[0].legend(fontsize=7)
