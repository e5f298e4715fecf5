"""Reconstruction loop and its CLI: progress on a small problem, determinism, stages, history, bad input."""

from __future__ import annotations

import json
import re
import warnings

import pytest
import torch

from meshmei.cli import main
from meshmei.errors import MeshError, ReconstructionError
from meshmei.metrics import surface_metrics
from meshmei.quality import count_self_intersections, health_report
from meshmei.reconstruct import (DEFAULT_STEPS, RBF_FOUR_LEVEL_OVERRIDES, RBF_THREE_LEVEL_OVERRIDES,
                                 ReconstructionSettings, default_stages, reconstruct, resolve_source, source_mesh,
                                 target_surface)
from meshmei.sampling import PointIndex, sample_points
from meshmei.shapes import initial_mesh, target_mesh

from conftest import icosphere

SMALL = dict(n_samples=2000, target_pool=20_000, eval_samples=5000)


@pytest.fixture(scope="module")
def bunny():
    return target_mesh("bunny")


@pytest.fixture(scope="module")
def sphere():
    return initial_mesh("sphere", n_vertices=300)


# Measured on this problem (80 steps): rbf 0.008, vertex 0.69, largesteps 0.03 of the initial Chamfer-L2.
@pytest.mark.parametrize("method, ratio", [("rbf", 0.05), ("vertex", 0.85), ("largesteps", 0.1)])
def test_each_method_reduces_chamfer(sphere, bunny, method, ratio):
    before = surface_metrics(*sphere, *bunny, n_samples=5000).chamfer_l2
    res = reconstruct(sphere, bunny, method, steps=80, **SMALL)
    assert len(res.history) == 80
    assert res.final.chamfer_l2 < ratio * before
    assert res.V.shape == sphere[0].shape and torch.equal(res.F, sphere[1])
    assert res.settings.method == method and res.settings.steps == 80
    # the final evaluation includes the result's health
    assert res.final.self_intersections == count_self_intersections(res.V, res.F)


@pytest.mark.parametrize("method", ["rbf", "largesteps"])
def test_same_seed_same_result(sphere, bunny, method):
    a = reconstruct(sphere, bunny, method, steps=15, seed=3, **SMALL)
    b = reconstruct(sphere, bunny, method, steps=15, seed=3, **SMALL)
    assert torch.equal(a.V, b.V)
    assert [h["loss"] for h in a.history] == [h["loss"] for h in b.history]
    c = reconstruct(sphere, bunny, method, steps=15, seed=4, **SMALL)
    assert not torch.equal(a.V, c.V)


def test_stages_remesh_between_stages(sphere, bunny):
    res = reconstruct(sphere, bunny, "rbf", steps=40, stages=(100, 300), stage_fractions=(1, 3), **SMALL)
    st = [h["stage"] for h in res.history]
    assert st == sorted(st) and st.count(0) == 10 and st.count(1) == 30
    assert [s["end_step"] for s in res.info["stages"]] == [10, 40]
    assert abs(res.info["stages"][0]["n_vertices"] - 100) < 30
    assert abs(res.V.shape[0] - 300) < 60
    assert res.info["stages"][1]["truncation_error"] <= 3.4e-4
    assert default_stages(2500) == ((625, 2500, 2500), (0.25, 0.45, 0.3))
    assert default_stages(10000, levels=3) == ((625, 2500, 10000, 10000), (0.15, 0.25, 0.35, 0.25))
    assert default_stages(10000, levels=4) == ((156, 625, 2500, 2500, 10000), (0.1, 0.15, 0.3, 0.2, 0.25))
    for n in (100, 2500, 10000, 40000):
        for levels in (2, 3):  # a ladder up to n, then n once more; one share per stage
            stages, shares = default_stages(n, levels)
            assert len(stages) == levels + 1 and stages[-2:] == (n, n) and list(stages) == sorted(stages)
            assert len(shares) == len(stages) and sum(shares) == pytest.approx(1.0)
        # four: three levels' stages for n/4 in three quarters of the budget, then n in the last quarter
        stages, shares = default_stages(n, 4)
        assert stages == (*default_stages(max(32, n // 4), 3)[0], n) and list(stages) == sorted(stages)
        assert len(shares) == 5 and sum(shares[:4]) == pytest.approx(0.75) and shares[-1] == 0.25
    for bad in (1, 5, "3"):
        with pytest.raises(ValueError, match="levels"):
            default_stages(2500, bad)


def test_settings_per_stage(sphere, bunny):
    from meshmei.reconstruct import DEFAULTS

    ov = ({"method": "largesteps"}, {"w_laplacian": 0.0, "lr": 0.02})
    res = reconstruct(sphere, bunny, "rbf", steps=20, stages=(100, 300), stage_overrides=ov, **SMALL)
    assert [st["method"] for st in res.info["stages"]] == ["largesteps", "rbf"]
    # each stage runs with its overrides, then its own method's defaults; the decay follows the whole run
    decay = res.settings.lr_decay
    lr0 = [DEFAULTS["largesteps"]["lr"], 0.02]
    for h in res.history:
        assert h["lr"] == pytest.approx(lr0[h["stage"]] * decay ** ((h["step"] - 1) / 20))
    assert [st["w_laplacian"] for st in res.info["stages"]] == [0.0, 0.0]
    assert res.info["stages"][1]["truncation_error"] > 0 and "truncation_error" not in res.info["stages"][0]
    # a value set for the run applies to every stage that does not override it
    res = reconstruct(sphere, bunny, "rbf", steps=4, stages=(100, 300), stage_overrides=({"lr": 0.02}, None),
                      lr=1e-3, w_laplacian=7.0, **SMALL)
    assert [h["lr"] for h in res.history][::2] == pytest.approx([0.02, 1e-3 * res.settings.lr_decay ** 0.5])
    r = 300 / 2500
    assert [st["w_laplacian"] for st in res.info["stages"]] == pytest.approx([7 * r**2] * 2)
    # a method chosen per stage is the same run as that method without overrides, bit for bit
    a = reconstruct(sphere, bunny, "largesteps", steps=12, stages=(100, 300), **SMALL)
    b = reconstruct(sphere, bunny, "rbf", steps=12, stages=(100, 300),
                    stage_overrides=({"method": "largesteps"}, {"method": "largesteps"}), **SMALL)
    assert torch.equal(a.V, b.V) and [h["loss"] for h in a.history] == [h["loss"] for h in b.history]
    for bad, says in [(dict(stage_overrides=(None,)), "one entry per stage"),
                      (dict(stages=None, stage_overrides=(None,)), "one entry per stage"),
                      (dict(stage_overrides=({"method": "magic"}, None)), "method"),
                      (dict(stage_overrides=({"lr": -1.0}, None)), "lr must be positive"),
                      (dict(stage_overrides=({"steps": 3}, None)), "cannot set 'steps'"),
                      (dict(stage_overrides=("rbf", None)), "dict or None")]:
        with pytest.raises(ValueError, match=says):
            ReconstructionSettings(**{"stages": (100, 300), **bad}).resolved()


def test_coarse_kernels_move_the_shape_further_early(sphere, bunny):
    # Measured (300-vertex sphere to bunny, 10 steps): 0.053 without the coarse set, 0.0075 with 20 kernels.
    plain = reconstruct(sphere, bunny, "rbf", steps=10, coarse_ratio=0, **SMALL)
    coarse = reconstruct(sphere, bunny, "rbf", steps=10, coarse_ratio=16, **SMALL)
    assert coarse.final.chamfer_l2 < 0.3 * plain.final.chamfer_l2
    st = coarse.info["stages"][0]
    assert st["n_coarse_kernels"] == round(sphere[0].shape[0] / 16) and "n_coarse_kernels" not in plain.info["stages"][0]
    # about sqrt(16) = 4 edges wide; the truncation bound covers both kernel sets
    from meshmei.operators import edges

    E = edges(sphere[1])
    h = float((sphere[0][E[:, 0]] - sphere[0][E[:, 1]]).norm(dim=1).mean())
    assert 2.5 * h < st["coarse_sigma"] < 6 * h
    assert st["truncation_error"] <= 3.4e-4
    assert ReconstructionSettings().resolved().coarse_ratio == 0
    assert ReconstructionSettings(method="largesteps").resolved().coarse_ratio == 0
    for bad, says in [(dict(coarse_ratio=1), "coarse_ratio"), (dict(coarse_ratio=-3), "coarse_ratio"),
                      (dict(coarse_ratio=2.5), "coarse_ratio"), (dict(coarse_ratio=16, coarse_lr=0.0), "coarse_lr"),
                      (dict(method="vertex", coarse_ratio=16), "coarse_ratio=16 applies only with method='rbf'"),
                      (dict(contact_edges="yes"), "contact_edges"), (dict(contact_edges=1), "contact_edges")]:
        with pytest.raises(ValueError, match=says):
            ReconstructionSettings(**bad).resolved()


def test_history_and_metric_records(sphere, bunny):
    res = reconstruct(sphere, bunny, "largesteps", steps=30, eval_every=10, **SMALL)
    assert [m["step"] for m in res.metrics] == [10, 20, 30]
    t = [h["time"] for h in res.history]
    assert t == sorted(t) and res.wall_time >= t[-1]
    assert res.metrics[-1]["chamfer_l2"] == res.final.chamfer_l2
    assert all(m["eval_seconds"] > 0 for m in res.metrics)
    assert res.eval_time == pytest.approx(sum(m["eval_seconds"] for m in res.metrics))
    for h in res.history:  # geometric decay to lr_decay of lr over the run
        assert h["lr"] == pytest.approx(res.settings.lr * res.settings.lr_decay ** ((h["step"] - 1) / 30))
    js = json.loads(json.dumps(res.to_json()))
    assert js["settings"]["method"] == "largesteps" and len(js["history"]) == 30


class _Clock:
    """A stand-in for the ``time`` module of the optimiser and the fit: every reading is ``tick`` seconds
    after the last, so a step costs ``tick`` whatever the machine's load (a time-budget test that read the
    real clock failed on a loaded machine, where one step took more than the whole budget)."""

    def __init__(self, tick: float):
        self.now, self.tick = 0.0, tick

    def perf_counter(self) -> float:
        self.now += self.tick
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += seconds


def _fake_clock(monkeypatch, tick: float) -> _Clock:
    import importlib

    clock = _Clock(tick)
    for name in ("meshmei.optim", "meshmei.reconstruct.fit"):
        monkeypatch.setattr(importlib.import_module(name), "time", clock)
    return clock


def test_callbacks_get_every_steps_record_and_their_time_is_not_the_runs(sphere, bunny, monkeypatch):
    """reconstruct's ``callbacks``, as optimize_mei's: each callable gets every step's record, the history's own,
    over both stages; what they spend is left out of the run's times (a clock that the callback moves on by
    100 s a step leaves them as they were); one that is not callable is refused before anything is built."""
    kw = dict(steps=8, stages=(100, 300), stage_fractions=(1, 3), **SMALL)
    _fake_clock(monkeypatch, 1e-3)
    plain = reconstruct(sphere, bunny, "rbf", **kw)
    clock, seen, also = _fake_clock(monkeypatch, 1e-3), [], []
    res = reconstruct(sphere, bunny, "rbf", callbacks=[seen.append, lambda rec: (also.append(rec["step"]),
                                                                                 clock.sleep(100.0))], **kw)
    assert seen == res.history and [r["stage"] for r in seen] == [0, 0, 1, 1, 1, 1, 1, 1]
    assert also == list(range(1, 9))
    # the same times, to the rounding of readings 100 s apart
    assert [h["time"] for h in res.history] == pytest.approx([h["time"] for h in plain.history], rel=0, abs=1e-9)
    assert torch.equal(res.V, plain.V)
    for bad, says in ((["not callable"], r"callbacks\[0\] is not callable"), (3, "callbacks must be a callable")):
        with pytest.raises(ReconstructionError, match=says):
            reconstruct(sphere, "no such target.obj", "rbf", callbacks=bad, **kw)
    with pytest.raises(ReconstructionError, match="callback must be callable"):
        reconstruct(sphere, "no such target.obj", "rbf", callback="print", **kw)


def test_time_budget_stops_the_run(sphere, bunny, monkeypatch):
    _fake_clock(monkeypatch, 0.01)
    res = reconstruct(sphere, bunny, "vertex", time_budget=0.3, eval_times=(0.1,), **SMALL)
    assert res.history[-1]["time"] >= 0.3 and res.history[-2]["time"] < 0.3
    assert res.metrics[0]["time"] >= 0.1
    # a budget that ends before the first step says so: it returned the start as the result without a word
    from meshmei.reconstruct import ReconstructionWarning

    with pytest.warns(ReconstructionWarning, match="ran out before the first step: the result is the start"):
        res = reconstruct(sphere, bunny, "vertex", time_budget=1e-9, **SMALL)
    assert not res.history


def test_target_files_are_normalised(tmp_path):
    from meshmei.mesh import save_mesh

    V, F = icosphere(1)
    save_mesh(tmp_path / "big.obj", 10 * V + 3, F)
    Vt, _ = target_surface(tmp_path / "big.obj")
    ext = Vt.max(0).values - Vt.min(0).values
    assert float(ext.norm()) == pytest.approx(1.0, rel=1e-6)
    assert float((Vt.max(0).values + Vt.min(0).values).abs().max()) < 1e-6


@pytest.mark.parametrize("method", ["vertex", "largesteps"])
def test_a_diverging_run_is_a_floating_point_error(sphere, method):
    # one step at lr=1e30 throws the vertices to ~1e30: the next step's sampling stopped deep in
    # torch.multinomial (an Inf area weight) instead of the documented FloatingPointError
    # (without the guard of valid steps, which refuses such steps instead: see test_validity.py)
    with pytest.raises(FloatingPointError, match=r"mesh became unusable after step 1 .*lower the learning rate"):
        reconstruct(sphere, "bunny", method, steps=3, lr=1e30, n_samples=500, target_pool=2000, eval_samples=500,
                    valid_steps=False)


def _write(path, text):
    path.write_text(text)
    return path


# file name -> (contents, what the error message must say besides the path)
BAD_FILES = {
    "not_a_mesh.obj": ("this is not a mesh\n", "empty mesh"),
    "empty.obj": ("# no vertices, no faces\n", "empty mesh"),
    "nan.obj": ("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n", "NaN"),
    "flat.obj": ("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n", "zero surface area"),
}


@pytest.mark.parametrize("name", sorted(BAD_FILES))
def test_bad_target_file_fails_before_optimisation(tmp_path, sphere, name):
    text, says = BAD_FILES[name]
    path = _write(tmp_path / name, text)
    steps = []
    with pytest.raises(MeshError, match=says) as info:
        reconstruct(sphere, path, "rbf", steps=5, callback=lambda *a: steps.append(a), **SMALL)
    assert steps == []
    assert str(path) in str(info.value)


def test_other_bad_input(sphere, bunny, tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        reconstruct(sphere, tmp_path / "missing.obj", steps=5)
    V, F = sphere
    Vn = V.clone()
    Vn[3, 1] = float("nan")
    with pytest.raises(MeshError, match="NaN"):
        reconstruct((Vn, F), bunny, steps=5)
    with pytest.raises(MeshError, match="empty"):
        reconstruct((torch.zeros(0, 3), torch.zeros(0, 3, dtype=torch.int64)), bunny, steps=5)
    with pytest.raises(ValueError, match="method"):
        reconstruct(sphere, bunny, "magic", steps=5)
    with pytest.raises(ValueError, match="steps"):
        reconstruct(sphere, bunny, steps=0)
    with pytest.raises(ValueError, match="stage_fractions"):
        reconstruct(sphere, bunny, steps=5, stages=(100, 300), stage_fractions=(1.0,))
    with pytest.raises(ValueError, match="optimizer"):
        ReconstructionSettings(optimizer="sgd").resolved()
    with pytest.raises(ValueError, match="lr_decay"):
        ReconstructionSettings(lr_decay=0.0).resolved()
    s = ReconstructionSettings(method="rbf", lr=1e-3).resolved()
    assert s.lr == 1e-3 and s.reg_decay is True and s.optimizer == "uniform" and s.steps == DEFAULT_STEPS
    with pytest.raises(ValueError, match="source"):
        source_mesh(42)


def _cli(args, capsys):
    rc = main(["reconstruct"] + [str(a) for a in args])
    return rc, capsys.readouterr()


@pytest.mark.parametrize("name", sorted(BAD_FILES))
def test_cli_reports_bad_target_files(tmp_path, capsys, name):
    path = _write(tmp_path / name, BAD_FILES[name][0])
    rc, out = _cli(["--init", "sphere", "--n-vertices", 100, "--target", path, "--out", tmp_path / "o"], capsys)
    assert rc == 2
    assert out.err.startswith("meshmei reconstruct: error:")
    assert str(path) in out.err and BAD_FILES[name][1] in out.err
    assert not (tmp_path / "o").exists()


def test_cli_missing_target(tmp_path, capsys):
    rc, out = _cli(["--target", tmp_path / "nope.obj", "--out", tmp_path / "o"], capsys)
    assert rc == 2 and "mesh file not found" in out.err


def test_cli_writes_mesh_history_and_plots(tmp_path, capsys):
    out_dir = tmp_path / "run"
    rc, out = _cli(["--init", "sphere", "--n-vertices", 100, "--target", "bunny", "--out", out_dir,
                    "--method", "largesteps", "--steps", 6, "--samples", 500, "--eval-every", 3,
                    "--eval-samples", 2000, "--stages", "none", "--no-progress"], capsys)
    assert rc == 0, out.err
    for name in ("mesh.obj", "history.json", "loss.png", "metrics.png"):
        assert (out_dir / name).stat().st_size > 0
    rec = json.loads((out_dir / "history.json").read_text())
    assert rec["settings"]["method"] == "largesteps" and len(rec["history"]) == 6
    assert [m["step"] for m in rec["metrics"]] == [3, 6]
    assert rec["target"] == "bunny" and "Chamfer-L2" in out.out
    assert f"area {rec['final']['area_ratio']:.2f}x the target's" in out.out
    from meshmei.mesh import load_mesh

    V, F = load_mesh(out_dir / "mesh.obj")
    assert V.shape[0] == rec["n_vertices"]
    # the closing line and history.json carry the result's health, as recomputed from the saved mesh
    h = health_report(V, F)
    final = rec["final"]
    assert (final["self_intersections"], final["boundary_edges"], final["nonmanifold_edges"], final["watertight"]) \
        == (h["self_intersections"], h["boundary_edges"], h["nonmanifold_edges"], h["watertight"])
    assert final["min_quality"] == pytest.approx(h["min_quality"], abs=1e-6)  # mesh.obj keeps 8 decimals
    assert (f"{final['self_intersections']} self-intersecting pairs, {final['inverted_faces']} faces against the "
            f"target's normals, {final['degenerate_faces']} degenerate, min triangle quality {final['min_quality']:.3f}, "
            f"{'watertight' if h['watertight'] else 'open'}") in out.out


def test_cli_stage_schedules(tmp_path, capsys):
    from meshmei.shapes import initial_mesh

    n = initial_mesh("sphere", n_vertices=800)[0].shape[0]
    for spec, levels in (("auto", 2), ("auto2", 2), ("auto3", 3), ("auto4", 4)):  # auto: two levels for rbf below 2k
        out_dir = tmp_path / spec
        rc, out = _cli(["--init", "sphere", "--n-vertices", 800, "--target", "bunny", "--out", out_dir, "--steps", 8,
                        "--samples", 300, "--eval-samples", 1000, "--stages", spec, "--no-progress"], capsys)
        assert rc == 0, out.err
        settings = json.loads((out_dir / "history.json").read_text())["settings"]
        stages, shares = default_stages(n, levels)
        assert tuple(settings["stages"]) == stages
        assert tuple(settings["stage_fractions"]) == pytest.approx(shares)
        # three levels with rbf: the benchmark's rbf-3levels (half the samples in the first stage, lighter
        # smoothing in the fine stages), with the first stage's samples following --samples
        first = {**RBF_THREE_LEVEL_OVERRIDES[0], "n_samples": 150}
        want = [first, *RBF_THREE_LEVEL_OVERRIDES[1:]] if levels == 3 else None
        if levels == 4:  # the same, and the last stage at n lighter still, with twice --samples
            want = [first, *RBF_FOUR_LEVEL_OVERRIDES[1:-1], {**RBF_FOUR_LEVEL_OVERRIDES[-1], "n_samples": 600}]
        assert settings["stage_overrides"] == want
    out_dir = tmp_path / "ls3"
    rc, out = _cli(["--init", "sphere", "--n-vertices", 800, "--target", "bunny", "--out", out_dir, "--steps", 4,
                    "--samples", 300, "--eval-samples", 1000, "--stages", "auto3", "--method", "largesteps",
                    "--no-progress"], capsys)
    assert rc == 0, out.err
    settings = json.loads((out_dir / "history.json").read_text())["settings"]
    assert tuple(settings["stages"]) == default_stages(n, 3)[0] and settings["stage_overrides"] is None
    rc, out = _cli(["--target", "bunny", "--out", tmp_path / "bad", "--stages", "auto5", "--no-progress"], capsys)
    assert rc == 2 and "auto3" in out.err


def test_default_schedule_gives_rbf_three_levels_from_2k_vertices_and_four_from_8k():
    from meshmei.reconstruct import (FOUR_LEVEL_MIN_VERTICES, RBF_FOUR_LEVEL_OVERRIDES, THREE_LEVEL_MIN_VERTICES,
                                     default_schedule)

    # measured at 10k and at the CLI's default 2,500: its starts (torus 2,431 vertices, sphere 2,550) get them
    starts = [initial_mesh(name, n_vertices=2500)[0].shape[0] for name in ("torus", "sphere")]
    assert THREE_LEVEL_MIN_VERTICES <= min(starts) and THREE_LEVEL_MIN_VERTICES >= 16 * 100  # first stage >= 100
    for n in (THREE_LEVEL_MIN_VERTICES, *starts, FOUR_LEVEL_MIN_VERTICES - 1):
        assert default_schedule("rbf", n) == (*default_stages(n, 3), RBF_THREE_LEVEL_OVERRIDES)
    # from 8k (the benchmark's 10k) four: what three give n/4, then one lighter stage at n
    assert FOUR_LEVEL_MIN_VERTICES == 4 * THREE_LEVEL_MIN_VERTICES
    # the first four stages as three levels' (and capped as below), the last with a fifth of the fine
    # stages' Laplacian weight and twice the run's samples
    assert [{k: v for k, v in o.items() if k != "max_steps"} for o in RBF_FOUR_LEVEL_OVERRIDES[:4]] == [
        {k: v for k, v in o.items() if k != "max_steps"} for o in RBF_THREE_LEVEL_OVERRIDES]
    assert RBF_FOUR_LEVEL_OVERRIDES[4] == {"w_laplacian": RBF_THREE_LEVEL_OVERRIDES[-1]["w_laplacian"] / 5,
                                          "n_samples": 2 * ReconstructionSettings().n_samples}
    for n in (FOUR_LEVEL_MIN_VERTICES, 10_000, 28_000):
        assert default_schedule("rbf", n) == (*default_stages(n, 4), RBF_FOUR_LEVEL_OVERRIDES)
    for n in (THREE_LEVEL_MIN_VERTICES, *starts, 10_000, 28_000):
        for method in ("largesteps", "vertex"):
            assert default_schedule(method, n) == (*default_stages(n, 2), None)
    for method in ("rbf", "largesteps", "vertex"):
        n = THREE_LEVEL_MIN_VERTICES - 1
        assert default_schedule(method, n) == (*default_stages(n, 2), None)
    # forced levels: rbf with three or four always gets the lighter fine stages, the others never
    assert default_schedule("rbf", 2500, 3) == (*default_stages(2500, 3), RBF_THREE_LEVEL_OVERRIDES)
    assert default_schedule("rbf", 2500, 4) == (*default_stages(2500, 4), RBF_FOUR_LEVEL_OVERRIDES)
    assert default_schedule("rbf", 10_000, 3) == (*default_stages(10_000, 3), RBF_THREE_LEVEL_OVERRIDES)
    assert default_schedule("rbf", 10_000, 2) == (*default_stages(10_000, 2), None)
    assert default_schedule("largesteps", 10_000, 4) == (*default_stages(10_000, 4), None)
    assert default_schedule("largesteps", 2500, 3) == (*default_stages(2500, 3), None)
    # the first stage draws half the run's samples: 5,000 of the default 10,000, or half of what is asked,
    # and matches them by normal (the only stage that does)
    assert RBF_THREE_LEVEL_OVERRIDES[0] == {"n_samples": ReconstructionSettings().n_samples // 2, "normal_match": 0.3,
                                            "max_steps": 150}
    assert all("normal_match" not in (o or {}) for o in RBF_THREE_LEVEL_OVERRIDES[1:])
    assert default_schedule("rbf", 10_000, 3, n_samples=3001)[2] == ({"n_samples": 1500, "normal_match": 0.3,
                                                                      "max_steps": 150}, *RBF_THREE_LEVEL_OVERRIDES[1:])
    assert default_schedule("rbf", 10_000, n_samples=3001)[2] == (
        {"n_samples": 1500, "normal_match": 0.3, "max_steps": 150}, *RBF_FOUR_LEVEL_OVERRIDES[1:-1],
        {**RBF_FOUR_LEVEL_OVERRIDES[-1], "n_samples": 6002})
    # the last stage's twice the samples stays within what the settings take
    from meshmei.reconstruct.settings import MAX_SAMPLES

    assert default_schedule("rbf", 10_000, n_samples=MAX_SAMPLES)[2][-1]["n_samples"] == MAX_SAMPLES
    # the limits of the coarse stages and the first fine one are the steps a default run gives them: they cut
    # only longer budgets, and the last stage has none
    shares = default_stages(10_000, 3)[1]
    assert [o["max_steps"] for o in RBF_THREE_LEVEL_OVERRIDES[:3]] == [round(f * DEFAULT_STEPS) for f in shares[:3]]
    assert "max_steps" not in RBF_THREE_LEVEL_OVERRIDES[3]
    # four levels: up to the last stage at most the steps the default three-level run gives its stages (the
    # 2,500-vertex default run's, stage by stage), so a long budget goes to the last stage; the default run
    # at 10k gives each stage fewer steps than its limit, so the limits cut only longer budgets
    four = [o.get("max_steps") for o in RBF_FOUR_LEVEL_OVERRIDES]
    assert four == [round(f * DEFAULT_STEPS) for f in shares] + [None]
    for n in (FOUR_LEVEL_MIN_VERTICES, 10_000):
        steps = [round(f * DEFAULT_STEPS) for f in default_stages(n, 4)[1]]
        assert all(k < cap for k, cap in zip(steps, four[:-1]))
    assert default_schedule("largesteps", 10_000, 3, n_samples=3000)[2] is None
    with pytest.raises(ValueError, match="method"):
        default_schedule("bogus", 10_000)
    with pytest.raises(ValueError, match="levels"):
        default_schedule("rbf", 10_000, 5)
    for bad in (1, 2.5, True, "10000"):
        with pytest.raises(ValueError, match="n_samples"):
            default_schedule("rbf", 10_000, n_samples=bad)


def test_cli_auto_gives_rbf_four_levels_on_a_10k_torus(tmp_path, capsys):
    out_dir = tmp_path / "t10k"
    rc, out = _cli(["--init", "torus", "--n-vertices", 10_000, "--target", "teapot", "--out", out_dir, "--steps", 10,
                    "--samples", 500, "--eval-samples", 1000, "--no-progress"], capsys)
    assert rc == 0, out.err
    history = json.loads((out_dir / "history.json").read_text())
    settings = history["settings"]
    n = initial_mesh("torus", n_vertices=10_000)[0].shape[0]
    assert history["n_vertices"] > 0.9 * n  # the last stage ran (3 steps left it out, and the result at 2.5k)
    assert tuple(settings["stages"]) == default_stages(n, 4)[0]
    assert settings["stage_overrides"] == [{**RBF_FOUR_LEVEL_OVERRIDES[0], "n_samples": 250},  # half of --samples
                                           *RBF_FOUR_LEVEL_OVERRIDES[1:-1],
                                           {**RBF_FOUR_LEVEL_OVERRIDES[-1], "n_samples": 1000}]  # and twice


def test_cli_starts_a_torus_through_the_targets_opening(tmp_path, capsys):
    from meshmei.mesh import load_mesh

    out_dir = tmp_path / "teapot"
    rc, out = _cli(["--init", "torus", "--n-vertices", 300, "--target", "teapot", "--out", out_dir,
                    "--steps", 3, "--samples", 500, "--eval-samples", 2000, "--stages", "none", "--no-progress"],
                   capsys)
    assert rc == 0, out.err
    assert "placed through the target's opening" in out.out
    V, _ = load_mesh(out_dir / "mesh.obj")
    centre = 0.5 * (V.min(0).values + V.max(0).values)
    assert float(centre[0]) < -0.2  # the start sat at the handle, left of the body, and three steps keep it there
    # the centred torus on request
    rc, out = _cli(["--init", "torus-centred", "--n-vertices", 300, "--target", "teapot", "--out", tmp_path / "c",
                    "--steps", 1, "--samples", 500, "--eval-samples", 2000, "--stages", "none", "--no-progress"],
                   capsys)
    assert rc == 0, out.err
    assert "placed centred" in out.out
    V, _ = load_mesh(tmp_path / "c" / "mesh.obj")
    assert float((0.5 * (V.min(0).values + V.max(0).values)).abs().max()) < 0.02
    # a target without a hole: a clear error and exit status 2, before any optimisation
    rc, out = _cli(["--init", "torus-through-opening", "--target", "bunny", "--out", tmp_path / "b", "--steps", 3,
                    "--no-progress"], capsys)
    assert rc == 2 and "no through-hole" in out.err and not (tmp_path / "b" / "mesh.obj").exists()


def test_source_mesh_places_the_torus_for_its_target():
    from meshmei.reconstruct import SOURCE_NAMES, source_mesh
    from meshmei.reconstruct.openings import torus_through_opening

    teapot, bunny = target_surface("teapot"), target_surface("bunny")
    centred = initial_mesh("torus", n_vertices=300)
    threaded = torus_through_opening(*teapot, n_vertices=300)
    for spec, target, want in [("torus", teapot, threaded), ("torus", None, centred), ("torus", bunny, centred),
                               ("torus-centred", teapot, centred), ("torus-through-opening", teapot, threaded)]:
        V, F = source_mesh(spec, n_vertices=300, target=target)
        assert torch.equal(V, want[0]) and torch.equal(F, want[1]), (spec, target is None)
    for name in ("sphere", "sheet"):  # the others do not depend on the target
        V, F = source_mesh(name, n_vertices=300, target=teapot)
        assert torch.equal(V, initial_mesh(name, n_vertices=300)[0])
    assert set(SOURCE_NAMES) == {"sheet", "sphere", "torus", "torus-centred", "torus-through-opening"}
    with pytest.raises(ValueError, match="needs the target"):
        source_mesh("torus-through-opening", n_vertices=300)
    with pytest.raises(MeshError, match="no through-hole"):
        source_mesh("torus-through-opening", n_vertices=300, target=bunny)
    # reconstruct resolves a named start against its target
    res = reconstruct("torus", "teapot", "rbf", steps=1, n_samples=500, target_pool=2000, eval_samples=1000)
    centre = 0.5 * (res.V.min(0).values + res.V.max(0).values)
    assert res.V.shape[0] == initial_mesh("torus", n_vertices=2500)[0].shape[0] and float(centre[0]) < -0.2


@pytest.mark.slow
def test_torus_to_teapot_with_default_stages():
    src = initial_mesh("torus", n_vertices=1000)
    stages, fr = default_stages(1000)
    res = reconstruct(src, "teapot", "rbf", steps=300, stages=stages, stage_fractions=fr)
    # guarded (the default) at this small budget: 1.08e-4 and F-score 0.897 with no intersecting pair; without
    # guard and barriers 1.74e-5 and 0.985 with 1,108 pairs (2026-11-28; the F-score bound of 0.9 predates the
    # guard and had failed since at least 9673eb4, unnoticed: slow tests do not run in CI)
    assert res.final.chamfer_l2 < 2e-4
    assert res.final.fscore > 0.85
    assert res.final.self_intersections == 0 and res.final.watertight


@pytest.mark.parametrize("module", ["meshmei.deform.rbf", "meshmei.metrics", "meshmei.deform.largesteps", "meshmei.reconstruct.fit"])
def test_docstring_examples_run(module):
    import doctest
    import importlib

    res = doctest.testmod(importlib.import_module(module))
    assert res.attempted > 0 and res.failed == 0


def test_regularizer_weights_follow_each_stages_resolution(sphere, bunny):
    from meshmei.regularizers import laplacian_loss

    n = sphere[0].shape[0]
    # One stage: the source's count; the first step's loss is Chamfer + weight * Laplacian at V0 (a large
    # weight, so that the float32 difference loss - chamfer resolves the term).
    res = reconstruct(sphere, bunny, "vertex", steps=1, w_laplacian=1e4, **SMALL)
    w = 1e4 * (n / 2500) ** 2
    assert res.info["w_laplacian"] == pytest.approx(w, rel=1e-12)
    h = res.history[0]
    assert h["loss"] - h["chamfer"] == pytest.approx(w * float(laplacian_loss(*sphere)), rel=1e-4)
    # Two stages: the first takes the second's count, so both use the final one; edge and ARAP weights
    # scale linearly.
    res = reconstruct(sphere, bunny, "rbf", steps=2, stages=(100, 400), w_laplacian=10.0, w_edge=2.0, w_arap=3.0,
                      **SMALL)
    r = 400 / 2500
    assert (res.info["w_laplacian"], res.info["w_edge"], res.info["w_arap"]) == pytest.approx((10 * r**2, 2 * r, 3 * r))
    for st in res.info["stages"]:
        assert (st["w_laplacian"], st["w_edge"], st["w_arap"]) == pytest.approx((10 * r**2, 2 * r, 3 * r))
    # Three counts: each stage its own, except the first, which takes the second's.
    res = reconstruct(sphere, bunny, "rbf", steps=3, stages=(50, 100, 400), w_laplacian=10.0, w_edge=2.0,
                      **SMALL)
    got = [w for st in res.info["stages"] for w in (st["w_laplacian"], st["w_edge"])]
    want = [w for c in (100, 100, 400) for w in (10 * (c / 2500) ** 2, 2 * c / 2500)]
    assert got == pytest.approx(want, rel=1e-12)
    # A later stage coarser than the second takes its own count (it took the larger of the two)
    from meshmei.reconstruct import stage_weights

    for stages, counts in (((625, 2500, 1000), (2500, 2500, 1000)), ((10000, 2500, 625), (2500, 2500, 625))):
        st = ReconstructionSettings(stages=stages, steps=10).resolved()
        got = [stage_weights(st, st, k, 2500)[0] for k in range(3)]
        assert got == pytest.approx([10.0 * (c / 2500) ** 2 for c in counts], rel=1e-12)
    # None: the weights as given.
    res = reconstruct(sphere, bunny, "vertex", steps=1, w_laplacian=10.0, reg_ref_vertices=None, **SMALL)
    assert res.info["w_laplacian"] == 10.0
    for bad in (0, -5, 2.5, True, "2500"):
        with pytest.raises(ValueError, match="reg_ref_vertices"):
            ReconstructionSettings(reg_ref_vertices=bad).resolved()


def test_laplacian_loss_falls_like_n_squared_which_the_weight_scaling_undoes():
    # On icospheres (642 -> 10,242 vertices) the raw uniform Laplacian loss falls about 100x; times (n/ref)^2
    # it changes 2.5x (the umbrella vectors' tangential part on an uneven mesh falls slower than h^2).
    from meshmei.regularizers import edge_loss, laplacian_loss

    (Va, Fa), (Vb, Fb) = icosphere(3), icosphere(5)
    na, nb = Va.shape[0], Vb.shape[0]
    raw = float(laplacian_loss(Va, Fa)) / float(laplacian_loss(Vb, Fb))
    scaled = raw * (na / nb) ** 2
    assert raw > 50 and 1 / 4 < scaled < 4
    edge = float(edge_loss(Va, Fa)) / float(edge_loss(Vb, Fb)) * (na / nb)
    assert raw > 50 and edge == pytest.approx(1.0, abs=0.05)


def test_stage_overrides_set_each_stages_sample_count(monkeypatch):
    import importlib

    R = importlib.import_module("meshmei.reconstruct.fit")  # the module that runs the loop

    drawn = []
    original = R.sample_points

    def spy(V, F, n, **kwargs):
        drawn.append(n)
        return original(V, F, n, **kwargs)

    monkeypatch.setattr(R, "sample_points", spy)
    src = initial_mesh("sphere", n_vertices=300)
    res = reconstruct(src, "bunny", "rbf", steps=6, stages=(100, 300), stage_overrides=({"n_samples": 300}, None),
                      n_samples=700, target_pool=2000, eval_samples=1000)
    assert drawn[0] == 2000  # the target pool, drawn once
    assert drawn[1:] == [300 if h["stage"] == 0 else 700 for h in res.history]
    assert {h["stage"] for h in res.history} == {0, 1}
    with pytest.raises(ValueError, match="stage 0: n_samples must be a positive integer, got 0"):
        reconstruct(src, "bunny", "rbf", steps=2, stages=(100, 300), stage_overrides=({"n_samples": 0}, None))


@pytest.mark.parametrize("method", ["largesteps", "vertex"])
def test_a_method_given_in_settings_is_honoured(sphere, method):
    from meshmei.reconstruct import ReconstructionSettings

    small = dict(steps=2, n_samples=300, target_pool=1000, eval_samples=500)
    res = reconstruct(sphere, "bunny", settings=ReconstructionSettings(method=method, **small))
    assert res.settings.method == method and res.info["stages"][0]["method"] == method
    # an explicit method still replaces the settings' one
    res = reconstruct(sphere, "bunny", "rbf", settings=ReconstructionSettings(method=method, **small))
    assert res.settings.method == "rbf"


def test_cli_contact_edges_choice_reaches_the_settings(tmp_path, capsys):
    for choice, value in (("auto", "auto"), ("on", True), ("off", False)):
        out_dir = tmp_path / choice
        rc, out = _cli(["--init", "sphere", "--n-vertices", 100, "--target", "bunny", "--out", out_dir, "--steps", 3,
                        "--samples", 300, "--eval-samples", 1000, "--stages", "none", "--contact-edges", choice,
                        "--no-progress"], capsys)
        assert rc == 0, out.err
        rec = json.loads((out_dir / "history.json").read_text())
        assert rec["settings"]["contact_edges"] == value
    with pytest.raises(SystemExit) as exc:
        main(["reconstruct", "--contact-edges", "sometimes"])
    assert exc.value.code == 2 and "--contact-edges" in capsys.readouterr().err


def test_unused_vertices_of_a_source_or_target_change_nothing(sphere, tmp_path):
    # an unused vertex far away used to stretch the target's unit-diagonal box (to 0.02 of the surface)
    # and the source's RBF kernel scale
    import trimesh

    V, F = sphere
    Vt, Ft = icosphere(2)
    far = torch.tensor([[50.0, 50.0, 50.0]])
    plain = reconstruct((V, F), (Vt, Ft), "rbf", steps=5, **SMALL)
    padded = reconstruct((torch.cat([far, V]), F + 1), (torch.cat([Vt, far.double()]), Ft), "rbf", steps=5, **SMALL)
    assert torch.equal(padded.V, plain.V) and torch.equal(padded.F, plain.F)
    assert padded.final == plain.final
    assert padded.info["stages"][0]["sigma_median"] == plain.info["stages"][0]["sigma_median"]
    path = tmp_path / "padded.ply"  # PLY keeps unused vertices
    trimesh.Trimesh(torch.cat([Vt, 100 * far.double()]).numpy(), Ft.numpy(), process=False).export(str(path))
    Vn, Fn = target_surface(path)
    torch.testing.assert_close(Vn, target_surface((Vt, Ft))[0], rtol=0, atol=1e-6)
    assert torch.equal(Fn, Ft)
    assert torch.equal(source_mesh(path)[1], Ft) and source_mesh(path)[0].shape == Vt.shape


@pytest.mark.parametrize("dtype", [torch.uint16, torch.uint32, torch.uint64])
def test_unsigned_faces_are_accepted(sphere, dtype):
    V, F = sphere
    for faces in (F.to(dtype), F.numpy().astype(str(dtype).split(".")[1])):
        assert torch.equal(source_mesh((V, faces))[1], F)
        assert torch.equal(target_surface((V, faces))[1], F)


def test_a_start_under_32_vertices_runs_the_automatic_schedule_in_one_stage(tmp_path, capsys):
    from meshmei.mesh import save_mesh
    from meshmei.reconstruct import default_schedule, schedule_from_text
    from meshmei.reconstruct.settings import MIN_STAGE_VERTICES

    for n in range(1, MIN_STAGE_VERTICES):
        for method in ("rbf", "vertex", "largesteps"):
            for levels in (None, 2, 3, 4):
                assert default_schedule(method, n, levels) == (None, None, None)
        with pytest.raises(ValueError, match=f"needs at least 32 vertices, got {n}"):
            default_stages(n)
    for n in range(MIN_STAGE_VERTICES, 300):  # every automatic schedule resolves
        for spec in ("auto", "auto2", "auto3", "auto4"):
            stages, fractions, overrides = schedule_from_text(spec, "rbf", n)
            ReconstructionSettings(stages=stages, stage_fractions=fractions, stage_overrides=overrides).resolved()
    tet = tmp_path / "tet.obj"
    save_mesh(tet, torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]),
              torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]))
    base = ["--init", tet, "--target", "bunny", "--steps", 3, "--samples", 300, "--eval-samples", 500, "--no-progress"]
    rc, out = _cli(base + ["--out", tmp_path / "auto"], capsys)
    assert rc == 0, out.err
    rec = json.loads((tmp_path / "auto" / "history.json").read_text())
    assert rec["settings"]["stages"] is None and rec["n_vertices"] == 4
    rc, out = _cli(base + ["--out", tmp_path / "bad", "--stages", "16,64"], capsys)
    assert rc == 2 and "--stages 16,64: every stage needs at least 32 vertices (the start has 4)" in out.err
    with pytest.raises(ValueError, match=r"at least 32, got \(16, 64\) \(stages=None runs one stage"):
        ReconstructionSettings(stages=(16, 64)).resolved()


@pytest.mark.parametrize("field, value", [
    ("lr", float("inf")), ("lr", float("nan")), ("r_cut", float("inf")), ("contact_distance", float("inf")),
    ("stage_fractions", (float("nan"), 1.0)), ("stage_fractions", (float("inf"), 1.0)),
    ("seed", 1.5), ("seed", 10 ** 23), ("seed", -(2 ** 63) - 1), ("seed", True), ("seed", "0"),
])
def test_settings_refuse_non_finite_values_and_bad_seeds(field, value):
    from meshmei.errors import ReconstructionError

    kw = {field: value, **({"stages": (100, 300)} if field == "stage_fractions" else {})}
    with pytest.raises(ReconstructionError, match=f"{field} must .* got {re.escape(repr(value))}$"):
        ReconstructionSettings(**kw).resolved()


def test_seeds_are_those_of_distinct_runs():
    """torch's CPU generator keeps a seed's low 32 bits: seeds 0, 2**32, 2**63 and -2**63 gave one run, bit for bit,
    although the documented range was -2**63 .. 2**64 - 2. The range is now the seeds of distinct runs."""
    import numpy as np

    from meshmei._checks import SEED_RANGE
    from meshmei.errors import ReconstructionError

    assert SEED_RANGE == (0, 2 ** 32 - 1)
    for seed in (0, 1, 2 ** 32 - 1, np.uint32(2 ** 32 - 1)):
        assert ReconstructionSettings(seed=seed).resolved().seed == seed
        torch.Generator().manual_seed(int(seed) + 1)  # the metrics' target seed fits as well
    draw = [torch.rand(4, generator=torch.Generator().manual_seed(s)) for s in (0, 2 ** 32, 2 ** 63, -(2 ** 63))]
    assert all(torch.equal(d, draw[0]) for d in draw)  # why: one run, four seeds
    for seed, twin in ((2 ** 32, 0), (2 ** 63, 0), (-(2 ** 63), 0), (-1, 2 ** 32 - 1), (2 ** 32 + 5, 5)):
        with pytest.raises(ReconstructionError, match=rf"^seed must lie in \[0, 4294967295\], the seeds of distinct "
                                                      rf"runs \(torch's CPU generator keeps a seed's low 32 bits; "
                                                      rf"{seed} gives the run of {twin}\), got {seed}$"):
            ReconstructionSettings(seed=seed).resolved()


@pytest.mark.parametrize("stages", [None, "auto"])
def test_a_source_beyond_float32s_range_asks_to_rescale_whatever_the_schedule(sphere, stages):
    from meshmei.reconstruct import default_schedule

    V, F = sphere
    kw = {}
    if stages == "auto":
        st, fr, ov = default_schedule("rbf", V.shape[0])
        kw = dict(stages=st, stage_fractions=fr, stage_overrides=ov)
    with pytest.raises(MeshError, match=r"^source: the face areas overflow torch.float32 .*rescale the mesh"):
        reconstruct((1e20 * V, F), "bunny", steps=4, **SMALL, **kw)
    # a float64 target is normalised before it is cast: beyond float32's range it still fits once scaled
    big = torch.cat([torch.tensor([[1e39, 0, 0]], dtype=torch.float64), V[1:].double()])
    assert bool(torch.isfinite(target_surface((big, F))[0]).all())
    with pytest.raises(MeshError, match=r"target: coordinates up to 1e\+39 do not fit in torch.float32"):
        target_surface((big, F), normalize=False)
    # a float64 target at 1e155, whose squared diagonal overflows float64, was called "zero surface area": it is
    # normalised as at 1 (scaled by a power of two first), and kept at its scale it is refused as overflowing
    assert torch.allclose(target_surface((1e155 * V.double(), F))[0], target_surface((V, F))[0], rtol=0, atol=1e-7)
    with pytest.raises(MeshError, match=r"^target: the face areas overflow torch.float64 \(largest coordinate "
                                        r"\S+e\+154\); rescale the mesh$"):
        target_surface((1e155 * V.double(), F), normalize=False, dtype=torch.float64)


def test_a_bfloat16_source_runs_in_bfloat16(sphere):
    V, F = sphere
    res = reconstruct((V.bfloat16(), F), "bunny", steps=3, **SMALL)
    assert res.V.dtype == torch.bfloat16 and res.V.shape == V.shape
    assert torch.isfinite(res.V.float()).all() and res.final.chamfer_l2 > 0


def _write_obj(path, V, F):
    """An OBJ with every float64 digit (save_mesh rounds to what trimesh writes)."""
    with open(path, "w") as fh:
        fh.writelines("v %r %r %r\n" % tuple(float(x) for x in v) for v in V)
        fh.writelines("f %d %d %d\n" % tuple(int(i) + 1 for i in t) for t in F)
    return path


def _slow_remeshes(monkeypatch, seconds: float, tick: float = 0.005) -> list:
    """A fake clock, and a remesh that takes ``seconds`` on it; returns the list of counts remeshed to."""
    import importlib

    fit = importlib.import_module("meshmei.reconstruct.fit")
    remesh, clock, calls = fit._remesh_clean, _fake_clock(monkeypatch, tick), []

    def slow_remesh(V, F, n, *args, **kwargs):
        clock.sleep(seconds)
        calls.append(n)
        return remesh(V, F, n, *args, **kwargs)

    monkeypatch.setattr(fit, "_remesh_clean", slow_remesh)
    return calls


def test_final_metrics_describe_the_returned_mesh_after_a_remesh(sphere, bunny, monkeypatch):
    # A time-budgeted run whose last stage gets no step (its remesh spends the rest of the budget): the
    # final metrics used to be the last evaluation's, of the mesh before the remesh.
    _slow_remeshes(monkeypatch, 0.6)  # past the whole budget
    n = sphere[0].shape[0]
    res = reconstruct(sphere, bunny, "rbf", time_budget=0.3, stages=(n, 100), eval_every=1,
                      **dict(SMALL, eval_samples=2000))
    assert [st["n_vertices"] for st in res.info["stages"]] == [n, res.V.shape[0]] and res.V.shape[0] < n
    assert res.info["stages"][1]["steps"] == 0
    assert res.metrics[-1]["n_vertices"] == res.V.shape[0]
    assert res.final == surface_metrics(res.V, res.F, *bunny, n_samples=2000, seed=0, health=True)


def test_a_stage_at_its_step_limit_passes_the_rest_of_its_share_on(sphere, bunny):
    from meshmei.errors import ReconstructionError

    # steps: stage 0's share is 12 of 40 steps and its limit 5; the 35 left go to stages 1 and 2 as 3 : 4
    # (their shares 0.3 : 0.4), 15 and 20 (bounds 5/40 + 0.3/0.7 * 35/40 = 0.5, then 1)
    ov = ({"max_steps": 5}, None, None)
    res = reconstruct(sphere, bunny, "rbf", steps=40, stages=(100, 300, 300), stage_fractions=(0.3, 0.3, 0.4),
                      stage_overrides=ov, **SMALL)
    stages = res.info["stages"]
    assert [st["end_step"] for st in stages] == [5, 20, 40] and len(res.history) == 40
    assert stages[0]["max_steps"] == 5 and stages[0]["ended_at_max_steps"] is True
    assert "max_steps" not in stages[1] and "max_steps" not in stages[2]
    # a limit the share does not reach changes nothing, bit for bit
    a = reconstruct(sphere, bunny, "rbf", steps=40, stages=(100, 300), stage_fractions=(0.25, 0.75), seed=2, **SMALL)
    b = reconstruct(sphere, bunny, "rbf", steps=40, stages=(100, 300), stage_fractions=(0.25, 0.75), seed=2,
                    stage_overrides=({"max_steps": 10}, None), **SMALL)
    assert torch.equal(a.V, b.V) and [h["loss"] for h in a.history] == [h["loss"] for h in b.history]
    assert b.info["stages"][0]["end_step"] == 10 and b.info["stages"][0]["ended_at_max_steps"] is False
    # a time budget: the stage after takes the time, and the run still uses the whole budget
    res = reconstruct(sphere, bunny, "rbf", time_budget=1.0, stages=(100, 300), stage_fractions=(0.9, 0.1),
                      stage_overrides=({"max_steps": 3}, None), **SMALL)
    stages = res.info["stages"]
    assert stages[0]["end_step"] == 3 and stages[0]["ended_at_max_steps"] is True
    assert stages[1]["steps"] > 0 and res.history[-1]["time"] >= 1.0
    # on the last stage, or a run without stages, the limit ends the run
    res = reconstruct(sphere, bunny, "rbf", steps=40, stages=(100, 300), stage_overrides=(None, {"max_steps": 4}),
                      **SMALL)
    assert [st["end_step"] for st in res.info["stages"]] == [20, 24] and len(res.history) == 24
    assert len(reconstruct(sphere, bunny, "rbf", steps=40, max_steps=7, **SMALL).history) == 7
    for bad in (0, -1, 2.5, True, "10"):
        with pytest.raises(ReconstructionError, match="max_steps must be a positive integer or None"):
            ReconstructionSettings(max_steps=bad).resolved()
        with pytest.raises(ReconstructionError, match="stage 0: max_steps must be a positive integer or None"):
            reconstruct(sphere, bunny, "rbf", steps=4, stages=(100, 300), stage_overrides=({"max_steps": bad}, None),
                        **SMALL)


@pytest.mark.parametrize("remesh_seconds, merged", [(0.2, True), (0.1, False)])
def test_a_restart_that_cannot_pay_for_its_set_up_is_merged(sphere, bunny, monkeypatch, remesh_seconds, merged):
    # stage 2 restarts at stage 1's count with a share of 0.3 s: a set-up of over 0.15 s (half of it) would
    # leave it fewer steps than it spent setting up, so stage 1 runs on through its share instead
    import importlib

    multiple = 2.0  # the module's RESTART_SETUP_MULTIPLE, set here: the remesh times above assume it
    monkeypatch.setattr(importlib.import_module("meshmei.reconstruct.fit"), "RESTART_SETUP_MULTIPLE", multiple)
    calls = _slow_remeshes(monkeypatch, remesh_seconds)
    res = reconstruct(sphere, bunny, "rbf", time_budget=1.0, stages=(100, 300, 300), stage_fractions=(0.4, 0.3, 0.3),
                      **SMALL)
    stages = res.info["stages"]
    setup = stages[1]["setup_seconds"]
    assert remesh_seconds < setup < remesh_seconds + 0.1  # the remesh, and the rest of the set-up on the fake clock
    assert (0.3 < multiple * setup) == merged
    assert len(stages) == 3 and all(st["steps"] > 0 for st in stages[:2])
    assert res.history[-1]["time"] >= 1.0  # the budget is used either way
    if merged:
        assert calls == [100, 300]
        assert stages[2] == {"n_vertices": res.V.shape[0], "end_step": stages[1]["end_step"], "steps": 0,
                             "merged_into": 1}
        assert {h["stage"] for h in res.history} == {0, 1} and stages[1]["end_step"] == len(res.history)
    else:
        assert calls == [100, 300, 300]
        assert stages[2]["steps"] > 0 and "merged_into" not in stages[2]
        assert [h["stage"] for h in res.history].count(2) == stages[2]["steps"]


def test_a_restart_is_not_merged_under_a_step_budget_or_with_its_own_settings(sphere, bunny, monkeypatch):
    calls = _slow_remeshes(monkeypatch, 5.0)  # longer than any budget here
    res = reconstruct(sphere, bunny, "rbf", steps=30, stages=(100, 300, 300), stage_fractions=(0.2, 0.5, 0.3),
                      **SMALL)
    assert calls == [100, 300, 300] and [st["end_step"] for st in res.info["stages"]] == [6, 21, 30]
    # the run that merges its restart above (a 0.2 s remesh, a 0.3 s share), the restart with its own weight
    import importlib

    monkeypatch.undo()
    multiple = 2.0  # the module's RESTART_SETUP_MULTIPLE, set here as in the test above
    monkeypatch.setattr(importlib.import_module("meshmei.reconstruct.fit"), "RESTART_SETUP_MULTIPLE", multiple)
    calls = _slow_remeshes(monkeypatch, 0.2)
    res = reconstruct(sphere, bunny, "rbf", time_budget=1.0, stages=(100, 300, 300), stage_fractions=(0.4, 0.3, 0.3),
                      stage_overrides=(None, None, {"w_laplacian": 1.0}), **SMALL)
    assert calls == [100, 300, 300] and res.info["stages"][2]["steps"] > 0
    assert 0.3 < multiple * res.info["stages"][1]["setup_seconds"]  # would merge with equal settings


def test_a_guarded_stage_bounds_a_step_to_one_mean_edge(sphere, bunny, monkeypatch):
    # the step bound is four barrier reaches, one mean edge of the stage's start at the default reach (a
    # quarter edge); half an edge halved nearly every step of a short run's coarse stages
    import importlib

    from meshmei.contact import mean_edge_length

    fit = importlib.import_module("meshmei.reconstruct.fit")
    seen = []

    class Spy(fit.StepGuard):
        def __init__(self, V, F, rules, *args, **kwargs):
            seen.append((mean_edge_length(V, F), rules.max_step))
            super().__init__(V, F, rules, *args, **kwargs)

    monkeypatch.setattr(fit, "StepGuard", Spy)
    reconstruct(sphere, bunny, "rbf", steps=4, stages=(100, 300), **SMALL)
    assert len(seen) == 2 and all(step == pytest.approx(edge, rel=1e-12) for edge, step in seen)
    assert seen[0][0] > 1.5 * seen[1][0]  # each stage's own edge: 100 vertices, then 300


def test_a_target_far_from_the_origin_is_normalised_in_float64(tmp_path):
    V, F = icosphere(3)
    near = target_surface(_write_obj(tmp_path / "near.obj", V, F))[0]
    far = target_surface(_write_obj(tmp_path / "far.obj", V + 1e5, F))[0]
    assert near.dtype == far.dtype == torch.float32
    torch.testing.assert_close(far, near, rtol=0, atol=1e-6)  # float32 first: shifted by up to 1e-2
    pair = target_surface((V + 1e5, F))[0]
    torch.testing.assert_close(pair, near, rtol=0, atol=1e-6)


def test_a_source_file_that_float32_cannot_hold_is_refused(tmp_path):
    V, F = icosphere(3)
    path = _write_obj(tmp_path / "far.obj", 0.01 * V + 1e5, F)  # edges 1e-3 long, float32 steps there 8e-3
    with pytest.raises(MeshError, match=r"source .*far.obj: \d+ of 1280 faces collapse to zero area in torch.float32"):
        source_mesh(path)
    Vs, _ = source_mesh(path, dtype=torch.float64)  # used as stored where the dtype holds it
    assert torch.equal(Vs, 0.01 * V + 1e5)


@pytest.mark.parametrize("scale", [1e-30, 1e30])
def test_normalize_unit_diagonal_takes_tiny_and_huge_float32_meshes(scale):
    from meshmei.shapes import normalize_unit_diagonal

    V, F = icosphere(2)
    W = normalize_unit_diagonal((V * scale).float())
    assert W.dtype == torch.float32
    torch.testing.assert_close(W, normalize_unit_diagonal(V).float(), rtol=0, atol=1e-6)
    torch.testing.assert_close(target_surface(((V * scale).float(), F))[0], W, rtol=0, atol=0)


@pytest.mark.parametrize("field, value", [
    ("lr_scale", float("inf")), ("coarse_lr", float("inf")), ("w_contact", float("inf")),
    ("w_laplacian", float("inf")), ("w_edge", float("inf")), ("w_arap", float("inf")), ("lam", float("inf")),
    ("eval_times", (float("nan"),)), ("eval_times", (1.0, float("inf"))), ("eval_times", (-1.0,)),
    ("eval_samples", 2000.5), ("n_samples", 100.5), ("target_pool", True), ("eval_every", 2.5),
    # each ran as something else, failed after the run had started, or raised a TypeError / OverflowError
    ("eval_times", "10"), ("centers", -5), ("centers", 2.5), ("centers", True), ("time_budget", "10"),
])
def test_settings_refuse_infinite_weights_and_bad_counts_up_front(sphere, field, value):
    from meshmei.errors import ReconstructionError

    with pytest.raises(ReconstructionError, match=f"^{field} must .* got {re.escape(repr(value))}$"):
        ReconstructionSettings(**{field: value}).resolved()
    steps = []
    with pytest.raises(ReconstructionError, match=f"^{field} must"):  # before the first step
        reconstruct(sphere, "bunny", steps=3, callback=lambda *a: steps.append(a), **{**SMALL, field: value})
    assert steps == []


def test_stage_settings_that_failed_late_are_refused_up_front():
    from meshmei.errors import ReconstructionError

    with pytest.raises(ReconstructionError, match=r"^centers given as vertex indices name the source's vertices"):
        ReconstructionSettings(centers=[0, 3, 6], stages=(100, 200)).resolved()  # reused on remeshed stages
    with pytest.raises(ReconstructionError, match=r"^centers=150 exceeds the smallest stage's 100 vertices"):
        ReconstructionSettings(centers=150, stages=(300, 100)).resolved()  # stage 1 failed after stage 0 ran
    with pytest.raises(ReconstructionError, match=r"^stage_fractions must give one positive, finite share"):
        ReconstructionSettings(stages=(100, 100), stage_fractions=(1e308, 1e308)).resolved()  # summed to inf: (0, 0)
    with pytest.raises(ReconstructionError, match=r"^stage_fractions must give one positive, finite share"):
        ReconstructionSettings(stages=(100, 200), stage_fractions=0.5).resolved()  # a TypeError
    with pytest.raises(ReconstructionError, match=r"^steps must be a positive integer, got inf$"):
        ReconstructionSettings(steps=float("inf")).resolved()  # an OverflowError
    with pytest.raises(ReconstructionError, match=r"^contact_distance must be at most 4 mean edge lengths, got 1000000000.0$"):
        ReconstructionSettings(contact_distance=1e9).resolved()  # a 4-step run took 77 s instead of 0.7 s
    for name in ("n_samples", "target_pool", "eval_samples"):  # 10**9 samples ran out of memory, killed silently
        with pytest.raises(ReconstructionError, match=rf"^{name} must be at most 10,000,000 samples, got 1000000000$"):
            ReconstructionSettings(**{name: 10**9}).resolved()
        ReconstructionSettings(**{name: 10**7}).resolved()  # the bound itself is allowed
    with pytest.raises(ValueError, match="stage 0: n_samples must be at most 10,000,000"):  # per stage too
        ReconstructionSettings(stages=(100, 300), stage_overrides=({"n_samples": 10**8}, None)).resolved()
    for stages in (500, (float("inf"),), (100.7, 500.9)):  # a TypeError, an OverflowError, truncated to (100, 500)
        with pytest.raises(ReconstructionError, match=rf"^stages must be integer vertex counts of at least 32, got "
                                                      rf"{re.escape(repr(stages))} \(stages=None"):
            ReconstructionSettings(stages=stages).resolved()


def test_a_stage_whose_remesh_would_multiply_the_mesh_keeps_the_mesh_it_had(sphere):
    """A needle's remesh to 40 vertices gave hundreds (to 160: 108,102 on a thinner one, and the run's checks
    then ran for minutes): the stage runs on the mesh it had, and says so."""
    from meshmei.reconstruct import ReconstructionWarning

    V, F = initial_mesh("sphere", n_vertices=160)[:2]
    needle = V * torch.tensor([20.0, 0.02, 0.02])
    with pytest.warns(ReconstructionWarning, match=r"stage 0: remeshing to about 40 vertices gave \d+: the mesh has "
                                                   r"parts thinner .*the stage runs on the mesh it had, \d+ vertices"):
        res = reconstruct((needle, F), "bunny", steps=4, stages=(40, 160), **SMALL)
    assert res.info["stages"][0]["n_vertices"] == V.shape[0] and len(res.history) == 4
    assert any("remeshing to about 40 vertices gave" in w for w in res.info["warnings"])


def test_a_step_budget_that_leaves_a_stage_without_a_step_is_refused():
    """--steps 3 --stages auto4 ran four of its five stages and ended on a 60-vertex mesh, without a word."""
    from meshmei.errors import ReconstructionError

    stages, fractions = (32, 32, 48, 48, 194), (0.1, 0.15, 0.3, 0.2, 0.25)
    with pytest.raises(ReconstructionError, match=r"^steps=3 gives stage 1 \(32 vertices\) no step with "
                                                  r"stage_fractions \(0.1, 0.15, 0.3, 0.2, 0.25\); give at least 10 "
                                                  r"steps, or fewer stages$"):
        ReconstructionSettings(steps=3, stages=stages, stage_fractions=fractions).resolved()
    ReconstructionSettings(steps=10, stages=stages, stage_fractions=fractions).resolved()  # each stage a step
    ReconstructionSettings(time_budget=0.1, stages=stages, stage_fractions=fractions).resolved()  # time: no count
    with pytest.raises(ReconstructionError, match=r"^steps=2 gives stage 2 \(300 vertices\) no step"):
        ReconstructionSettings(steps=2, stages=(100, 200, 300)).resolved()  # equal shares: thirds of 2 steps


@pytest.mark.parametrize("kwargs, says", [
    (dict(method="largesteps", lr_scale=0.01), "lr_scale=0.01 applies only with method='rbf', not with method='largesteps'"),
    (dict(method="vertex", centers=10), "centers=10 applies only with method='rbf'"),
    (dict(method="largesteps", sigma_factor=2.0), "sigma_factor=2.0 applies only with method='rbf'"),
    (dict(method="vertex", r_cut=3.0), "r_cut=3.0 applies only with method='rbf'"),
    (dict(method="vertex", coarse_lr=2.0), "coarse_lr=2.0 applies only with method='rbf'"),
    (dict(method="rbf", lam=5.0), "lam=5.0 applies only with method='largesteps', not with method='rbf'"),
    (dict(method="vertex", lam=5.0), "lam=5.0 applies only with method='largesteps'"),
    (dict(coarse_lr=5.0), r"coarse_lr=5.0 applies only with coarse_ratio > 0, not with coarse_ratio=0; leave it at "
                          r"its default \(3.0\)"),
    (dict(w_contact=0.0, contact_distance=0.5), "contact_distance=0.5 applies only with w_contact > 0"),
    (dict(w_contact=0.0, contact_edges=True), "contact_edges=True applies only with w_contact > 0"),
    (dict(valid_steps=False, min_quality=0.05), "min_quality=0.05 applies only with valid_steps=True"),
    (dict(stages=(100, 300), stage_overrides=({"method": "largesteps"}, None), lr_scale=0.01),
     "^stage 0: lr_scale=0.01 applies only with method='rbf', not with method='largesteps'"),
    (dict(stages=(100, 300), stage_overrides=(None, {"lam": 3.0})), "^stage 1: lam=3.0 applies only"),
])
def test_a_setting_the_run_would_ignore_is_refused(kwargs, says):
    from meshmei.errors import ReconstructionError

    with pytest.raises(ReconstructionError, match=says):
        ReconstructionSettings(**kwargs).resolved()


def test_settings_each_run_uses_are_accepted():
    for method in ("rbf", "vertex", "largesteps"):  # every method's defaults, with or without guard and barrier
        for extra in ({}, dict(valid_steps=False, w_contact=0.0), dict(w_contact=0.0, contact_edges=False)):
            ReconstructionSettings(method=method, **extra).resolved()
    ReconstructionSettings(method="rbf", lr_scale=0.01, sigma_factor=2.0, r_cut=3.0, centers=torch.arange(10),
                           coarse_ratio=16, coarse_lr=5.0).resolved()
    ReconstructionSettings(method="largesteps", lam=5.0, lr_scale=0.0, coarse_lr=0.0).resolved()  # its defaults
    ReconstructionSettings(contact_distance=0.5, contact_edges=True, min_quality=0.05).resolved()
    # per stage: each stage is checked against its own method
    ReconstructionSettings(stages=(100, 300), stage_overrides=({"method": "largesteps", "lam": 5.0},
                                                                {"sigma_factor": 2.0})).resolved()
    ReconstructionSettings(method="largesteps", stages=(100, 300),
                           stage_overrides=(None, {"method": "rbf", "lr_scale": 0.01})).resolved()


def test_cli_refuses_options_it_would_ignore(sphere, tmp_path, capsys):
    from meshmei.mesh import save_mesh

    save_mesh(tmp_path / "start.obj", *sphere)
    base = ["--target", "bunny", "--steps", 2, "--samples", 300, "--eval-samples", 500, "--stages", "none",
            "--no-progress"]
    rc, out = _cli(base + ["--init", tmp_path / "start.obj", "--n-vertices", 500, "--out", tmp_path / "a"], capsys)
    assert rc == 2 and "--n-vertices 500 sets the size of a generated --init" in out.err
    assert "start.obj" in out.err and not (tmp_path / "a").exists()
    rc, out = _cli(base + ["--init", "sphre", "--n-vertices", 500, "--out", tmp_path / "a"], capsys)  # no such file
    assert rc == 2 and out.err.strip().endswith("source sphre: neither a built-in source (sheet, sphere, torus, "
                                                 "torus-centred, torus-through-opening) nor a mesh file")
    assert not (tmp_path / "a").exists()  # it was called "the mesh file sphre"
    rc, out = _cli(base + ["--init", "sphere", "--n-vertices", 100, "--contact-edges", "on", "--contact-weight", 0,
                           "--out", tmp_path / "b"], capsys)
    assert rc == 2 and "contact_edges=True applies only with w_contact > 0" in out.err and not (tmp_path / "b").exists()
    rc, out = _cli(base + ["--init", tmp_path / "start.obj", "--out", tmp_path / "c"], capsys)  # the file as it is
    assert rc == 0, out.err
    assert json.loads((tmp_path / "c" / "history.json").read_text())["n_vertices"] == sphere[0].shape[0]
    rc, out = _cli(base + ["--init", "sphere", "--n-vertices", 100, "--facing-weight", -1, "--out", tmp_path / "d"],
                   capsys)
    assert rc == 2 and out.err.strip().endswith("w_facing must be non-negative and finite, got -1.0")
    assert not (tmp_path / "d").exists()


def test_save_reconstruction_writes_a_whole_folder_or_none(sphere, tmp_path, monkeypatch):
    import importlib

    from meshmei.errors import ReconstructionError
    from meshmei.reconstruct import save_reconstruction

    res = reconstruct(sphere, "bunny", steps=2, **SMALL)
    other = tmp_path / "mei_run"  # another command's folder
    other.mkdir()
    (other / "summary.json").write_text(json.dumps({"format": 1, "complete": True, "neuron": 0, "activation": 1.0}))
    with pytest.raises(ReconstructionError, match="mei_run exists; pass overwrite=True"):
        save_reconstruction(res, other)
    assert sorted(p.name for p in other.iterdir()) == ["summary.json"]
    save_reconstruction(res, other, overwrite=True)  # replaced whole: nothing of the old folder is left
    assert sorted(p.name for p in other.iterdir()) == ["history.json", "loss.png", "mesh.obj", "metrics.png"]

    def broken(result, out):
        raise OSError("disk full")

    monkeypatch.setattr(importlib.import_module("meshmei.reconstruct.runs"), "reconstruction_figures", broken)
    with pytest.raises(OSError, match="disk full"):
        save_reconstruction(res, tmp_path / "new")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mei_run"]  # no folder, no partial one


def test_cli_refuses_an_existing_out_folder_without_overwrite(tmp_path, capsys, monkeypatch):
    out_dir = tmp_path / "run"
    args = ["--init", "sphere", "--n-vertices", 100, "--target", "bunny", "--out", out_dir, "--steps", 2,
            "--samples", 300, "--eval-samples", 500, "--stages", "none", "--no-progress"]
    rc, out = _cli(args, capsys)
    assert rc == 0, out.err
    first = (out_dir / "history.json").stat().st_mtime_ns
    rc, out = _cli(args, capsys)
    assert rc == 2 and f"{out_dir} exists; pass --overwrite to replace it" in out.err
    assert (out_dir / "history.json").stat().st_mtime_ns == first
    rc, out = _cli(args + ["--overwrite"], capsys)
    assert rc == 0, out.err
    assert sorted(p.name for p in out_dir.iterdir()) == ["history.json", "loss.png", "mesh.obj", "metrics.png"]
    # a folder of files meshmei did not write is not replaced, even with --overwrite, and no run starts
    theirs = tmp_path / "data"
    theirs.mkdir()
    (theirs / "precious.txt").write_text("keep")
    import meshmei.cli as cli_module

    runs = []
    monkeypatch.setattr(cli_module, "reconstruct", lambda *a, **k: runs.append(a))
    rc, out = _cli(args[:7] + [theirs] + args[8:] + ["--overwrite"], capsys)
    assert rc == 2 and "holds files meshmei did not write" in out.err and runs == []
    assert [p.name for p in theirs.iterdir()] == ["precious.txt"]
    # a result file's name is not enough (a training script's history.json): the folder, with the scan being
    # fitted in it, was replaced
    (theirs / "history.json").write_text(json.dumps({"epoch": [1, 2], "loss": [0.9, 0.5]}))
    rc, out = _cli(args[:7] + [theirs] + args[8:] + ["--overwrite"], capsys)
    assert rc == 2 and "holds files meshmei did not write" in out.err and runs == []
    assert sorted(p.name for p in theirs.iterdir()) == ["history.json", "precious.txt"]


def test_cli_refuses_an_out_folder_that_holds_an_input(tmp_path, capsys, monkeypatch):
    """``--target run/scan.obj --out run --overwrite`` deleted the scan being fitted, once the run was done."""
    import meshmei.cli as cli_module
    from meshmei.mesh import save_mesh

    out_dir = tmp_path / "run"
    args = ["--init", "sphere", "--n-vertices", 100, "--target", "bunny", "--out", out_dir, "--steps", 2,
            "--samples", 300, "--eval-samples", 500, "--stages", "none", "--no-progress"]
    assert _cli(args, capsys)[0] == 0  # a meshmei result: replaceable as such
    V, F = initial_mesh("sphere", n_vertices=100)
    scan = out_dir / "scans" / "scan.obj"
    scan.parent.mkdir()
    save_mesh(scan, V * 2.0, F)
    runs = []
    monkeypatch.setattr(cli_module, "reconstruct", lambda *a, **k: runs.append(a))
    for flag, path in (("--target", scan), ("--init", scan), ("--target", out_dir)):
        given = [str(x) for x in args]
        given[given.index(flag) + 1] = str(path)
        if flag == "--init":
            given[given.index("--n-vertices"):given.index("--n-vertices") + 2] = []
        rc, out = _cli(given + ["--overwrite"], capsys)
        assert rc == 2 and f"the output folder {out_dir.resolve()} is the input" in out.err, out.err
        assert runs == [] and scan.is_file()


def test_a_files_target_frame_is_recorded_and_maps_the_result_back(sphere, tmp_path):
    """A user's target is fitted in the unit frame; nothing recorded where that frame lay in the file."""
    from meshmei.mesh import load_mesh, save_mesh
    from meshmei.reconstruct import save_reconstruction

    Vb, Fb = target_mesh("bunny")
    V_file = Vb.double() * torch.tensor([3.0, 3.0, 3.0], dtype=torch.float64) + torch.tensor([10.0, -2.0, 0.5], dtype=torch.float64)
    save_mesh(tmp_path / "scan.obj", V_file, Fb)
    res = reconstruct(sphere, tmp_path / "scan.obj", "rbf", steps=2, **SMALL)
    frame = res.info["target_frame"]
    Vt = load_mesh(tmp_path / "scan.obj", dtype=torch.float64)[0]
    lo, hi = Vt.min(0).values, Vt.max(0).values
    assert frame["centre"] == pytest.approx((0.5 * (lo + hi)).tolist(), abs=1e-12)
    assert frame["scale"] == pytest.approx(float((hi - lo).norm()), rel=1e-12)
    # the fitted unit-frame target, mapped with the frame, is the file's mesh
    from meshmei.reconstruct import target_surface

    Vu, _ = target_surface(tmp_path / "scan.obj", dtype=torch.float64)
    torch.testing.assert_close(Vu * frame["scale"] + torch.tensor(frame["centre"], dtype=torch.float64), Vt,
                               rtol=0, atol=1e-12)
    out = save_reconstruction(res, tmp_path / "r")
    assert json.loads((out / "history.json").read_text())["info"]["target_frame"] == frame
    assert "target_frame" not in reconstruct(sphere, "bunny", "rbf", steps=1, **SMALL).info


def test_a_path_in_the_record_is_saved_as_its_text(sphere, tmp_path):
    from pathlib import Path

    from meshmei.reconstruct import save_reconstruction

    res = reconstruct(sphere, "bunny", "rbf", steps=2, **SMALL)
    out = save_reconstruction(res, tmp_path / "r", target=Path("scans") / "scan.obj")  # a TypeError from json
    assert json.loads((out / "history.json").read_text())["target"] == str(Path("scans") / "scan.obj")


def test_centers_given_as_vertex_indices_are_saved_as_lists(sphere, tmp_path):
    import numpy as np

    from meshmei.reconstruct import save_reconstruction

    n = sphere[0].shape[0]
    for centers in (torch.arange(0, n, 3), np.arange(0, n, 3)):
        res = reconstruct(sphere, "bunny", "rbf", steps=2, centers=centers, **SMALL)
        assert res.info["stages"][0]["n_kernels"] == len(range(0, n, 3))
        out = save_reconstruction(res, tmp_path / type(centers).__name__)
        rec = json.loads((out / "history.json").read_text())
        assert rec["settings"]["centers"] == list(range(0, n, 3))


def test_a_stage_that_accepts_no_step_warns(sphere):
    from meshmei.reconstruct import ReconstructionWarning

    V, F = sphere
    # a start 1e-3 the target's size: the learning rate is absolute, the guard's longest step scales with
    # the mesh, so every step is refused; the run used to report success
    with pytest.warns(ReconstructionWarning, match=r"stage 0 \(\d+ vertices\) accepted none of its 3 steps: .*"
                                                   r"farther than the guard allows .* scale the source"):
        res = reconstruct((V * 1e-3, F), "bunny", steps=3, **SMALL)
    st = res.info["stages"][0]
    assert st["steps"] == 3 and st["accepted_steps"] == 0 and torch.equal(res.V, V * 1e-3)
    assert len(res.info["warnings"]) == 1 and "accepted none" in res.info["warnings"][0]
    # a start with one sliver face (an edge's midpoint, rounded to float32): its normal, set by rounding,
    # turned over at every step and the guard's turn rule refused them all; the rule now leaves out faces
    # that start below the quality bound (meshmei.validity), and the run moves, clean
    Vd = V.double()
    V2 = torch.cat([Vd, ((Vd[F[0, 0]] + Vd[F[0, 1]]) / 2)[None]]).float()
    F2 = torch.cat([F, torch.tensor([[F[0, 0], F[0, 1], V.shape[0]]])])
    # (the midpoint lies on face 0, which it is not part of: the contact barrier leaves that pair out, and says so)
    with pytest.warns(ReconstructionWarning, match=r"^stage 0: \d+ vertex-face or edge pairs of the start are in contact"):
        res = reconstruct((V2, F2), "bunny", steps=3, **SMALL)
    assert not any("accepted none" in w for w in res.info["warnings"])
    assert res.info["stages"][0]["accepted_steps"] == 3 and res.info["stages"][0]["refused_by"]["turn"] == 0
    assert res.final.self_intersections == 0
    # a run that moves has no warning
    res = reconstruct(sphere, "bunny", steps=3, **SMALL)
    assert res.info["warnings"] == [] and res.info["stages"][0]["accepted_steps"] == 3


def test_a_start_too_small_for_the_deformation_is_a_clear_error(sphere):
    from meshmei.errors import ReconstructionError

    V, F = sphere
    steps = []
    with pytest.raises(ReconstructionError, match=r"^stage 0: the rbf deformation gives non-finite vertices at its "
                                                  r"start, a mesh 1(\.\d+)?e-20 across .*scale the source"):
        reconstruct((V * 1e-20, F), "bunny", steps=3, callback=lambda *a: steps.append(a), **SMALL)
    assert steps == []


def test_cli_says_when_a_stage_accepted_no_step(sphere, tmp_path, capsys):
    from meshmei.mesh import save_mesh

    save_mesh(tmp_path / "small.obj", sphere[0] * 1e-3, sphere[1])
    rc, out = _cli(["--init", tmp_path / "small.obj", "--target", "bunny", "--out", tmp_path / "o", "--steps", 2,
                    "--samples", 300, "--eval-samples", 500, "--stages", "none", "--no-progress"], capsys)
    assert rc == 0, out.err
    assert "WARNING: 1 warning(s) (below)" in out.out
    assert "meshmei reconstruct: warning: stage 0" in out.err and "accepted none of its 2 steps" in out.err
    assert json.loads((tmp_path / "o" / "history.json").read_text())["info"]["warnings"]


def test_truthy_strings_and_mistyped_names_are_clear_errors(sphere):
    """valid_steps="no" switched the guard on (a truthy string); a mistyped built-in name read as a missing
    file without the names that exist."""
    from meshmei.errors import ReconstructionError

    for name in ("valid_steps", "reg_decay"):
        with pytest.raises(ReconstructionError, match=f"{name} must be True or False, got 'no'"):
            reconstruct(sphere, "bunny", steps=1, **{name: "no"})
    with pytest.raises(FileNotFoundError, match=r"target bunnny: neither a built-in target \(bunny, teapot"):
        reconstruct(sphere, "bunnny", steps=1)
    with pytest.raises(ReconstructionError, match=r"^unknown ReconstructionSettings fields \['bogus', 'lr_scales'\]$"):
        reconstruct(sphere, "bunny", steps=1, lr_scales=0.1, bogus=3)  # a TypeError naming __init__
    with pytest.raises(FileNotFoundError, match=r"source sphre: neither a built-in source \(sheet, sphere"):
        resolve_source("sphre", 100, torch.float32, None)


def test_a_run_repeats_exactly_on_two_threads():
    """Chamfer's nearest samples, the surface samples' corners and the contact pairs were gathered by
    advanced indexing, whose backward (an accumulating index_put) adds in a thread-dependent order on the
    CPU: the same run on two threads ended up to 2e-5 apart. They use index_select now."""
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        runs = [reconstruct("sphere", "bunny", steps=12, stages=(400, 800), eval_samples=5000) for _ in range(3)]
    finally:
        torch.set_num_threads(threads)
    losses = [[h["loss"] for h in r.history] for r in runs]
    assert all(torch.equal(r.V, runs[0].V) and x == losses[0] for r, x in zip(runs[1:], losses[1:]))


def test_a_remesh_that_welds_pieces_is_refused_between_stages():
    """pymeshlab's remesh welds the teapot's handle to its body at a shared point (a bow-tie vertex, one piece
    fewer); the stage check compared intersection counts only and took it. It now keeps the topology."""
    from meshmei.metrics import face_components
    from meshmei.quality import topology
    from meshmei.shapes import remesh

    V, F = target_mesh("teapot", resolution=4)
    welded = remesh(V, F, 500)
    before, after = topology(F), topology(welded[1])
    assert before["nonmanifold_vertices"] == 0 and after["nonmanifold_vertices"] > 0 and after["euler"] != before["euler"]
    res = reconstruct((V, F), "bunny", "vertex", steps=2, stages=(700,), n_samples=300, target_pool=1000,
                      eval_samples=500)
    st = res.info["stages"][0]
    assert st["remesh_iterations"] is None and "nonmanifold_vertices" in st["remesh_refused_topology"]
    assert st["remesh_tries"] == 3 and "remesh_out_of_time" not in st  # a step budget: every try
    assert topology(res.F) == before
    assert face_components(res.F, res.V.shape[0]).max() == face_components(F, V.shape[0]).max()


def test_under_a_time_budget_a_refused_remesh_is_retried_only_while_the_stages_share_has_room(monkeypatch):
    """Three tries of a refused 10k remesh (about a second each with their checks) spent the whole share of
    a 10 s run's last stage, which took no step and ran the run 11 % over budget. On a fake clock where a
    remesh takes 0.2 s (the teapot's, refused: it welds the handle to the body): a stage whose share has
    0.5 s left makes one try (a second would leave 0.1 s, less than a try) and keeps its mesh, says why, and
    the run ends within a step of its budget (three tries would have ended it 0.1 s over); with 1.1 s left, all
    three tries are made; a step budget makes all three as before."""
    import importlib

    from meshmei.reconstruct import ReconstructionWarning
    from meshmei.shapes import remesh

    fit = importlib.import_module("meshmei.reconstruct.fit")
    clock = _fake_clock(monkeypatch, 0.005)
    calls = []

    def slow(V, F, n, **kw):
        clock.sleep(0.2)
        calls.append(kw.get("iterations"))
        return remesh(V, F, n, **kw)

    monkeypatch.setattr(fit, "remesh", slow)
    V, F = target_mesh("teapot", resolution=4)
    kw = dict(stages=(V.shape[0], 700), n_samples=300, target_pool=1000, eval_samples=500)
    with pytest.warns(ReconstructionWarning, match=r"the remesh \(tried 1 of 3 times: the stage's share of the time "
                      r"budget left no room for another\) to 700 vertices"):
        res = reconstruct((V, F), "bunny", "vertex", time_budget=1.0, stage_fractions=(0.5, 0.5), **kw)
    st = res.info["stages"][1]
    assert calls == [None] and st["remesh_tries"] == 1 and st["remesh_out_of_time"] is True
    assert st["remesh_iterations"] is None and st["steps"] > 0 and res.V.shape == V.shape
    assert res.history[-1]["time"] < 1.0 + 0.05 and res.wall_time < 1.0 + 0.05
    calls.clear()
    res = reconstruct((V, F), "bunny", "vertex", time_budget=2.2, stage_fractions=(0.5, 0.5), **kw)
    st = res.info["stages"][1]
    assert calls == [None, 10, 3] and st["remesh_tries"] == 3 and "remesh_out_of_time" not in st
    calls.clear()
    res = reconstruct((V, F), "bunny", "vertex", steps=4, stage_fractions=(0.5, 0.5), **kw)
    assert calls == [None, 10, 3] and res.info["stages"][1]["remesh_tries"] == 3


def test_a_growing_stage_whose_remesh_is_refused_runs_on_its_mesh_split_in_four(sphere, monkeypatch):
    """A 10k stage whose every remesh was refused ran on the 2,351-vertex mesh it had (a 10 s bunny run at
    10k). A stage that grows the mesh now splits every face in four at its edges' midpoints (the same
    surface, about four times the vertices) when that lands nearer the count asked for and passes the same
    checks. Here a remesh that grows the mesh crosses its surface (one vertex pushed through the far side)."""
    import importlib

    from meshmei.reconstruct import ReconstructionWarning
    from meshmei.shapes import remesh
    from meshmei.topology import mesh_topology

    fit = importlib.import_module("meshmei.reconstruct.fit")

    def crossing(V, F, n, **kw):  # a remesh that grows the mesh crosses it
        V2, F2 = remesh(V, F, n, **kw)
        if n > V.shape[0]:
            V2 = V2.clone()
            V2[0] = -1.5 * V2[0]
        return V2, F2

    monkeypatch.setattr(fit, "remesh", crossing)
    V, F = sphere
    n, e = V.shape[0], int(mesh_topology(F, V.shape[0]).edges.shape[0])
    U, G, rec = fit._remesh_clean(V, F, 4 * n, True)
    assert rec["remesh_subdivided"] is True and rec["remesh_iterations"] is None and rec["remesh_tries"] == 3
    assert rec["remesh_refused_pairs"] > 0 and U.shape == (n + e, 3) and G.shape == (4 * F.shape[0], 3)
    assert U.dtype == V.dtype and torch.equal(U[:n], V) and count_self_intersections(U, G) == 0
    # every new vertex is the midpoint of an edge of the old mesh
    E = mesh_topology(F, n).edges
    mid = 0.5 * (V[E[:, 0]].double() + V[E[:, 1]].double())
    assert torch.cdist(U[n:].double(), mid).min(1).values.max() < 1e-6
    assert fit._remesh_clean(V, F, n + 10, True)[0] is V  # not growing: the mesh it had
    with pytest.warns(ReconstructionWarning, match=r"every remesh to \d+ vertices added self-intersections .*: the "
                      r"stage runs on the mesh it had with every face split in four \(the same surface\), \d+ "
                      r"vertices"):
        res = reconstruct(sphere, "bunny", "rbf", steps=6, stages=(n // 4, n), **SMALL)
    first, second = res.info["stages"]
    assert second["remesh_subdivided"] is True and second["n_vertices"] > 3 * first["n_vertices"]
    assert res.final.self_intersections == 0 and res.V.shape[0] == second["n_vertices"]


def test_a_remesh_that_clears_one_crossing_and_makes_another_elsewhere_is_refused():
    """The stage check compared counts: with a source that already crossed itself in one place, a remesh
    that made a new crossing elsewhere passed as long as the total did not grow (5 new pairs in a clean
    part of a fin with two overlapping balls beside it; review). Pairs are now told apart by place."""
    import importlib

    from meshmei.quality import self_intersecting_pairs

    fit = importlib.import_module("meshmei.reconstruct.fit")

    def flat(c):
        return torch.tensor([[c - 1, -1, 0], [c + 1, -1, 0], [c, 1, 0]], dtype=torch.float64)

    def upright(c):
        return torch.tensor([[c, -1, -1], [c, 1, -1], [c, 0, 1]], dtype=torch.float64)

    F = torch.tensor([[0, 1, 2], [3, 4, 5], [6, 7, 8], [9, 10, 11]])
    before = torch.cat([flat(0.0), upright(0.0), flat(10.0), upright(20.0)])  # one crossing, at the origin
    moved = torch.cat([flat(0.0), upright(0.3), flat(10.0), upright(20.0)])  # the same crossing, moved
    elsewhere = torch.cat([flat(0.0), upright(5.0), flat(10.0), upright(10.0)])  # it cleared, one at x = 10
    assert count_self_intersections(before, F) == count_self_intersections(elsewhere, F) == 1
    assert fit._new_intersections(before, F, self_intersecting_pairs(before, F), moved, F) == 0
    assert fit._new_intersections(before, F, self_intersecting_pairs(before, F), elsewhere, F) == 1
    assert fit._new_intersections(before, F, self_intersecting_pairs(before, F),
                                 torch.cat([flat(0.0), upright(0.0), flat(10.0), upright(10.0)]), F) == 1
    assert fit._new_intersections(elsewhere, F, self_intersecting_pairs(elsewhere, F), elsewhere, F) == 0


def test_a_stage_whose_remesh_is_refused_takes_the_weights_of_the_mesh_it_runs_on(sphere, monkeypatch):
    """A stage that kept its mesh (every remesh refused) took the weights of the count it asked for: a
    9,917-vertex stage ran with the Laplacian weight of 100 vertices, 615x below the rule (review)."""
    import importlib

    fit = importlib.import_module("meshmei.reconstruct.fit")
    monkeypatch.setattr(fit, "_remesh_clean", lambda V, F, n, clean, seconds_left=None: (V, F, {
        "remesh_iterations": None, "remesh_refused_pairs": 3, "remesh_refused_topology": []}))
    V, F = sphere
    n = V.shape[0]
    res = reconstruct(sphere, "bunny", "vertex", steps=2, stages=(n // 4, n // 2), **SMALL)  # asked: n / 2
    s = res.settings
    for st in res.info["stages"]:
        assert st["n_vertices"] == n
        assert st["w_laplacian"] == pytest.approx(s.w_laplacian * (n / s.reg_ref_vertices) ** 2, rel=1e-12)
        assert st["w_edge"] == pytest.approx(s.w_edge * n / s.reg_ref_vertices, rel=1e-12)
    assert sum("the stage runs on the mesh it had" in w for w in res.info["warnings"]) == 2


def test_a_stage_whose_remesh_lands_far_from_its_count_takes_the_weights_of_the_count_it_got():
    """stages=(128, 32) on a 190-vertex sphere: the remesh to 32 gives 93 vertices, and the stage ran with the
    Laplacian weight of 32, 8.4x too light for its mesh, without a word (fuzzing)."""
    from meshmei.reconstruct.fit import STAGE_COUNT_TOLERANCE

    src = initial_mesh("sphere", n_vertices=194)
    from meshmei.reconstruct import ReconstructionWarning

    with pytest.warns(ReconstructionWarning, match=r"stage 1: asked for 32 vertices, the remesh gave \d+"):
        res = reconstruct(src, "bunny", "rbf", steps=4, stages=(128, 32), seed=0, **SMALL)
    s = res.settings
    first, second = res.info["stages"]
    assert (first["n_vertices_asked"], second["n_vertices_asked"]) == (128, 32)
    n = second["n_vertices"]
    assert n > 32 * STAGE_COUNT_TOLERANCE
    assert second["w_laplacian"] == pytest.approx(s.w_laplacian * (n / s.reg_ref_vertices) ** 2, rel=1e-12)
    assert second["w_edge"] == pytest.approx(s.w_edge * n / s.reg_ref_vertices, rel=1e-12)
    # the first stage landed within the tolerance and states the second's asked count, as before
    assert 128 / STAGE_COUNT_TOLERANCE <= first["n_vertices"] <= 128 * STAGE_COUNT_TOLERANCE
    assert first["w_laplacian"] == pytest.approx(s.w_laplacian * (32 / s.reg_ref_vertices) ** 2, rel=1e-12)
    assert sum("asked for" in w for w in res.info["warnings"]) == 1


def test_a_results_settings_replay_a_run_whose_stages_change_the_method():
    """The recorded (resolved) settings hold rbf's defaults; replayed, a largesteps stage refused rbf's
    coarse_lr (and would have taken rbf's learning rate)."""
    src = initial_mesh("sphere", n_vertices=100)
    kw = dict(n_samples=300, target_pool=1000, eval_samples=500)
    r = reconstruct(src, "bunny", steps=2, stages=(100, 100), stage_overrides=({"method": "largesteps"}, None), **kw)
    again = reconstruct(src, "bunny", settings=r.settings)
    assert [(st["method"], st["lr"]) for st in again.info["stages"]] == [("largesteps", 0.05), ("rbf", 0.006)]
    assert [(st["method"], st["lr"]) for st in r.info["stages"]] == [("largesteps", 0.05), ("rbf", 0.006)]
    assert torch.equal(again.V, r.V)


def test_a_kernel_count_at_a_stage_size_takes_the_vertices_the_remesh_gave(sphere):
    """centers=300 with a 300-vertex stage passed the settings check, and the stage, remeshed to 296
    vertices, failed after the first stage had run; centers=10.0 passed the check and the deformer refused it."""
    res = reconstruct(sphere, "bunny", "rbf", steps=4, stages=(380, 300), centers=300, **SMALL)
    for st in res.info["stages"]:
        assert st["n_kernels"] == min(300, st["n_vertices"])
    assert res.info["stages"][1]["n_vertices"] < 300  # the case that failed: fewer vertices than kernels asked
    res = reconstruct(sphere, "bunny", "rbf", steps=2, centers=10.0, **SMALL)
    assert res.settings.centers == 10 and isinstance(res.settings.centers, int)
    assert res.info["stages"][0]["n_kernels"] == 10


def test_a_method_given_with_another_methods_settings_runs_with_its_own_defaults(sphere):
    """``reconstruct(..., "largesteps", settings=vertex_result.settings)`` ran largesteps at the vertex
    method's lr, Adam and Laplacian weight; rbf from vertex settings refused vertex's values."""
    kw = dict(steps=2, **SMALL)
    rv = reconstruct(sphere, "bunny", "vertex", **kw)
    fresh = reconstruct(sphere, "bunny", "largesteps", **kw).settings
    swapped = reconstruct(sphere, "bunny", "largesteps", settings=rv.settings).settings
    assert swapped == fresh
    assert reconstruct(sphere, "bunny", "rbf", settings=rv.settings).settings == reconstruct(sphere, "bunny", "rbf", **kw).settings
    # a value the caller sets is kept
    assert reconstruct(sphere, "bunny", "largesteps", settings=rv.settings, lr=0.02).settings.lr == 0.02


def test_cli_n_vertices_zero_is_refused_not_replaced_by_the_default(tmp_path, capsys):
    rc, out = _cli(["--init", "sphere", "--n-vertices", 0, "--target", "bunny", "--out", tmp_path / "o",
                    "--steps", 2], capsys)
    assert rc == 2 and "n_vertices must be positive" in out.err and not (tmp_path / "o").exists()


def test_the_facing_term_charges_surface_turned_away_from_the_target_only():
    """The facing term against closed forms: a sphere against itself faces the same way everywhere (0), the
    same sphere with every face reversed faces away at every sample (1); the Chamfer term is the same for
    both, and the same as without target normals (the pool and the samples are drawn alike)."""
    import importlib

    fit = importlib.import_module("meshmei.reconstruct.fit")
    V, F = icosphere(3)
    V, F = V.double(), F
    values = {}
    for name, faces in (("out", F), ("in", F[:, [0, 2, 1]])):
        for normals in (True, False):
            chamfer = fit._SampledChamfer(V, F, 20_000, torch.Generator().manual_seed(0), normals=normals)
            values[name, normals] = chamfer(V, faces, 5000, 0, 1e-3)
    assert values["out", True][1].item() == pytest.approx(0.0, abs=1e-12)
    assert values["in", True][1].item() == pytest.approx(1.0, abs=0.05)  # faces tilted a little off the pool's
    assert values["out", False][1] is None and values["in", False][1] is None
    for name in ("out", "in"):
        assert torch.equal(values[name, True][0], values[name, False][0])


def test_pairing_by_normal_pulls_on_surface_that_faces_the_same_way():
    """A slab 0.05 thick between two sheets: one 0.005 above its top, facing down, one 0.275 above it, facing
    up. By position alone the samples of the slab's top pair with the near sheet, which faces away from them;
    with ``normal_match`` they are paired again by position and normal, with the far sheet, while those of its
    bottom keep the near sheet, which faces their way. The mesh samples keep their nearest target samples."""
    import importlib

    import trimesh

    fit = importlib.import_module("meshmei.reconstruct.fit")
    box = trimesh.creation.box(extents=(1.0, 1.0, 0.05))
    Vt, Ft = torch.tensor(box.vertices, dtype=torch.float64), torch.tensor(box.faces, dtype=torch.int64)
    quad = torch.tensor([[-0.4, -0.4], [0.4, -0.4], [0.4, 0.4], [-0.4, 0.4]], dtype=torch.float64)
    V = torch.cat([torch.nn.functional.pad(quad, (0, 1), value=0.03), torch.nn.functional.pad(quad, (0, 1), value=0.3)])
    F = torch.tensor([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7]])  # the near sheet faces -z, the far one +z
    g = torch.Generator().manual_seed(0)
    chamfer = fit._SampledChamfer(Vt, Ft, 20_000, g, normals=True)
    P, N = sample_points(V, F, 4000, generator=g, return_normals=True)
    sub = torch.arange(chamfer.pool.shape[0])
    nq = chamfer.pool_normals
    flat = nq[:, 2].abs() > 0.99  # the slab's top and bottom: each has a sheet that faces its way
    plain = torch.from_numpy(PointIndex(P).query(chamfer.pool, near_first=True))
    for weight in (0.0, 0.3):
        i_qp = plain.clone()
        if weight:
            chamfer._pair_by_normal(P, N, sub, i_qp, weight)
            facing = (nq * N[plain]).sum(-1) >= 0
            assert torch.equal(i_qp[facing], plain[facing])  # pairs that face each other stay
        agree, z = (nq * N[i_qp]).sum(-1)[flat], P[i_qp][flat][:, 2]
        top = nq[flat, 2] > 0
        if weight:
            assert torch.all(agree > 0.99)
            assert torch.allclose(z[top], torch.full_like(z[top], 0.3))
            assert torch.allclose(z[~top], torch.full_like(z[~top], 0.03))
        else:
            assert torch.all(agree[top] < -0.99) and torch.allclose(z, torch.full_like(z, 0.03))
    # in the term: the mesh samples' pairs are the same, the target samples' are farther
    terms = {w: fit._SampledChamfer(Vt, Ft, 20_000, torch.Generator().manual_seed(1), normals=True)(
        V, F, 2000, 0, 1e-3, w) for w in (0.0, 0.3)}
    assert terms[0.3][1].item() == terms[0.0][1].item()  # the facing term reads the mesh samples' pairs
    assert terms[0.3][0].item() > terms[0.0][0].item()


def test_pairing_by_normal_runs_only_where_the_stage_start_encloses_the_target():
    """A sphere around the bunny pairs by normal in the stage that asks for it and records so; a torus through
    the teapot's handle, which does not enclose it, runs that stage on plain pairs (recorded too), the same run
    bit for bit as without the setting; stages that do not ask record nothing."""
    over = ({"normal_match": 0.3}, None)
    kw = dict(steps=6, n_samples=400, eval_samples=1000, stages=(150, 150), stage_fractions=(0.5, 0.5))
    sphere = reconstruct(initial_mesh("sphere", n_vertices=300), "bunny", "rbf", stage_overrides=over, **kw)
    assert sphere.info["stages"][0]["normal_match"] == 0.3 and sphere.info["stages"][0]["start_encloses_target"] is True
    assert "normal_match" not in sphere.info["stages"][1]
    torus = initial_mesh("torus", n_vertices=300)
    paired = reconstruct(torus, "teapot", "rbf", stage_overrides=over, **kw)
    plain = reconstruct(torus, "teapot", "rbf", stage_overrides=(None, None), **kw)
    first = paired.info["stages"][0]
    assert first["normal_match"] == 0.0 and first["start_encloses_target"] is False
    assert torch.equal(paired.V, plain.V) and torch.equal(paired.F, plain.F)


@pytest.mark.slow
def test_the_default_run_enters_a_cup_and_stays_clean():
    """The cup (walls 0.05 thick, one of the two thin targets normal_match was chosen on) from the CLI's
    2,500-vertex sphere: by position alone the run covers the opening and ends near 1.6e-3; paired by normal in
    its first stage it lines the inside (5.8e-7 when measured), with no intersecting pair."""
    from meshmei.reconstruct import default_schedule

    V, F = initial_mesh("sphere", n_vertices=2500)
    stages, fractions, overrides = default_schedule("rbf", V.shape[0])
    res = reconstruct((V, F), "cup", "rbf", stages=stages, stage_fractions=fractions, stage_overrides=overrides)
    assert res.final.chamfer_l2 < 1e-5 and res.final.self_intersections == 0


def test_a_facing_weight_adds_the_term_and_records_it_and_bad_weights_are_refused():
    from meshmei.errors import ReconstructionError

    src = initial_mesh("sphere", n_vertices=200)
    plain = reconstruct(src, "bunny", "rbf", steps=8, eval_samples=2000)
    facing = reconstruct(src, "bunny", "rbf", steps=8, eval_samples=2000, w_facing=1e-3)
    assert all("facing" not in h for h in plain.history)
    assert all(h["facing"] >= 0 for h in facing.history) and len(facing.history) == len(plain.history)
    assert not torch.equal(plain.V, facing.V)  # the term moves the mesh
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ReconstructionError, match=r"^w_facing must be non-negative and finite"):
            ReconstructionSettings(w_facing=bad).resolved()
        with pytest.raises(ReconstructionError, match=r"^normal_match must be non-negative and finite"):
            ReconstructionSettings(normal_match=bad).resolved()


def test_stage_and_step_counts_too_large_are_refused_in_one_line(tmp_path, capsys):
    """Found by fuzzing: --stages 10**400 raised OverflowError in the weights' scaling, --stages 10**8 was
    quietly capped at 196,610 vertices, and --steps 10**400 overflowed tqdm."""
    from meshmei.cli import main

    for option, value, message in (("--stages", str(10**400), "stages must be vertex counts of at most 5,000,000"),
                                   ("--stages", str(10**8), "stages must be vertex counts of at most 5,000,000"),
                                   ("--steps", str(10**400), "steps must be at most 1e+12")):
        out = tmp_path / option.strip("-")
        args = ["reconstruct", "--out", str(out), "--target", "bunny", "--n-vertices", "200", "--no-progress"]
        assert main([*args, "--steps", "2", option, value]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and message in err and not out.exists()


def test_number_settings_of_other_kinds_are_named_and_numpy_numbers_reach_the_run_as_pythons(sphere, bunny):
    # found by fuzzing: lr='0.01' (also in a stage's overrides) was a bare TypeError from a comparison; an
    # np.float32 lr reached the run's JSON as a NumPy number, and a NumPy seed failed in torch's Generator
    import numpy as np

    from meshmei.errors import ReconstructionError

    for kw, says in ((dict(lr="0.01"), "lr must be a number, got '0.01'"),
                     (dict(w_laplacian=[1.0]), r"w_laplacian must be a number, got \[1.0\]"),
                     (dict(lr_decay=1 + 0j), "lr_decay must be a number"),
                     (dict(stages=(60, 300), stage_overrides=({"lr": "0.01"}, None)),
                      "stage 0: lr must be a number, got '0.01'")):
        with pytest.raises(ReconstructionError, match=says):
            reconstruct(sphere, bunny, "rbf", steps=4, **SMALL, **kw)
    odd = reconstruct(sphere, bunny, "rbf", steps=4, **SMALL, lr=np.float32(0.006), seed=np.int64(3),
                      w_laplacian=torch.tensor(0.5))
    plain = reconstruct(sphere, bunny, "rbf", steps=4, **SMALL, lr=float(np.float32(0.006)), seed=3, w_laplacian=0.5)
    assert type(odd.settings.lr) is float and type(odd.settings.seed) is int and type(odd.settings.w_laplacian) is float
    assert torch.equal(odd.V, plain.V)
    json.loads(json.dumps(odd.to_json()))  # plain JSON


def test_a_record_may_not_replace_the_results_own_fields_and_normal_match_is_bounded(sphere, bunny, tmp_path):
    # found by fuzzing: save_reconstruction(res, d, final={...}) wrote that as the result's final metrics, and
    # normal_match=1e160 was an IndexError inside the fit
    from meshmei.errors import ReconstructionError
    from meshmei.reconstruct import save_reconstruction

    res = reconstruct(sphere, bunny, "rbf", steps=2, **SMALL)
    with pytest.raises(ReconstructionError, match=r"the record's \['final', 'settings'\] would replace"):
        save_reconstruction(res, tmp_path / "r", final={"chamfer_l2": 0.0}, settings="x")
    assert not (tmp_path / "r").exists()
    saved = json.loads((save_reconstruction(res, tmp_path / "r", target="bunny") / "history.json").read_text())
    assert saved["target"] == "bunny" and saved["final"]["chamfer_l2"] == res.final.chamfer_l2
    with pytest.raises(ReconstructionError, match="normal_match must be at most"):
        reconstruct(sphere, bunny, "rbf", steps=2, normal_match=1e160, **SMALL)


def test_a_stage_whose_steps_all_come_to_zero_says_so(sphere, bunny):
    # found by fuzzing: w_edge=1e30 overflowed Adam's squared gradient, every step was 0, and the result said
    # nothing: four steps at the stage's lr, the mesh its start
    from meshmei.reconstruct.settings import ReconstructionWarning

    with pytest.warns(ReconstructionWarning, match="none of its 4 steps moved the mesh"):
        res = reconstruct(sphere, bunny, "rbf", steps=4, w_edge=1e30, **SMALL)
    assert torch.equal(res.V, sphere[0]) and len(res.info["warnings"]) == 1
    assert not reconstruct(sphere, bunny, "rbf", steps=4, **SMALL).info["warnings"]


def test_a_meta_source_or_target_is_refused_before_any_work(sphere):
    """Found by fuzzing: a source or target on torch's "meta" device (V, F or both) ended in torch's
    'Tensor.item() cannot be called on meta tensors' from inside the face checks."""
    V, F = sphere
    for pair in [(V.to("meta"), F.to("meta")), (V.to("meta"), F), (V, F.to("meta"))]:
        name = "F" if pair[0] is V else "V"
        with pytest.raises(MeshError, match=rf"^{name} is a meta tensor .*torch's 'meta' device holds no values"):
            reconstruct(pair, "bunny", steps=4, **SMALL)
        with pytest.raises(MeshError, match=rf"^{name} is a meta tensor"):
            reconstruct(sphere, pair, steps=4, **SMALL)
        with pytest.raises(MeshError, match=rf"^{name} is a meta tensor"):
            target_surface(pair)
        with pytest.raises(MeshError, match=rf"^{name} is a meta tensor"):
            source_mesh(pair)


def test_a_target_beyond_1e154_has_a_finite_frame_that_maps_the_result_back(sphere):
    """Found by fuzzing: a float64 target 1e300 across had info['target_frame']['scale'] inf ((hi - lo).norm()
    overflowed), so history.json held 'Infinity' and p * scale + centre mapped the result to inf."""
    V, F = sphere
    big = V.double() * 1e300
    Vt, _, frame = target_surface((big, F), return_frame=True)
    _, _, unit = target_surface((V.double(), F), return_frame=True)
    assert frame["scale"] == pytest.approx(1e300 * unit["scale"], rel=1e-14)
    assert frame["centre"] == pytest.approx([1e300 * c for c in unit["centre"]], rel=1e-14, abs=1e286)
    back = Vt.double() * frame["scale"] + torch.tensor(frame["centre"], dtype=torch.float64)
    torch.testing.assert_close(back, big, rtol=0, atol=1e-7 * frame["scale"])  # the target is float32
    res = reconstruct(sphere, (big, F), steps=2, **SMALL)
    assert res.info["target_frame"] == frame
    assert json.loads(json.dumps(res.to_json(), allow_nan=False))["info"]["target_frame"] == frame


def test_a_non_finite_number_is_never_written_as_json_but_refused_naming_its_key(sphere, tmp_path):
    """Found by fuzzing: history.json held 'Infinity' (a target frame's scale, a kernel scale), which standard
    JSON does not have; to_json gave a dict that json.dumps(allow_nan=False) refused."""
    from dataclasses import replace

    from meshmei.errors import ReconstructionError
    from meshmei.reconstruct import save_reconstruction

    res = reconstruct(sphere, "bunny", "rbf", steps=2, **SMALL)
    stages = [dict(res.info["stages"][0], sigma_median=float("inf"))]
    bad = replace(res, info={**res.info, "stages": stages})
    with pytest.raises(ReconstructionError, match=r"^the result's info\['stages'\]\[0\]\['sigma_median'\] is inf: "
                                                  r"JSON has no NaN or Infinity"):
        bad.to_json()
    with pytest.raises(ReconstructionError, match=r"^the result's info\['stages'\]\[0\]\['sigma_median'\] is inf"):
        save_reconstruction(bad, tmp_path / "bad")
    nan_step = replace(res, history=[dict(res.history[0], chamfer=float("nan"))] + res.history[1:])
    with pytest.raises(ReconstructionError, match=r"^the result's history\[0\]\['chamfer'\] is nan"):
        save_reconstruction(nan_step, tmp_path / "bad")
    with pytest.raises(ReconstructionError, match=r"^the record's score\[1\] is -inf: JSON has no NaN or Infinity"):
        save_reconstruction(res, tmp_path / "bad", score=[1.0, -float("inf")])
    assert list(tmp_path.iterdir()) == []  # refused before anything was written

    def strict(text):
        return json.loads(text, parse_constant=lambda c: pytest.fail(f"history.json holds {c}"))

    out = save_reconstruction(res, tmp_path / "r", score=[1.0, None])
    written = strict((out / "history.json").read_text())
    assert written.pop("score") == [1.0, None]
    assert written == json.loads(json.dumps(res.to_json(), allow_nan=False))


def test_an_lr_scale_that_overflows_the_kernel_scales_is_refused(sphere, tmp_path, monkeypatch):
    """Found by fuzzing: lr_scale=1e10 moved every log-scale by about 1e10 at the first step (Adam and the uniform
    step move a parameter by up to its lr), exp overflowed, every kernel weighed 1 at every vertex (all n^2
    pairs listed) and the run went on as one translation: sigma_median inf, 'Infinity' in history.json."""
    from meshmei.errors import ReconstructionError
    from meshmei.reconstruct import fit
    for value in (1e10, 100.0, 10.5):  # refused before the target (a missing file) is read
        with pytest.raises(ReconstructionError, match=rf"^lr_scale must be at most 10 \(a step may widen an RBF kernel "
                                                      rf"e\^lr_scale times; .*\), got {value!r}$"):
            reconstruct(sphere, tmp_path / "missing.obj", steps=4, lr_scale=value, **SMALL)
    with pytest.raises(ReconstructionError, match=r"^stage 0: lr_scale must be at most 10 .*got 100\.0$"):
        ReconstructionSettings(stages=(100, 300), stage_overrides=({"lr_scale": 100.0}, None)).resolved()
    assert ReconstructionSettings(lr_scale=10).resolved().lr_scale == 10.0

    # below the ceiling a scale may still leave float32's range over many steps: the run ends, saying so
    build = fit._parameterisation

    def overflowing(sk, V0, F):
        param = build(sk, V0, F)
        with torch.no_grad():
            param.rbf.log_sigma[7] = 100.0  # exp(100) is inf in float32: the kernel weighs 1 everywhere
        return param

    monkeypatch.setattr(fit, "_parameterisation", overflowing)
    with pytest.raises(FloatingPointError, match=r"^stage 0: lr_scale=0\.01 took an RBF kernel's scale out of "
                                                 r"torch\.float32's range by step 0 \(a log-scale of 100; .*lower "
                                                 r"lr_scale$"):
        reconstruct(sphere, "bunny", "rbf", steps=3, lr_scale=0.01, **SMALL)


def test_source_mesh_places_the_torus_for_a_target_given_by_name_or_file(tmp_path):
    """Found by fuzzing: source_mesh('torus', target='bunny') unpacked the name as a mesh: find_opening's
    TypeError 'takes 2 positional arguments but 5 were given'. A name or a file is resolved as reconstruct
    resolves it (target_surface), so the torus is placed as reconstruct places it."""
    from meshmei.mesh import save_mesh

    teapot = target_surface("teapot")
    threaded = source_mesh("torus", n_vertices=300, target=teapot)
    assert not torch.equal(threaded[0], initial_mesh("torus", n_vertices=300)[0])  # placed through the handle
    save_mesh(tmp_path / "teapot.obj", 5 * teapot[0].double() + 2, teapot[1])  # normalised back when resolved
    for target in ("teapot", tmp_path / "teapot.obj"):
        for name in ("torus", "torus-through-opening"):
            V, F = source_mesh(name, n_vertices=300, target=target)
            torch.testing.assert_close(V, threaded[0], rtol=0, atol=1e-5)  # the file's round trip: float32 digits
            assert torch.equal(F, threaded[1])
    V, F = source_mesh("torus", n_vertices=300, target="bunny")  # no through-hole: centred
    assert torch.equal(V, initial_mesh("torus", n_vertices=300)[0])
    with pytest.raises(ValueError, match=r"^target must be a name, a mesh file path or a \(V, F\) pair, got int$"):
        source_mesh("torus", n_vertices=300, target=42)
    with pytest.raises(FileNotFoundError, match="neither a built-in target"):
        source_mesh("torus", n_vertices=300, target="teapto")


def test_target_surface_takes_normalize_and_return_frame_as_bools_only(sphere):
    """normalize='no' was taken as true (a string is truthy): the target was normalised."""
    from meshmei.errors import ReconstructionError

    for name, value in (("normalize", "no"), ("normalize", 0), ("return_frame", "yes"), ("return_frame", None)):
        with pytest.raises(ReconstructionError, match=rf"^{name} must be True or False, got {re.escape(repr(value))}$"):
            target_surface(sphere, **{name: value})
    V, _ = target_surface((sphere[0] * 3.0, sphere[1]), normalize=False)
    assert torch.equal(V, sphere[0] * 3.0)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), 100.7, 100.0, "100", True, 0, -2500, None])
def test_schedules_take_a_vertex_count_that_is_a_positive_integer(bad):
    """Found by fuzzing: default_stages(nan) and default_schedule('rbf', nan) gave Python's 'cannot convert float
    NaN to integer', inf an OverflowError; 100.7 was truncated to 100 and '100' taken as 100."""
    import numpy as np

    from meshmei.errors import ReconstructionError
    from meshmei.reconstruct import default_schedule, schedule_from_text

    said = rf"^n_vertices must be a positive integer, got {re.escape(repr(bad))}$"
    with pytest.raises(ReconstructionError, match=said):
        default_stages(bad)
    with pytest.raises(ReconstructionError, match=said):
        default_schedule("rbf", bad)
    for spec in ("auto", "none", "600,2500"):
        with pytest.raises(ReconstructionError, match=said):
            schedule_from_text(spec, "rbf", bad)
    # NumPy's integers are counts too
    assert default_stages(np.int64(2500)) == default_stages(2500) == ((625, 2500, 2500), (0.25, 0.45, 0.3))
    assert default_schedule("vertex", np.int32(2500)) == (*default_stages(2500), None)
    assert default_schedule("rbf", 31) == (None, None, None)


def test_a_stage_too_small_for_its_coarse_ratio_warns_that_it_has_no_coarse_kernels(sphere, bunny):
    """Found by fuzzing: coarse_ratio=10**6 on a small mesh gave round(n / 10**6) = 0 coarse kernels, and the run
    went on without them, without a word."""
    from meshmei.reconstruct import ReconstructionWarning

    n = sphere[0].shape[0]
    with pytest.warns(ReconstructionWarning) as caught:
        res = reconstruct(sphere, bunny, "rbf", steps=3, coarse_ratio=10 ** 6, **SMALL)
    said = [str(w.message) for w in caught if issubclass(w.category, ReconstructionWarning)]
    assert said == res.info["warnings"] == [
        f"stage 0 ({n} vertices): coarse_ratio=1000000 gives 0 coarse kernels, fewer than 4 (which would only "
        "translate the shape): the stage runs without coarse kernels"]
    assert res.info["stages"][0]["n_coarse_kernels"] == 0
    assert torch.equal(res.V, reconstruct(sphere, bunny, "rbf", steps=3, **SMALL).V)  # the run it was
    # with stages, only the stage too small for the ratio: about 100 / 50 rounds to 2, 300 / 50 to 6
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        res = reconstruct(sphere, bunny, "rbf", steps=4, stages=(100, 300), coarse_ratio=50, **SMALL)
    first, second = res.info["stages"]
    assert res.info["warnings"] == [f"stage 0 ({first['n_vertices']} vertices): coarse_ratio=50 gives "
                                    f"{round(first['n_vertices'] / 50)} coarse kernels, fewer than 4 (which would "
                                    "only translate the shape): the stage runs without coarse kernels"]
    assert first["n_coarse_kernels"] == 0 and second["n_coarse_kernels"] == round(second["n_vertices"] / 50) >= 4


def test_a_budget_spent_before_the_first_step_says_whether_the_start_was_remeshed(sphere, bunny):
    """Found by fuzzing: with stages=None the warning said 'the result is the start after its remeshing', which
    never happened (its condition, a stage record, always held)."""
    from meshmei.reconstruct import ReconstructionWarning

    with pytest.warns(ReconstructionWarning) as caught:
        res = reconstruct(sphere, bunny, "vertex", time_budget=1e-9, **SMALL)
    assert not res.history and torch.equal(res.V, sphere[0]) and torch.equal(res.F, sphere[1])
    assert [str(w.message) for w in caught] == res.info["warnings"] == [
        "the time budget (1e-09 s) ran out before the first step: the result is the start as given, not a fit"]
    with pytest.warns(ReconstructionWarning) as caught:
        res = reconstruct(sphere, bunny, "vertex", time_budget=1e-9, stages=(100, 300), **SMALL)
    assert not res.history and res.V.shape[0] == res.info["stages"][0]["n_vertices"] != sphere[0].shape[0]
    assert res.info["warnings"][-1] == (f"the time budget (1e-09 s) ran out before the first step: the result is "
                                        f"the start remeshed to {res.V.shape[0]} vertices, not a fit")


def test_stages_auto_runs_the_command_lines_schedule_of_the_source_as_built(sphere, bunny):
    from meshmei.reconstruct import NAMED_SCHEDULES, default_schedule, source_mesh

    assert NAMED_SCHEDULES == ("auto", "auto2", "auto3", "auto4")
    n = sphere[0].shape[0]
    for name, levels in (("auto", None), ("auto3", 3)):
        stages, fractions, overrides = default_schedule("rbf", n, levels, n_samples=SMALL["n_samples"])
        assert stages is not None and (overrides is not None) == (levels == 3)
        named = reconstruct(sphere, bunny, "rbf", steps=16, stages=name, seed=1, **SMALL)
        given = reconstruct(sphere, bunny, "rbf", steps=16, stages=stages, stage_fractions=fractions,
                            stage_overrides=overrides, seed=1, **SMALL)
        # the same run bit for bit, and its settings hold the schedule it resolved to (a replay needs no name)
        assert torch.equal(named.V, given.V) and torch.equal(named.F, given.F)
        assert [h["loss"] for h in named.history] == [h["loss"] for h in given.history]
        assert named.to_json()["settings"] == given.to_json()["settings"]
        assert [st["n_vertices_asked"] for st in named.info["stages"] if "n_vertices_asked" in st] == list(stages)
    # a named source is counted as built (the torus of 2,500 vertices lands under 2,500), as the CLI counts it
    teapot = target_mesh("teapot")
    built = source_mesh("torus", target=teapot)[0].shape[0]
    assert built != 2500 and default_schedule("rbf", built)[0] != default_schedule("rbf", 2500)[0]
    res = reconstruct("torus", teapot, "rbf", steps=8, stages="auto", **SMALL)
    assert tuple(res.to_json()["settings"]["stages"]) == default_schedule("rbf", built)[0]
    # what it cannot be given with, and names it does not know: refused before anything is built
    for bad in (dict(stages="auto", stage_fractions=(0.5, 0.5)), dict(stages="auto3", stage_overrides=(None,) * 4)):
        with pytest.raises(ReconstructionError, match="sets the stages' shares and overrides itself"):
            reconstruct(sphere, "no/such/target.obj", "rbf", steps=4, **bad)
    with pytest.raises(ReconstructionError, match=r"one of \('auto', 'auto2', 'auto3', 'auto4'\), got 'auto5'"):
        reconstruct(sphere, "no/such/target.obj", "rbf", steps=4, stages="auto5")
    with pytest.raises(ReconstructionError, match="reconstruct\\(\\) resolves it"):
        ReconstructionSettings(stages="auto").resolved()
