"""Valid steps (issue 16): what the guarantee costs per step, and what 3D-MEIs reach with it.

Run: ``python -m meshmei.benchmarks.validity [--steps 300] [--cells 8]``; writes the "validity" section of
``docs/benchmarks.md``.

- Cost: seconds per step with ``valid_steps`` on and off, in one process, alternating, for the 3D-MEI at
  64 px and 400 vertices and for reconstruction (rbf, sphere to bunny) at 2,500 and 10,000 vertices.
- 3D-MEIs: simple and complex Gabor cells over a spread of orientations, frequencies, positions, sizes and
  phases that no test uses, from sheet, sphere and torus: the fraction of the bound (best of the default
  seeds) and the result's health, with the guard on and off.
"""

from __future__ import annotations

import argparse
import math
import os
import time

import torch

from meshmei.benchmarks._report import machine_line, markdown_table, write_section
from meshmei.encoders import GaborComplexCell, GaborSimpleCell
from meshmei.mei import MEISettings, optimize_mei
from meshmei.quality import health_report
from meshmei.reconstruct import reconstruct
from meshmei.shapes import initial_mesh


def _median(xs):
    xs = sorted(xs)
    return xs[len(xs) // 2]


def _step_times(history, skip=5):
    t = [h["time"] for h in history]
    return [b - a for a, b in zip(t[:-1], t[1:])][skip:]


def mei_cost(steps: int = 60) -> list:
    """Median ms per 3D-MEI step (64 px, 400 vertices, sphere, simple cell), guard on and off, alternating."""
    times = {True: [], False: []}
    for _ in range(3):
        for on in (False, True):
            res = optimize_mei(GaborSimpleCell(), 0, "sphere", steps=steps, seeds=(0,), valid_steps=on)
            dt = [b - a for a, b in zip(res.time_history[:-1], res.time_history[1:])][5:]
            times[on].append(_median(dt))
    off, on = _median(times[False]), _median(times[True])
    return ["3D-MEI, 64 px, 400 vertices", f"{1000 * off:.1f}", f"{1000 * on:.1f}", f"{on / off:.2f}"]


def reconstruction_cost(n_vertices: int, steps: int = 40) -> list:
    """Median ms per reconstruction step (rbf, one stage), guard on and off, alternating, and the guard's share."""
    src = initial_mesh("sphere", n_vertices=n_vertices)
    times = {True: [], False: []}
    for _ in range(2):
        for on in (False, True):
            res = reconstruct(src, "bunny", "rbf", steps=steps, valid_steps=on, eval_samples=2000)
            times[on].append(_median(_step_times(res.history)))
    off, on = _median(times[False]), _median(times[True])
    return [f"reconstruction rbf, {src[0].shape[0]} vertices", f"{1000 * off:.1f}", f"{1000 * on:.1f}",
            f"{on / off:.2f}"]


def cells(n: int) -> list:
    """``n`` Gabor cells (alternately simple and complex) spread over the parameters, none a test's."""
    g = torch.Generator().manual_seed(16)
    out = []
    for i in range(n):
        u = torch.rand(6, generator=g, dtype=torch.float64).tolist()
        params = dict(x0=0.4 * (u[0] - 0.5), y0=0.4 * (u[1] - 0.5), orientation=math.pi * u[2],
                      frequency=2.5 + 2.5 * u[3], sigma=0.25 + 0.2 * u[4], phase=2 * math.pi * u[5])
        kind = GaborSimpleCell if i % 2 == 0 else GaborComplexCell
        out.append((kind.__name__.replace("Gabor", "").replace("Cell", "").lower(), params, kind(**params)))
    return out


def mei_outcomes(n_cells: int, steps: int) -> list:
    rows = []
    for name, params, cell in cells(n_cells):
        for init in ("sheet", "sphere", "torus"):
            row = [name, ", ".join(f"{k} {v:.2f}" for k, v in params.items()), init]
            for on in (True, False):
                t = time.perf_counter()
                res = optimize_mei(cell, 0, init, MEISettings(steps=steps, valid_steps=on))
                h = health_report(res.V, res.F, res.V0)
                row += [f"{res.activation:.3f}", h["self_intersections"], h["flipped_faces"], f"{h['min_quality']:.3f}",
                        f"{time.perf_counter() - t:.0f}"]
            rows.append(row)
            print(rows[-1], flush=True)
    return rows


def run(steps: int, n_cells: int):
    load = os.getloadavg()[0]
    cost = [mei_cost()] + [reconstruction_cost(n) for n in (2500, 10000)]
    for r in cost:
        print(r, flush=True)
    outcomes = mei_outcomes(n_cells, steps)
    on = [float(r[3]) for r in outcomes]
    body = "\n".join([
        "## Valid steps (`python -m meshmei.benchmarks.validity`)",
        "",
        f"Machine: {machine_line()}; 1-minute load average at the start {load:.1f}.",
        "",
        "Cost of the guarantee: median seconds per step with `valid_steps` off and on (same process, runs "
        "alternated; the check is libigl's exact self-intersection test over an AABB tree, the triangle "
        "quality and the face turn, after every step, plus the halvings of refused steps).",
        "",
        markdown_table(["problem", "ms/step off", "ms/step on", "ratio"], cost),
        "",
        f"3D-MEIs of {n_cells} Gabor cells (parameters drawn once, seed 16) from three starts, default "
        f"`MEISettings` ({steps} steps, seeds 0, 1, 2, best kept), with the guard on and off. Response = "
        "fraction of the upper bound; SI = self-intersecting face pairs; flipped = faces flipped against "
        "the start; q = minimum triangle quality; s = wall time.",
        "",
        markdown_table(["cell", "parameters", "start", "on: response", "on: SI", "on: flipped", "on: q", "on: s",
                        "off: response", "off: SI", "off: flipped", "off: q", "off: s"], outcomes),
        "",
        f"With the guard: {sum(1 for r in outcomes if r[4] == 0 and r[5] == 0)} of {len(outcomes)} results "
        f"have no self-intersection and no flipped face; {sum(1 for x in on if x >= 0.95)} of {len(on)} "
        f"reach 0.95 of the bound (lowest {min(on):.3f}).",
    ])
    return write_section("validity", body)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=MEISettings.steps)
    ap.add_argument("--cells", type=int, default=6)
    args = ap.parse_args(argv)
    t = time.perf_counter()
    print(f"wrote {run(args.steps, args.cells)} in {time.perf_counter() - t:.0f} s")


if __name__ == "__main__":
    main()
