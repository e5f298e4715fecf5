"""The benchmark's section of ``docs/benchmarks.md``, written from its records as they are stored."""

from __future__ import annotations

from ...quality import closedness
from .._report import machine_line, markdown_table
from .curves import best_of_runs, slower_levels
from .problems import BLOCKING, BUDGETS, PROBLEMS, TARGETS
from .records import Records, RunKey, key_text, ordered

__all__ = ["render", "teapot_piece_names"]

# What the numbers are and how they were measured (the paragraph under the section's first line).
_METHODS_NOTE = (
    "Both targets normalised to unit bounding-box diagonal. Chamfer-L2 is the sum over both directions of "
    "the mean squared point-to-surface distance of 100,000 area-uniform samples (exact distances, seed 0); "
    "F-score at 1 % of the diagonal; NC = normal consistency; SI = self-intersecting face pairs of the "
    "result (the teapot target has its own, see the floor rows); inverted = faces whose normal points against "
    "the target's at the nearest target point; q = the smallest triangle quality; watertight = closed and "
    "edge-manifold (rows measured before these were recorded show '-'); area = the result's surface area over the "
    "target's (`area_ratio`: folds lying on the target add area and dilute the accuracy term). Time is "
    "optimisation wall time, single "
    "torch thread, metric evaluation excluded; each budget is a separate run whose schedule follows its "
    "budget (coarse-to-fine stages n/4, n, n with shares 0.25/0.45/0.3, learning rate decaying 10x). "
    "Each run uses one core of an otherwise idle machine, one run at a time, after a few warm-up steps of "
    "each method on a tiny problem (so that no timed run pays the process's one-off costs). Regularizer weights are the "
    "defaults stated for 2,500 vertices and scaled to each stage's vertex count, the first stage taking the "
    "second's (`reg_ref_vertices`; with stages n/4, n, n every stage uses n, and the Laplacian weight is 16x "
    "larger at 10k vertices). rbf is meshmei's default as `meshmei reconstruct` runs it: the step guard "
    "and the contact barrier on (issue 16), and the CLI's schedule: at 2.5k three levels as rbf-3levels "
    "below, at 10k (since 2026-11-29 17:00) four, the three-level schedule of 2,500 vertices and then one stage "
    "at 10k (stages 156, 625, 2,500, 2,500, 10,000 with shares 0.1/0.15/0.3/0.2/0.25, `default_stages(n, "
    "levels=4)`; the last stage with a fifth of the fine stages' Laplacian weight since 2026-11-30 15:00, as light "
    "as them before, and twice the run's Chamfer samples since 2026-12-01 07:49, `RBF_FOUR_LEVEL_OVERRIDES`); "
    "rbf-unguarded is rbf "
    "with two levels and neither (the default before issue 16); the peers and the other rbf variants run "
    "without guard or barrier. "
    "rbf-nolap is rbf without the Laplacian term "
    "(lr 2e-3), at 2.5k vertices only; largesteps-lr0.025 is large steps at half the default learning "
    "rate, at 10k vertices only. rbf-coarse is rbf with a second set of kernels at one vertex in 64, about 8 "
    "edges wide, with their own offsets (`coarse_ratio=64`). rbf-3levels and largesteps-3levels (10k vertices "
    "only) start one level coarser: stages n/16, n/4, n, n with shares 0.15/0.25/0.35/0.25 "
    "(`default_stages(n, levels=3)`); rbf-3levels has the Laplacian weight of 2,500 vertices (10) in the first "
    "two stages (`reg_ref_vertices`) and `w_laplacian=2.5` (40 after scaling, against the default 160) in "
    "the two 10k stages, and draws 5,000 Chamfer samples a step instead of 10,000 in its 625-vertex stage "
    "(`RBF_THREE_LEVEL_OVERRIDES`); since 2026-11-29 those overrides also pair target samples by normal in "
    "the 625-vertex stage and end the two coarse stages after at most 150 and 250 steps, what a 1,000-step run "
    "gives them, the rest of their share going to the fine stages (`normal_match`, `max_steps`): rbf has "
    "both, the rbf-3levels rows (2026-11-21) neither; since 2026-11-30 rbf's four levels at 10k also end "
    "their two 2,500-vertex stages after at most 350 and 250 steps (what the 2,500-vertex default run gives "
    "them). teapot starts from the torus placed with its hole through the handle, as "
    "`meshmei reconstruct --init torus` places it (`meshmei.reconstruct.openings.torus_through_opening`: the through-hole "
    "found by `find_opening`, the torus's axis along it, its hole twice the opening's clearance); "
    "teapot-centred from the centred torus (`--init torus-centred`), whose hole is where the teapot has none "
    "and whose surface must block the handle: it shows what that start costs (the membrane floor below)."
)


def teapot_piece_names(parts):
    """Name the four pieces of the teapot from their boxes: handle at -x, spout at +x, lid on top, body
    the largest."""
    left = min(parts, key=lambda p: p["bbox_max"][0])
    right = max(parts, key=lambda p: p["bbox_min"][0])
    rest = [p for p in parts if p is not left and p is not right]
    body = max(rest, key=lambda p: p["area_share"])
    lid = [p for p in rest if p is not body]
    named = {"handle": left, "spout": right, "body": body}
    if lid:
        named["lid"] = lid[0]
    return named


def _area(d):
    """The area ratio of a result or floor record, or '-' for records from before it was measured."""
    return f"{d['area_ratio']:.2f}" if "area_ratio" in d else "-"


def _fmt(x):
    return "-" if x is None else f"{x:.2e}"


def render(results, floors, quick, budgets=BUDGETS, membrane=None):
    """The markdown of the section "reconstruction" of ``docs/benchmarks.md``.

    Parameters
    ----------
    results, floors : dict
        As stored in ``docs/reconstruction_benchmark.json`` (keys ``"problem|n|variant"`` and ``"problem|n"``).
    quick : bool
        Say that the numbers come from a smoke run.
    budgets : tuple of float
        The time budgets (s) shown in the table, the longest last.
    membrane : dict or None
        Target name -> membrane floor record, as stored.

    Returns
    -------
    str
    """
    records = Records.from_json({"results": results, "floors": floors, "membrane": membrane})
    lines = ["Written by `python -m meshmei.benchmarks.reconstruct`. " + machine_line() + ".", "", _METHODS_NOTE, ""]
    if quick:
        lines.insert(0, "**Quick smoke run: budgets in seconds are tiny; numbers are not meaningful.**\n")
    lines += _runs_note(records.results)
    lines.append(_results_table(records.results, records.floors, budgets))
    for target, mf in sorted(records.membrane.items()):
        lines += ["", _membrane_note(records.results, target, mf)]
    lines += _targets_notes(records.results)
    lines += _levels_notes(records.results, budgets)
    lines += _parts_table(records.results, budgets)
    shown = [p for p in PROBLEMS if any(key.problem == p for key in records.results)]
    lines += ["", "Curves: " + ", ".join(f"`docs/reconstruction_{p}.png`" for p in shown)
              + ". Raw numbers: `docs/reconstruction_benchmark.json`."]
    return "\n".join(lines)


def _runs_note(results):
    """Which variants come from which run, when there is more than one (``--merge``)."""
    runs = {}
    for key, r in ordered(results):
        runs.setdefault(r.get("run", "an earlier run"), set()).add(key.variant)
    if len(runs) <= 1:
        return []
    return ["Rows from more than one run (`--merge`): " + "; ".join(
        f"{', '.join(sorted(v))} from {k}" for k, v in sorted(runs.items())) + ". Compare times within one run.", ""]


def _results_table(results, floors, budgets):
    """One row per configuration (Chamfer-L2 and self-intersections at every budget: a short budget's result
    can be folded where the long one is not; the rest at the longest), then the decimation floors."""
    T = f"{budgets[-1]:g} s"
    header = (["problem", "n", "method"] + [f"CD-L2 @{t:g} s" for t in budgets] + [f"SI @{t:g} s" for t in budgets]
              + [f"{c} @{T}" for c in _HEALTH] + [f"area @{T}", f"F @{T}", f"NC @{T}", f"steps @{T}"])
    rows = []
    for key, r in ordered(results):
        b = r["budgets"]
        last = b.get(str(budgets[-1]))
        rows.append(list(key) + [_fmt(b[str(t)]["chamfer_l2"]) if str(t) in b else "-" for t in budgets]
                    + [str(b[str(t)]["self_intersections"]) if str(t) in b else "-" for t in budgets]
                    + (_health(last) + [_area(last), f"{last['fscore']:.4f}", f"{last['normal_consistency']:.4f}",
                                        str(last["steps"])] if last else ["-"] * (len(_HEALTH) + 4)))
    for case, fl in floors.items():
        what = "target itself" if fl["chamfer_l2"] < 1e-15 else "decimated"
        pad = [""] * (len(budgets) - 1)
        rows.append(list(case) + [f"floor ({what}, {fl['faces']} faces)"] + pad + [_fmt(fl["chamfer_l2"])] + pad
                    + [str(fl["self_intersections"])] + _health(fl) + [_area(fl), f"{fl['fscore']:.4f}",
                                                                      f"{fl['normal_consistency']:.4f}", ""])
    return markdown_table(header, rows)


# The rest of a result's health beside its SI (records from before these were measured show "-").
_HEALTH = ["inverted", "q", "watertight"]


def _health(d) -> list:
    """Inverted faces, smallest triangle quality and watertight (yes, or what keeps it from it) of a record."""
    cells = [str(d["inverted_faces"]) if "inverted_faces" in d else "-",
             f"{d['min_quality']:.3f}" if "min_quality" in d else "-"]
    if "watertight" in d:
        cells.append("yes" if d["watertight"] else closedness(d["boundary_edges"], d["nonmanifold_edges"]))
    else:
        cells.append("-")
    return cells


def _membrane_note(results, target, mf):
    """What blocking the target's opening costs, and the check that every result that blocks it (from the
    centred torus) respects the bound at its own area."""
    text = (f"**What blocking the {target}'s opening costs** (`meshmei.benchmarks.reconstruct.membrane_floor`, "
            f"spacing {mf['spacing']:g}): a closed surface whose solid blocks the opening (a torus whose hole does "
            f"not go through it) crosses every line through the opening twice, at least as far from the {target} "
            f"as that line comes. That alone gives it accuracy of at least {mf['integral']:.2e} / its area: "
            f"{mf['accuracy']:.2e} at the {target}'s own area, {mf['integral'] / (2 * mf['target_area']):.2e} "
            f"at twice it. A lower bound that tightens as the spacing falls: {mf['limit']:.2e} at the {target}'s "
            f"area with spacing {mf['limit_spacing']:g}.")
    blocking = [p for p in BLOCKING if PROBLEMS[p][0] == target]
    ratios = [(r["budgets"][k]["accuracy"] * r["budgets"][k]["area_ratio"] * mf["target_area"] / mf["integral"],
               key, _opening_cut(r["budgets"][k]))
              for key, r in results.items() if key.problem in blocking for k in r["budgets"]
              if "area_ratio" in r["budgets"][k]]
    held = [(x, key) for x, key, cut in ratios if not cut]
    cut = [x for x, _, cut in ratios if cut]
    if held:
        lowest, key = min(held)
        text += (f" Check on the {len(held)} results from the centred torus with a recorded area that kept its "
                 f"topology: accuracy times area over the bound is at least {lowest:.2f} ({key_text(key, ', ')}), "
                 f"so none goes below it.")
    if cut:
        one = len(cut) == 1
        text += (f" The {len(cut)} result{'' if one else 's'} whose opening topology surgery cut (rbf since "
                 f"2026-11-30; docs/reconstruction.md, *Topology surgery*) no longer block{'s' if one else ''} it "
                 f"and {'is' if one else 'are'} not bound by it: the same ratio is {min(cut):.2f} to "
                 f"{max(cut):.2f} there.")
    return text


def _opening_cut(record) -> bool:
    """Whether a run's topology surgery cut a sheet (in the mesh or in a seal's voxels) in some stage."""
    return any(st.get("surgery", {}).get("perforated") or st.get("surgery", {}).get("carved")
               for st in record.get("info", {}).get("stages", []))


def _targets_notes(results):
    """The targets of the issue: rbf's best Chamfer-L2 on each problem against it."""
    lines = ["", "**Targets.**"]
    for prob, lim in TARGETS.items():
        best = [(r["budgets"][k]["chamfer_l2"], key) for key, r in results.items()
                if key.problem == prob and key.variant == "rbf" for k in r["budgets"]]
        if best:
            c, key = min(best)
            lines.append(f"- rbf on {prob}: best Chamfer-L2 {c:.2e} ({key.n_vertices} vertices) against the target "
                         f"{lim:.0e}: {'met' if c < lim else 'not met'}.")
    return lines


def _levels_notes(results, budgets):
    """Whether each variant reaches largesteps' Chamfer levels as early, on the longest run's curve and on the
    best of the runs."""
    head = (f"- Time to reach the Chamfer levels that largesteps reaches (its {budgets[-1]:g} s curve, "
            "evaluated at the first step past each of 1, 2, 5, 10, 20, 30, 50 and 70 s and at the end, plus "
            "the starting mesh at 0 s); 'yes' if the method gets to every such level at the same checkpoint "
            "as largesteps or an earlier one, else the levels where it is later. Two readings: the "
            f"longest run's curve alone, and the best of the runs (the lowest value reached by each "
            f"time over the {budgets[-1]:g} s curve and the ends of the shorter runs, for both methods: "
            "what a user who picks the budget for a level gets; the levels are then largesteps' own "
            "best of the runs). The area of each result along the curves is in the raw numbers "
            "(`metrics[i].area_ratio`):")
    extra = sorted({float(k) for r in results.values() for k in r["budgets"]} - set(budgets))
    if extra:
        which = [key_text(key, " ") for key, r in ordered(results) if {float(k) for k in r["budgets"]} - set(budgets)]
        head = head[:-1] + (f". Runs of {', '.join(f'{b:g}' for b in extra)} s count in the best of the "
                            f"runs too, for the configurations that have them ({', '.join(which)}):")
    lines = [head]
    for key, r in ordered(results):
        ls = results.get(key._replace(variant="largesteps"))
        if key.variant == "largesteps" or ls is None:
            continue
        lines += _level_lines(key, r, ls)
    return lines


def _level_lines(key: RunKey, r, ls):
    """The comparison of one configuration ``r`` with largesteps' ``ls`` on the same problem and count."""
    where = f"  - {key.problem}, {key.n_vertices} vertices, {key.variant}"
    if r.get("run") != ls.get("run"):
        return [f"{where}: not compared (measured in a different run from largesteps)"]
    lines = []
    for label, mine, ref in (("longest run", r["curve"], ls["curve"]),
                             ("best of the runs", best_of_runs(r), best_of_runs(ls))):
        late = slower_levels(mine, ref)
        if not late:
            lines.append(f"{where}, {label}: yes")
        else:
            shown = "; ".join(f"{c:.1e} at {t:.0f} s against {t_ls:.0f} s" for c, t, t_ls in late[:4])
            lines.append(f"{where}, {label}: no, later at {len(late)} of {len(ref)} "
                         f"levels ({shown}{'; ...' if len(late) > 4 else ''})")
    return lines


def _parts_table(results, budgets):
    """Where the teapot error sits at the longest budget, per piece of the teapot."""
    end = str(budgets[-1])
    parts = [(key, r["budgets"][end]) for key, r in ordered(results)
             if end in r["budgets"] and "by_part" in r["budgets"][end]]
    if not parts:
        return []
    rows = []
    for key, r_end in parts:
        pp = r_end["by_part"]
        named = teapot_piece_names(pp)
        acc = sum(p["accuracy"] for p in pp)
        comp = sum(p["completeness"] for p in pp)
        rows.append(list(key) + [str(r_end["self_intersections"]), _fmt(acc), _fmt(comp)]
                    + [f"{named[k]['accuracy']:.1e} ({named[k]['area_share']:.0%})"
                       for k in ("body", "lid", "spout", "handle")])
    return ["", f"**Where the teapot error sits** ({budgets[-1]:g} s results; "
            "`meshmei.metrics.error_by_part`: each result sample is charged to the teapot piece nearest "
            "to it, each teapot sample to its own piece).", "",
            markdown_table(["problem", "n", "method", "SI", "accuracy (result to teapot)", "completeness (teapot to result)",
                            "accuracy on body (area share)", "lid", "spout", "handle"], rows)]
