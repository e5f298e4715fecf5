"""3D-MEI optimisation curves on simulated cells (fraction of the bound vs step and wall time), 3D-MEI vs
pixel MEI, and the time per step at 64 x 64 and 128 x 128.

Run: ``python -m meshmei.benchmarks.mei [--steps 400] [--seeds 0]``; writes the "mei" section of
``docs/benchmarks.md`` and ``docs/figures/mei_curves.png``, ``docs/figures/mei_vs_pixel.png``.

Each optimisation (a cell's 3D-MEI from a start, a cell's pixel MEI, the demo neuron's runs, a start's weight
grid) is saved as it finishes (``docs/.mei.partial.json``, :class:`~meshmei.benchmarks._report.FinishedRows`):
the same command run again after an interruption takes them (unless meshmei's source has changed since, or
with ``--restart``) and says so in the section; the time-per-step table is always this run's.
"""

from __future__ import annotations

import time
from dataclasses import replace

import torch

from meshmei.benchmarks._report import (HEALTH_COLUMNS, HEALTH_LEGEND, FinishedRows, add_restart, benchmark_parser,
                                        docs_dir, health_cells, machine_line, markdown_table, write_section)
from meshmei.encoders import DEMO_MODEL_PATH, GaborComplexCell, GaborSimpleCell, load_demo_model
from meshmei.mei import MEISettings, grid_search, optimize_mei, pixel_mei, random_mesh_responses


def _first(xs, ts, level):
    for x, t in zip(xs, ts):
        if x >= level:
            return t
    return None


def _fmt(x, spec=".3f"):
    return "-" if x is None else format(x, spec)


def time_per_step(image_size: int, n_vertices: int, steps: int = 30) -> tuple[float, float]:
    """Median and minimum seconds per step; the minimum is the cost on an otherwise idle machine."""
    res = optimize_mei(GaborSimpleCell(), 0, "sphere", steps=steps, seeds=(0,), image_size=image_size,
                       n_vertices=n_vertices)
    ts = torch.tensor([0.0] + res.time_history)
    dt = (ts[1:] - ts[:-1])[5:]  # skip the first steps (allocator warm-up)
    return float(dt.median()), float(dt.min())


def cell_runs(settings: MEISettings, pixel_steps: int, finished: FinishedRows | None = None) -> tuple[dict, list, list]:
    """Simple and complex cells from sheet and sphere: curves, table rows, and 3D-vs-pixel bars; each pixel MEI
    and 3D-MEI kept in ``finished`` as it ends."""
    finished = finished or FinishedRows(None)
    curves, rows, bars = {}, [], []
    for cname, cell in (("simple", GaborSimpleCell()), ("complex", GaborComplexCell())):
        pm = finished.get(f"pixel|{cname}|{settings.image_size}|{pixel_steps}", lambda: dict(
            activation=pixel_mei(cell, 0, image_size=settings.image_size, steps=pixel_steps).activation))
        for init in ("sheet", "sphere"):
            def one():
                res = optimize_mei(cell, 0, init, settings)
                return dict(activation=res.activation, history=res.history, time_history=res.time_history,
                            seconds_per_step=res.seconds_per_step, health=res.health())
            res = finished.get(f"3d|{cname}|{init}|{settings.steps}|{list(settings.seeds)}", one)
            h = res["history"]
            best = [max(h[: i + 1]) for i in range(len(h))]
            curves[(cname, init)] = (h, res["time_history"])
            rows.append([cname, init, f"{res['activation']:.3f}", f"{max(h):.3f}",
                         _fmt(_first(best, range(1, len(h) + 1), 0.9), "d"),
                         _fmt(_first(best, res["time_history"], 0.9), ".1f"),
                         _fmt(_first(best, range(1, len(h) + 1), 0.95), "d"),
                         f"{1000 * res['seconds_per_step']:.0f}", *health_cells([res["health"]]),
                         f"{pm['activation']:.4f}"])
            bars.append((f"{cname}\n{init}", res["activation"], pm["activation"]))
            print(rows[-1], flush=True)
    return curves, rows, bars


def demo_run(settings: MEISettings, pixel_steps: int, bars: list, finished: FinishedRows | None = None) -> str:
    """The demo model's neuron 0 against random deformed spheres and its pixel MEI (a line; adds a bar); the
    three kept in ``finished`` together when they end."""
    if not DEMO_MODEL_PATH.is_file():
        return ""

    def one():
        model = load_demo_model()
        rand = random_mesh_responses(model, 0, "sphere", 1000, settings)
        res = optimize_mei(model, 0, "sphere", settings)
        pm = pixel_mei(model, 0, image_size=settings.image_size, steps=pixel_steps)
        return dict(random_max=float(rand.max()), random_median=float(rand.median()), activation=res.activation,
                    pixel_activation=pm.activation)
    r = (finished or FinishedRows(None)).get(f"demo|{settings.steps}|{list(settings.seeds)}|{pixel_steps}", one)
    bars.append(("demo n0\nsphere", r["activation"], r["pixel_activation"]))
    line = (f"Demo model neuron 0 (sphere start): best of 1000 random deformed spheres "
            f"{r['random_max']:.3f} (median {r['random_median']:.3f}), 3D-MEI {r['activation']:.3f}, "
            f"pixel MEI {r['pixel_activation']:.3f}.")
    print(line, flush=True)
    return line


def plot(curves: dict, bars: list, out_dir) -> None:
    """``mei_curves.png`` (fraction of the bound against step and time) and ``mei_vs_pixel.png``."""
    from matplotlib.figure import Figure  # deferred: only the benchmark draws

    fig = Figure(figsize=(10, 3.6))
    axes = fig.subplots(1, 2)
    for (cname, init), (h, ts) in curves.items():
        ls = "-" if cname == "simple" else "--"
        axes[0].plot(range(1, len(h) + 1), h, ls, label=f"{cname} cell, {init}")
        axes[1].plot(ts, h, ls, label=f"{cname} cell, {init}")
    for ax, xl in zip(axes, ("step", "wall time (s)")):
        ax.axhline(1.0, color="k", lw=0.5)
        ax.axhline(0.9, color="gray", lw=0.5, ls=":")
        ax.set_xlabel(xl)
        ax.set_ylabel("fraction of upper bound")
        ax.set_ylim(0, 1.02)
    axes[0].legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(out_dir / "mei_curves.png", dpi=120)
    fig = Figure(figsize=(1.4 * len(bars) + 1, 3.4))
    ax = fig.subplots()
    x = torch.arange(len(bars)).float()
    ax.bar(x - 0.2, [b[1] for b in bars], 0.4, label="3D-MEI")
    ax.bar(x + 0.2, [b[2] for b in bars], 0.4, label="pixel MEI")
    ax.set_xticks(x.tolist(), [b[0] for b in bars], fontsize=8)
    ax.set_ylabel("response")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out_dir / "mei_vs_pixel.png", dpi=120)


def grid_rows(settings: MEISettings, finished: FinishedRows | None = None) -> list:
    """Regularizer-weight grid on the complex cell (200 steps, seed 0, edge weight 30); each start's grid kept
    in ``finished`` when it ends."""
    finished = finished or FinishedRows(None)
    rows = []
    for init in ("sphere", "sheet"):
        def one():
            grid = grid_search(GaborComplexCell(), 0, init, {"laplacian": [0.0, 30.0, 100.0], "area": [0.0, 1000.0]},
                               replace(settings, steps=200, seeds=(0,), weights={"edge": 30.0}))
            return [dict(weights=r["weights"], activation=r["activation"], health={
                k: v for k, v in r.items() if k not in ("weights", "activation", "fraction_of_bound", "seconds")})
                for r in grid]
        for r in finished.get(f"grid|{init}", one):
            w = r["weights"]
            rows.append([init, w["laplacian"], w["edge"], w["area"], f"{r['activation']:.3f}",
                         f"{r['health']['mean_quality']:.3f}", *health_cells([r["health"]])])
            print(rows[-1], flush=True)
    return rows


def speed_rows() -> list:
    rows = []
    for size, nv in ((64, 400), (64, 1500), (128, 400), (128, 1500)):
        med, low = time_per_step(size, nv)
        rows.append([f"{size} x {size}", nv, f"{1000 * med:.1f}", f"{1000 * low:.1f}"])
        print(rows[-1], flush=True)
    return rows


def run(steps: int = 400, seeds=(0,), pixel_steps: int = 200, out_dir=None, restart: bool = False):
    out_dir = out_dir or docs_dir() / "figures"
    out_dir.mkdir(parents=True, exist_ok=True)
    finished = FinishedRows("mei", restart)
    settings = MEISettings(steps=steps, seeds=tuple(seeds))
    curves, rows, bars = cell_runs(settings, pixel_steps, finished)
    demo_line = demo_run(settings, pixel_steps, bars, finished)
    plot(curves, bars, out_dir)
    grid, speed = grid_rows(settings, finished), speed_rows()
    body = "\n".join([
        "## 3D-MEI on simulated cells (`python -m meshmei.benchmarks.mei`)",
        "",
        f"Machine: {machine_line()}.{finished.note()}",
        f"Default `MEISettings` ({settings.n_vertices}-vertex initial mesh, {settings.image_size} x "
        f"{settings.image_size} image, RBF on every vertex, weights {settings.weights}), {steps} steps, "
        f"seeds {list(seeds)}; the response of a Gabor cell is its fraction of the upper bound 1. "
        "'steps/s to 0.9' count until the best response so far first reaches 0.9; " + HEALTH_LEGEND + ".",
        "",
        markdown_table(["cell", "init", "final", "best", "steps to 0.9", "s to 0.9", "steps to 0.95", "ms/step",
                        *HEALTH_COLUMNS, "pixel MEI"], rows),
        "",
        demo_line,
        "",
        "![curves](figures/mei_curves.png)",
        "",
        "![3D vs pixel MEI](figures/mei_vs_pixel.png)",
        "",
        "Grid search over regularizer weights (`grid_search`; complex cell, 200 steps, seed 0, edge weight 30):",
        "",
        markdown_table(["init", "laplacian", "edge", "area", "response", "mean tri quality", *HEALTH_COLUMNS],
                       grid),
        "",
        "Time per optimisation step (render + encoder + regularizers + backward + Adam; sphere, simple cell):",
        "",
        markdown_table(["image", "vertices", "median ms/step", "min ms/step"], speed),
        "",
        "The machine is shared: wall times (the 'ms/step' and 's to 0.9' columns, the median) include waiting "
        "for other processes; the minimum is the better estimate of the cost itself.",
    ])
    path = write_section("mei", body)
    finished.close()
    return path


def main(argv=None):
    ap = benchmark_parser(__file__, __doc__)
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--pixel-steps", type=int, default=200)
    add_restart(ap)
    args = ap.parse_args(argv)
    t = time.perf_counter()
    path = run(args.steps, tuple(args.seeds), args.pixel_steps, restart=args.restart)
    print(f"wrote {path} in {time.perf_counter() - t:.0f} s")


if __name__ == "__main__":
    main()
