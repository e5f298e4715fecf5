"""The same 3D-MEI settings at 400 and 2,500 vertices (issue 16, resolution-aware defaults).

Run: ``python -m meshmei.benchmarks.resolution [--steps 300] [--sizes 400,2500]``; writes the "resolution"
section of ``docs/benchmarks.md``. For a simple and a complex Gabor cell (the built-in cells' neuron 0), from
the sheet and from the sphere, seed 0, 64 px, the guard on: each vertex count with the regularizer weights as
given (``reg_ref_vertices=None``), with the weights stated for 400 vertices and scaled to the mesh
(``reg_ref_vertices=400, lr_by_edge=False``), and, the default, scaled with the offsets' learning rate shrunk
with the edge length as well (``lr * sqrt(400 / n)``). Reported: the fraction of the cell's bound, the health
of the result (self-intersecting pairs, flipped faces, minimum triangle quality, watertight, manifold), the
steps the guard refused and the wall time.

Each run is saved as it finishes (``docs/.resolution.partial.json``,
:class:`~meshmei.benchmarks._report.FinishedRows`): the same command run again after an interruption takes
them (unless meshmei's source has changed since, or with ``--restart``) and says so in the section.
"""

from __future__ import annotations

import os
import time

from meshmei.benchmarks._report import (HEALTH_COLUMNS, HEALTH_LEGEND, FinishedRows, add_restart, benchmark_parser,
                                        health_cells, int_list, machine_line, markdown_table, write_section)
from meshmei.encoders import make_encoder
from meshmei.mei import MEISettings, optimize_mei

REF = 400
VARIANTS = {
    "as given": dict(reg_ref_vertices=None),
    "scaled": dict(reg_ref_vertices=REF, lr_by_edge=False),
    "scaled, lr by edge (default)": dict(reg_ref_vertices=REF),
}


def run(steps: int, sizes: list[int], starts=("sheet", "sphere"), cells=("gabor-simple", "gabor-complex"),
        restart: bool = False) -> str:
    load = os.getloadavg()[0]
    finished = FinishedRows("resolution", restart)
    rows, spread = [], {}
    for cell in cells:
        enc = make_encoder(cell)
        for start in starts:
            for name, kw in VARIANTS.items():
                for n in sizes:
                    if n == REF and name != "as given":
                        continue  # every variant is the same run at the reference count
                    def one():
                        t0 = time.perf_counter()
                        res = optimize_mei(enc, 0, start, MEISettings(n_vertices=n, steps=steps, seeds=(0,), **kw))
                        secs = time.perf_counter() - t0
                        g = res.extra.get("guard") or {}
                        return dict(fraction_of_bound=res.fraction_of_bound, vertices=res.V.shape[0],
                                    health=res.health(), refused=g.get("refused", "-"), seconds=secs)
                    r = finished.get(f"{cell}|{start}|{name}|{n}|{steps}", one)
                    frac = r["fraction_of_bound"]
                    label = name if n != REF else "(all)"
                    rows.append([cell, start, n, r["vertices"], label, f"{frac:.3f}", *health_cells([r["health"]]),
                                 r["refused"], f"{r['seconds']:.0f}"])
                    print(rows[-1], flush=True)
                    for v in VARIANTS if n == REF else (name,):
                        spread.setdefault((cell, start, v), []).append(frac)
    lines = []
    for v in VARIANTS:
        gaps = [max(f) - min(f) for (c, s, name), f in spread.items() if name == v]
        lines.append(f"- {v}: the largest spread of the fraction of the bound over the sizes, per cell and start, "
                     f"{max(gaps):.3f} (mean {sum(gaps) / len(gaps):.3f}).")
    body = "\n".join([
        "## The same settings at other vertex counts (`python -m meshmei.benchmarks.resolution`)",
        "",
        f"Machine: {machine_line()}; 1-minute load average at the start {load:.1f}.{finished.note()}",
        "",
        f"Built-in cells' neuron 0 (simple and complex Gabor cells), 64 px, seed 0, {steps} steps from either "
        "start, the guard and the default barriers on. n = the requested vertex count (the start's own in "
        "the next column); weights 'as given' = `reg_ref_vertices=None`; 'scaled' = the default weights stated "
        f"for {REF} vertices and scaled to n (`reg_ref_vertices={REF}, lr_by_edge=False`: Laplacian and area by "
        f"(n/{REF})^2, edge and ARAP by n/{REF}); 'lr by edge' (the default since issue 16) also shrinks the "
        f"offsets' learning rate as the edge length, `lr * sqrt({REF} / n)`. At {REF} vertices the three are "
        f"the same run. Response = fraction of the cell's bound; {HEALTH_LEGEND}; refused = candidate steps "
        "the guard refused; s = wall time.",
        "",
        markdown_table(["cell", "start", "n", "vertices", "weights", "response", *HEALTH_COLUMNS, "refused", "s"],
                       rows),
        "",
        *lines,
    ])
    path = write_section("resolution", body)
    finished.close()
    return path


def main(argv=None):
    ap = benchmark_parser(__file__, __doc__)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--sizes", type=int_list, default="400,2500")
    add_restart(ap)
    args = ap.parse_args(argv)
    t = time.perf_counter()
    print(f"wrote {run(args.steps, args.sizes, restart=args.restart)} in {time.perf_counter() - t:.0f} s")


if __name__ == "__main__":
    main()
