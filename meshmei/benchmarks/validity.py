"""Valid steps (issue 16): what the guarantee costs per step, and what 3D-MEIs reach with it.

Run: ``python -m meshmei.benchmarks.validity [--steps 300] [--cells 8]``; writes the "validity" section of
``docs/benchmarks.md``.

- Cost: seconds per step with ``valid_steps`` on and off, in one process, alternating, for the 3D-MEI at
  64 px and 400 vertices and for reconstruction (rbf, sphere to bunny) at 2,500 and 10,000 vertices.
- 3D-MEIs: simple and complex Gabor cells over a spread of orientations, frequencies, positions, sizes and
  phases that no test uses, from sheet, sphere and torus: the fraction of the bound (best of the default
  seeds) and the result's health, with the guard on and off.
- Reconstruction (``--parts reconstruction``, its own section "validity-reconstruction"): the CLI's default
  run (2,500 vertices, 1,000 steps, ``--stages auto``) on the bunny and through the teapot's handle over three
  seeds, with meshmei's defaults (step guard and contact barrier), without them, and large steps as
  published.

A part's section is written when the part ends, but each of its runs is saved as it finishes
(``docs/.SECTION.partial.json``, :class:`~meshmei.benchmarks._report.FinishedRows`): an interrupted part
loses none of them, and the same command run again takes them (unless meshmei's source has changed since,
or with ``--restart``) and says so in the section.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import queue
import time
from pathlib import Path

import torch

from meshmei.benchmarks._report import (HEALTH_COLUMNS, HEALTH_LEGEND, SURFACE_HEALTH_COLUMNS, SURFACE_HEALTH_LEGEND,
                                        FinishedRows, add_restart, benchmark_parser, health_cells, int_list,
                                        machine_line, markdown_table, median, step_intervals, surface_health,
                                        write_section)
from meshmei.benchmarks.reconstruct.problems import UNGUARDED
from meshmei.encoders import GaborComplexCell, GaborSimpleCell
from meshmei.mei import MEISettings, optimize_mei
from meshmei.mei import DEFAULT_STEPS as MEI_DEFAULT_STEPS
from meshmei.quality import health_report
from meshmei.reconstruct import DEFAULT_STEPS, default_schedule, reconstruct
from meshmei.reconstruct.sources import resolve_source, target_surface
from meshmei.shapes import initial_mesh
from meshmei.shapes.targets import THIN_TARGETS


def mean_step(times, skip: int = 5) -> float:
    """The mean duration of a run's steps from its cumulative ``times`` (a ``time_history``), the first ``skip``
    left out (warm-up): what the run pays per step, its occasional long steps (a contact search, a halving)
    included, which a median would pass over (the guarded 3D-MEI from the sphere: a median step 1.18-1.36
    times the unguarded one over windows of an 800-step run, its wall time 1.33-1.38 times)."""
    steps = step_intervals(times, skip)
    return sum(steps) / len(steps)


def paired_ratio(times: list, base: list) -> str:
    """The median over rounds of each round's ratio ``times / base``, with its range: a paired ratio (this
    machine's load drifts between rounds far more than within one)."""
    ratios = [t / o for t, o in zip(times, base)]
    return f"{median(ratios):.2f} ({min(ratios):.2f}-{max(ratios):.2f})"


def fastest_ratio(times: list, base: list) -> str:
    """The ratio of the two fastest rounds, ``min(times) / min(base)``: other jobs on the machine only add
    time, so each mode's fastest round is its least disturbed one (a second reading beside
    :func:`paired_ratio`, not paired)."""
    return f"{min(times) / min(base):.2f}"


def alternated(modes: dict, rounds: int, run) -> dict:
    """``run(**kwargs)`` for each of ``modes`` (name -> keyword arguments), in ``rounds`` rounds whose order is
    reversed every other round; each mode's results, round by round."""
    results = {m: [] for m in modes}
    for r in range(rounds):
        order = list(modes.items())
        for mode, kw in (order[::-1] if r % 2 else order):
            results[mode].append(run(**kw))
    return results


def _pass_turn(k: int, turns, done) -> None:
    """Hand the turn from run ``k`` to the next run that has not finished (none left: keep it)."""
    n = len(turns)
    for j in range(1, n):
        if not done[(k + j) % n]:
            turns[(k + j) % n].release()
            return


def _lockstep_child(k: int, fn, args: tuple, block: int, turns, done, results) -> None:
    """Run ``k`` of :func:`lockstep`, in its own process: wait for its turn, run ``fn(*args, callbacks)``
    handing the turn on after every ``block`` steps, and put ``(k, result or error text)`` on ``results``."""
    turns[k].acquire()

    def after_step(record):
        if record["step"] % block == 0 and any(not done[j] for j in range(len(turns)) if j != k):
            _pass_turn(k, turns, done)
            turns[k].acquire()

    try:
        results.put((k, True, fn(*args, [after_step])))
    except BaseException as e:  # noqa: BLE001 - handed to the parent, which raises it
        results.put((k, False, f"{type(e).__name__}: {e}"))
    finally:
        done[k] = 1
        _pass_turn(k, turns, done)


def lockstep(runs: dict, block: int = 20) -> dict:
    """Run each of ``runs`` (name -> ``(fn, args)``; ``fn(*args, callbacks)`` a module-level function that calls
    each of ``callbacks`` after every step with the step's record, leaves their time out of its own times,
    and returns something picklable) in its own process, ``block`` steps each in turn, in the order given:
    each run's result by name. Between its blocks a run waits in its callback, so the runs meet the same load
    of the machine block by block, not round by round (this machine's load drifts within seconds: in one
    table paired rounds of 60 steps gave ratios from 1.0 to 2.0), and each run's own times count its steps
    alone. A run that fails, or whose process dies, raises a RuntimeError with its error (or exit code), after
    the others have finished.

    Processes, not threads: torch's OpenMP threads serve a second Python thread badly (a loop of small
    matrix products and convolutions ran 2.2 times slower in a thread than in the main thread here, after
    half a second of rest too; a known torch limitation, pytorch/pytorch#37259), and two 300-step 3D-MEIs
    in threads took 5.2-6.1 ms a step against 4.0-4.8 in the main thread, with the guarded run's ratio to
    the unguarded at 1.11-1.22 against 1.28-1.41 alone. Blocks of some steps: a hand-over wakes the
    other process's torch threads, which may have gone to sleep, and a block of 20 makes hand-overs rare
    (with it, three 300-step pairs from the sphere gave 1.25, 1.24 and 1.26; turns of one step were only
    tried in threads)."""
    ctx = mp.get_context("spawn")  # a fresh interpreter: torch's threads do not survive a fork
    names = list(runs)
    turns = [ctx.Semaphore(0) for _ in names]
    done, results = ctx.Array("b", len(names), lock=False), ctx.Queue()
    procs = [ctx.Process(target=_lockstep_child, args=(k, *runs[name], block, turns, done, results),
                         name=f"lockstep-{name}") for k, name in enumerate(names)]
    for p in procs:
        p.start()
    turns[0].release()
    got = {}
    try:
        while len(got) < len(names):
            try:
                k, ok, value = results.get(timeout=1.0)
                got[names[k]] = (ok, value)
            except queue.Empty:
                for k, p in enumerate(procs):  # a run that died without a word (a crash, a kill): say so, and
                    if p.exitcode not in (None, 0) and names[k] not in got:  # pass its turn on if it held it
                        got[names[k]] = (False, f"its process ended with code {p.exitcode}")
                        if not done[k]:
                            done[k] = 1
                            _pass_turn(k, turns, done)
    finally:
        for p in procs:
            p.join()
    failed = [f"{name}: {value}" for name, (ok, value) in got.items() if not ok]
    if failed:
        raise RuntimeError("lockstep run(s) failed: " + "; ".join(failed))
    return {name: got[name][1] for name in names}


def lockstep_pair(fn, args: tuple, unguarded: dict, k: int) -> dict:
    """``fn(*args, kwargs, callbacks)`` with the settings ``unguarded`` (``"off"``) and with the defaults
    (``"default"``, ``kwargs`` empty), stepped in :func:`lockstep`: the pair ``k`` of a table, whose unguarded
    run goes first for even ``k`` and second for odd (which goes first alternates from pair to pair)."""
    modes = {"off": unguarded, "default": {}}
    order = list(modes) if k % 2 == 0 else list(modes)[::-1]
    return lockstep({m: (fn, (*args, modes[m])) for m in order})


def lockstep_mei(init: str, seed: int, kwargs: dict, callbacks) -> dict:
    """One 3D-MEI run of the simple cell for :func:`lockstep` (``kwargs``: :class:`MEISettings` fields): its
    ``time_history``, ``activation``, ``health`` (:meth:`~meshmei.mei.MEIResult.health`) and the
    ``time.monotonic()`` at the end of each step (``ends``: one clock for every process, which shows how the
    runs took turns)."""
    ends = []
    res = optimize_mei(GaborSimpleCell(), 0, init, seeds=(seed,),
                       callbacks=[lambda record: ends.append(time.monotonic()), *callbacks], **kwargs)
    return {"time_history": res.time_history, "activation": res.activation, "health": res.health(), "ends": ends}


def mei_cost(steps: int = 60, rounds: int = 5) -> list:
    """Mean ms per 3D-MEI step (:func:`mean_step`, the median over rounds; 64 px, 400 vertices, sphere, simple
    cell), guard on and off, alternating (the order reversed every other round); the ratio as
    :func:`paired_ratio`."""
    runs = alternated({False: dict(valid_steps=False), True: dict(valid_steps=True)}, rounds,
                      lambda **kw: optimize_mei(GaborSimpleCell(), 0, "sphere", steps=steps, seeds=(0,), **kw))
    times = {on: [mean_step(res.time_history) for res in rs] for on, rs in runs.items()}
    off, on = median(times[False]), median(times[True])
    return ["3D-MEI, 64 px, 400 vertices", f"{1000 * off:.1f}",
            f"{1000 * on:.1f} ({paired_ratio(times[True], times[False])})", "-", "-"]


MEI_MODES = {"off": dict(valid_steps=False), "guard alone": dict(barrier_weight=0.0, contact_weight=0.0),
             "guard + its barrier": dict(contact_weight=0.0), "guard + both barriers": dict(contact_weight=100.0),
             "default": {}}


def mei_cost_split(steps: int = 60, rounds: int = 5) -> list:
    """Mean ms per 3D-MEI step (:func:`mean_step`; simple cell, 64 px, 400 vertices) from the sphere and the
    sheet, for each of :data:`MEI_MODES`, alternating (the order reversed every other round); the median over
    rounds of each round's ratio to off (a paired ratio: this machine's load drifts between rounds far more
    than within one), with its range, and the ratio of the fastest rounds (:func:`fastest_ratio`); and the
    response and :data:`HEALTH_COLUMNS` after ``steps`` steps (last round)."""
    rows = []
    for init in ("sphere", "sheet"):
        runs = alternated(MEI_MODES, rounds,
                          lambda **kw: optimize_mei(GaborSimpleCell(), 0, init, steps=steps, seeds=(0,), **kw))
        times = {mode: [mean_step(res.time_history) for res in rs] for mode, rs in runs.items()}
        for mode in MEI_MODES:
            last = runs[mode][-1]
            rows.append([init, mode, f"{1000 * median(times[mode]):.1f}", paired_ratio(times[mode], times["off"]),
                         fastest_ratio(times[mode], times["off"]), f"{last.activation:.3f}",
                         *health_cells([last.health()])])
            print(rows[-1], flush=True)
    return rows


def run_mei_cost(rounds: int = 9) -> Path:
    load = os.getloadavg()[0]
    rows = mei_cost_split(rounds=rounds)
    body = "\n".join([
        "## Cost of valid 3D-MEI steps (`python -m meshmei.benchmarks.validity --parts mei-cost`)",
        "",
        f"Machine: {machine_line()}; 1-minute load average at the start {load:.1f}.",
        "",
        "Simple cell, 64 px, 400-vertex start, 60 steps, seed 0; ms per step = a run's mean step (wall time, its "
        f"searches and the halvings of refused steps included; the first five steps left out), the median over "
        f"{rounds} alternated rounds (the modes' order reversed every other round); ratio to off = the median "
        "of each round's ratio (range over rounds in brackets: the load of this machine drifts between rounds); "
        "fastest rounds = the ratio of the mode's fastest round to off's (other jobs only add time: the least "
        "disturbed reading, not paired); response = fraction of the bound "
        "after 60 steps (last round), and the health of that result: " + HEALTH_LEGEND + ". "
        "The default is the guard with its barrier, plus the contact barrier "
        "from the sphere, not from the sheet (`meshmei.mei.DEFAULT_CONTACT_WEIGHT`); the guard's "
        "intersection test is a certificate where it holds (`meshmei.certify`), else libigl's. Issue 16's "
        "target: the guarantee costs at most 1.30 times the step.",
        "",
        markdown_table(["start", "mode", "ms/step", "ratio to off", "fastest rounds", "response", *HEALTH_COLUMNS],
                       rows),
    ])
    return write_section("validity-mei-cost", body)


def mei_cost_lockstep(starts=("sphere", "sheet", "torus"), seeds=(0, 1, 2), rounds: int = 2) -> list:
    """Whole default 3D-MEI runs (simple cell, 64 px, 400 vertices, the start's default steps), the default
    guarded run and the unguarded one stepped in :func:`lockstep`, one pair per seed and round (which goes
    first alternates): per start, each mode's mean step (:func:`mean_step`, the median over pairs), the
    median over pairs of each pair's ratio with its range, each mode's response (the median over pairs), and
    the default runs' results' :data:`HEALTH_COLUMNS` (all pairs)."""
    rows = []
    for init in starts:
        times, acts, health = {"off": [], "default": []}, {"off": [], "default": []}, []
        for k, seed in enumerate(seed for _ in range(rounds) for seed in seeds):
            runs = lockstep_pair(lockstep_mei, (init, seed), dict(valid_steps=False), k)
            for m, res in runs.items():
                times[m].append(mean_step(res["time_history"]))
                acts[m].append(res["activation"])
            health.append(runs["default"]["health"])
        steps = len(runs["off"]["time_history"])
        rows.append([init, steps, len(times["off"]), f"{1000 * median(times['off']):.2f}",
                     f"{1000 * median(times['default']):.2f}", paired_ratio(times["default"], times["off"]),
                     f"{median(acts['off']):.3f}", f"{median(acts['default']):.3f}", *health_cells(health)])
        print(rows[-1], flush=True)
    return rows


def run_mei_cost_lockstep(rounds: int = 2) -> Path:
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    rows = mei_cost_lockstep(rounds=rounds)
    body = "\n".join([
        "## Cost of valid 3D-MEI steps, whole runs in lockstep (`python -m meshmei.benchmarks.validity --parts "
        "mei-lockstep`)",
        "",
        f"Machine: {machine_line()}; 1-minute load average at the start {load:.1f}; "
        f"{time.perf_counter() - t0:.0f} s in all.",
        "",
        "Simple cell, 64 px, 400-vertex start, `optimize_mei`'s defaults for each start (its steps, one seed a "
        "run), the default guarded run and the unguarded one stepped in lockstep: each in its own process, 20 "
        "steps each in turn (`meshmei.benchmarks.validity.lockstep`), so that both meet the same load of the "
        f"machine; seeds 0, 1 and 2, {rounds} rounds (which run steps first alternates). ms per "
        "step = a run's mean step (its contact searches and the halvings of refused steps included; the first "
        "five steps left out), the median over pairs; ratio = the median over pairs of each pair's ratio (range "
        "in brackets); response = fraction of the bound, the median over pairs (single seeds: the benchmark "
        "tables report the best of three); the health of the default runs' results: " + HEALTH_LEGEND + ". "
        "Issue 16's target: the guarantee costs at most 1.30 times the step.",
        "",
        markdown_table(["start", "steps", "pairs", "ms/step off", "ms/step default", "ratio", "response off",
                        "response default", *HEALTH_COLUMNS], rows),
    ])
    return write_section("validity-mei-lockstep", body)


def reconstruction_cost(n_vertices: int, steps: int = 40, rounds: int = 2) -> list:
    """Mean ms per reconstruction step (:func:`mean_step`; rbf, one stage), with nothing, the guard alone, and the
    guard and the contact barrier (the default), alternating (the order reversed every other round); ratios to
    nothing as :func:`paired_ratio`."""
    src = initial_mesh("sphere", n_vertices=n_vertices)
    modes = {"off": UNGUARDED, "guard": dict(valid_steps=True, w_contact=0.0),
             "default": dict(valid_steps=True)}
    runs = alternated(modes, rounds,
                      lambda **kw: reconstruct(src, "bunny", "rbf", steps=steps, eval_samples=2000, **kw))
    times = {m: [mean_step([h["time"] for h in res.history]) for res in rs] for m, rs in runs.items()}
    t = {m: median(v) for m, v in times.items()}
    return [f"reconstruction rbf, {src[0].shape[0]} vertices", f"{1000 * t['off']:.1f}",
            f"{1000 * t['guard']:.1f} ({paired_ratio(times['guard'], times['off'])})", f"{1000 * t['default']:.1f}",
            paired_ratio(times["default"], times["off"])]


def run_reconstruction_cost(rounds: int = 9) -> Path:
    load = os.getloadavg()[0]
    rows = [reconstruction_cost(n, rounds=rounds) for n in (2500, 10000)]
    body = "\n".join([
        "## Cost of valid reconstruction steps (`python -m meshmei.benchmarks.validity --parts recon-cost`)",
        "",
        f"Machine: {machine_line()}; 1-minute load average at the start {load:.1f}.",
        "",
        "rbf in one stage from a sphere toward the bunny, the first 40 steps, seed 0; a run's mean ms per step (the "
        f"first five left out), the median over {rounds} rounds that alternate the modes (the order reversed every "
        "other round); the ratio is the median "
        "of each round's ratio to off (range over rounds in brackets). Off: no guard, no barrier; guard: the step "
        "guard alone (its star certificate, `meshmei.certify`, stands in for libigl's test while the sphere is "
        "star-shaped); default: the guard and the contact barrier. The worst case for the barrier: the sphere "
        "moves fast, and its candidate search (a vertex-face and an edge-edge broad phase, `_contact.c`) runs at "
        "nearly every step; a default run's whole-run ratio is in *Valid steps in reconstruction* (wall times). "
        "Issue 16's target: the guarantee costs at most 1.30 times the step.",
        "",
        markdown_table(["problem", "ms/step off", "ms/step guard (ratio)", "ms/step default", "ratio"], rows),
    ])
    return write_section("validity-reconstruction-cost", body)


# Default CLI runs of the reconstruction: meshmei's defaults, the same without guard and barrier, large steps.
RECONSTRUCTION_MODES = {"rbf (defaults: guard + barrier)": ("rbf", {}),
                        "rbf, no guard, no barrier": ("rbf", UNGUARDED),
                        "largesteps (as published)": ("largesteps", UNGUARDED)}


def _default_run(V, F, target, method: str, seed: int, **kwargs):
    """``meshmei reconstruct``'s default run of ``method`` (``--stages auto``) from ``(V, F)``."""
    stages, fractions, overrides = default_schedule(method, V.shape[0])
    return reconstruct((V, F), target, method, stages=stages, stage_fractions=fractions, stage_overrides=overrides,
                       seed=seed, **kwargs)


def lockstep_reconstruction(problem: str, init: str, n_vertices: int, seed: int, kwargs: dict, callbacks) -> dict:
    """``meshmei reconstruct``'s default rbf run (:func:`_default_run`) of ``init`` toward ``problem`` for
    :func:`lockstep` (``kwargs``: settings on top of the defaults): its per-step ``time_history``, the seconds
    of its optimisation in all (``seconds``: the steps and each stage's set-up, the remesh, the guard's and
    the barrier's start included), the final Chamfer-L2 and the result's health (:func:`surface_health`)."""
    target = target_surface(problem)
    V, F, _ = resolve_source(init, n_vertices, torch.float32, target)
    res = _default_run(V, F, target, "rbf", seed, callbacks=callbacks, **kwargs)
    return {"time_history": [h["time"] for h in res.history], "seconds": res.history[-1]["time"],
            "chamfer_l2": res.final.chamfer_l2, "health": surface_health(res.final)}


def reconstruction_cost_lockstep(problems=(("bunny", "sphere"), ("teapot", "torus")), seeds=(0, 1, 2),
                                 n_vertices: int = 2500) -> list:
    """The CLI's default rbf runs and the same without guard and barrier (:data:`UNGUARDED`), stepped in
    :func:`lockstep`, one pair per seed (which goes first alternates): per problem, each mode's seconds per
    step over the whole run (set-ups included; the median over pairs), the median over pairs of each pair's
    ratio with its range, each mode's Chamfer-L2 (median) and the default runs' :data:`SURFACE_HEALTH_COLUMNS`."""
    rows = []
    for problem, init in problems:
        per_step, cds, health = {"off": [], "default": []}, {"off": [], "default": []}, []
        for k, seed in enumerate(seeds):
            runs = lockstep_pair(lockstep_reconstruction, (problem, init, n_vertices, seed), UNGUARDED, k)
            for m, res in runs.items():
                per_step[m].append(res["seconds"] / len(res["time_history"]))
                cds[m].append(res["chamfer_l2"])
            health.append(runs["default"]["health"])
        rows.append([f"{problem} from the {init}, {n_vertices} vertices", len(seeds),
                     f"{1000 * median(per_step['off']):.1f}", f"{1000 * median(per_step['default']):.1f}",
                     paired_ratio(per_step["default"], per_step["off"]), f"{median(cds['off']):.2e}",
                     f"{median(cds['default']):.2e}", *health_cells(health)])
        print(rows[-1], flush=True)
    return rows


def run_reconstruction_cost_lockstep(n_vertices: int = 2500, seeds=(0, 1, 2)) -> Path:
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    rows = reconstruction_cost_lockstep(seeds=seeds, n_vertices=n_vertices)
    flags = ("" if n_vertices == 2500 else
             f" --lockstep-vertices {n_vertices} --lockstep-seeds {','.join(map(str, seeds))}")
    body = "\n".join([
        f"## Cost of valid reconstruction steps, whole runs in lockstep at {n_vertices:,} vertices "
        f"(`python -m meshmei.benchmarks.validity --parts recon-lockstep{flags}`)",
        "",
        f"Machine: {machine_line()}; 1-minute load average at the start {load:.1f}; "
        f"{time.perf_counter() - t0:.0f} s in all.",
        "",
        f"`meshmei reconstruct`'s default rbf run ({n_vertices:,} vertices, `default_schedule`, 1,000 steps) and the "
        "same without guard and contact barrier, stepped in lockstep: each in its own process, 20 steps each in "
        f"turn (`meshmei.benchmarks.validity.lockstep`), seeds {', '.join(map(str, seeds))} (which run steps "
        "first alternates). ms per "
        "step = the run's optimisation seconds (every stage's set-up, the remesh, the guard's and the barrier's "
        "start included) over its steps, the median over pairs; ratio = the median over pairs of each pair's "
        "ratio (range in brackets); Chamfer-L2 the median over seeds; the health of the default runs' results: "
        + SURFACE_HEALTH_LEGEND + ". Issue 16's target: the guarantee costs at most 1.30 times the step.",
        "",
        markdown_table(["problem", "pairs", "ms/step off", "ms/step default", "ratio", "Chamfer-L2 off",
                        "Chamfer-L2 default", *SURFACE_HEALTH_COLUMNS], rows),
    ])
    return write_section("validity-reconstruction-lockstep" + ("" if n_vertices == 2500 else f"-{n_vertices}"), body)


def reconstruction_outcomes(seeds=(0, 1, 2), n_vertices: int = 2500, problems=(("bunny", "sphere"), ("teapot", "torus")),
                            finished: FinishedRows | None = None) -> list:
    """Chamfer-L2, self-intersections (and the rest of :data:`SURFACE_HEALTH_COLUMNS`, over the seeds),
    refused steps and wall time of the CLI's default run per problem, mode and seed; each seed's run kept
    in ``finished`` as it ends."""
    finished = finished or FinishedRows(None)
    rows = []
    for problem, init in problems:
        target = target_surface(problem)
        for label, (method, kw) in RECONSTRUCTION_MODES.items():
            V, F, _ = resolve_source(init, n_vertices, torch.float32, target)
            cds, sis, walls, refused, health = [], [], [], [], []
            for seed in seeds:
                def one():
                    res = _default_run(V, F, target, method, seed, **kw)
                    return dict(chamfer_l2=res.final.chamfer_l2, self_intersections=res.final.self_intersections,
                                health=surface_health(res.final), wall_time=res.wall_time,
                                refused=sum(st.get("refused", 0) for st in res.info["stages"]))
                r = finished.get(f"reconstruction|{problem}|{init}|{n_vertices}|{label}|{seed}", one)
                cds.append(r["chamfer_l2"])
                sis.append(r["self_intersections"])
                health.append(r["health"])
                walls.append(r["wall_time"])
                refused.append(r["refused"])
                print(problem, label, seed, cds[-1], sis[-1], walls[-1], refused[-1], flush=True)
            rows.append([f"{problem}, {V.shape[0]} vertices", label, ", ".join(f"{c:.2e}" for c in cds), f"{median(cds):.2e}",
                         ", ".join(str(s) for s in sis), *health_cells(health)[1:],
                         ", ".join(str(r) for r in refused) if kw == {} else "-", f"{sum(walls) / len(walls):.1f}"])
    return rows


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


def _mei_row(name: str, params: dict, cell, init: str, steps: int | None) -> list:
    row = [name, ", ".join(f"{k} {v:.2f}" for k, v in params.items()), init]
    for on in (True, False):
        t = time.perf_counter()
        res = optimize_mei(cell, 0, init, MEISettings(steps=steps, valid_steps=on))
        h = health_report(res.V, res.F, res.V0)
        row += [f"{res.activation:.3f}", h["self_intersections"], h["flipped_faces"], f"{h['min_quality']:.3f}"]
        if on:  # the guard's results: closed and manifold as well
            row += ["yes" if h["watertight"] else "no", "yes" if h["nonmanifold_edges"] == 0 else "no"]
        row.append(f"{time.perf_counter() - t:.0f}")
    return row


def mei_outcomes(n_cells: int, steps: int | None, finished: FinishedRows | None = None) -> list:
    """One row per cell and start (the guard on, then off), each kept in ``finished`` as it ends."""
    finished = finished or FinishedRows(None)
    rows = []
    for i, (name, params, cell) in enumerate(cells(n_cells)):
        for init in ("sheet", "sphere", "torus"):
            rows.append(finished.get(f"mei|{i}|{init}|{steps}", lambda: _mei_row(name, params, cell, init, steps)))
            print(rows[-1], flush=True)
    return rows


def thin_outcomes(names=tuple(THIN_TARGETS), seed: int = 0, n_vertices: int = 2500,
                  finished: FinishedRows | None = None) -> list:
    """The thin-part targets (the fin and the bowl used for no tuning): meshmei's default run (sphere start of
    about ``n_vertices``, ``DEFAULT_STEPS`` steps), the same without guard and barrier, and large steps as
    published given the default run's time; each row kept in ``finished`` as it ends."""
    finished = finished or FinishedRows(None)
    rows = []
    for name in names:
        target = target_surface(name)
        V, F, _ = resolve_source("sphere", n_vertices, torch.float32, target)
        wall = {}
        for label, method, kw in (("rbf (defaults: guard + barrier)", "rbf", {}),
                                  ("rbf, no guard, no barrier", "rbf", UNGUARDED),
                                  ("largesteps, same time", "largesteps", UNGUARDED)):
            budget = dict(time_budget=wall["rbf (defaults: guard + barrier)"]) if method == "largesteps" else {}

            def one():
                res = _default_run(V, F, target, method, seed, **kw, **budget)
                refused = sum(st.get("refused", 0) for st in res.info["stages"])
                return dict(wall_time=res.wall_time, row=[
                    name, V.shape[0], label, f"{res.final.chamfer_l2:.2e}", *health_cells([surface_health(res.final)]),
                    refused if kw == {} else "-", f"{res.wall_time:.1f}"])
            r = finished.get(f"thin|{name}|{n_vertices}|{seed}|{label}", one)
            wall[label] = r["wall_time"]
            rows.append(r["row"])
            print(rows[-1], flush=True)
    return rows


def run_thin(resolutions=(2500,), restart: bool = False):
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    finished = FinishedRows("validity-thin", restart)
    rows = [row for n in resolutions for row in thin_outcomes(n_vertices=n, finished=finished)]
    body = "\n".join([
        "## Valid steps on targets with thin parts (`python -m meshmei.benchmarks.validity --parts thin`)",
        "",
        f"Machine: {machine_line()}; 1-minute load average at the start {load:.1f}; "
        f"{time.perf_counter() - t0:.0f} s in all.{finished.note()}",
        "",
        "Targets `dumbbell` (two balls joined by a rod of radius 0.05), `fin` (a disc 0.06 thick through a ball), "
        "`cup` (walls 0.05 thick) and `bowl` (a spherical shell 0.05 thick, open above), unit diagonal, "
        "watertight, made for this (`meshmei.shapes.targets.THIN_TARGETS`); the cup and the dumbbell chose the "
        "weight and form of the coarsest stage's pairing by normal (`normal_match`), the fin and the bowl "
        "nothing. From a sphere of about " + " and ".join(f"{n:,}" for n in resolutions) + " vertices (the "
        "vertices column: the start's count), seed 0: meshmei's default run "
        f"({DEFAULT_STEPS:,} steps), the same without guard and barrier, and large steps as published with the default "
        "run's wall time as its budget. " + SURFACE_HEALTH_LEGEND + "; refused = candidates the guard "
        "refused; s = optimisation wall time.",
        "",
        markdown_table(["target", "vertices", "run", "Chamfer-L2", *SURFACE_HEALTH_COLUMNS, "refused", "s"], rows),
    ])
    path = write_section("validity-thin", body)
    finished.close()
    return path


def run_reconstruction(seeds=(0, 1, 2), restart: bool = False):
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    finished = FinishedRows("validity-reconstruction", restart)
    rows = (reconstruction_outcomes(seeds, finished=finished)
            + reconstruction_outcomes((0,), 10000, (("bunny", "sphere"),), finished=finished))
    body = "\n".join([
        "## Valid steps in reconstruction (`python -m meshmei.benchmarks.validity --parts reconstruction`)",
        "",
        f"Machine: {machine_line()}; 1-minute load average at the start {load:.1f}; "
        f"{time.perf_counter() - t0:.0f} s in all.{finished.note()}",
        "",
        "The CLI's default run (`meshmei reconstruct --init sphere --target bunny` and `--init torus --target "
        f"teapot`: 2,500 vertices, {DEFAULT_STEPS:,} steps, `--stages auto`, which gives rbf three levels), seeds " + ", ".join(map(str, seeds)) + "; and "
        "the bunny at `--n-vertices 10000`, seed 0 only (four levels for rbf since 2026-11-29 17:00). "
        "Chamfer-L2 from 100,000 samples per surface; " + SURFACE_HEALTH_LEGEND + " (the teapot target has "
        "294 self-intersecting pairs of its own); refused = candidate steps the guard refused, summed over "
        "stages; s = mean optimisation wall time.",
        "",
        markdown_table(["problem", "run", "Chamfer-L2 per seed", "median", "SI per seed",
                        *SURFACE_HEALTH_COLUMNS[1:], "refused per seed", "s"], rows),
    ])
    path = write_section("validity-reconstruction", body)
    finished.close()
    return path


def steps_text(steps: int | None) -> str:
    """How many steps a 3D-MEI run of the benchmark took, in words."""
    if steps is not None:
        return f"{steps} steps"
    return ", ".join(f"{n} steps from the {k}" for k, n in MEI_DEFAULT_STEPS.items() if k != "custom")


def run(steps: int | None, n_cells: int, restart: bool = False):
    load = os.getloadavg()[0]
    finished = FinishedRows("validity", restart)
    cost = [mei_cost()] + [reconstruction_cost(n) for n in (2500, 10000)]
    for r in cost:
        print(r, flush=True)
    outcomes = mei_outcomes(n_cells, steps, finished)
    on = [float(r[3]) for r in outcomes]
    body = "\n".join([
        "## Valid steps (`python -m meshmei.benchmarks.validity`)",
        "",
        f"Machine: {machine_line()}; 1-minute load average at the start {load:.1f}.{finished.note()}",
        "",
        "Cost of the guarantee: milliseconds per step (a run's mean step, the median over rounds) with "
        "`valid_steps` off and on (the 3D-MEI's "
        "default: the guard, its barrier and the contact barrier; the split is in *Cost of valid 3D-MEI "
        "steps*), and for reconstruction the guard alone and the guard with the contact barrier (its "
        "default). Same process, runs alternated; the check is libigl's exact self-intersection test over "
        "an AABB tree, the triangle quality and the face turn, after every step, plus the halvings of "
        "refused steps; the contact barrier adds a KD-tree search for near vertex-face pairs (and, in the "
        "3D-MEI, edge-edge pairs) when a vertex has moved an eighth of an edge since the last search. The "
        "reconstruction rows time the first 40 steps of one stage from a sphere toward the bunny, where the "
        "guard's star certificate (`meshmei.certify`) still stands in for libigl; a default run leaves star "
        "shape within its first stage, so its later stages pay libigl's test: the whole-run ratio is in "
        "*Valid steps in reconstruction* (wall times). The ratios are the median of each round's ratio (five "
        "rounds for the 3D-MEI, two for reconstruction, in alternating order), with the range in brackets (more "
        "rounds: *Cost of valid 3D-MEI steps*, *Cost of valid reconstruction steps*).",
        "",
        markdown_table(["problem", "ms/step off", "ms/step guard (ratio)", "ms/step guard + contact barrier",
                        "ratio"], cost),
        "",
        f"3D-MEIs of {n_cells} Gabor cells (parameters drawn once, seed 16) from three starts, default "
        f"`MEISettings` ({steps_text(steps)}, seeds 0, 1, 2, best kept), with the guard on and off. Response = "
        "fraction of the upper bound; SI = self-intersecting face pairs; flipped = faces flipped against "
        "the start; q = minimum triangle quality; watertight = closed and manifold (the sheet is open by "
        "design); manifold = no edge with more than two faces; s = wall time.",
        "",
        markdown_table(["cell", "parameters", "start", "on: response", "on: SI", "on: flipped", "on: q",
                        "on: watertight", "on: manifold", "on: s", "off: response", "off: SI", "off: flipped",
                        "off: q", "off: s"], outcomes),
        "",
        f"With the guard: {sum(1 for r in outcomes if r[4] == 0 and r[5] == 0)} of {len(outcomes)} results "
        f"have no self-intersection and no flipped face, {sum(1 for r in outcomes if r[8] == 'yes')} are "
        f"manifold and {sum(1 for r in outcomes if r[7] == 'yes')} watertight (of "
        f"{sum(1 for r in outcomes if r[2] != 'sheet')} from closed starts); {sum(1 for x in on if x >= 0.95)} "
        f"of {len(on)} reach 0.95 of the bound (lowest {min(on):.3f}).",
    ])
    path = write_section("validity", body)
    finished.close()
    return path


def main(argv=None):
    ap = benchmark_parser(__file__, __doc__)
    ap.add_argument("--steps", type=int, default=None, help="3D-MEI steps per seed (default: by start, as MEISettings)")
    ap.add_argument("--cells", type=int, default=6)
    ap.add_argument("--rounds", type=int, default=9,
                    help="alternated rounds of the mei-cost and recon-cost parts (their medians), and of the "
                         "mei-lockstep part (three seeds each)")
    ap.add_argument("--thin-vertices", type=int_list, default="2500",
                    help="comma-separated start sizes of the thin part, e.g. 2500,10000 (default 2500)")
    ap.add_argument("--lockstep-vertices", type=int, default=2500,
                    help="start size of the recon-lockstep part (its own section unless 2500)")
    ap.add_argument("--lockstep-seeds", type=int_list, default="0,1,2", help="seeds of the recon-lockstep part")
    add_restart(ap)
    ap.add_argument("--parts", default="mei,reconstruction",
                    help="comma-separated: mei (cost and 3D-MEIs), mei-cost (the 3D-MEI's cost, split), mei-lockstep "
                         "(the 3D-MEI's cost over whole default runs, stepped in lockstep), recon-lockstep (the same "
                         "for reconstruction's default runs at 2,500 vertices), recon-cost "
                         "(the reconstruction step's cost), reconstruction (default CLI runs), thin (targets with "
                         "thin parts)")
    args = ap.parse_args(argv)
    parts = set(args.parts.split(","))
    known = {"mei", "mei-cost", "mei-lockstep", "recon-lockstep", "recon-cost", "reconstruction", "thin"}
    if not parts <= known:  # an unknown part ran nothing and exited 0
        ap.error(f"--parts: unknown {', '.join(sorted(parts - known))} (known: {', '.join(sorted(known))})")
    if min(args.thin_vertices) < 32:
        ap.error(f"--thin-vertices: each start needs at least 32 vertices, got {args.thin_vertices}")
    t = time.perf_counter()
    if "mei" in parts:
        print(f"wrote {run(args.steps, args.cells, args.restart)} in {time.perf_counter() - t:.0f} s")
    if "mei-cost" in parts:
        print(f"wrote {run_mei_cost(args.rounds)} in {time.perf_counter() - t:.0f} s")
    if "mei-lockstep" in parts:
        print(f"wrote {run_mei_cost_lockstep(args.rounds)} in {time.perf_counter() - t:.0f} s")
    if "recon-lockstep" in parts:
        print(f"wrote {run_reconstruction_cost_lockstep(args.lockstep_vertices, tuple(args.lockstep_seeds))} in "
              f"{time.perf_counter() - t:.0f} s")
    if "recon-cost" in parts:
        print(f"wrote {run_reconstruction_cost(args.rounds)} in {time.perf_counter() - t:.0f} s")
    if "reconstruction" in parts:
        print(f"wrote {run_reconstruction(restart=args.restart)} in {time.perf_counter() - t:.0f} s")
    if "thin" in parts:
        print(f"wrote {run_thin(args.thin_vertices, args.restart)} in {time.perf_counter() - t:.0f} s")


if __name__ == "__main__":
    main()
