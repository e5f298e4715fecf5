"""Running the reconstruction benchmark: its command line, the runs of each configuration, and their records."""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import dataclass

import numpy as np
import torch

from ...metrics import error_by_part, surface_metrics
from ...reconstruct import reconstruct, source_mesh
from ...shapes import initial_mesh, target_mesh
from ...shapes.remeshing import mesh_arrays
from .._report import docs_dir, keep_docs_for_full_runs, write_section
from .curves import CHECKPOINTS
from .figures import plot
from .membrane import membrane_floor
from .problems import BUDGETS, PROBLEMS, RESOLUTIONS, VARIANTS, variant_settings
from .rbf_cost import rbf_cost
from .report import render
from .records import Records, RunKey

__all__ = ["main", "start_mesh", "decimation_floor", "warm_up"]

DESCRIPTION = ("Reconstruction benchmark: sphere -> bunny and torus -> teapot, each method, Chamfer-L2 / F-score / "
               "normal consistency against wall time, at about 2.5k and 10k vertices, with the decimation floor.")


def start_mesh(init, n_vertices, Vt, Ft):
    """The starting mesh of a problem: a name of :data:`meshmei.reconstruct.SOURCE_NAMES`, placed for the
    target as ``meshmei reconstruct --init`` places it (:func:`meshmei.reconstruct.source_mesh`)."""
    return source_mesh(init, n_vertices=n_vertices, target=(Vt, Ft))


def decimation_floor(Vt, Ft, n_faces, *, n_samples=100_000):
    """Metrics of the target decimated (pymeshlab quadric edge collapse) to ``n_faces`` faces."""
    import pymeshlab  # deferred on purpose: a heavy optional dependency, needed for the floors only

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=Vt.double().numpy(), face_matrix=Ft.numpy().astype(np.int32)))
    # every parameter named: pymeshlab keeps a parameter's last value as its default for the whole process
    ms.meshing_decimation_quadric_edge_collapse(targetfacenum=int(n_faces), targetperc=0.0, qualitythr=0.3,
                                                preserveboundary=True, boundaryweight=1.0, preservenormal=True,
                                                preservetopology=False, optimalplacement=True, planarquadric=False,
                                                planarweight=0.001, qualityweight=False, autoclean=True, selected=False)
    V, F = (torch.as_tensor(x) for x in mesh_arrays(ms.current_mesh()))
    return surface_metrics(V, F, Vt.double(), Ft, n_samples=n_samples), int(V.shape[0]), int(F.shape[0])


def warm_up(methods):
    """Run each method for a few steps on a tiny problem, so that the first timed run does not pay the
    process's one-off costs (library loading, first calls into pymeshlab, scipy and torch: about a second,
    which is a tenth of the 10 s budget)."""
    Vt, Ft = target_mesh("bunny")
    src = initial_mesh("sphere", n_vertices=300)
    for method in sorted(methods):
        reconstruct(src, (Vt, Ft), method, steps=4, stages=(100, 300), n_samples=500, target_pool=2000,
                    eval_samples=500)


def _parser():
    ap = argparse.ArgumentParser(prog="python -m meshmei.benchmarks.reconstruct", description=DESCRIPTION)
    ap.add_argument("--quick", action="store_true", help="tiny budgets, to check that the script runs")
    ap.add_argument("--extra-budgets", default="",
                    help="comma-separated seconds below the longest budget, e.g. 50,70: more runs of each "
                         "configuration, whose ends enter the best-of-runs reading of the levels (not the table)")
    ap.add_argument("--rbf-cost", action="store_true", help="only the RBF cost table (section reconstruction-rbf-cost)")
    ap.add_argument("--merge", action="store_true",
                    help="keep results of configurations not re-run from docs/reconstruction_benchmark.json")
    ap.add_argument("--render-only", action="store_true",
                    help="rewrite the section and plots from docs/reconstruction_benchmark.json without running")
    ap.add_argument("--skip-existing", action="store_true",
                    help="with --merge, do not re-run configurations already in the JSON")
    ap.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated subset of " + ", ".join(VARIANTS))
    ap.add_argument("--problems", default=",".join(PROBLEMS), help="comma-separated subset of " + ", ".join(PROBLEMS))
    ap.add_argument("--resolutions", default=",".join(map(str, RESOLUTIONS)),
                    help="comma-separated subset of " + ", ".join(map(str, RESOLUTIONS)))
    return ap


@dataclass(frozen=True)
class _Plan:
    """What one invocation runs."""

    quick: bool
    budgets: tuple  # the table's, the longest last
    runs: tuple  # the budgets and the extra ones, the longest last: it gives the curve
    resolutions: tuple
    eval_samples: int
    variants: list
    problems: list


def _plan(ap, args) -> _Plan:
    """Read and check the options (``ap.error`` exits with status 2 before anything runs)."""
    budgets = (1.0, 2.0, 3.0) if args.quick else BUDGETS
    try:
        extra = tuple(float(b) for b in args.extra_budgets.split(",") if b.strip())
    except ValueError:
        ap.error(f"--extra-budgets must be comma-separated seconds, got {args.extra_budgets!r}")
    if any(not 0 < b < budgets[-1] for b in extra):
        ap.error(f"--extra-budgets must lie between 0 and the longest budget ({budgets[-1]:g} s), got {extra}")
    try:
        chosen = tuple(int(r) for r in args.resolutions.split(","))
    except ValueError:
        ap.error(f"--resolutions must be comma-separated integers, got {args.resolutions!r}")
    if any(r not in RESOLUTIONS for r in chosen):
        ap.error(f"--resolutions must be among {RESOLUTIONS}, got {args.resolutions!r}")
    if args.quick and args.resolutions != ",".join(map(str, RESOLUTIONS)):  # it was dropped silently
        ap.error("--quick runs at 300 vertices; --resolutions applies to full runs")
    names = [v.strip() for v in args.variants.split(",")]
    problems = [p.strip() for p in args.problems.split(",")]
    for bad in [x for x in names if x not in VARIANTS] + [x for x in problems if x not in PROBLEMS]:
        ap.error(f"unknown variant or problem {bad!r}")
    return _Plan(quick=args.quick, budgets=budgets, runs=tuple(sorted(set(budgets) | set(extra))),
                 resolutions=(300,) if args.quick else chosen, eval_samples=5000 if args.quick else 100_000,
                 variants=names, problems=problems)


def _membrane_record(Vt, Ft) -> dict:
    """What the centred torus's start costs on the teapot: its hole cannot pass through the handle."""
    mf = membrane_floor(Vt.double(), Ft, spacing=0.001)
    limit = membrane_floor(Vt.double(), Ft, spacing=0.0005)
    return dict(integral=mf.integral, accuracy=mf.accuracy(), opening_area=mf.opening_area,
                target_area=mf.target_area, spacing=mf.spacing, limit=limit.accuracy(), limit_spacing=limit.spacing)


class _Benchmark:
    """One invocation's runs, and the records they go into (written after every configuration, so that an
    interrupted run still leaves its numbers)."""

    def __init__(self, plan: _Plan, records: Records, out, *, skip_existing: bool):
        self.plan, self.records, self.out, self.skip_existing = plan, records, out, skip_existing
        self.floors_done, self.membrane_done = set(), set()  # measured again in every run (records gain fields)
        # which run wrote an entry (--merge keeps older ones), with the 1-minute load average at its start
        self.run_label = f"{time.strftime('%Y-%m-%d %H:%M')} (load {os.getloadavg()[0]:.1f})"
        self.t_all = time.perf_counter()

    def problem(self, prob):
        """Every chosen resolution and variant of problem ``prob``."""
        target, init = PROBLEMS[prob]
        Vt, Ft = target_mesh(target)
        if target == "teapot" and target not in self.membrane_done and not self.plan.quick:
            self.membrane_done.add(target)
            self.records.membrane[target] = _membrane_record(Vt, Ft)
        for n in self.plan.resolutions:
            src = start_mesh(init, n, Vt, Ft)
            start = surface_metrics(*src, Vt, Ft, n_samples=self.plan.eval_samples, health=False).chamfer_l2
            for name in self.plan.variants:
                key = RunKey(prob, n, name)
                only = VARIANTS[name].resolutions
                if only is not None and n not in only and not self.plan.quick:
                    continue  # shown at one resolution only, to bound the run time
                if self.skip_existing and key in self.records.results:
                    continue
                self.records.results[key] = self.configuration(key, src, (Vt, Ft), start)
                self.save()

    def configuration(self, key: RunKey, src, target, start: float) -> dict:
        """The record of one configuration: a run at each budget, the longest evaluated along the way."""
        entry = {"budgets": {}, "curve": [], "metrics": [], "run": self.run_label}
        method, settings = VARIANTS[key.variant].method, variant_settings(key.variant, key.n_vertices)
        for budget in self.plan.runs:
            last = budget == self.plan.runs[-1]
            evals = tuple(t for t in CHECKPOINTS[1:] if t < budget) if last else ()
            res = reconstruct(src, target, method, time_budget=budget, eval_times=evals,
                              eval_samples=self.plan.eval_samples, **settings)
            f = res.final.as_dict()
            f.update(steps=len(res.history), wall_time=res.wall_time, n_vertices=int(res.V.shape[0]),
                     n_faces=int(res.F.shape[0]), info=res.info)
            entry["budgets"][str(budget)] = f
            if last:
                self._longest(key, entry, res, target, start)
            print(f"{key.problem} {key.n_vertices} {key.variant} {budget:g}s: {len(res.history)} steps, "
                  f"CD {f['chamfer_l2']:.3e}, F {f['fscore']:.4f}, NC {f['normal_consistency']:.4f}, "
                  f"SI {f['self_intersections']} [{time.perf_counter() - self.t_all:.0f} s elapsed]", flush=True)
        return entry

    def _longest(self, key: RunKey, entry, res, target, start):
        """What only the longest run records: the curve, the teapot's error by piece, the decimation floor."""
        Vt, Ft = target
        if PROBLEMS[key.problem][0] == "teapot":
            # which piece of the teapot the remaining error sits on
            entry["budgets"][str(self.plan.runs[-1])]["by_part"] = error_by_part(
                res.V, res.F, Vt, Ft, n_samples=self.plan.eval_samples)
        entry["metrics"] = res.metrics
        # every method starts from the same mesh at time 0
        entry["curve"] = [(0.0, start)] + [(m["time"], m["chamfer_l2"]) for m in res.metrics]
        entry["settings"] = res.to_json()["settings"]
        if key.case not in self.floors_done:
            self.floors_done.add(key.case)
            fl, nv, nf = decimation_floor(Vt, Ft, res.F.shape[0], n_samples=self.plan.eval_samples)
            self.records.floors[key.case] = dict(fl.as_dict(), vertices=nv, faces=nf)

    def save(self):
        """Write the JSON, then the section and figures from what was written."""
        raw = self.records.save(self.out / "reconstruction_benchmark.json")
        write_section("reconstruction", render(raw["results"], raw["floors"], self.plan.quick, self.plan.budgets,
                                               raw["membrane"]))
        plot(raw["results"], raw["floors"], self.out)


def main(argv=None):
    ap = _parser()
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    if args.render_only or args.rbf_cost:  # they read none of the run's options: refuse them, not drop them
        run_options = ("variants", "problems", "resolutions", "extra_budgets", "merge", "skip_existing")
        given = [f"--{o.replace('_', '-')}" for o in run_options if getattr(args, o) != ap.get_default(o)]
        if given:
            ap.error(f"{'--render-only' if args.render_only else '--rbf-cost'} takes none of {', '.join(given)}")
    else:
        plan = _plan(ap, args)  # checked before anything is made or written
    published = docs_dir()
    keep_docs_for_full_runs(args.quick)  # every --quick mode: a smoke run must not overwrite the published numbers
    if args.render_only:
        raw = Records.load(published / "reconstruction_benchmark.json").to_json()
        write_section("reconstruction", render(raw["results"], raw["floors"], args.quick, membrane=raw["membrane"]))
        plot(raw["results"], raw["floors"], docs_dir())
        return
    if args.rbf_cost:
        rbf_cost(args.quick)
        return
    out = docs_dir()
    out.mkdir(parents=True, exist_ok=True)
    raw_path = out / "reconstruction_benchmark.json"
    # --merge keeps the configurations not re-run now, so a subset (--variants) can be refreshed on its own
    records = Records.load(raw_path) if args.merge and raw_path.exists() else Records()
    warm_up({VARIANTS[name].method for name in plan.variants})
    bench = _Benchmark(plan, records, out, skip_existing=args.skip_existing)
    for prob in plan.problems:
        bench.problem(prob)
    print(f"done in {time.perf_counter() - bench.t_all:.0f} s; wrote {out / 'benchmarks.md'}")
