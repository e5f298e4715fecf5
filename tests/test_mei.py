"""3D-MEI optimisation: validation on simulated cells with known optima, run directories, grid search, CLI."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import time
import warnings
from pathlib import Path

import pytest
import torch

from meshmei.encoders import GaborComplexCell, GaborSimpleCell
from meshmei.errors import MEIError
from meshmei.mei import ALBEDO_MIN_STEPS, DEFAULT_CONTACT_WEIGHT, DEFAULT_STEPS, MEISettings, grid_search, load_run, optimize_mei, pixel_mei, save_run
from meshmei.mei import DEFAULT_SIGMA_FACTOR
from meshmei.mei.settings import make_deformer
from meshmei.quality import health_line
from meshmei.shapes import initial_mesh

from conftest import shipped_demo

TINY = dict(image_size=32, n_vertices=80, steps=4, seeds=(0,))


@pytest.fixture(scope="module")
def tiny_run():
    return optimize_mei(GaborSimpleCell(), 0, "sheet", **TINY)


# ---------------------------------------------------------------------------------------------- validation

@pytest.mark.parametrize("cls", [GaborSimpleCell, GaborComplexCell])
@pytest.mark.parametrize("init", ["sheet", pytest.param("sphere", marks=pytest.mark.slow)])  # 800 steps: 85 s each
def test_3d_mei_reaches_090_of_the_bound(cls, init):
    cell = cls()
    # single seeds land between 0.85 and 0.96 (see docs/mei.md); the method keeps the best of its default
    # seeds. At 200 steps and two seeds the complex cell's sheet sat at the threshold (0.907, then 0.888
    # after a change that moved float32 rounding alone), so this runs the defaults users get.
    res = optimize_mei(cell, 0, init)
    assert res.fraction_of_bound >= 0.9, res.seed_activations
    # the reported response is that of the returned mesh rendered in the returned scene
    torch.testing.assert_close(cell(res.render())[0, 0], torch.tensor(res.activation))
    # the pixel MEI in the same image space reaches the bound and beats the 3D-MEI
    pm = pixel_mei(cell, 0, image_size=res.settings.image_size, steps=60, seeds=(0,))
    assert pm.activation >= 0.99 and pm.activation >= res.activation


@pytest.mark.parametrize("cls", [GaborSimpleCell, GaborComplexCell])
def test_3d_mei_from_the_sphere_reaches_090_of_the_bound_in_300_steps(cls):
    """The sphere's check in the default suite: its 800 default steps (the test above, marked slow) took 85 s
    per cell; at 300 steps the best of the default seeds is already past 0.9 (0.964 and 0.950 when this test
    was written, every seed at least 0.93)."""
    cell = cls()
    res = optimize_mei(cell, 0, "sphere", steps=300)
    assert res.fraction_of_bound >= 0.9, res.seed_activations
    torch.testing.assert_close(cell(res.render())[0, 0], torch.tensor(res.activation))


def test_complex_cell_seeds_give_different_phases_with_high_response():
    cell = GaborComplexCell()
    phases, acts = [], []
    for seed in (0, 1, 2):
        res = optimize_mei(cell, 0, "sheet", steps=120, seeds=(seed,), init_noise=0.01)
        acts.append(res.activation)
        phases.append(float(cell.phase_of(res.image)))
    assert min(acts) >= 0.8, acts
    spread = max(abs(math.remainder(a - b, 2 * math.pi)) for a in phases for b in phases)
    assert spread >= 0.25, phases


# ---------------------------------------------------------------------------------------------- behaviour

def test_deterministic_for_a_seed(tiny_run):
    # reproducible up to rounding: torch's CPU kernels may round differently from call to call
    # (vectorised loops depend on memory alignment), so compare with a tight tolerance, not bitwise
    again = optimize_mei(GaborSimpleCell(), 0, "sheet", **TINY)
    torch.testing.assert_close(again.V, tiny_run.V, atol=1e-5, rtol=0)
    assert again.history == pytest.approx(tiny_run.history, abs=1e-5)
    other = optimize_mei(GaborSimpleCell(), 0, "sheet", **{**TINY, "seeds": (5,)})
    assert not torch.equal(other.V, tiny_run.V)


def test_callbacks_see_every_step_of_every_seed():
    """``callbacks`` get each step's history record with its seed, seed after seed, and leave the run as it
    is; one that is not callable is refused before any step."""
    kw = dict(steps=3, seeds=(0, 1), image_size=16, n_vertices=64)
    seen, also = [], []
    res = optimize_mei(GaborSimpleCell(), 0, "sheet", callbacks=[seen.append, also.append], **kw)
    assert [(r["step"], r["seed"]) for r in seen] == [(1, 0), (2, 0), (3, 0), (1, 1), (2, 1), (3, 1)] and also == seen
    assert {"time", "loss", "response", "step_scale"} <= set(seen[0])
    plain = optimize_mei(GaborSimpleCell(), 0, "sheet", **kw)
    torch.testing.assert_close(res.V, plain.V, atol=1e-5, rtol=0)  # rounding: as test_deterministic_for_a_seed
    one = []
    optimize_mei(GaborSimpleCell(), 0, "sheet", callbacks=one.append, **{**kw, "seeds": (0,)})
    assert [r["step"] for r in one] == [1, 2, 3]
    for bad, says in (([print, 3], r"callbacks\[1\] is not callable"), (3, "a callable or a sequence")):
        with pytest.raises(MEIError, match=says):
            optimize_mei(GaborSimpleCell(), 0, "sheet", callbacks=bad, **kw)


def test_result_contents(tiny_run):
    r = tiny_run
    assert r.V.shape == r.V0.shape and r.F.dtype == torch.int64
    assert r.image.shape == (1, 1, 32, 32)
    assert len(r.history) == len(r.loss_history) == TINY["steps"]
    assert set(r.reg_history) == {k for k, w in r.settings.weights.items() if w > 0}
    assert r.encoder["kind"] == "gabor-simple" and r.encoder["upper_bound"] == 1.0
    torch.testing.assert_close(r.deformer()().detach(), r.V)
    assert r.activation == r.seed_activations[r.seed]


# no regularizer, barrier or contact term: the loss is minus the response, so "lowest loss" is "highest response"
PLAIN = dict(weights={"laplacian": 0, "edge": 0, "area": 0, "arap": 0}, valid_steps=False, contact_weight=0.0)


def test_the_seed_with_the_lowest_loss_wins_and_is_its_run_alone():
    # the check this replaced ("... or res.seed in (0, 1)" with seeds (0, 1)) held for any choice of seed
    alone = {s: optimize_mei(GaborSimpleCell(), 0, "sphere", **{**TINY, **PLAIN, "seeds": (s,), "keep": "last"})
             for s in (0, 1, 2)}
    res = optimize_mei(GaborSimpleCell(), 0, "sphere", **{**TINY, **PLAIN, "seeds": (0, 1, 2), "keep": "last"})
    assert res.seed_activations == {s: r.activation for s, r in alone.items()}
    assert res.seed == max(alone, key=lambda s: alone[s].activation)
    assert torch.equal(res.V, alone[res.seed].V) and res.activation == alone[res.seed].activation


def test_keep_best_returns_the_best_iterate_it_evaluated():
    # the check this replaced (min loss >= -activation - 1 for a response of at most 1) held for any iterate
    best = optimize_mei(GaborSimpleCell(), 0, "sphere", **{**TINY, **PLAIN, "keep": "best"})
    last = optimize_mei(GaborSimpleCell(), 0, "sphere", **{**TINY, **PLAIN, "keep": "last"})
    assert best.history == last.history  # the same climb; only the returned iterate differs
    assert best.activation == max([*best.history, last.activation])


def test_joint_light_and_pose():
    res = optimize_mei(GaborSimpleCell(), 0, "sphere", **TINY, optimize_light=True, optimize_pose=True,
                       keep="last")
    assert res.light is not None and not torch.equal(res.light, torch.tensor([0.0, 0.0, 2.5]))
    assert res.rotation.abs().sum() > 0 and res.translation.abs().sum() > 0
    torch.testing.assert_close(GaborSimpleCell()(res.render())[0, 0], torch.tensor(res.activation))


def test_custom_initial_mesh_and_float64():
    from meshmei.shapes import initial_mesh

    V, F = initial_mesh("torus", n_vertices=120, dtype=torch.float64)
    res = optimize_mei(GaborComplexCell(), 0, (V, F), **TINY, dtype="float64")
    assert res.init == "custom" and res.V.dtype == torch.float64 and torch.isfinite(res.V).all()



def test_steps_and_contact_weight_default_by_start():
    # None: the start decides (a closed start has farther to travel); a given count is kept as it is
    assert MEISettings().steps is None and MEISettings().contact_weight is None
    assert {k: MEISettings().for_start(k).steps for k in DEFAULT_STEPS} == DEFAULT_STEPS
    assert {k: MEISettings().for_start(k).contact_weight for k in DEFAULT_CONTACT_WEIGHT} == DEFAULT_CONTACT_WEIGHT
    assert DEFAULT_STEPS["sphere"] > DEFAULT_STEPS["sheet"] and DEFAULT_STEPS["torus"] > DEFAULT_STEPS["sheet"]
    assert MEISettings(steps=7).for_start("torus").steps == 7
    # with an albedo at least ALBEDO_MIN_STEPS (its texture climbs for longer); a given count is still kept
    assert MEISettings(albedo=True).for_start("sheet").steps == ALBEDO_MIN_STEPS > DEFAULT_STEPS["sheet"]
    assert MEISettings(albedo=True).for_start("sphere").steps == max(ALBEDO_MIN_STEPS, DEFAULT_STEPS["sphere"])
    assert MEISettings(albedo=True, steps=7).for_start("sheet").steps == 7
    # the sheet alone goes without the contact barrier (it stays a graph); an explicit weight is kept
    assert MEISettings().for_start("sheet").contact_weight == 0 < MEISettings().for_start("torus").contact_weight
    assert MEISettings(contact_weight=5.0).for_start("sheet").contact_weight == 5.0
    assert MEISettings().for_start("my_mesh").contact_weight == DEFAULT_CONTACT_WEIGHT["custom"] > 0
    # a run records the count it used, and its history has that many steps
    V = torch.tensor([[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [-0.5, 0.5, 0.0]])
    F = torch.tensor([[0, 1, 2], [0, 2, 3]])
    res = optimize_mei(GaborSimpleCell(), 0, (V, F), image_size=16, seeds=(0,), valid_steps=False)
    assert res.settings.steps == DEFAULT_STEPS["custom"] == len(res.history)
    assert res.settings.contact_weight == DEFAULT_CONTACT_WEIGHT["custom"]
    assert res.settings.to_dict()["steps"] == DEFAULT_STEPS["custom"]  # what summary.json stores
    assert res.settings.sigma_factor == DEFAULT_SIGMA_FACTOR["custom"]


def test_kernel_width_default_by_start():
    # None: the start decides (narrower kernels from the torus, with its longer run); a given width is kept
    assert MEISettings().sigma_factor is None
    assert {k: MEISettings().for_start(k).sigma_factor for k in DEFAULT_SIGMA_FACTOR} == DEFAULT_SIGMA_FACTOR
    assert DEFAULT_SIGMA_FACTOR["torus"] < DEFAULT_SIGMA_FACTOR["sphere"] == DEFAULT_SIGMA_FACTOR["sheet"]
    assert MEISettings(sigma_factor=3.0).for_start("torus").sigma_factor == 3.0
    assert MEISettings().for_start("my_mesh").sigma_factor == DEFAULT_SIGMA_FACTOR["custom"]
    # a run's kernels have the width it records: sigma = sigma_factor * the mean centre spacing
    for init in ("torus", "sphere"):
        res = optimize_mei(GaborSimpleCell(), 0, init, image_size=16, seeds=(0,), steps=1, n_vertices=120,
                           lr_scales=0.0)  # the scales stay where the run started them
        assert res.settings.sigma_factor == DEFAULT_SIGMA_FACTOR[init]
        unscaled = make_deformer(res.V0, dataclasses.replace(res.settings, sigma_factor=1.0))
        ratio = res.deformer().log_sigma.exp() / unscaled.log_sigma.exp()
        assert torch.allclose(ratio, torch.full_like(ratio, DEFAULT_SIGMA_FACTOR[init]), rtol=1e-5)
    # settings not resolved for a start build a mesh of your own's kernels
    ratio = make_deformer(res.V0, MEISettings()).log_sigma.exp() / unscaled.log_sigma.exp()
    assert torch.allclose(ratio, torch.full_like(ratio, DEFAULT_SIGMA_FACTOR["custom"]), rtol=1e-5)
    with pytest.raises(MEIError, match="sigma_factor"):
        MEISettings(sigma_factor=float("nan"))


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="names an fd's file through /proc")
def test_a_saved_run_is_on_disk_before_it_is_renamed_into_place(tmp_path, tiny_run, monkeypatch):
    """Every file of a run folder is fsynced before the folder's rename makes it a finished result: a
    population resume took a neuron whose state.pt was left empty (as a power loss after the rename may
    leave it) for finished."""
    synced, real = [], os.fsync

    def recording(fd):
        synced.append(os.readlink(f"/proc/self/fd/{fd}"))
        return real(fd)

    monkeypatch.setattr(os, "fsync", recording)
    out = save_run(tiny_run, tmp_path / "run")
    files = sorted(p.name for p in out.iterdir() if p.is_file())
    inside = [Path(p).name for p in synced if Path(p).parent.name.startswith(".run.partial-")]
    assert files and sorted(inside) == files
    assert str(tmp_path) in synced  # and the folder that holds the renamed result


def test_save_and_load_run_exactly(tmp_path, tiny_run):
    out = save_run(tiny_run, tmp_path / "run")
    for name in ("mesh.obj", "rest.obj", "state.pt", "summary.json", "render.png", "views.png", "activation.png"):
        assert (out / name).is_file(), name
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left behind
    back = load_run(out, rebuild_encoder=True)
    assert torch.equal(back.V, tiny_run.V) and torch.equal(back.F, tiny_run.F)
    assert back.settings == tiny_run.settings and back.history == tiny_run.history
    assert torch.equal(back.render(), tiny_run.render())  # the exact scene is rebuilt
    assert back.encoder_module(back.render())[0, 0].item() == pytest.approx(tiny_run.activation, abs=1e-6)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["complete"] and summary["quality"]["min_quality"] > 0
    with pytest.raises(MEIError, match="exists"):
        save_run(tiny_run, out)
    save_run(tiny_run, out, overwrite=True)
    assert load_run(out).activation == tiny_run.activation


def test_interrupted_or_corrupt_run_is_rejected(tmp_path, tiny_run, monkeypatch):
    import meshmei.mei.runs as runs

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(runs, "mei_figures", boom)
    with pytest.raises(KeyboardInterrupt):
        save_run(tiny_run, tmp_path / "run")
    assert not (tmp_path / "run").exists() and list(tmp_path.iterdir()) == []
    monkeypatch.undo()
    with pytest.raises(MEIError, match="no MEI run"):
        load_run(tmp_path / "run")
    out = save_run(tiny_run, tmp_path / "run", figures=False)
    (out / "state.pt").write_bytes(b"garbage")
    with pytest.raises(MEIError, match="corrupt"):
        load_run(out)
    (out / "summary.json").write_text("{")
    with pytest.raises(MEIError, match="unreadable"):
        load_run(out)
    (out / "summary.json").unlink()
    with pytest.raises(MEIError, match="missing"):
        load_run(out)


def test_grid_search_reports_activation_and_quality():
    rows = grid_search(GaborSimpleCell(), 0, "sphere", {"laplacian": [0.0, 100.0]}, **TINY)
    assert [r["weights"]["laplacian"] for r in rows] == [0.0, 100.0]
    for r in rows:
        assert {"activation", "fraction_of_bound", "min_quality", "mean_quality", "self_intersections", "seconds",
                "flipped_faces", "watertight"} <= set(r)
        assert isinstance(r["self_intersections"], int) and isinstance(r["flipped_faces"], int)
        assert r["watertight"] is True  # the sphere stays closed
        # each row is the run it names: a grid that ignored its weights gave one run under every label
        alone = optimize_mei(GaborSimpleCell(), 0, "sphere", **{**TINY, "weights": r["weights"]})
        h = alone.health()
        assert (r["activation"], r["fraction_of_bound"]) == (alone.activation, alone.activation)  # upper bound 1
        assert (r["self_intersections"], r["flipped_faces"], r["min_quality"]) == (
            h["self_intersections"], h["flipped_faces"], h["min_quality"])
    assert rows[0]["activation"] != rows[1]["activation"]


def test_bad_input_raises_mei_error():
    cell = GaborSimpleCell()
    assert issubclass(MEIError, ValueError)
    with pytest.raises(MEIError, match="init"):
        optimize_mei(cell, 0, "cube", **TINY)
    with pytest.raises(MEIError, match="out of range"):
        optimize_mei(cell, 3, "sheet", **TINY)
    with pytest.raises(MEIError, match="single index"):
        optimize_mei(cell, [0, 0], "sheet", **TINY)
    with pytest.raises(MEIError, match="encoder"):
        optimize_mei(lambda x: x, 0, "sheet")
    with pytest.raises(MEIError, match="unknown regularizer"):
        MEISettings(weights={"smoothness": 1.0})
    with pytest.raises(MEIError, match="steps"):
        MEISettings(steps=0)
    with pytest.raises(MEIError, match="seeds"):
        MEISettings(seeds=())
    with pytest.raises(MEIError, match="keep"):
        MEISettings(keep="first")
    with pytest.raises(MEIError, match="min_quality must lie in"):
        MEISettings(min_quality=1.5)
    with pytest.raises(MEIError, match=r"contact_distance must lie in \(0, 4\] mean edge lengths, got 5"):
        MEISettings(contact_distance=5)
    with pytest.raises(MEIError, match="reg_ref_vertices must be a positive integer"):
        MEISettings(reg_ref_vertices=0)
    with pytest.raises(MEIError, match="RenderSettings"):
        MEISettings(render={"colour": 1})
    with pytest.raises(MEIError, match="unknown MEISettings"):
        optimize_mei(cell, 0, "sheet", step=3)
    with pytest.raises(MEIError, match="grid"):
        grid_search(cell, 0, "sheet", {"laplacian": []}, **TINY)
    # kernels too narrow for float32 gave NaN vertices, reported as a mesh error at the first render
    with pytest.raises(MEIError, match=r"^sigma_factor=1e-30: the RBF kernels are \S+ wide, too narrow for "
                                       r"torch.float32 arithmetic \(1 / sigma\^2 overflows\); raise sigma_factor$"):
        optimize_mei(cell, 0, "sheet", **{**TINY, "sigma_factor": 1e-30})


def test_cli_writes_a_run(tmp_path, capsys, monkeypatch):
    import meshmei.cli as cli
    from meshmei.cli import main

    seen = []
    monkeypatch.setattr(cli, "pixel_mei", lambda *a, **k: (seen.append(k.get("seeds")), pixel_mei(*a, **k))[1])
    out = tmp_path / "cli"
    rc = main(["mei", "--encoder", "gabor-complex", "--neuron", "0", "--init", "sheet", "--out", str(out),
               "--steps", "3", "--seeds", "0", "--image-size", "32", "--n-vertices", "80", "--quiet",
               "--pixel-mei"])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "of the upper bound" in printed
    # its health in full, as recomputed from the saved run: the sheet is open, so not watertight
    h = load_run(out).health()
    assert health_line(h) in printed and h["boundary_edges"] > 0 and f"open: {h['boundary_edges']} boundary edges" in printed
    summary = json.loads((out / "summary.json").read_text())
    assert summary["encoder"]["kind"] == "gabor-complex" and "pixel_mei_activation" in summary
    assert seen == [(0,)]  # the pixel MEI takes --seeds too (it ran seeds 0, 1, 2 whatever --seeds said)
    assert main(["mei", "--out", str(out), "--steps", "1", "--quiet"]) == 2  # exists: clear error


@pytest.mark.parametrize("device", ["tpu", "cuda:x", "cpu:1"] + ([] if torch.cuda.is_available() else ["cuda"]))
def test_cli_refuses_a_device_it_cannot_use_in_one_line_and_writes_nothing(tmp_path, capsys, device):
    from meshmei.cli import main

    out = tmp_path / "run"
    assert main(["mei", "--out", str(out), "--steps", "1", "--quiet", "--device", device]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and ("must be cpu, cuda or cuda:N" in err or "has no CUDA device" in err)
    assert not out.exists()


@pytest.mark.parametrize("command", [["mei", "--quiet"], ["reconstruct", "--target", "bunny", "--no-progress"],
                                     ["population", "--neurons", "0", "--quiet"]])
def test_cli_refuses_an_output_folder_below_a_file_in_one_line_before_the_run(tmp_path, capsys, monkeypatch, command):
    """--out afile/sub ended in errno 17 or 20, reconstruct's after its whole run."""
    import meshmei.cli as cli
    import meshmei.population.run as population_run

    def ran(*args, **kwargs):
        raise AssertionError("the run started before its output folder was checked")

    for module, name in ((cli, "optimize_mei"), (cli, "reconstruct"), (population_run, "mei_batches")):
        monkeypatch.setattr(module, name, ran)
    (tmp_path / "afile").write_text("mine")
    assert cli.main([*command, "--out", str(tmp_path / "afile" / "sub"), "--steps", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.endswith(f"cannot make {tmp_path / 'afile' / 'sub'}: {tmp_path / 'afile'} is a file, not a folder; "
                        "choose another output path") and "\n" not in err
    assert (tmp_path / "afile").read_text() == "mine"


def test_cli_refuses_the_current_folder_as_an_output_to_replace(tmp_path, monkeypatch, capsys):
    """--out . --overwrite in a run folder failed with errno 16 after the run."""
    import meshmei.cli as cli

    (tmp_path / "summary.json").write_text("{}")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(cli, "optimize_mei", lambda *a, **k: pytest.fail("ran before refusing its output"))
    for out in (".", "", str(tmp_path.parent)):
        assert cli.main(["mei", "--out", out, "--overwrite", "--steps", "1", "--quiet"]) == 2
        err = capsys.readouterr().err.strip()
        assert "is the current folder or holds it; it cannot be replaced" in err and "\n" not in err
    assert (tmp_path / "summary.json").read_text() == "{}"


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs a folder that takes no new folder: Linux's /proc")
def test_cli_refuses_an_output_where_no_folder_can_be_made_before_the_run(monkeypatch, capsys):
    """--out /proc/x passed the permission test and failed after the run, naming a hidden partial folder."""
    import meshmei.cli as cli

    monkeypatch.setattr(cli, "optimize_mei", lambda *a, **k: pytest.fail("ran before refusing its output"))
    assert cli.main(["mei", "--out", "/proc/meshmei-x", "--steps", "1", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("meshmei mei: error: cannot make /proc/meshmei-x: /proc takes no new folder") and "\n" not in err


def test_cli_reads_a_tilde_left_by_the_shell_as_the_home_folder(tmp_path, monkeypatch, capsys):
    """--out '~/run' (quoted, or after '=') made a folder named '~' and failed after the run."""
    from meshmei.cli import main

    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.chdir(tmp_path)
    assert main(["mei", "--out=~/run", "--steps", "1", "--image-size", "16", "--n-vertices", "40", "--quiet"]) == 0
    assert (tmp_path / "home" / "run" / "summary.json").is_file() and not (tmp_path / "~").exists()


def test_ctrl_c_ends_the_cli_in_one_line_with_code_130_and_writes_nothing(tmp_path, capsys, monkeypatch):
    import meshmei.cli as cli

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "optimize_mei", interrupted)
    assert cli.main(["mei", "--out", str(tmp_path / "run"), "--steps", "2", "--quiet"]) == 130
    err = capsys.readouterr().err.strip()
    assert err.startswith("meshmei mei: interrupted") and "\n" not in err and not (tmp_path / "run").exists()


def test_sigterm_ends_the_cli_as_ctrl_c_does(tmp_path):
    """SIGTERM (a scheduler cancelling the job) ended `meshmei mei` with code 143 and no word; it now ends it
    as Ctrl-C does, in one line with code 130, and nothing is written."""
    import signal
    import subprocess
    import sys

    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "meshmei.cli", "mei", "--encoder", "gabor-simple", "--init", "sphere", "--steps",
           "100000", "--seeds", "0", "--image-size", "16", "--n-vertices", "60", "--out", str(out)]
    proc = subprocess.Popen(cmd, env={**os.environ, "OMP_NUM_THREADS": "1"}, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    first = proc.stderr.read(1)  # the progress bar's first character: imports done, the handler in place
    assert first and proc.poll() is None, "the run ended before it could be stopped"
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    last = err.strip().splitlines()[-1]
    assert last == "meshmei mei: interrupted (runs and sweeps are written whole or not at all)"
    assert not out.exists() and not list(tmp_path.glob(".run.partial-*"))


def test_a_whole_write_removes_what_killed_writers_left_beside_it(tmp_path):
    """A process killed while it wrote (SIGKILL) leaves its hidden .NAME.partial-XXXX folder; it was never
    removed. The next whole write of NAME removes those untouched for STALE_SECONDS; a recent one (a
    writer still at work) and other names' stay."""
    from meshmei._files import STALE_SECONDS, atomic_directory

    old, recent, other = (tmp_path / n for n in (".run.partial-0000dead", ".run.partial-0000live",
                                                  ".other.partial-0000dead"))
    for folder in (old, recent, other):
        folder.mkdir()
        (folder / "state.pt").write_text("half")
    then = time.time() - STALE_SECONDS - 60
    for folder in (old, other):
        os.utime(folder, (then, then))
    atomic_directory(tmp_path / "run", lambda tmp: (tmp / "summary.json").write_text("{}"))
    assert not old.exists() and recent.exists() and other.exists() and (tmp_path / "run" / "summary.json").is_file()


def test_a_damaged_summary_is_one_clear_error(tmp_path):
    res = optimize_mei(GaborSimpleCell(), 0, "sheet", steps=2, seeds=(0,), image_size=16, n_vertices=40)
    run = save_run(res, tmp_path / "run", figures=False)
    good = json.loads((run / "summary.json").read_text())
    for damage in ({"encoder": "gabor"}, {"activation": None}, {"seed_activations": [1, 2]}, {"neuron": "x"}):
        (run / "summary.json").write_text(json.dumps({**good, **damage}))
        with pytest.raises(MEIError, match="summary.json is damaged"):
            load_run(run, rebuild_encoder=True)
    for key in ("encoder", "neuron", "history"):
        (run / "summary.json").write_text(json.dumps({k: v for k, v in good.items() if k != key}))
        with pytest.raises(MEIError, match="summary.json is damaged"):
            load_run(run, rebuild_encoder=True)


def test_a_seed_that_ended_without_a_finite_response_is_saved_as_null_and_read_back_as_nan(tmp_path):
    """A losing seed's NaN response went into summary.json as NaN, which JSON does not have (strict readers
    refuse the file)."""
    res = optimize_mei(GaborSimpleCell(), 0, "sheet", steps=2, seeds=(0, 1), image_size=16, n_vertices=40)
    res.seed_activations[1 - res.seed] = math.nan
    run = save_run(res, tmp_path / "run", figures=False)

    def no_constants(name):
        raise AssertionError(f"summary.json holds {name}")

    summary = json.loads((run / "summary.json").read_text(), parse_constant=no_constants)
    assert summary["seed_activations"] == {str(res.seed): res.activation, str(1 - res.seed): None}
    back = load_run(run, rebuild_encoder=True)
    assert back.seed_activations[res.seed] == res.activation and math.isnan(back.seed_activations[1 - res.seed])
    for damage in ({"0": "high", "1": None}, {"first": 0.5}, {"0": math.inf}):
        (run / "summary.json").write_text(json.dumps({**summary, "seed_activations": damage}))
        with pytest.raises(MEIError, match="seed_activations must be a dict of seeds"):
            load_run(run, rebuild_encoder=True)


def test_a_run_is_read_only_with_its_own_encoder_and_image_size(tmp_path, capsys):
    """An edited summary.json (another cell, another image size) or a model that is not the run's was swept
    and reported under the run's name; each is now refused, naming what differs."""
    from meshmei.cli import main

    res = optimize_mei(GaborSimpleCell(), 0, "sheet", steps=2, seeds=(0,), image_size=16, n_vertices=40)
    run = save_run(res, tmp_path / "run", figures=False)
    good = json.loads((run / "summary.json").read_text())
    assert load_run(run, encoder=GaborSimpleCell()).activation == res.activation  # the run's own encoder passes
    with pytest.raises(MEIError, match="the encoder given gives the saved image a response of .* not the run's"):
        load_run(run, encoder=GaborSimpleCell(orientation=1.0))
    other = {**good["encoder"], "params": {**good["encoder"]["params"], "orientation": [1.0]}}
    size = {**good["settings"], "image_size": 32}
    for damage, says in [({"encoder": other}, "the encoder summary.json describes .* not the run's encoder"),
                         ({"settings": size}, "the saved image has shape \\(1, 1, 16, 16\\), not the \\(1, 1, 32, 32\\)")]:
        (run / "summary.json").write_text(json.dumps({**good, **damage}))
        with pytest.raises(MEIError, match=says):
            load_run(run, rebuild_encoder=True)
        assert main(["tune", "pose", "--mei", str(run), "--elevation", "0:0:1", "--azimuth", "0:0:1"]) == 2
        err = capsys.readouterr().err.strip()
        assert re.search(says, err) and "\n" not in err and not (run / "tuning_pose").exists()


def test_a_damaged_state_is_one_clear_error_naming_state_pt(tmp_path, capsys):
    """A state.pt without V failed with a KeyError in the CLI, one with V a list or empty inside torch, one
    without the image was blamed on summary.json, and NaN offsets passed the reproduction check."""
    from meshmei.cli import main

    res = optimize_mei(GaborSimpleCell(), 0, "sheet", steps=2, seeds=(0,), image_size=16, n_vertices=40)
    run = save_run(res, tmp_path / "run", figures=False)
    good = torch.load(run / "state.pt", weights_only=True)
    nan_offsets = {**good["deformer"], "offsets": torch.full_like(good["deformer"]["offsets"], math.nan)}
    for damage, says in [({"V": None}, "missing \\['V'\\]"), ({"image": None}, "missing \\['image'\\]"),
                         ({"V": good["V"].tolist()}, "V must be tensors, got list"), ({"V": torch.zeros(0, 3)}, "mesh is empty"),
                         ({"V0": good["V0"][:5]}, "rest pose V0 of shape \\(5, 3\\) does not match"), ({"rotation": None}, "missing \\['rotation'\\]"),
                         ({"rotation": torch.zeros(3, 3)}, "rotation must have shape \\(3,\\)"),
                         ({"deformer": nan_offsets}, "deformer offsets holds NaN or Inf"),
                         ({"translation": torch.tensor([0.0, math.inf, 0.0])}, "translation holds NaN or Inf"),
                         ({"F": good["F"] + 1000}, "F holds vertex index"), ({"format": 9}, "its format is 9")]:
        state = {k: v for k, v in {**good, **damage}.items() if v is not None}
        torch.save(state, run / "state.pt")
        with pytest.raises(MEIError, match=rf"^{re.escape(str(run / 'state.pt'))} is damaged: .*{says}"):
            load_run(run)
        assert main(["tune", "pose", "--mei", str(run), "--elevation", "0:0:1", "--azimuth", "0:0:1"]) == 2
        err = capsys.readouterr().err.strip()
        assert "state.pt is damaged" in err and "\n" not in err and not (run / "tuning_pose").exists()
    torch.save([1, 2], run / "state.pt")
    with pytest.raises(MEIError, match="state.pt is damaged: it holds a list, not the dict save_run writes"):
        load_run(run)
    (run / "state.pt").write_bytes(b"garbage " * 10)  # not torch's advice to load it with weights_only=False
    with pytest.raises(MEIError, match=r"is corrupt: state.pt: UnpicklingError: it is not a file save_run wrote$"):
        load_run(run)
    torch.save(good, run / "state.pt")
    assert torch.equal(load_run(run).V, res.V)


def test_a_start_of_your_own_drops_the_vertices_no_face_uses():
    V, F = initial_mesh("sphere", n_vertices=120)[:2]
    far = torch.cat([V, torch.tensor([[40.0, 40.0, 40.0]])])  # one stray vertex: it widened every kernel
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a unit-sized start: no warning about its scale
        a = optimize_mei(GaborSimpleCell(), 0, (V, F), steps=3, seeds=(0,), image_size=32)
        b = optimize_mei(GaborSimpleCell(), 0, (far, F), steps=3, seeds=(0,), image_size=32)
    assert torch.equal(a.V, b.V) and b.V0.shape == V.shape


def test_cli_says_how_many_steps_the_guard_undid(tmp_path, capsys):
    """A stalled run (here every step at lr=1e30 turns faces over) names it on the final line; a run that
    undid none says nothing of it."""
    from meshmei.cli import main

    common = ["mei", "--init", "sphere", "--steps", "3", "--seeds", "0", "--image-size", "16", "--n-vertices", "80",
              "--quiet"]
    assert main(common + ["--out", str(tmp_path / "wild"), "--lr", "1e30"]) == 0
    printed = capsys.readouterr().out
    assert "; the step guard undid 3 of its 3 steps" in printed
    assert json.loads((tmp_path / "wild" / "summary.json").read_text())["guard"]["undone"] == 3
    assert main(common + ["--out", str(tmp_path / "calm")]) == 0
    assert "undid" not in capsys.readouterr().out


def test_cli_starts_from_a_mesh_file_placed_as_the_built_in_starts(tmp_path, capsys):
    import trimesh
    from meshmei.cli import main
    from meshmei.mesh import load_mesh

    sphere = trimesh.creation.icosphere(2, radius=7.0)
    sphere.apply_translation([100.0, -3.0, 2.0])  # far off the camera's view, 14 wide
    sphere.export(tmp_path / "ball.obj")
    out = tmp_path / "run"
    rc = main(["mei", "--init", str(tmp_path / "ball.obj"), "--out", str(out), "--steps", "3", "--seeds", "0",
               "--image-size", "32", "--quiet"])
    assert rc == 0, capsys.readouterr().err
    V0, F0 = load_mesh(out / "rest.obj", dtype=torch.float64)
    lo, hi = V0.min(0).values, V0.max(0).values
    torch.testing.assert_close(0.5 * (lo + hi), torch.zeros(3, dtype=torch.float64), atol=1e-6, rtol=0)
    assert float((hi - lo).max()) == pytest.approx(1.0, abs=1e-6) and F0.shape == (len(sphere.faces), 3)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["quality"]["self_intersections"] == 0
    image = load_run(out).image[0, 0]
    assert float((image - 0.5).abs().gt(1e-3).float().mean()) > 0.2  # in view: it covers the image's middle
    assert main(["mei", "--init", str(tmp_path / "none.obj"), "--out", str(tmp_path / "x"), "--quiet"]) == 2
    assert "a mesh file; " in capsys.readouterr().err


def test_the_random_baselines_seed_is_one_of_the_seeds_of_distinct_draws():
    """random_mesh_responses took any int: 2**32 drew the deformations of seed 0, -1 those of 2**32 - 1."""
    from meshmei.mei import random_mesh_responses

    for seed, says in ((2 ** 32, "4294967296 gives the run of 0"), (-1, "-1 gives the run of 4294967295")):
        with pytest.raises(MEIError, match=rf"^seed must lie in \[0, 4294967295\], .*{says}\), got {seed}$"):
            random_mesh_responses(GaborSimpleCell(), 0, "sphere", 2, seed=seed)
    with pytest.raises(MEIError, match=r"^seed must be an integer in \[0, 4294967295\], got 1\.5$"):
        random_mesh_responses(GaborSimpleCell(), 0, "sphere", 2, seed=1.5)


# ---------------------------------------------------------------------------------------------- demo model

def test_demo_neuron_3d_mei_beats_random_meshes_and_pixel_mei_is_higher_still():
    from meshmei.mei import random_mesh_responses

    _, model = shipped_demo()
    rand = random_mesh_responses(model, 0, "sphere", 1000)
    res = optimize_mei(model, 0, "sphere", steps=60, seeds=(0,))
    assert res.activation >= float(rand.max()), (res.activation, float(rand.max()))
    pm = pixel_mei(model, 0, image_size=res.settings.image_size, steps=300, seeds=(0,))
    assert pm.activation >= res.activation, (pm.activation, res.activation)


# ---------------------------------------------------------------------------------------------- bad input

def test_random_mesh_responses_take_one_neuron_only():
    from meshmei.encoders import CoreReadoutModel
    from meshmei.mei import random_mesh_responses

    model, s = CoreReadoutModel(6), MEISettings(image_size=16, n_vertices=40)
    for neuron in ([3, 5], None):  # used to answer for neuron 3 and neuron 0, silently
        with pytest.raises(MEIError, match="neuron must be a single index"):
            random_mesh_responses(model, neuron, "sheet", n=2, settings=s)


def test_keep_last_refuses_a_non_finite_final_loss():
    # lr 1e37 overflows the one step; keep="last" used to return the NaN mesh and response as a result
    with pytest.raises(MEIError, match=r"the loss became nan at step 1 of seed 0; lower the learning rate"):
        optimize_mei(GaborSimpleCell(), 0, "sheet", seeds=(0,), steps=1, image_size=16, n_vertices=40, lr=1e37,
                     valid_steps=False, keep="last")


def test_a_seed_with_a_non_finite_end_never_wins():
    from meshmei.mei.optimize import initial, result_from_seeds

    res = optimize_mei(GaborSimpleCell(), 0, "sheet", seeds=(0,), steps=1, image_size=16, n_vertices=40)
    run = dict(V=res.V, image=res.image, activation=res.activation, loss=res.loss_history[-1],
               history=res.history, loss_history=res.loss_history, reg_history=res.reg_history,
               time_history=res.time_history, deformer_state=res.deformer_state, light=res.light,
               rotation=res.rotation, translation=res.translation)
    V0, F, _ = initial("sheet", res.settings)
    runs = {0: {**run, "loss": math.nan}, 1: run, 2: {**run, "loss": -1e9, "activation": math.nan}}
    assert result_from_seeds(runs, V0, F, res.settings, 0, GaborSimpleCell(), "sheet", 1.0).seed == 1
    with pytest.raises(MEIError, match="no seed of neuron 0 ended with a finite loss and response"):
        result_from_seeds({0: runs[0], 2: runs[2]}, V0, F, res.settings, 0, GaborSimpleCell(), "sheet", 1.0)


@pytest.mark.parametrize("kw, match", [
    (dict(lr=1e39), "lr must be at most 3.4e[+]37"),
    (dict(lr=1e38), "lr must be at most 3.4e[+]37"),
    (dict(lr_scales=1e39), "lr_scales must be at most"),
    # a step may widen a kernel e^lr_scales times: 100 overflowed every scale at the first step, silently
    (dict(lr_scales=100.0), r"^lr_scales must be at most 10 \(a step may widen an RBF kernel e\^lr_scales times; .*"
                            r"got 100\.0$"),
    (dict(lr_scales=10.5), r"^lr_scales must be at most 10 .*got 10\.5$"),
    (dict(lr_light=1e39), "lr_light must be at most"),
    (dict(lr_pose=1e39), "lr_pose must be at most"),
    (dict(lr_albedo=1e39), "lr_albedo must be at most"),
    (dict(lr=1e-3, albedo=True, albedo_shape_lr=1e50), r"lr \* albedo_shape_lr must be at most"),
    (dict(lr_decay=2.0), r"lr_decay must lie in \[0, 1\]"),
    (dict(centers=10.0), "centers must be None or an int"),
    (dict(fov_degrees=0), r"fov_degrees must lie in \(0, 180\), got 0"),
    (dict(fov_degrees=180), r"fov_degrees must lie in \(0, 180\), got 180"),
    (dict(fov_degrees=300), r"fov_degrees must lie in \(0, 180\), got 300"),
    (dict(camera_distance=0), "camera_distance must be positive, got 0"),
    (dict(min_quality="0.1"), r"min_quality must lie in \[0, 1\), got '0.1'"),
    (dict(albedo_init="0.5"), r"albedo_init must lie in \(0, 1\), got '0.5'"),
    (dict(albedo=1), "albedo must be True or False, got 1"),
    (dict(light=5), "light must be three finite numbers or None, got 5"),
    (dict(light="abc"), "light must be three finite numbers or None, got 'abc'"),
    (dict(light="123"), "light must be three finite numbers or None, got '123'"),
    (dict(reg_ref_vertices="abc"), "reg_ref_vertices must be a positive integer or None, got 'abc'"),
    (dict(reg_ref_vertices=math.nan), "reg_ref_vertices must be a positive integer or None, got nan"),
    # "false" is a true string: the pose and light were optimised and the guard ran
    (dict(optimize_pose="false"), "optimize_pose must be True or False, got 'false'"),
    (dict(optimize_light="false"), "optimize_light must be True or False, got 'false'"),
    (dict(valid_steps="false"), "valid_steps must be True or False, got 'false'"),
    (dict(seeds=None), "seeds must be a non-empty sequence of integers, got None"),  # a TypeError
    (dict(seeds=[math.inf]), r"seeds must be a non-empty sequence of integers, got \[inf\]"),  # an OverflowError
    # torch's 'Overflow when unpacking long long' at the first seed; two runs of one seed
    (dict(seeds=(2 ** 64,)), r"seeds must lie in \[0, 4294967295\], the seeds of distinct runs"),
    # torch's CPU generator keeps a seed's low 32 bits: -1 was the run of 2**32 - 1, 2**32 the run of 0
    (dict(seeds=(-1, 0)), r"seeds must lie in \[0, 4294967295\], .*low 32 bits; -1 gives the run of 4294967295\), "
                          r"got \[-1\]$"),
    (dict(seeds=(0, 2 ** 32)), r"4294967296 gives the run of 0\), got \[4294967296\]$"),
    # 810,000 renders a step: torch's allocation error after the run started
    (dict(robust_pose=20, robust_light=20, robust_points=30), "robust_points=30 gives 810,000 views per step"),
    (dict(robust_pose=1e6), "robust_pose must be at most 180 degrees"),
])
def test_settings_that_would_fail_later_are_one_line_mei_errors(kw, match):
    # each used to pass, or to fail as a TypeError / ValueError / RuntimeError from deep inside a run
    with pytest.raises(MEIError, match=match) as err:
        MEISettings(**kw)
    assert "\n" not in str(err.value)


def test_numpy_scalars_are_taken_as_python_numbers_and_the_run_saves(tmp_path):
    """np.int64 centres and an np.float32 quality bound passed the checks and broke save_run's JSON after
    the whole run."""
    import numpy as np

    s = MEISettings(centers=np.int64(20), min_quality=np.float32(0.01), reg_ref_vertices=np.int64(400),
                    seeds=(np.int64(0),), valid_steps=np.bool_(True))
    assert [type(v) for v in (s.centers, s.min_quality, s.reg_ref_vertices, s.seeds[0], s.valid_steps)] == [
        int, float, int, int, bool]
    res = optimize_mei(GaborSimpleCell(), 0, "sheet", s, steps=2, image_size=16, n_vertices=60)
    back = load_run(save_run(res, tmp_path / "run", figures=False))
    assert back.settings == res.settings and back.settings.centers == 20


def test_extra_entries_may_not_overwrite_the_runs_own_fields(tmp_path):
    res = optimize_mei(GaborSimpleCell(), 0, "sheet", steps=2, image_size=16, n_vertices=60, seeds=(0,))
    bad = dataclasses.replace(res, extra={**res.extra, "activation": 123.0, "format": 2})
    with pytest.raises(MEIError, match=r"^result.extra holds \['activation', 'format'\], which are the run's own"):
        save_run(bad, tmp_path / "run", figures=False)
    assert not (tmp_path / "run").exists()
    good = dataclasses.replace(res, extra={**res.extra, "note": "mine"})
    back = load_run(save_run(good, tmp_path / "run", figures=False))
    assert back.extra["note"] == "mine" and back.activation == res.activation


def test_the_learning_rate_bound_follows_the_dtype():
    MEISettings(lr=3e37)  # Adam's first step, 3e38, is still a float32
    assert MEISettings(lr=1e39, dtype="float64").lr == 1e39


def test_a_neuron_given_as_a_string_is_an_mei_error():
    with pytest.raises(MEIError, match="a neuron must be an integer index"):
        optimize_mei(GaborSimpleCell(), "0", "sheet", seeds=(0,), steps=1, image_size=16, n_vertices=40)


def test_cli_refuses_n_vertices_with_a_mesh_file_and_records_the_files_count(tmp_path, capsys):
    import trimesh
    from meshmei.cli import main

    trimesh.creation.icosphere(1).export(tmp_path / "ball.obj")  # 42 vertices
    common = ["mei", "--init", str(tmp_path / "ball.obj"), "--steps", "1", "--seeds", "0", "--image-size", "16",
              "--quiet"]
    assert main([*common, "--n-vertices", "40", "--out", str(tmp_path / "a")]) == 2  # used to be ignored
    err = capsys.readouterr().err.strip()
    assert "--n-vertices 40" in err and "42 vertices" in err and "\n" not in err and not (tmp_path / "a").exists()
    assert main([*common, "--out", str(tmp_path / "b")]) == 0
    summary = json.loads((tmp_path / "b" / "summary.json").read_text())
    assert summary["settings"]["n_vertices"] == summary["n_vertices"] == 42  # was 400, the unused default
    assert main(["mei", "--init", "sheet", "--n-vertices", "40", "--steps", "1", "--seeds", "0", "--image-size",
                 "16", "--quiet", "--out", str(tmp_path / "c")]) == 0
    assert json.loads((tmp_path / "c" / "summary.json").read_text())["settings"]["n_vertices"] == 40


def test_load_run_holds_the_rebuilt_deformer_to_the_truncation_bound(tmp_path):
    # learnable scales that grow past the pair list's headroom at r_cut=1: the run's pair list and the rebuilt
    # deformer's differ, and deformer()() is off V by up to exp(-r_cut^2 / 2) sum_k |offsets_k|, not equal
    res = optimize_mei(GaborComplexCell(), 0, "sphere", steps=5, seeds=(0,), image_size=16, n_vertices=80,
                       lr=0.02, lr_scales=0.5, r_cut=1.0)
    bound = math.exp(-0.5) * float(res.deformer_state["offsets"].double().norm(dim=-1).sum())
    with torch.no_grad():
        gap = float((res.deformer()().double() - res.V.double()).abs().max())
    assert 1e-3 < gap <= bound
    run = save_run(res, tmp_path / "run", figures=False)
    assert torch.equal(load_run(run).V, res.V)  # the saved vertices, not the rebuilt ones
    state = torch.load(run / "state.pt", weights_only=True)
    state["V"] = state["V"].clone()
    state["V"][0, 0] += 1.5 * bound  # within the old, doubled tolerance; beyond what truncation explains
    torch.save(state, run / "state.pt")
    with pytest.raises(MEIError, match="state.pt is not the file"):  # the digest summary.json records
        load_run(run)
    summary = json.loads((run / "summary.json").read_text())
    del summary["sha256"]  # as a run saved before the digests: the reproduction check still holds
    (run / "summary.json").write_text(json.dumps(summary))
    with pytest.raises(MEIError, match="does not reproduce the saved vertices"):
        load_run(run)


def test_cli_overwrite_never_removes_a_folder_of_other_files(tmp_path, capsys, monkeypatch):
    """meshmei mei --out DIR --overwrite deleted every file in DIR; now refused, before the run."""
    import meshmei.cli as cli_module

    theirs = tmp_path / "data"
    (theirs / "sub").mkdir(parents=True)
    (theirs / "precious.txt").write_text("keep")
    runs = []
    monkeypatch.setattr(cli_module, "optimize_mei", lambda *a, **k: runs.append(a))
    rc = cli_module.main(["mei", "--encoder", "gabor-simple", "--out", str(theirs), "--overwrite", "--steps", "2",
                          "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and "holds files meshmei did not write" in err and len(err.splitlines()) == 1 and runs == []
    assert sorted(p.name for p in theirs.iterdir()) == ["precious.txt", "sub"]


def test_bad_inputs_of_the_batch_diverse_and_baseline_helpers_are_mei_errors():
    """Each escaped as a bare TypeError from inside, or ran as something else ('10' as weights 1 and 0)."""
    from meshmei.mei import diverse_meis, optimize_mei_batch, random_mesh_responses

    enc = GaborSimpleCell(orientation=[0.0, 0.5])
    base = dict(steps=2, image_size=16, seeds=(0,), n_vertices=64)
    cases = [
        (lambda: optimize_mei_batch(enc, 1, "sheet", **base), r"^neurons must be a sequence of neuron indices \(e.g. \[1\]\)"),
        (lambda: diverse_meis(enc, 0, k=2, diversity="a", **base), r"^need diversity >= 0 and floor in \[0, 1\], got 'a'"),
        (lambda: diverse_meis(enc, 0, k=2, floor=None, **base), r"^need diversity >= 0 and floor in \[0, 1\], got 0.5, None"),
        (lambda: random_mesh_responses(enc, 0, "sheet", n=0, settings=MEISettings(**base)), r"^n must be a positive integer"),
        (lambda: random_mesh_responses(enc, 0, "sheet", n=2.5, settings=MEISettings(**base)), r"^n must be a positive integer"),
        (lambda: grid_search(enc, 0, "sheet", grid={"edge": "10"}, **base), r"^grid entry 'edge' must be a sequence"),
    ]
    for call, match in cases:
        with pytest.raises(MEIError, match=match):
            call()


def test_the_default_weights_and_step_follow_the_mesh_resolution():
    """Issue 16: the weights are stated for the 400-vertex default and scaled to the run's mesh (Laplacian
    and area by (n/400)^2, edge by n/400), and above 400 vertices the offsets' learning rate shrinks as the
    edge length; at 400 vertices the run is the one it was before (the weights and lr exactly as given)."""
    from meshmei.mei.optimize import objective_weights
    from meshmei.mei.scene import SeedScene

    s = MEISettings()
    assert s.reg_ref_vertices == 400 and s.lr_by_edge
    assert objective_weights(s, 400) == {k: w for k, w in s.weights.items() if w > 0}
    assert objective_weights(s, 1600) == {"laplacian": 16 * s.weights["laplacian"], "edge": 4 * s.weights["edge"],
                                          "area": 16 * s.weights["area"]}
    assert objective_weights(MEISettings(reg_ref_vertices=None), 1600) == objective_weights(s, 400)
    assert s.offset_lr(400) == s.lr and s.offset_lr(100) == s.lr  # never larger below the reference
    assert s.offset_lr(1600) == pytest.approx(s.lr / 2, rel=1e-15)
    assert MEISettings(lr_by_edge=False).offset_lr(1600) == MEISettings(reg_ref_vertices=None).offset_lr(1600) == s.lr
    assert MEISettings(albedo=True, albedo_shape_lr=0.1).offset_lr(1600) == pytest.approx(s.lr / 20, rel=1e-15)
    V0, F = initial_mesh("sheet", n_vertices=1600)
    assert SeedScene(V0, s, 0, n_weights=1600).groups[0]["lr"] == s.offset_lr(1600)
    assert SeedScene(V0, s, 0).groups[0]["lr"] == s.offset_lr(V0.shape[0])  # a mesh of your own: its count
    with pytest.raises(MEIError, match="lr_by_edge must be True or False"):
        MEISettings(lr_by_edge="no")


def test_cli_reg_ref_vertices_reaches_the_settings(tmp_path, capsys):
    from meshmei.cli import main

    base = ["mei", "--init", "sheet", "--n-vertices", "40", "--steps", "1", "--seeds", "0", "--image-size", "16",
            "--quiet"]
    for value, expected in (("none", None), ("100", 100)):
        out = tmp_path / value
        assert main(base + ["--out", str(out), "--reg-ref-vertices", value]) == 0
        assert json.loads((out / "summary.json").read_text())["settings"]["reg_ref_vertices"] == expected
    assert json.loads((tmp_path / "none" / "summary.json").read_text())["settings"]["lr_by_edge"] is True
    with pytest.raises(SystemExit) as exit_:
        main(base + ["--out", str(tmp_path / "bad"), "--reg-ref-vertices", "0"])
    assert exit_.value.code == 2 and "positive integer or 'none'" in capsys.readouterr().err


@pytest.mark.slow
def test_a_simple_cell_from_the_sheet_climbs_alike_at_400_and_1600_vertices():
    """Issue 16's resolution-aware defaults (about 50 s): with the weights scaled to the mesh and the step
    shrunk with its edge, 1,600 vertices reach the 400-vertex response (measured 0.935 against 0.940 at 32
    px, 100 steps); with the weights and lr as given they fall short (0.840)."""
    cell = GaborSimpleCell()
    kw = dict(image_size=32, steps=100, seeds=(0,))
    coarse = optimize_mei(cell, 0, "sheet", n_vertices=400, **kw)
    fine = optimize_mei(cell, 0, "sheet", n_vertices=1600, **kw)
    as_given = optimize_mei(cell, 0, "sheet", n_vertices=1600, reg_ref_vertices=None, **kw)
    assert abs(fine.fraction_of_bound - coarse.fraction_of_bound) < 0.03
    assert as_given.fraction_of_bound < coarse.fraction_of_bound - 0.05
    for r in (coarse, fine):
        h = r.health()
        assert h["self_intersections"] == 0 and h["flipped_faces"] == 0


@pytest.mark.parametrize("option, value, message", [
    ("--steps", str(10**400), "steps must be at most 1e+12"),
    ("--reg-ref-vertices", str(10**400), "reg_ref_vertices must be a vertex count of at most 5,000,000"),
    ("--reg-ref-vertices", str(10**20), "reg_ref_vertices must be a vertex count of at most 5,000,000"),  # a KeyError deep in the run
])
def test_cli_refuses_counts_too_large_in_one_line(tmp_path, capsys, option, value, message):
    """Found by fuzzing: these ended in an OverflowError or a KeyError traceback."""
    from meshmei.cli import main

    out = tmp_path / "run"
    assert main(["mei", "--out", str(out), "--steps", "2", "--quiet", option, value]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err and not out.exists()


def test_load_run_refuses_mixed_files_and_summary_fields_of_the_wrong_kind(tmp_path):
    # found by fuzzing: another run's state.pt or summary.json copied in loaded as this run (its mesh under this
    # neuron), and an activation of NaN or text, a neuron of -1 or 3.7, a history of text were read as they were
    a = save_run(optimize_mei(GaborSimpleCell(), 0, "sheet", **TINY), tmp_path / "a", figures=False)
    b = save_run(optimize_mei(GaborSimpleCell(), 0, "sheet", **{**TINY, "n_vertices": 120}), tmp_path / "b",
                 figures=False)
    c = save_run(optimize_mei(GaborSimpleCell(orientation=1.0), 0, "sheet", **TINY), tmp_path / "c", figures=False)
    kept = {name: (a / name).read_bytes() for name in ("summary.json", "state.pt", "mesh.obj")}

    def restore():
        for name, data in kept.items():
            (a / name).write_bytes(data)

    (a / "state.pt").write_bytes((c / "state.pt").read_bytes())  # a run of the same size
    with pytest.raises(MEIError, match="state.pt is not the file"):
        load_run(a)
    restore()
    (a / "mesh.obj").write_bytes((c / "mesh.obj").read_bytes())
    with pytest.raises(MEIError, match="mesh.obj is not the file"):
        load_run(a)
    restore()
    (a / "summary.json").write_bytes((b / "summary.json").read_bytes())  # another size: caught by the counts
    with pytest.raises(MEIError, match="summary.json's n_vertices is .* not of one run"):
        load_run(a)
    restore()
    summary = json.loads(kept["summary.json"])
    for key, value in (("activation", math.nan), ("activation", "0.5"), ("activation", True), ("neuron", -1),
                       ("neuron", 3.7), ("seed", 0.5), ("history", "abc"), ("history", [math.nan]),
                       ("wall_time_s", -5), ("init", 5), ("activation", 10 ** 400)):  # an OverflowError
        (a / "summary.json").write_text(json.dumps({**summary, key: value}))
        with pytest.raises(MEIError, match=f"summary.json is damaged: {key} must be"):
            load_run(a)
    (a / "summary.json").write_bytes(b"\xff\xfe{")
    with pytest.raises(MEIError, match="summary.json is unreadable"):
        load_run(a)
    restore()
    assert torch.equal(load_run(a).V, torch.load(a / "state.pt", weights_only=True)["V"])
    # a run saved with seed -3 (taken until SEED_RANGE) was the run of 2**32 - 3: it loads as that seed
    twin = save_run(optimize_mei(GaborSimpleCell(), 0, "sheet", **{**TINY, "seeds": (2 ** 32 - 3,)}), tmp_path / "n",
                    figures=False)
    summary = json.loads((twin / "summary.json").read_text())
    act = summary["seed_activations"].pop(str(2 ** 32 - 3))
    summary.update(seed=-3, seed_activations={"-3": act}, settings={**summary["settings"], "seeds": [-3]})
    (twin / "summary.json").write_text(json.dumps(summary))
    old = load_run(twin)
    assert (old.seed, old.seed_activations, old.settings.seeds) == (2 ** 32 - 3, {2 ** 32 - 3: act}, (2 ** 32 - 3,))


def test_load_run_refuses_a_light_or_albedo_of_another_shape(tmp_path):
    # found by fuzzing: both loaded and failed only when the run was rendered, with a message about rotation
    run = save_run(optimize_mei(GaborSimpleCell(), 0, "sphere", **{**TINY, "albedo": True, "optimize_light": True}),
                   tmp_path / "run", figures=False)
    kept = (run / "state.pt").read_bytes()
    for key, value, says in (("light", torch.ones(5), r"light must have shape \(3,\), got \(5,\)"),
                             ("albedo", torch.ones(1), r"albedo must be one value per vertex")):
        state = torch.load(run / "state.pt", weights_only=True)
        state[key] = value
        torch.save(state, run / "state.pt")
        with pytest.raises(MEIError, match=says):
            load_run(run)
        (run / "state.pt").write_bytes(kept)
    again = load_run(run)
    assert torch.equal(again.albedo, torch.load(run / "state.pt", weights_only=True)["albedo"])
