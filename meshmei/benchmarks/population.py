"""Batched 3D-MEIs (issue 18): throughput per (neuron, seed) item against running items one at a time.

Run: ``python -m meshmei.benchmarks.population [--steps 60]``; writes the "population" section of
``docs/benchmarks.md``. ``--device cuda`` runs the same on a GPU at B = 1, 8, 64 (``--sizes``) and writes the
"population-gpu" section instead.

The demo model at its default 64 px, sheet start, default settings otherwise. For each batch size B the
same neurons (0 .. B-1, one seed) run through :func:`meshmei.mei.optimize_mei_batch`; B = 1 is
:func:`meshmei.mei.optimize_mei` on one neuron. Reported: the median optimisation step of the batch
(from the run's time history) divided by B, and the end-to-end wall time per item-step (start mesh,
deformers and the final evaluation included). Rounds alternate the batch sizes, so each sees the same
machine state. Nothing is saved for an interrupted run to resume: its units are timings in alternated rounds,
and taking some from another run would mix two machine states in one table.
"""

from __future__ import annotations

import os
import time

import torch

from meshmei.benchmarks._report import (benchmark_parser, int_list, machine_line, markdown_table, median, step_intervals,
                                        write_section)
from meshmei.encoders import make_encoder
from meshmei.mei import MEISettings, optimize_mei, optimize_mei_batch

SIZES = (1, 2, 4, 8, 15)
GPU_SIZES = (1, 8, 64)


def _one(enc, B: int, steps: int, valid_steps: bool = True) -> tuple[float, float]:
    # B neurons with one seed each; beyond the model's neurons (the demo has 15), k neurons with B / k seeds
    k = max(d for d in range(1, min(B, enc.n_neurons) + 1) if B % d == 0)
    s = MEISettings(steps=steps, seeds=tuple(range(B // k)), valid_steps=valid_steps)
    t0 = time.perf_counter()
    if B == 1:
        th = optimize_mei(enc, 6, "sheet", s).time_history
    else:
        th = optimize_mei_batch(enc, list(range(k)), "sheet", s, batch_size=B)[0].time_history
    wall = time.perf_counter() - t0
    step = median(step_intervals(th, 3))
    return step / B, wall / (steps * B)


def measure(steps: int = 60, rounds: int = 5, device="cpu", sizes=SIZES) -> dict:
    """``{(B, valid_steps): (step s per item, wall s per item-step)}``: every batch size with valid steps
    (the default), and B = 1 and the largest size up to 8 without, all alternated; on ``device``."""
    enc = make_encoder("demo").to(device)
    keys = [(B, True) for B in sizes] + [(1, False), (max(b for b in sizes if b <= 8), False)]
    res = {k: [] for k in keys}
    for _ in range(rounds):
        for B, valid in keys:
            res[B, valid].append(_one(enc, B, steps, valid))
    return {k: (median([a for a, _ in v]), median([b for _, b in v])) for k, v in res.items()}


def _table(r: dict) -> str:
    """The table of :func:`measure`'s results, each speed-up against B = 1 in the same mode."""
    rows = []
    for (B, valid), (a, b) in r.items():
        step1, wall1 = r[1, valid]
        rows.append([B, "on" if valid else "off", f"{1000 * a:.2f}", f"{step1 / a:.2f}", f"{1000 * b:.2f}",
                     f"{wall1 / b:.2f}", f"{1 / a:.0f}"])
    return markdown_table(["B", "valid steps", "step ms / item", "speed-up", "wall ms / item-step", "speed-up",
                           "item-steps / s"], rows)


def run(steps: int, device="cpu", sizes=None, rounds: int = 5) -> str:
    if torch.device(device).type != "cpu":
        return _run_gpu(steps, device, tuple(sizes or GPU_SIZES), rounds)
    load = os.getloadavg()[0]
    r = measure(steps, rounds)
    step1, wall1 = r[1, True]
    at8 = step1 / r[8, True][0]
    off8 = r[1, False][0] / r[8, False][0]
    body = "\n".join([
        "## Batched 3D-MEIs (`python -m meshmei.benchmarks.population`)",
        "",
        f"Machine: {machine_line()}; 1-minute load average at the start {load:.1f}; {torch.get_num_threads()} "
        "torch threads; CPU.",
        "",
        f"The demo model at 64 px, sheet start, default settings, {steps} steps; B items (neurons 0 .. B-1, "
        f"one seed) in one batch; B = 1 is `optimize_mei` alone. Medians of {rounds} alternating rounds. "
        "'step' is the optimisation step divided by B; 'wall' is the whole call (start mesh, deformers, final "
        "evaluation) per item-step. 'valid steps' on is the default (each item's guard, its barrier and "
        "its contact barrier run item by item: libigl's test alone is about 1.3 ms per item); off is "
        "`--no-valid-steps`. Speed-ups are against B = 1 in the same mode.",
        "",
        _table(r),
        "",
        f"Target (issue 18): at least 2x throughput per item at B = 8 on 2 CPU cores: with valid steps "
        f"(the default) {'met' if at8 >= 2 else 'not met'} ({at8:.2f}x per step, "
        f"{wall1 / r[8, True][1]:.2f}x end to end); without them {off8:.2f}x per step.",
        "On a GPU: `--device cuda` writes the section *population-gpu* (B = 1, 8, 64).",
    ])
    return write_section("population", body)


def _run_gpu(steps: int, device, sizes: tuple, rounds: int) -> str:
    """The GPU section: the same measurement on ``device``, items per second at each B and the speed-up."""
    if not torch.cuda.is_available():
        raise SystemExit(f"--device {device}: this machine has no CUDA device")
    load = os.getloadavg()[0]
    sizes = tuple(sorted({1, *sizes}))  # the speed-ups are against B = 1
    r = measure(steps, rounds, device=device, sizes=sizes)
    body = "\n".join([
        "## Batched 3D-MEIs on a GPU (`python -m meshmei.benchmarks.population --device cuda`)",
        "",
        f"Machine: {machine_line()}; {torch.cuda.get_device_name(torch.device(device))}; 1-minute load average "
        f"at the start {load:.1f}.",
        "",
        f"As the CPU section (*population*), on the GPU: the demo model at 64 px, sheet start, {steps} steps, "
        "B items in one batch (beyond the model's 15 neurons, k neurons with B / k seeds each: 8 x 8 at B = 64), "
        f"medians of {rounds} alternating rounds. The render, the deformation, the regularizers "
        "and the model run on the GPU (torch code: the compiled kernels are CPU-only); the step guard's checks "
        "and the barriers run on a CPU copy of the vertices (libigl's exact predicates), item by item.",
        "",
        _table(r),
    ])
    return write_section("population-gpu", body)


def main(argv=None):
    ap = benchmark_parser(__file__, __doc__)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--device", default="cpu", help="cpu (the default section) or cuda / cuda:N (population-gpu)")
    ap.add_argument("--sizes", type=int_list, default=None, help=f"batch sizes on a GPU (default {GPU_SIZES})")
    ap.add_argument("--rounds", type=int, default=5,
                    help="alternating rounds whose medians the table gives (default 5; it was 3 until 2026-11-29, "
                         "when the B = 1 step of one run was an outlier that the per-step ratio divides by)")
    args = ap.parse_args(argv)
    t = time.perf_counter()
    print(f"wrote {run(args.steps, args.device, args.sizes, args.rounds)} in {time.perf_counter() - t:.0f} s")


if __name__ == "__main__":
    main()
