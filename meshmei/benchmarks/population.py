"""Batched 3D-MEIs (issue 18): throughput per (neuron, seed) item against running items one at a time.

Run: ``python -m meshmei.benchmarks.population [--steps 60]``; writes the "population" section of
``docs/benchmarks.md``.

The demo model at its default 64 px, sheet start, default settings otherwise. For each batch size B the
same neurons (0 .. B-1, one seed) run through :func:`meshmei.mei.optimize_mei_batch`; B = 1 is
:func:`meshmei.mei.optimize_mei` on one neuron. Reported: the median optimisation step of the batch
(from the run's time history) divided by B, and the end-to-end wall time per item-step (start mesh,
deformers and the final evaluation included). Rounds alternate the batch sizes, so each sees the same
machine state.
"""

from __future__ import annotations

import argparse
import os
import time

import torch

from meshmei.benchmarks._report import machine_line, markdown_table, write_section
from meshmei.encoders import make_encoder
from meshmei.mei import MEISettings, optimize_mei, optimize_mei_batch

SIZES = (1, 2, 4, 8, 15)


def _median(xs):
    xs = sorted(xs)
    return xs[len(xs) // 2]


def _one(enc, B: int, steps: int) -> tuple[float, float]:
    s = MEISettings(steps=steps, seeds=(0,))
    t0 = time.perf_counter()
    if B == 1:
        th = optimize_mei(enc, 6, "sheet", s).time_history
    else:
        th = optimize_mei_batch(enc, list(range(B)), "sheet", s, batch_size=B)[0].time_history
    wall = time.perf_counter() - t0
    step = _median([b - a for a, b in zip(th[:-1], th[1:])][3:])
    return step / B, wall / (steps * B)


def measure(steps: int = 60, rounds: int = 3) -> dict:
    enc = make_encoder("demo")
    res = {B: [] for B in SIZES}
    for _ in range(rounds):
        for B in SIZES:
            res[B].append(_one(enc, B, steps))
    return {B: (_median([a for a, _ in v]), _median([b for _, b in v])) for B, v in res.items()}


def run(steps: int) -> str:
    load = os.getloadavg()[0]
    r = measure(steps)
    step1, wall1 = r[1]
    rows = [[B, f"{1000 * a:.2f}", f"{step1 / a:.2f}", f"{1000 * b:.2f}", f"{wall1 / b:.2f}", f"{1 / a:.0f}"]
            for B, (a, b) in r.items()]
    at8 = step1 / r[8][0]
    body = "\n".join([
        "## Batched 3D-MEIs (`python -m meshmei.benchmarks.population`)",
        "",
        f"Machine: {machine_line()}; 1-minute load average at the start {load:.1f}; {torch.get_num_threads()} "
        "torch threads; CPU.",
        "",
        f"The demo model at 64 px, sheet start, default settings, {steps} steps; B items (neurons 0 .. B-1, "
        "one seed) in one batch; B = 1 is `optimize_mei` alone. Medians of 3 alternating rounds. 'step' is "
        "the optimisation step divided by B; 'wall' is the whole call (start mesh, deformers, final "
        "evaluation) per item-step.",
        "",
        markdown_table(["B", "step ms / item", "speed-up", "wall ms / item-step", "speed-up", "item-steps / s"],
                       rows),
        "",
        f"Target (issue 18): at least 2x throughput per item at B = 8 on 2 CPU cores: "
        f"{'met' if at8 >= 2 else 'not met'} ({at8:.2f}x per step, {wall1 / r[8][1]:.2f}x end to end).",
        "No GPU was lent to this task: the B = 64 GPU numbers the issue asks for are not measured, and this "
        "version renders on the CPU.",
    ])
    return write_section("population", body)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=60)
    args = ap.parse_args(argv)
    t = time.perf_counter()
    print(f"wrote {run(args.steps)} in {time.perf_counter() - t:.0f} s")


if __name__ == "__main__":
    main()
