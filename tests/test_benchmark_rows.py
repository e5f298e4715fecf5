"""A benchmark part that is interrupted loses none of its finished results (``FinishedRows``)."""

from __future__ import annotations

import json
import os
import re
from types import SimpleNamespace

import pytest
import torch

from meshmei.benchmarks import _report
from meshmei.benchmarks._report import FinishedRows


@pytest.fixture
def docs(tmp_path, monkeypatch):
    monkeypatch.setenv("MESHMEI_DOCS", str(tmp_path))
    return tmp_path


def _never():
    raise AssertionError("a finished result was computed again")


def test_results_finished_before_an_interruption_are_taken_by_the_next_run(docs):
    first = FinishedRows("part")
    assert first.get("a", lambda: (1, "x", 2.5)) == [1, "x", 2.5]  # its JSON form, as a resumed run gets it
    assert first.get("b", lambda: {"k": (3,)}) == {"k": [3]}
    with pytest.raises(KeyboardInterrupt):
        first.get("c", lambda: (_ for _ in ()).throw(KeyboardInterrupt()))
    assert set(json.loads((docs / ".part.partial.json").read_text())["rows"]) == {"a", "b"}

    again = FinishedRows("part")
    assert again.get("a", _never) == [1, "x", 2.5] and again.get("b", _never) == {"k": [3]}
    assert again.get("c", lambda: 7) == 7
    assert again.resumed == 2 and "2 of its results" in again.note()
    again.close()
    assert not (docs / ".part.partial.json").exists()
    assert FinishedRows("part").get("a", lambda: "new") == "new"  # closed: nothing left to take


def test_results_of_other_source_or_with_restart_are_computed_again(docs, monkeypatch, capsys):
    FinishedRows("part").get("a", lambda: 1)
    assert FinishedRows("part", restart=True).get("a", lambda: 2) == 2
    assert "--restart" in capsys.readouterr().out
    FinishedRows("part").get("a", lambda: 1)  # restart dropped it; saved again
    monkeypatch.setattr(_report, "source_hash", lambda: "edited")
    assert FinishedRows("part").get("a", lambda: 3) == 3
    assert "source has changed" in capsys.readouterr().out


@pytest.mark.parametrize("text", ["", "{\"rows\": ", "[]", "{\"rows\": 3}"])
def test_a_damaged_file_is_a_run_to_redo(docs, text):
    (docs / ".part.partial.json").write_text(text)
    rows = FinishedRows("part")
    assert rows.get("a", lambda: 1) == 1 and rows.resumed == 0


def test_numpy_and_torch_scalars_keep_their_kind(docs):
    import numpy as np

    got = FinishedRows("part").get("a", lambda: [np.int64(3), np.float32(0.5), torch.tensor(2), np.bool_(True)])
    assert got == [3, 0.5, 2, True] and [type(x) for x in got] == [int, float, int, bool]


def test_a_file_without_its_start_time_is_still_taken(docs):
    from meshmei.benchmarks._report import source_hash

    (docs / ".part.partial.json").write_text(json.dumps({"source": source_hash(), "rows": {"a": 1}}))
    rows = FinishedRows("part")
    assert rows.get("a", _never) == 1 and "not recorded" in rows.note()


def test_without_a_name_nothing_is_written(docs):
    rows = FinishedRows(None)
    assert rows.get("a", lambda: 1) == 1 and rows.get("a", _never) == 1
    rows.close()
    assert list(docs.iterdir()) == []


def test_an_interrupted_thin_part_resumes_where_it_stopped(docs, monkeypatch):
    """The thin targets' part: the run interrupted in its third run takes the first two from the file, and
    large steps' budget is the saved default run's time; the table is the uninterrupted run's."""
    from meshmei.benchmarks import validity

    V, F = torch.rand(40, 3), torch.randint(0, 40, (60, 3))
    monkeypatch.setattr(validity, "target_surface", lambda name: name)
    monkeypatch.setattr(validity, "resolve_source", lambda init, n, dtype, target: (V, F, None))
    calls, stop_at = [], [0]  # the call that is interrupted (0: none)

    def fake_run(V, F, target, method, seed, **kw):
        calls.append((target, method, kw.get("time_budget")))
        if len(calls) == stop_at[0]:
            raise KeyboardInterrupt
        health = dict(self_intersections=0, inverted_faces=0, min_quality=0.25, watertight=True, nonmanifold_edges=0)
        final = SimpleNamespace(chamfer_l2=len(target) * (2e-6 if method == "largesteps" else 1e-6),
                                as_dict=lambda: health)
        wall = 10.0 + len(target) + (1.0 if kw else 0.0)  # the cup's default run: 13 s
        return SimpleNamespace(final=final, wall_time=wall, info={"stages": [{"refused": 1}]})

    monkeypatch.setattr(validity, "_default_run", fake_run)
    whole = validity.thin_outcomes(names=("cup", "fin"), n_vertices=40)
    calls.clear()
    stop_at[0] = 3
    with pytest.raises(KeyboardInterrupt):
        validity.thin_outcomes(names=("cup", "fin"), n_vertices=40, finished=FinishedRows("validity-thin"))
    assert len(calls) == 3
    calls.clear()
    stop_at[0] = 0
    resumed = FinishedRows("validity-thin")
    rows = validity.thin_outcomes(names=("cup", "fin"), n_vertices=40, finished=resumed)
    assert resumed.resumed == 2
    # large steps on the cup ran now, with the budget its default run took (13 s) before the interruption
    assert calls[0] == ("cup", "largesteps", 13.0) and [c[0] for c in calls[1:]] == ["fin"] * 3
    assert rows == whole and len(rows) == 6


# The other benchmarks that save each finished run: an interrupted run resumed writes the uninterrupted run's
# section (but for the note that says so), computing only what was not finished. Their optimisations are
# stand-ins that return fixed fields, from their arguments alone, and record each call.

_NOTE = (r" (\d+) of its results were finished by an interrupted run of the same source that started [^;]+; "
         r"the machine line, load and total time are this run's\.")
_HEALTH = dict(self_intersections=0, flipped_faces=1, degenerate_faces=0, min_quality=0.23456, mean_quality=0.71,
               boundary_edges=4, nonmanifold_edges=0, watertight=False)


def _section(docs, name: str) -> str:
    text = (docs / "benchmarks.md").read_text()
    return text.split(f"<!-- BEGIN {name} -->")[1].split(f"<!-- END {name} -->")[0]


class _Calls(list):
    """The stand-ins' calls, in order; the one numbered ``stop`` (from 1; 0: none) is interrupted."""

    stop = 0

    def __call__(self, *what):
        self.append(what)
        if len(self) == self.stop:
            raise KeyboardInterrupt


def _assert_resumes(docs, monkeypatch, name: str, run, calls: _Calls, stop: int, done: int, units: int):
    """``run()`` whole, then interrupted at its ``stop``-th call, then again: the last computes only the calls
    after the first ``done`` (those of the ``units`` results the interrupted run finished) and writes the
    whole run's section but for the note."""
    monkeypatch.setattr(os, "getloadavg", lambda: (0.5, 0.5, 0.5))
    partial = docs / f".{name}.partial.json"
    run()
    whole, everything = _section(docs, name), list(calls)
    assert not partial.exists() and not re.search(_NOTE, whole)
    calls.clear()
    calls.stop = stop
    with pytest.raises(KeyboardInterrupt):
        run()
    assert list(calls) == everything[:stop] and len(json.loads(partial.read_text())["rows"]) == units
    calls.clear()
    calls.stop = 0
    run()
    assert list(calls) == everything[done:]  # the finished results were taken, not computed again
    resumed = _section(docs, name)
    assert [int(n) for n in re.findall(_NOTE, resumed)] == [units]
    assert re.sub(_NOTE, "", resumed) == whole
    assert not partial.exists()
    return whole


def test_an_interrupted_mei_benchmark_resumes_where_it_stopped(docs, monkeypatch):
    """The mei section: interrupted in the complex cell's first 3D-MEI (its fifth optimisation), the run
    again takes the pixel MEIs and 3D-MEIs finished before it, and draws the same curves and bars."""
    from meshmei.benchmarks import mei

    calls = _Calls()

    def fake_mei(cell, neuron, init, settings):
        name = getattr(cell, "name", type(cell).__name__)
        calls("3d", name, init, settings.steps)
        top = 0.9 + 0.01 * len(init) + 0.03 * len(name) / 20
        return SimpleNamespace(activation=top - 0.001, history=[0.3, 0.91, 0.94, top],
                               time_history=[0.5, 1.0, 1.5, 2.0], seconds_per_step=0.0123 * len(init),
                               health=lambda: dict(_HEALTH, flipped_faces=len(init)))

    def fake_pixel(cell, neuron, image_size=64, steps=200):
        calls("pixel", getattr(cell, "name", type(cell).__name__), steps)
        return SimpleNamespace(activation=0.98765)

    def fake_random(model, neuron, init, n, settings):
        calls("random", n)
        return torch.linspace(0.1, 0.6, n)

    def fake_grid(cell, neuron, init, grid, settings):
        calls("grid", init)
        return [dict(weights=dict(settings.weights, laplacian=lap, area=area), activation=0.5 + lap / 1000,
                     fraction_of_bound=0.5, seconds=3.0, **dict(_HEALTH, min_quality=area / 5000 + 0.1))
                for lap in grid["laplacian"] for area in grid["area"]]

    drawn = []
    monkeypatch.setattr(mei, "optimize_mei", fake_mei)
    monkeypatch.setattr(mei, "pixel_mei", fake_pixel)
    monkeypatch.setattr(mei, "random_mesh_responses", fake_random)
    monkeypatch.setattr(mei, "load_demo_model", lambda: SimpleNamespace(name="demo"))
    monkeypatch.setattr(mei, "DEMO_MODEL_PATH", SimpleNamespace(is_file=lambda: True))
    monkeypatch.setattr(mei, "grid_search", fake_grid)
    monkeypatch.setattr(mei, "time_per_step", lambda size, nv: (0.002, 0.001))  # timings: always this run's
    monkeypatch.setattr(mei, "plot", lambda curves, bars, out_dir: drawn.append((curves, bars)))
    # pixel (simple), 3D (simple, sheet and sphere), pixel (complex), then 3D (complex, sheet) is interrupted
    whole = _assert_resumes(docs, monkeypatch, "mei", lambda: mei.run(steps=4, seeds=(0,), pixel_steps=3),
                            calls, stop=5, done=4, units=4)
    assert len(drawn) == 2 and drawn[0] == drawn[1]  # the interrupted run drew nothing
    assert len(drawn[0][0]) == 4 and len(drawn[0][1]) == 5  # curves of 2 cells x 2 starts; bars + the demo's
    assert "| complex | sphere | 0.983 | 0.984 | 2 | 1.0 | 4 | 74 | 0 | 6 | 0.235 | 0/1 | 1/1 | 0.9877 |" in whole
    assert "3D-MEI 0.965, pixel MEI 0.988." in whole and "| sheet | 100.0 | 30.0 | 1000.0 | 0.600 |" in whole


def test_an_interrupted_robust_benchmark_resumes_where_it_stopped(docs, monkeypatch):
    """The robust section: a run and its two sweeps are one result; interrupted in the second run's light
    sweep, the run again computes that run and its sweeps anew."""
    import numpy as np

    from meshmei.benchmarks import robust

    calls = _Calls()

    def fake_mei(enc, n, init, settings):
        calls("3d", n, settings.robust_pose, settings.robust_light)
        act = 0.5 + 0.01 * n - 0.001 * (settings.robust_pose + 2 * settings.robust_light)
        return SimpleNamespace(activation=act, n=n, pose=settings.robust_pose, light=settings.robust_light,
                               health=lambda: dict(_HEALTH, self_intersections=n))

    def fake_sweep(kind):
        def sweep(res, enc, neurons):  # broader along the axis the run was made robust to
            calls(kind, res.n)
            return SimpleNamespace(neurons=[9] + neurons,
                                   responses=[[0.0], np.linspace(0, 1, 41) ** (10 / (10 + getattr(res, kind)))])
        return sweep

    monkeypatch.setattr(robust, "make_encoder", lambda name: SimpleNamespace(name=name))
    monkeypatch.setattr(robust, "optimize_mei", fake_mei)
    monkeypatch.setattr(robust, "pose_sweep", fake_sweep("pose"))
    monkeypatch.setattr(robust, "light_sweep", fake_sweep("light"))
    whole = _assert_resumes(docs, monkeypatch, "robust", lambda: robust.run([6, 0]), calls, stop=6, done=3, units=1)
    assert "| 6 | robust pose 20 | 0.540 (0.96) | 87.8 % | 51.2 % | 1.71x | 6 | 1 | 0.235 | 0/1 | 1/1 | 0 |" in whole


def test_interrupted_albedo_resolution_and_diverse_benchmarks_resume_where_they_stopped(docs, monkeypatch):
    """One result per optimisation (albedo: each of a neuron's four runs; resolution: each cell, start,
    weights and size; diverse: each set of K members), interrupted in the middle of the part."""
    from meshmei.benchmarks import albedo, diverse, resolution

    calls = _Calls()
    monkeypatch.setattr(albedo, "make_encoder", lambda name: SimpleNamespace(name=name))

    def fake_albedo_mei(enc, n, init, settings):
        calls("3d", n, settings.albedo, settings.albedo_shape_lr)
        act = 0.6 + 0.01 * n + 0.1 * settings.albedo * settings.albedo_shape_lr
        return SimpleNamespace(activation=act, albedo=torch.tensor([0.125, 0.5 + n / 100]),
                               health=lambda: dict(_HEALTH, flipped_faces=n))

    def fake_pixel(enc, n):
        calls("pixel", n)
        return SimpleNamespace(activation=0.65 + 0.001 * n)

    monkeypatch.setattr(albedo, "optimize_mei", fake_albedo_mei)
    monkeypatch.setattr(albedo, "pixel_mei", fake_pixel)
    whole = _assert_resumes(docs, monkeypatch, "albedo", lambda: albedo.run([0, 3]), calls, stop=6, done=5, units=5)
    assert "| 3 | 0.653 | 0.630 (0.965) | 0.730 (1.118) | 0.12-0.53 | 0 | 3 | 0.235 | 0/1 | 1/1 |" in whole

    calls = _Calls()

    def fake_resolution_mei(enc, n, start, settings):
        calls(enc.name, start, settings.n_vertices, settings.reg_ref_vertices, settings.lr_by_edge)
        frac = 0.8 + settings.n_vertices / 10 ** 5 + 0.01 * settings.lr_by_edge + 0.001 * len(start)
        return SimpleNamespace(fraction_of_bound=frac, V=torch.zeros(settings.n_vertices + 2, 3),
                               extra={"guard": {"refused": len(start)}} if settings.lr_by_edge else {},
                               health=lambda: _HEALTH)

    monkeypatch.setattr(resolution, "make_encoder", lambda name: SimpleNamespace(name=name))
    monkeypatch.setattr(resolution, "optimize_mei", fake_resolution_mei)
    whole = _assert_resumes(docs, monkeypatch, "resolution", lambda: resolution.run(10, [400, 2500]), calls,
                            stop=7, done=6, units=6)
    assert "| gabor-simple | sphere | 2500 | 2502 | scaled | 0.831 | 0 | 1 | 0.235 | 0/1 | 1/1 | - | 0 |" in whole

    calls = _Calls()

    def fake_diverse(enc, neuron, k, diversity):
        calls(type(enc).__name__, neuron, k, diversity)
        g = torch.Generator().manual_seed(neuron + int(10 * diversity))
        results = [SimpleNamespace(activation=0.9 - 0.01 * i + diversity / 10, image=torch.rand(1, 1, 64, 64, generator=g),
                                   health=lambda i=i: dict(_HEALTH, self_intersections=i)) for i in range(k)]
        d = torch.arange(k, dtype=torch.float32)
        dissimilarity = (d[:, None] - d[None]).abs() * (0.25 + diversity / 2)
        return SimpleNamespace(results=results, responses=[r.activation for r in results],
                               dissimilarity=dissimilarity)

    monkeypatch.setattr(diverse, "make_encoder", lambda name: SimpleNamespace(name=name))
    monkeypatch.setattr(diverse, "diverse_meis", fake_diverse)
    whole = _assert_resumes(docs, monkeypatch, "diverse", lambda: diverse.run(3), calls, stop=4, done=3, units=3)
    phases = re.search(r"\| complex cell \| 0.5 \| 0.950, 0.940, 0.930 \| 0.667 \| 0.500 \| ([^|]*) \| 3 \|", whole)
    assert phases and len(phases.group(1).split(", ")) == 3  # the complex cell's members' phases, as saved
    assert "| simple cell | 0.5 | 0.950, 0.940, 0.930 | 0.667 | 0.500 |  | 3 | 3 | 0.235 | 0/3 | 3/3 | 0 |" in whole


@pytest.mark.parametrize("name, argv", [("mei", []), ("robust", []), ("diverse", []), ("albedo", []),
                                        ("resolution", []), ("validity", ["--parts", "thin"])])
def test_each_saving_benchmark_takes_restart(monkeypatch, name, argv):
    import importlib

    module = importlib.import_module(f"meshmei.benchmarks.{name}")
    got = []
    run = "run_thin" if name == "validity" else "run"
    monkeypatch.setattr(module, run, lambda *a, **kw: got.append(kw.get("restart", a[-1])))
    module.main(argv)
    module.main(argv + ["--restart"])
    assert got == [False, True]


def test_the_reconstruction_cost_alternates_the_modes_and_pairs_each_rounds_ratio(monkeypatch):
    """recon-cost: the modes' order reversed every other round, and the ratio the median over rounds of each
    round's ratio to off (a round whose load doubles every time cancels out), with its range."""
    from meshmei.benchmarks import validity

    load = iter([1.0, 1.0, 1.0, 2.0, 2.0, 2.0, 3.0, 3.0, 3.0])  # the machine slows down between rounds
    order = []

    def fake(src, target, method, steps, eval_samples, **kw):
        mode = "off" if not kw.get("valid_steps", True) else "guard" if kw.get("w_contact") == 0.0 else "default"
        order.append(mode)
        per_step = {"off": 10.0, "guard": 12.0, "default": 15.0}[mode] * next(load) / 1000  # seconds
        return SimpleNamespace(history=[{"time": per_step * (i + 1)} for i in range(steps)])

    monkeypatch.setattr(validity, "reconstruct", fake)
    monkeypatch.setattr(validity, "initial_mesh", lambda kind, n_vertices: (torch.zeros(n_vertices, 3), None))
    row = validity.reconstruction_cost(100, steps=12, rounds=3)
    assert order == ["off", "guard", "default", "default", "guard", "off", "off", "guard", "default"]
    # each round's ratios are 1.2 and 1.5 exactly, whatever its load; the medians of the times are not
    assert row == ["reconstruction rbf, 100 vertices", "20.0", "24.0 (1.20 (1.20-1.20))", "30.0", "1.50 (1.50-1.50)"]
    assert validity.paired_ratio([2.0, 3.0, 9.0], [1.0, 2.0, 3.0]) == "2.00 (1.50-3.00)"
    assert validity.fastest_ratio([2.0, 3.0, 9.0], [1.5, 1.0, 3.0]) == "2.00"  # min / min, not paired


def test_the_mei_cost_table_pairs_each_rounds_ratio_and_reads_the_fastest_rounds(monkeypatch):
    """mei-cost: each start's modes alternate, the order reversed every other round; a row gives the median
    of the rounds' paired ratios with their range, and the ratio of the fastest rounds."""
    from meshmei.benchmarks import validity

    cost = {"off": 10.0, "guard alone": 20.0, "guard + its barrier": 11.0, "guard + both barriers": 12.0,
            "default": 13.0}
    loads = iter([1.0] * 5 + [3.0] * 5 + [2.0] * 5 + [1.0] * 5 + [3.0] * 5 + [2.0] * 5)  # per round and start
    order = []

    def fake(encoder, neuron, init, steps, seeds, **kw):
        mode = next(m for m, mkw in validity.MEI_MODES.items() if mkw == kw)
        order.append((init, mode))
        per_step = cost[mode] * next(loads) / 1000
        health = {"self_intersections": 0, "flipped_faces": 0, "min_quality": 0.5, "watertight": True,
                  "nonmanifold_edges": 0}
        return SimpleNamespace(time_history=[per_step * i for i in range(steps)], activation=0.9,
                               health=lambda: health)

    monkeypatch.setattr(validity, "optimize_mei", fake)
    rows = validity.mei_cost_split(steps=12, rounds=3)
    modes = list(validity.MEI_MODES)
    rounds = modes + modes[::-1] + modes
    assert order == [("sphere", m) for m in rounds] + [("sheet", m) for m in rounds]
    default = next(r for r in rows if r[:2] == ["sphere", "default"])
    # every round's ratio is 1.3 whatever its load; the fastest rounds (load 1) give 1.3 too
    assert default[2:6] == ["26.0", "1.30 (1.30-1.30)", "1.30", "0.900"]
    assert [r[3] for r in rows if r[0] == "sheet"] == ["1.00 (1.00-1.00)", "2.00 (2.00-2.00)", "1.10 (1.10-1.10)",
                                                       "1.20 (1.20-1.20)", "1.30 (1.30-1.30)"]


def test_a_cost_reading_is_the_mean_step_after_the_warm_up():
    """The cost tables read a run's mean step, its occasional long steps (a contact search, a halving) included,
    which a median passes over; the first five steps (warm-up) left out."""
    from meshmei.benchmarks import validity

    steps = [9.0] * 5 + [1.0, 1.0, 1.0, 4.0]  # warm-up, then three plain steps and one with a search
    times = [0.0]
    for d in steps:
        times.append(times[-1] + d)
    assert validity.mean_step(times) == 7.0 / 4


def test_lockstep_takes_turns_block_by_block_and_gives_each_run_its_own_result():
    """lockstep: each run in its own process, ``block`` steps each in turn in the order given (their step
    ends, on one clock, come in blocks), a run that ends sooner leaves the others to go on; each gives the
    result it gives alone."""
    from meshmei.benchmarks.validity import lockstep, lockstep_mei

    tiny = dict(image_size=16, n_vertices=64)
    runs = {"on": (lockstep_mei, ("sphere", 0, dict(steps=7, **tiny))),
            "off": (lockstep_mei, ("sphere", 0, dict(steps=4, valid_steps=False, **tiny)))}
    both = lockstep(runs, block=2)
    assert list(both) == ["on", "off"]
    ends = sorted((t, name) for name, r in both.items() for t in r["ends"])
    assert "".join(name[1] for _, name in ends) == "nnffnnffnnn"  # o[n], o[f]f: two steps each, then on alone
    for name, (fn, args) in runs.items():
        alone = fn(*args, [])
        assert len(both[name]["time_history"]) == len(alone["time_history"]) == args[2]["steps"]
        assert both[name]["activation"] == pytest.approx(alone["activation"], abs=1e-5)  # rounding, as a repeat


def test_a_failed_lockstep_run_is_reported_after_the_others_end():
    from meshmei.benchmarks.validity import lockstep, lockstep_mei

    tiny = dict(image_size=16, n_vertices=64)
    with pytest.raises(RuntimeError, match=r"bad: MEIError: .*lr"):
        lockstep({"good": (lockstep_mei, ("sheet", 0, dict(steps=3, **tiny))),
                  "bad": (lockstep_mei, ("sheet", 0, dict(steps=3, lr=-1.0, **tiny)))}, block=1)


def _dies(callbacks):
    """A lockstep run whose process ends without a result (as a crash would)."""
    os._exit(5)


def test_a_lockstep_run_whose_process_dies_is_reported_and_the_others_go_on():
    from meshmei.benchmarks.validity import lockstep, lockstep_mei

    with pytest.raises(RuntimeError, match="dies: its process ended with code 5"):
        lockstep({"dies": (_dies, ()),
                  "good": (lockstep_mei, ("sheet", 0, dict(steps=3, image_size=16, n_vertices=64)))}, block=1)


def test_the_lockstep_cost_table_pairs_each_run_with_its_unguarded_twin(monkeypatch):
    """mei-lockstep: per start, one lockstep pair per seed and round, which mode goes first alternating; the
    ratio is the median over pairs of each pair's mean-step ratio, with its range."""
    from meshmei.benchmarks import validity

    pairs = []

    def fake_lockstep(runs):
        pairs.append(list(runs))
        return {m: fn(*args, []) for m, (fn, args) in runs.items()}

    def fake(encoder, neuron, init, seeds, callbacks, **kw):
        per_step = (10.0 if kw.get("valid_steps") is False else 12.0 + seeds[0]) / 1000
        health = {"self_intersections": 0 if kw.get("valid_steps") is None else 7, "flipped_faces": 0,
                  "min_quality": 0.2 + 0.1 * seeds[0], "watertight": True, "nonmanifold_edges": 0}
        return SimpleNamespace(time_history=[per_step * i for i in range(1, 21)], activation=0.9 + 0.01 * seeds[0],
                               health=lambda: health)

    monkeypatch.setattr(validity, "lockstep", fake_lockstep)
    monkeypatch.setattr(validity, "optimize_mei", fake)
    rows = validity.mei_cost_lockstep(starts=("sphere",), seeds=(0, 1, 2), rounds=2)
    assert pairs == [["off", "default"], ["default", "off"]] * 3
    # the health of the six default runs' results (the unguarded ones' 7 pairs each are not in it)
    assert rows == [["sphere", 20, 6, "10.00", "13.00", "1.30 (1.20-1.40)", "0.910", "0.910", 0, 0, "0.200", "6/6",
                     "6/6"]]


def test_the_reconstruction_lockstep_table_reads_whole_runs_per_step(monkeypatch):
    """recon-lockstep: per problem one lockstep pair per seed, which mode goes first alternating; a run's cost
    per step is its optimisation seconds (set-ups included) over its steps; the ratio the median over pairs."""
    from meshmei.benchmarks import validity

    pairs = []

    def fake_lockstep(runs):
        pairs.append(list(runs))
        return {m: fn(*args, []) for m, (fn, args) in runs.items()}

    def fake_run(problem, init, n_vertices, seed, kwargs, callbacks):
        guarded = kwargs == {}
        seconds = (1.1 + 0.1 * seed if guarded else 1.0) * 10
        health = {"self_intersections": 0 if guarded else 9, "flipped_faces": 0, "min_quality": 0.3,
                  "watertight": True, "nonmanifold_edges": 0}
        return {"time_history": [seconds * i / 1000 for i in range(1, 1001)], "seconds": seconds,
                "chamfer_l2": 1e-6 if guarded else 2e-6, "health": health}

    monkeypatch.setattr(validity, "lockstep", fake_lockstep)
    monkeypatch.setattr(validity, "lockstep_reconstruction", fake_run)
    rows = validity.reconstruction_cost_lockstep(problems=(("bunny", "sphere"),), seeds=(0, 1, 2), n_vertices=2500)
    assert pairs == [["off", "default"], ["default", "off"], ["off", "default"]]
    assert rows == [["bunny from the sphere, 2500 vertices", 3, "10.0", "12.0", "1.20 (1.10-1.30)", "2.00e-06",
                     "1.00e-06", 0, 0, "0.300", "3/3", "3/3"]]
