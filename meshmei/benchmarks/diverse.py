"""Diverse 3D-MEIs (issue 19): K members of one neuron, with and without the diversity reward.

Run: ``python -m meshmei.benchmarks.diverse``; writes the "diverse" section of ``docs/benchmarks.md``. The
Gabor complex cell (phase-invariant: its members should take distinct phases), the simple cell (one
optimum: its members should not drift from it) and demo neuron 6; K = 4, sheet, default settings
otherwise; ``diversity`` 0 (four runs kept at their final iterate) and 0.5 (``floor`` 0.8).

Each set of K members is saved as it finishes (``docs/.diverse.partial.json``,
:class:`~meshmei.benchmarks._report.FinishedRows`): the same command run again after an interruption takes
them (unless meshmei's source has changed since, or with ``--restart``) and says so in the section.
"""

from __future__ import annotations

import os
import time

import torch

from meshmei.benchmarks._report import (HEALTH_COLUMNS, HEALTH_LEGEND, FinishedRows, add_restart, benchmark_parser,
                                        health_cells, machine_line, markdown_table, write_section)
from meshmei.encoders import GaborComplexCell, GaborSimpleCell, make_encoder
from meshmei.mei import diverse_meis

CASES = (("complex cell", GaborComplexCell, 0), ("simple cell", GaborSimpleCell, 0), ("demo neuron 6", None, 6))


def run(k: int = 4, restart: bool = False) -> str:
    load = os.getloadavg()[0]
    finished = FinishedRows("diverse", restart)
    rows = []
    for name, cls, neuron in CASES:
        enc = cls() if cls is not None else make_encoder("demo")
        for w in (0.0, 0.5):
            def one():
                t0 = time.perf_counter()
                d = diverse_meis(enc, neuron, k=k, diversity=w)
                secs = time.perf_counter() - t0
                off = d.dissimilarity[~torch.eye(k, dtype=torch.bool)]
                phases = []  # the complex cell's members' phases
                if isinstance(enc, GaborComplexCell):
                    phases = [float(enc.phase_of(r.image)[0]) for r in d.results]
                return dict(responses=d.responses, mean_dissimilarity=float(off.mean()),
                            min_dissimilarity=float(off.min()), phases=phases,
                            health=[r.health() for r in d.results], seconds=secs)
            r = finished.get(f"{name}|{k}|{w}", one)
            rows.append([name, w, ", ".join(f"{x:.3f}" for x in r["responses"]), f"{r['mean_dissimilarity']:.3f}",
                         f"{r['min_dissimilarity']:.3f}", ", ".join(f"{p:+.2f}" for p in r["phases"]),
                         *health_cells(r["health"]), f"{r['seconds']:.0f}"])
    body = "\n".join([
        "## Diverse 3D-MEIs (`python -m meshmei.benchmarks.diverse`)",
        "",
        f"Machine: {machine_line()}; 1-minute load average at the start {load:.1f}.{finished.note()}",
        "",
        f"K = {k} members from the sheet, default settings (64 px, 300 steps); 'responses' per member; "
        "dissimilarity is the distance between two members' preprocessed images as a share of the largest "
        "possible (mean and smallest over pairs); 'phases' the complex cell members' phase against its "
        f"quadrature pair (radians); health over the K members: {HEALTH_LEGEND}.",
        "",
        markdown_table(["neuron", "diversity", "responses", "mean dissimilarity", "min dissimilarity", "phases",
                        *HEALTH_COLUMNS, "s"], rows),
    ])
    path = write_section("diverse", body)
    finished.close()
    return path


def main(argv=None):
    ap = benchmark_parser(__file__, __doc__)
    ap.add_argument("--k", type=int, default=4)
    add_restart(ap)
    args = ap.parse_args(argv)
    t = time.perf_counter()
    print(f"wrote {run(args.k, args.restart)} in {time.perf_counter() - t:.0f} s")


if __name__ == "__main__":
    main()
