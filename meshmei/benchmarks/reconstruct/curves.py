"""Reading the benchmark's Chamfer curves: checkpoints, time to reach a level, and the best of several runs."""

from __future__ import annotations

__all__ = ["CHECKPOINTS", "time_to_reach", "on_checkpoints", "slower_levels", "best_of_runs"]

# The times (s) at which the longest run is evaluated (0: the starting mesh), besides its end.
CHECKPOINTS = (0.0, 1.0, 2.0, 5.0, 10.0, 20.0, 30.0, 50.0, 70.0)


def time_to_reach(curve, level):
    """First time in ``curve`` [(t, chamfer)] at which chamfer <= level (inf if never)."""
    for t, c in curve:
        if c <= level:
            return t
    return float("inf")


def on_checkpoints(curve, checkpoints=CHECKPOINTS):
    """Replace each measured time by the checkpoint it was taken for: the evaluation "at 10 s" happens at
    the first step past 10 s, a few tens of milliseconds later for one method than for another, and that
    difference is not a difference in speed. The last point (the end of the budget) keeps its time."""
    out = []
    for i, (t, c) in enumerate(curve):
        if i == len(curve) - 1 and t > checkpoints[-1]:
            out.append((float(round(t)), c))
        else:
            out.append((max(k for k in checkpoints if k <= t + 1e-9), c))
    return out


def slower_levels(curve, reference):
    """The Chamfer levels of ``reference`` that ``curve`` reaches at a later checkpoint:
    [(level, t_curve, t_reference)].

    Both curves are [(t, chamfer)] in time order and should start with the starting mesh at t = 0; times
    are compared on the checkpoints (:func:`on_checkpoints`)."""
    curve, reference = on_checkpoints(curve), on_checkpoints(reference)
    out = []
    for _, c in reference:
        t, t_ref = time_to_reach(curve, c), time_to_reach(reference, c)
        if t > t_ref:
            out.append((c, t, t_ref))
    return out


def best_of_runs(entry, budgets=None):
    """The lowest Chamfer-L2 a method has reached by each time, over its runs: the checkpoints of its
    longest run and the ends of its shorter runs (a shorter budget decays its learning rate and
    regularizers sooner, so it can be ahead of the long run at its end). [(t, chamfer)], non-increasing.
    This is what a user who picks the budget for a level gets. ``budgets``: the runs to count, the
    longest last (default: every run the entry has, including those outside the table's budgets)."""
    if budgets is None:
        budgets = sorted(float(b) for b in entry["budgets"])
    pts = on_checkpoints(entry["curve"]) + [(float(b), entry["budgets"][str(b)]["chamfer_l2"])
                                            for b in budgets[:-1] if str(b) in entry["budgets"]]
    out, best = [], float("inf")
    for t, c in sorted(pts):
        best = min(best, c)
        if out and out[-1][0] == t:
            out[-1] = (t, best)
        else:
            out.append((t, best))
    return out
