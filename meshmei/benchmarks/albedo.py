"""Shape + albedo 3D-MEIs against the pixel MEI (issue 19): the demo model's neurons.

Run: ``python -m meshmei.benchmarks.albedo [--neurons 0,1,3,6,9]``; writes the "albedo" section of
``docs/benchmarks.md``. For each neuron, in the same image space (the demo model's 64 px): the pixel MEI
(defaults), the shape-only 3D-MEI (the paper's setting, defaults) and the shape + albedo 3D-MEI (defaults
with ``albedo=True``: a 64 x 64 texture over the sheet's grid, the shape at its full learning rate), and
the same with the shape at a tenth of its learning rate, from the sheet.

Each of a neuron's four runs is saved as it finishes (``docs/.albedo.partial.json``,
:class:`~meshmei.benchmarks._report.FinishedRows`): the same command run again after an interruption takes
them (unless meshmei's source has changed since, or with ``--restart``) and says so in the section.
"""

from __future__ import annotations

import os
import time

from meshmei.benchmarks._report import (HEALTH_COLUMNS, HEALTH_LEGEND, FinishedRows, add_restart, benchmark_parser,
                                        health_cells, int_list, machine_line, markdown_table, write_section)
from meshmei.encoders import make_encoder
from meshmei.mei import ALBEDO_MIN_STEPS, DEFAULT_STEPS, MEISettings, optimize_mei, pixel_mei



def _albedo_run(enc, n: int, settings: MEISettings) -> dict:
    """A shape + albedo 3D-MEI of neuron ``n`` as the table reads it: response, the albedo's range, health and
    wall time."""
    t0 = time.perf_counter()
    res = optimize_mei(enc, n, "sheet", settings)
    secs = time.perf_counter() - t0
    return dict(activation=res.activation, albedo_min=float(res.albedo.min()), albedo_max=float(res.albedo.max()),
                health=res.health(), seconds=secs)


def run(neurons: list[int], restart: bool = False) -> str:
    load = os.getloadavg()[0]
    finished = FinishedRows("albedo", restart)
    enc = make_encoder("demo")
    rows, ratios, full_ratios = [], [], []
    for n in neurons:
        pm = finished.get(f"{n}|pixel", lambda: dict(activation=pixel_mei(enc, n).activation))
        shape = finished.get(f"{n}|shape", lambda: dict(
            activation=optimize_mei(enc, n, "sheet", MEISettings()).activation))
        alb = finished.get(f"{n}|albedo", lambda: _albedo_run(enc, n, MEISettings(albedo=True)))
        full = finished.get(f"{n}|albedo, shape lr 0.1",
                            lambda: _albedo_run(enc, n, MEISettings(albedo=True, albedo_shape_lr=0.1)))
        secs = alb["seconds"]
        r, r_full = alb["activation"] / pm["activation"], full["activation"] / pm["activation"]
        ratios.append(r)
        full_ratios.append(r_full)
        rows.append([n, f"{pm['activation']:.3f}",
                     f"{shape['activation']:.3f} ({shape['activation'] / pm['activation']:.3f})",
                     f"{alb['activation']:.3f} ({r:.3f})", f"{alb['albedo_min']:.2f}-{alb['albedo_max']:.2f}",
                     *health_cells([alb["health"]]), f"{full['activation']:.3f} ({r_full:.3f})",
                     *health_cells([full["health"]])[:2], f"{secs:.0f}"])
    met = sum(r >= 0.95 for r in ratios)
    body = "\n".join([
        "## Shape + albedo 3D-MEIs (`python -m meshmei.benchmarks.albedo`)",
        "",
        f"Machine: {machine_line()}; 1-minute load average at the start {load:.1f}.{finished.note()}",
        "",
        f"The demo model at 64 px, from the sheet, default settings (seeds 0-2; {DEFAULT_STEPS['sheet']} steps for "
        f"the shape alone, {max(DEFAULT_STEPS['sheet'], ALBEDO_MIN_STEPS)} with an albedo); the albedo run adds "
        "`albedo=True` (a 64 x 64 texture in [0, 1] over the sheet's grid, `lr_albedo` 0.2, smoothness 1, the "
        "offsets at their full `lr`), then the same with the offsets at a tenth of `lr` (`albedo_shape_lr=0.1`, "
        "the default while steps were unguarded). "
        "Responses, with their ratio to the pixel MEI's in brackets; 'albedo' is the range the texture uses; "
        "then the health of the albedo run's mesh: " + HEALTH_LEGEND + "; and SI and flipped of the run with the "
        "shape at a tenth of lr.",
        "",
        markdown_table(["neuron", "pixel MEI", "shape only", "shape + albedo", "albedo", *HEALTH_COLUMNS,
                        "shape + albedo, shape at a tenth of lr", *HEALTH_COLUMNS[:2], "s"], rows),
        "",
        f"Target (issue 19): shape + albedo at least 0.95 of the pixel MEI on at least 5 demo neurons: "
        f"{'met' if met >= 5 else 'not met'} at the defaults ({met} of {len(ratios)}; ratios "
        f"{', '.join(f'{r:.3f}' for r in ratios)}); with the shape at a tenth of its learning rate "
        f"(`albedo_shape_lr=0.1`): {sum(r >= 0.95 for r in full_ratios)} of {len(full_ratios)} "
        f"({', '.join(f'{r:.3f}' for r in full_ratios)}).",
    ])
    path = write_section("albedo", body)
    finished.close()
    return path


def main(argv=None):
    ap = benchmark_parser(__file__, __doc__)
    ap.add_argument("--neurons", type=int_list, default="0,1,3,6,9")
    add_restart(ap)
    args = ap.parse_args(argv)
    t = time.perf_counter()
    print(f"wrote {run(args.neurons, args.restart)} in {time.perf_counter() - t:.0f} s")


if __name__ == "__main__":
    main()
