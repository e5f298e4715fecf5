"""Populations: batched runs of many neurons into one folder, resumable, idempotent, on a local Ray cluster."""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from meshmei.encoders import GaborComplexCell, GaborSimpleCell, encoder_from_model, make_encoder
from meshmei.errors import MEIError
from meshmei.mei import MEISettings, load_run, optimize_mei, pixel_mei
from meshmei.population import parse_neurons, read_table, run_population
from meshmei.population.store import table_row

SMALL = dict(steps=6, seeds=(0, 1), image_size=20, n_vertices=50, dtype="float64")
TINY = dict(steps=2, seeds=(0,), image_size=20, n_vertices=40, dtype="float64")


def cells():
    """Four Gabor cells as one model's neurons."""
    units = [GaborSimpleCell(), GaborComplexCell(orientation=0.7), GaborSimpleCell(orientation=1.2, phase=1.0),
             GaborComplexCell(frequency=3.0)]

    def model(x):
        return torch.cat([u(x, preprocessed=True) for u in units], 1)

    return encoder_from_model(model, mean=0.5, std=0.2, image_size=20)


def test_neuron_lists_parse_ranges_and_keep_order():
    assert parse_neurons("0-3") == [0, 1, 2, 3]
    assert parse_neurons("7,2-4,3,9") == [7, 2, 3, 4, 9]
    for bad in ("", "a-b", "5-2", "-3", "+1", "1_0", "\u0663"):  # int() reads the last three (as 1, 10 and 3)
        with pytest.raises(MEIError):
            parse_neurons(bad)
    assert parse_neurons("0-3", 4) == [0, 1, 2, 3]
    with pytest.raises(MEIError, match="out of range for 4 neurons: got 999999999"):
        parse_neurons("0-999999999", 4)  # refused before the range is built (it would take GBs)
    # found by fuzzing: without a count, 0-99999999999 ran out of memory and 5,000 digits were Python's error
    with pytest.raises(MEIError, match="names more than 1,000,000 neurons"):
        parse_neurons("0-99999999999")
    with pytest.raises(MEIError, match="neurons must be ranges and lists"):
        parse_neurons("1" * 5000)
    for count in ("10", 0, True, 2.5):
        with pytest.raises(MEIError, match="n_neurons must be a positive integer"):
            parse_neurons("0-3", count)
    assert parse_neurons("0-3", np.int64(4)) == [0, 1, 2, 3]


@pytest.mark.parametrize("neurons, match", [(2, "neurons must be a sequence of neuron indices"),
                                             (None, "neurons must be a sequence of neuron indices"),
                                             ("0-3", "parse_neurons reads"), ([], "neurons is empty")])
def test_neurons_that_are_not_a_list_of_indices_are_refused_before_the_folder(tmp_path, neurons, match):
    # 2 and None were a TypeError from a list comprehension; [] wrote a folder with an empty table
    with pytest.raises(MEIError, match=match):
        run_population(cells(), neurons, tmp_path / "pop", settings=MEISettings(**SMALL), progress=False)
    assert not (tmp_path / "pop").exists()


def test_repeated_seeds_are_refused_not_silently_dropped():
    # a repeated seed once left every neuron unfinished: the run wrote an empty table and reported success
    with pytest.raises(MEIError, match=r"seeds must be distinct; \[0\] repeated"):
        MEISettings(seeds=(0, 0, 1))


def test_a_planned_neuron_without_a_result_is_an_error_not_a_short_table(tmp_path, monkeypatch):
    import meshmei.population.run as pr

    real = pr.neuron_results

    def losing(*args, **kwargs):  # a backend that drops neuron 1 (as repeated seeds once dropped every neuron)
        return ((n, res, seconds) for n, res, seconds in real(*args, **kwargs) if n != 1)

    monkeypatch.setattr(pr, "neuron_results", losing)
    with pytest.raises(MEIError, match=r"neurons \[1\] were asked for but produced no result"):
        run_population(cells(), [0, 1], tmp_path / "pop", settings=MEISettings(**TINY), pixel_steps=0,
                       progress=False)
    assert not (tmp_path / "pop" / "population.png").exists()


def test_the_ratio_is_empty_unless_the_pixel_mei_excites():
    row = {"neuron": 0, "activation": 2.0}
    assert table_row({**row, "pixel_mei_activation": 4.0})["ratio"] == 0.5
    for pix in (None, 0.0, -1.0, -4.0):  # a ratio to a response <= 0 says nothing (and flips sign)
        assert table_row({**row, "pixel_mei_activation": pix})["ratio"] is None


def test_the_population_figure_leaves_the_callers_backend_alone_and_draws_non_finite_ratios(tmp_path):
    import matplotlib

    from meshmei.population.figure import population_figure

    before = matplotlib.get_backend()
    rows = [{"neuron": 0, "mei_response": 1.0, "pixel_mei_response": 2.0, "ratio": 0.5},
            {"neuron": 1, "mei_response": math.inf, "pixel_mei_response": 2.0, "ratio": math.inf},
            {"neuron": 2, "mei_response": math.nan, "pixel_mei_response": 2.0, "ratio": math.nan}]
    matplotlib.use("svg")  # a session on another backend than Agg: population_figure switched it to Agg
    try:
        path = population_figure(tmp_path, rows)
        assert matplotlib.get_backend() == "svg" and path.stat().st_size > 0
    finally:
        matplotlib.use(before)


def test_a_refused_call_writes_nothing_so_the_corrected_one_runs(tmp_path):
    enc, out = cells(), tmp_path / "pop"
    for kwargs in (dict(n_vertices=3), dict(batch_size=0), dict(cluster="slurm")):
        settings = {**SMALL, **{k: v for k, v in kwargs.items() if k == "n_vertices"}}
        extra = {k: v for k, v in kwargs.items() if k != "n_vertices"}
        with pytest.raises(MEIError):
            run_population(enc, [0], out, settings=MEISettings(**settings), pixel_steps=0, progress=False, **extra)
        assert not out.exists()
    # what the pixel MEI would refuse after every 3D-MEI was done, refused first (found by fuzzing: 1e20 pixel
    # steps failed after the 3D work as "steps must be at most 1e+12"; image_size 1 ran the 3D-MEIs at 1 x 1)
    for model, settings, pixel_steps, says in (
            (enc, SMALL, 10**20, r"^pixel_steps must be at most 1e\+12, got 10+$"),
            (make_encoder("demo"), {**SMALL, "image_size": 1}, 2, "the pixel MEI needs images of at least 2 x 2")):
        with pytest.raises(MEIError, match=says):
            run_population(model, [0], out, settings=MEISettings(**settings), pixel_steps=pixel_steps, progress=False)
        assert not out.exists()
    # an image size the cell cannot take fails at the encoder's probe, before the folder is written (it failed
    # at the first step, and the folder then refused the corrected call)
    with pytest.raises(ValueError, match="constant on this pixel grid"):
        run_population(make_encoder("gabor-simple"), [0], out, settings=MEISettings(**{**SMALL, "image_size": 2}),
                       pixel_steps=0, progress=False)
    assert not out.exists()
    assert [r["neuron"] for r in run_population(enc, [0], out, settings=MEISettings(**SMALL), pixel_steps=0,
                                                progress=False)] == [0]


def test_damaged_folders_are_named_in_one_clear_error(tmp_path):
    enc, out = cells(), tmp_path / "pop"
    run_population(enc, [0, 1], out, settings=MEISettings(**SMALL), pixel_steps=0, progress=False)
    folder = out / "neurons" / "neuron_00001"
    summary = (folder / "summary.json").read_text()
    damage = [(folder / "summary.json", "[]"), (folder / "summary.json", json.dumps({**json.loads(summary), "neuron": 3})),
              (folder / "summary.json", json.dumps({k: v for k, v in json.loads(summary).items() if k != "neuron"})),
              *((folder / "summary.json", json.dumps({**json.loads(summary), **bad})) for bad in (
                  {"complete": False}, {"neuron": True}, {"activation": "1.0"}, {"quality": []},
                  {"pixel_mei_activation": "1.0"},
                  # found by fuzzing: the CLI's min() of the qualities failed on "x"; NaN made the table's means nan
                  {"quality": {**json.loads(summary)["quality"], "min_quality": "x"}},
                  {"quality": {**json.loads(summary)["quality"], "watertight": 1}},
                  {"activation": float("nan")}, {"pixel_mei_activation": float("inf")})),
              (folder / "state.pt", None), (folder / "mesh.obj", None), (folder / "state.pt", ""),
              (folder / "mesh.obj", ""),  # an empty file counted as a finished neuron
              (folder / "state.pt", "garbage, not torch's zip archive")]  # so did other bytes
    for path, text in damage:
        kept = path.read_bytes()
        path.unlink() if text is None else path.write_text(text)
        with pytest.raises(MEIError, match="neuron_00001 is not a complete run folder; remove it and resume"):
            run_population(enc, [0, 1], out, settings=MEISettings(**SMALL), pixel_steps=0, progress=False)
        path.write_bytes(kept)
    both = out / "neurons" / "neuron_00000" / "mesh.obj", folder / "mesh.obj"
    kept = [p.read_bytes() for p in both]
    for p in both:  # named together: one per rerun before
        p.unlink()
    with pytest.raises(MEIError, match=r"2 folders in .*neurons are not complete run folders \(neuron_00000, "
                                       r"neuron_00001\); remove them and resume"):
        run_population(enc, [0, 1], out, settings=MEISettings(**SMALL), pixel_steps=0, progress=False)
    for p, data in zip(both, kept):
        p.write_bytes(data)
    meta = out / "population.json"
    meta.write_text("[1]")
    with pytest.raises(MEIError, match="is not a population description"):
        run_population(enc, [0, 1], out, settings=MEISettings(**SMALL), pixel_steps=0, progress=False)
    # cut short (by a full disk, say): the finished neurons, all made with these settings, are resumed
    meta.write_text('{"format": ')
    with pytest.warns(UserWarning, match="population.json was unreadable .* rewritten with this run's settings"):
        rows = run_population(enc, [0, 1], out, settings=MEISettings(**SMALL), pixel_steps=0, progress=False)
    assert [r["neuron"] for r in rows] == [0, 1] and json.loads(meta.read_text())["config"]
    described = json.loads(meta.read_text())
    meta.write_text('{"format": ')  # other settings than the neurons': refused as before
    with pytest.raises(MEIError, match="population.json is unreadable .*; choose another --out"):
        run_population(enc, [0, 1], out, settings=MEISettings(**{**SMALL, "steps": SMALL["steps"] + 1}),
                       pixel_steps=0, progress=False)
    meta.unlink()  # deleted: as when unreadable, and refused for other settings
    with pytest.raises(MEIError, match="exists and is not a population folder; choose another --out"):
        run_population(enc, [0, 1], out, settings=MEISettings(**{**SMALL, "steps": SMALL["steps"] + 1}),
                       pixel_steps=0, progress=False)
    with pytest.warns(UserWarning, match="population.json was missing; written again with this run's settings"):
        again = run_population(enc, [0, 1], out, settings=MEISettings(**SMALL), pixel_steps=0, progress=False)
    assert again == rows and json.loads(meta.read_text()) == described


def test_a_neuron_another_job_finished_meanwhile_is_kept_and_the_run_goes_on(tmp_path, monkeypatch):
    import shutil

    import meshmei.population.run as pr

    enc, s = cells(), MEISettings(**SMALL)
    run_population(enc, [0], tmp_path / "other", settings=s, pixel_steps=0, progress=False)
    out = tmp_path / "pop"
    run_population(enc, [2], out, settings=s, pixel_steps=0, progress=False)
    real = pr.neuron_results

    def racing(*args, **kwargs):  # another array task saves neuron 0 just before this one does
        for n, res, seconds in real(*args, **kwargs):
            if n == 0:
                shutil.copytree(tmp_path / "other" / "neurons" / "neuron_00000", out / "neurons" / "neuron_00000")
            yield n, res, seconds

    monkeypatch.setattr(pr, "neuron_results", racing)
    rows = run_population(enc, [0, 1], out, settings=s, pixel_steps=0, progress=False)
    assert [r["neuron"] for r in rows] == [0, 1, 2]
    other = json.loads((tmp_path / "other" / "neurons" / "neuron_00000" / "summary.json").read_text())
    assert json.loads((out / "neurons" / "neuron_00000" / "summary.json").read_text()) == other


def test_a_neuron_another_job_lands_while_this_one_writes_it_is_kept(tmp_path, monkeypatch):
    """Both jobs finish the neuron at once: the other job's folder lands while this one writes its own, so this
    one's rename into place fails (it must not replace the other's); a landed folder of other settings is an
    error."""
    import shutil

    import meshmei.mei.runs as runs

    enc, s = cells(), MEISettings(**TINY)
    run_population(enc, [0], tmp_path / "other", settings=s, pixel_steps=0, progress=False)
    other, out = tmp_path / "other" / "neurons" / "neuron_00000", tmp_path / "pop"
    real = runs.save_mesh

    def landing(path, *args, **kwargs):  # the other job's rename lands during this job's first write
        target = out / "neurons" / "neuron_00000"
        if not target.exists():
            shutil.copytree(other, target)
        return real(path, *args, **kwargs)

    monkeypatch.setattr(runs, "save_mesh", landing)
    rows = run_population(enc, [0, 1], out, settings=s, pixel_steps=0, progress=False)
    assert [r["neuron"] for r in rows] == [0, 1]
    assert (out / "neurons" / "neuron_00000" / "summary.json").read_text() == (other / "summary.json").read_text()
    assert sorted(p.name for p in (out / "neurons").iterdir()) == ["neuron_00000", "neuron_00001"]  # no leftovers

    data = json.loads((other / "summary.json").read_text())
    (other / "summary.json").write_text(json.dumps({**data, "config_hash": "0" * 16}))
    out = tmp_path / "pop2"  # where a folder of other settings lands the same way
    with pytest.raises(MEIError, match="neuron_00000 was made with other settings"):
        run_population(enc, [0], out, settings=s, pixel_steps=0, progress=False)


def test_a_changed_model_is_refused_and_the_same_model_by_another_path_resumes(tmp_path, monkeypatch):
    from meshmei.cli import main

    body = (
        "import torch\n"
        "def build():\n"
        "    torch.manual_seed(0)\n"
        "    lin = torch.nn.Linear(16 * 16, 3)\n"
        "    with torch.no_grad():\n"
        "        lin.weight *= SCALE\n"
        "    return {'model': torch.nn.Sequential(torch.nn.Flatten(), lin), 'mean': 0.5, 'std': 0.2, 'image_size': 16}\n")
    (tmp_path / "m.py").write_text("SCALE = 1.0\n" + body)
    monkeypatch.chdir(tmp_path)
    common = ["--steps", "2", "--seeds", "0", "--n-vertices", "40", "--pixel-steps", "0", "--quiet", "--out", "pop"]
    assert main(["population", "--model", "m.py:build", "--neurons", "0", *common]) == 0
    assert main(["population", "--model", "./m.py:build", "--neurons", "1", *common]) == 0  # the same model
    (tmp_path / "m.py").write_text("SCALE = -5.0\n" + body)
    assert main(["population", "--model", "m.py:build", "--neurons", "2", *common]) == 2  # another model
    assert [r["neuron"] for r in read_table(tmp_path / "pop")] == [0, 1]


def test_a_population_writes_one_run_per_neuron_and_a_table(tmp_path):
    enc = cells()
    rows = run_population(enc, [2, 0], tmp_path / "pop", settings=MEISettings(**SMALL), batch_size=3,
                          pixel_steps=5, progress=False)
    assert [r["neuron"] for r in rows] == [0, 2]
    assert read_table(tmp_path / "pop") == rows and (tmp_path / "pop" / "population.png").is_file()
    s = MEISettings(**SMALL)
    for r in rows:
        n = r["neuron"]
        run = load_run(tmp_path / "pop" / "neurons" / f"neuron_{n:05d}")
        solo = optimize_mei(enc, n, "sheet", s)
        assert run.neuron == n and run.seed == solo.seed == r["seed"]
        assert r["mei_response"] == pytest.approx(solo.activation, rel=1e-9)
        assert r["pixel_mei_response"] == pytest.approx(
            pixel_mei(enc, n, image_size=s.image_size, steps=5, seeds=s.seeds).activation, rel=1e-9)
        assert r["ratio"] == pytest.approx(r["mei_response"] / r["pixel_mei_response"])
        assert r["self_intersections"] == run.health()["self_intersections"]
        assert r["seconds"] > 0


def test_a_non_square_model_gets_its_pixel_mei_in_its_own_image_space(tmp_path):
    # the pixel MEI was asked for a square of the render size: "preprocessed images must be 20 x 30, the
    # model's size; got (30, 30)" after the first neuron's 3D-MEI, and nothing written
    def model(x):
        return torch.stack([x.mean((1, 2, 3)), x[..., :10].std((1, 2, 3))], 1)

    enc = encoder_from_model(model, mean=0.5, std=0.2, image_size=(20, 30))
    rows = run_population(enc, [0, 1], tmp_path / "pop", settings=MEISettings(**TINY), pixel_steps=3, progress=False)
    for r in rows:
        alone = pixel_mei(enc, r["neuron"], steps=3, seeds=TINY["seeds"])  # the model's own size by default
        assert alone.image.shape[-2:] == (20, 30)
        assert r["pixel_mei_response"] == pytest.approx(alone.activation, rel=1e-9)


def test_a_damaged_table_is_one_error_naming_its_line(tmp_path):
    # found by fuzzing: a short row, a NUL byte or extra cells were TypeErrors; nan, inf, other scripts' digits,
    # '1_0' and a BOM were read as they were; a missing file was Python's FileNotFoundError
    out = tmp_path / "pop"
    rows = run_population(cells(), [0, 1], out, settings=MEISettings(**TINY), pixel_steps=0, progress=False)
    table = out / "population.csv"
    text = table.read_text()
    assert read_table(out) == rows
    header, first, second = text.splitlines()[:3]
    cells0 = first.split(",")
    for bad, says in ((text.replace(first, ",".join(cells0[:5])), "line 2: 5 cells, not 12"),
                      (text.replace(first, first + ",9"), "line 2: 13 cells, not 12"),
                      (text.replace(first, ",".join(["nan", *cells0[1:]])), "line 2: neuron holds 'nan'"),
                      (text.replace(first, ",".join([cells0[0], "inf", *cells0[2:]])),
                       "line 2: mei_response holds 'inf'"),
                      (text.replace(first, ",".join(["\u0663", *cells0[1:]])), "neuron holds"),
                      (text.replace(first, ",".join([cells0[0], "1_0", *cells0[2:]])), "mei_response holds '1_0'"),
                      (text.replace(header, "a,b"), "is not a population table")):
        table.write_text(bad, encoding="utf-8")
        with pytest.raises(MEIError, match=says):
            read_table(out)
    table.write_text("\ufeff" + text, encoding="utf-8")  # a spreadsheet's save: read as it was
    assert read_table(out) == rows
    table.write_bytes(b"\xff\xfe" + text.encode())
    with pytest.raises(MEIError, match="is unreadable"):
        read_table(out)
    table.unlink()
    with pytest.raises(MEIError, match="no population table at"):
        read_table(out)


def test_a_rerun_skips_finished_neurons_and_other_settings_are_refused(tmp_path, monkeypatch):
    import meshmei.population.run as population_run

    asked, real = [], population_run.neuron_results
    monkeypatch.setattr(population_run, "neuron_results",
                        lambda enc, todo, *a, **k: asked.append(list(todo)) or real(enc, todo, *a, **k))
    enc, out = cells(), tmp_path / "pop"
    run_population(enc, [0, 1], out, settings=MEISettings(**SMALL), pixel_steps=0, progress=False)
    first = (out / "neurons" / "neuron_00000" / "summary.json").stat().st_mtime_ns
    rows = run_population(enc, [0, 1, 3], out, settings=MEISettings(**SMALL), pixel_steps=0, progress=False)
    assert [r["neuron"] for r in rows] == [0, 1, 3]
    # not redone: the rerun optimises neuron 3 alone (the file's time alone could not tell: a recomputed
    # neuron's folder is not written again; review)
    assert asked == [[0, 1], [3]]
    assert (out / "neurons" / "neuron_00000" / "summary.json").stat().st_mtime_ns == first
    assert all(r["pixel_mei_response"] is None and r["ratio"] is None for r in rows)
    with pytest.raises(MEIError, match="other settings.*differing: settings"):
        run_population(enc, [2], out, settings=MEISettings(**{**SMALL, "steps": 7}), pixel_steps=0, progress=False)
    with pytest.raises(MEIError, match="other settings.*differing: pixel_mei"):
        run_population(enc, [2], out, settings=MEISettings(**SMALL), pixel_steps=4, progress=False)
    # a neuron folder from another configuration is never mixed in
    summary = out / "neurons" / "neuron_00001" / "summary.json"
    data = json.loads(summary.read_text())
    summary.write_text(json.dumps({**data, "config_hash": "0" * 16}))
    with pytest.raises(MEIError, match="neuron_00001 was made with other settings"):
        run_population(enc, [2], out, settings=MEISettings(**SMALL), pixel_steps=0, progress=False)
    with pytest.raises(MEIError, match="not a population folder"):
        (tmp_path / "other").mkdir()
        (tmp_path / "other" / "notes.txt").write_text("mine")
        run_population(enc, [0], tmp_path / "other", settings=MEISettings(**SMALL), progress=False)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL])
def test_an_interrupted_population_resumes_with_nothing_lost_or_repeated(tmp_path, sig):
    """The CLI on the demo model is stopped once a neuron is finished; the same command then completes the
    population: every neuron once, and the ones finished before the stop are untouched."""
    out = tmp_path / "pop"
    cmd = [sys.executable, "-m", "meshmei.cli", "population", "--neurons", "0-7", "--steps", "40", "--seeds", "0",
           "--batch-size", "1", "--pixel-steps", "0", "--image-size", "32", "--n-vertices", "80", "--out", str(out),
           "--quiet"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while time.time() < deadline and not list((out / "neurons").glob("neuron_*")) if (out / "neurons").exists() \
            else time.time() < deadline:
        if proc.poll() is not None:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the run ended before it could be interrupted; make it longer"
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    kept = {p.name: (p / "summary.json").stat().st_mtime_ns for p in (out / "neurons").glob("neuron_*")}
    assert 1 <= len(kept) < 8
    if sig == signal.SIGTERM:
        assert proc.returncode == 130 and "finished neurons are kept" in err
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    rows = read_table(out)
    assert [r["neuron"] for r in rows] == list(range(8))
    assert sorted(p.name for p in (out / "neurons").glob("neuron_*")) == [f"neuron_{n:05d}" for n in range(8)]
    for name, mtime in kept.items():
        assert (out / "neurons" / name / "summary.json").stat().st_mtime_ns == mtime


def test_the_cli_passes_the_objective_options_into_every_run(tmp_path):
    """meshmei population shares meshmei mei's objective options: a robust, unguarded population records
    them in each run's settings (and so in the configuration hash)."""
    from meshmei.cli import main

    out = tmp_path / "pop"
    assert main(["population", "--encoder", "gabor-simple", "--neurons", "0", "--steps", "2", "--seeds", "0",
                 "--image-size", "16", "--n-vertices", "40", "--pixel-steps", "0", "--robust-pose", "10",
                 "--robust-light", "5", "--no-valid-steps", "--out", str(out), "--quiet"]) == 0
    s = json.loads((out / "neurons" / "neuron_00000" / "summary.json").read_text())["settings"]
    assert (s["robust_pose"], s["robust_light"], s["valid_steps"], s["albedo"]) == (10.0, 5.0, False, False)


def test_the_cli_gives_meshmeis_warnings_one_line_each(tmp_path, capsys):
    # the rewritten description's warning came as Python's two lines: "...store.py:75: UserWarning: ..." and
    # the source line it was raised at
    from meshmei.cli import main

    out = tmp_path / "pop"
    args = ["population", "--encoder", "gabor-simple", "--neurons", "0", "--steps", "2", "--seeds", "0",
            "--image-size", "16", "--n-vertices", "40", "--pixel-steps", "0", "--out", str(out), "--quiet"]
    assert main(args) == 0
    (out / "population.json").write_text('{"format": ')
    capsys.readouterr()
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        before = warnings.showwarning
        assert main(args) == 0
        assert warnings.showwarning is before  # put back
    err = capsys.readouterr().err.splitlines()
    assert err == [f"meshmei population: warning: {out / 'population.json'} was unreadable (Expecting value: line 1 "
                   "column 12 (char 11)); rewritten with this run's settings, which every finished neuron there "
                   "was made with"]


def test_tune_on_a_population_sweeps_each_finished_neuron_on_its_own_neuron(tmp_path, capsys):
    # the population's folder was refused: "not a complete MEI run: missing ['summary.json', ...]"
    from meshmei.cli import main
    from meshmei.tuning.files import load_sweep

    out = tmp_path / "pop"
    assert main(["population", "--encoder", "demo", "--neurons", "1,3", "--steps", "2", "--seeds", "0",
                 "--image-size", "16", "--n-vertices", "40", "--pixel-steps", "0", "--out", str(out), "--quiet"]) == 0
    capsys.readouterr()
    assert main(["tune", "pose", "--mei", str(out), "--elevation", "0:0:1", "--azimuth=-10:10:3"]) == 0
    for n in (1, 3):
        run = out / "neurons" / f"neuron_{n:05d}"
        sweep = load_sweep(run / "tuning_pose")
        assert tuple(sweep.neurons) == (n,)
        assert sweep.of(n)[0, 1] == pytest.approx(load_run(run).activation, rel=1e-4)  # (0, 0): the run's view
    assert capsys.readouterr().out.count("pose sweep, neuron") == 2
    assert main(["tune", "light", "--mei", str(out), "--elevation", "0:90:2", "--azimuth", "0:90:2", "--out",
                 str(tmp_path / "light")]) == 0
    assert sorted(p.name for p in (tmp_path / "light").iterdir()) == ["neuron_00001", "neuron_00003"]
    (out / "neurons" / "neuron_00003" / "state.pt").unlink()  # damaged: named before any sweep
    assert main(["tune", "pose", "--mei", str(out), "--out", str(tmp_path / "again")]) == 2
    err = capsys.readouterr().err
    assert "1 of the neuron folders in" in err and "(neuron_00003)" in err and not (tmp_path / "again").exists()
    empty = tmp_path / "empty"
    assert main(["population", "--encoder", "demo", "--neurons", "1", "--steps", "2", "--seeds", "0",
                 "--image-size", "16", "--n-vertices", "40", "--pixel-steps", "0", "--out", str(empty), "--quiet"]) == 0
    for d in (empty / "neurons").iterdir():
        shutil.rmtree(d)
    assert main(["tune", "pose", "--mei", str(empty)]) == 2
    assert "a population folder without a finished neuron yet" in capsys.readouterr().err


@pytest.mark.parametrize("device", ["tpu", "cuda:x", "cpu:1", "meta", 3.5])
def test_devices_that_are_not_cpu_or_cuda_are_refused_clearly(tmp_path, device):
    with pytest.raises(MEIError, match="device must be cpu, cuda or cuda:N"):
        run_population(cells(), [0], tmp_path / "p", device=device, settings=MEISettings(**SMALL), progress=False)
    assert not (tmp_path / "p").exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA device")
def test_cuda_on_a_machine_without_it_is_refused_clearly(tmp_path):
    with pytest.raises(MEIError, match="'cuda' asked for, but this machine has no CUDA device"):
        run_population(cells(), [0], tmp_path / "p", device="cuda", settings=MEISettings(**SMALL), progress=False)
    assert not (tmp_path / "p").exists()


def test_a_start_mesh_of_your_own_is_told_apart_by_its_values(tmp_path):
    """A population folder took a dented sphere for the sphere it was started with (the start was recorded by
    its printed form, which abbreviates large tensors), and refused the same mesh given as arrays."""
    from meshmei.shapes import initial_mesh

    V, F = initial_mesh("sphere", n_vertices=400, dtype=torch.float64)
    dented = V.clone()
    dented[100:300] *= 0.7
    kw = dict(settings=MEISettings(**{**SMALL, "seeds": (0,), "steps": 2}), pixel_steps=0, progress=False)
    run_population(cells(), [0], tmp_path, init=(V, F), **kw)
    with pytest.raises(MEIError, match="init"):
        run_population(cells(), [1], tmp_path, init=(dented, F), **kw)
    rows = run_population(cells(), [1], tmp_path, init=[V.numpy(), F.numpy()], **kw)  # the same mesh, as arrays
    assert [r["neuron"] for r in rows] == [0, 1]


# ---------------------------------------------------------------------------------------------- Ray
try:
    import ray
except ImportError:  # without the 'cluster' extra the Ray tests skip; a module-level importorskip here skipped
    ray = None  # every test of this file (seen on a machine without Ray, 2026-11-29)


def one_ray_at_a_time(test):
    """The Ray tests run one after another in one test process, so that no two local Ray instances start at
    once when the suite runs in parallel (pytest-xdist, --dist loadgroup); without Ray they skip."""
    test = pytest.mark.xdist_group("ray")(test)
    return pytest.mark.skipif(ray is None, reason="Ray is not installed (the 'cluster' extra)")(test)


@one_ray_at_a_time
def test_a_ray_run_matches_the_local_run(tmp_path):
    enc, s = cells(), MEISettings(**SMALL)
    local = run_population(enc, [0, 1, 3], tmp_path / "local", settings=s, batch_size=2, pixel_steps=3,
                           progress=False)
    remote = run_population(enc, [0, 1, 3], tmp_path / "ray", settings=s, batch_size=2, pixel_steps=3,
                            cluster="ray", progress=False)
    assert not ray.is_initialized()  # the local Ray instance it started is stopped
    assert [r["neuron"] for r in remote] == [0, 1, 3]
    for a, b in zip(local, remote):
        for k in ("mei_response", "pixel_mei_response", "seed", "self_intersections", "min_quality"):
            assert a[k] == pytest.approx(b[k], rel=1e-9), k


@one_ray_at_a_time
def test_a_ray_task_whose_worker_dies_is_retried_with_nothing_lost_or_repeated(tmp_path):
    """The model kills its worker process the first time it runs there; Ray retries the task."""
    marker, driver = tmp_path / "killed-once", os.getpid()
    unit = GaborSimpleCell()

    def fragile(x):
        if os.getpid() != driver and not os.path.exists(marker):
            Path(marker).write_text(str(os.getpid()))
            os._exit(1)  # the worker dies mid-task
        return torch.cat([unit(x, preprocessed=True)] * 3, 1)

    enc = encoder_from_model(fragile, mean=0.5, std=0.2, image_size=20)
    rows = run_population(enc, [0, 1, 2], tmp_path / "pop", settings=MEISettings(**SMALL), batch_size=2,
                          pixel_steps=0, cluster="ray", progress=False)
    assert marker.is_file()  # a worker did die
    assert [r["neuron"] for r in rows] == [0, 1, 2]
    assert sorted(p.name for p in (tmp_path / "pop" / "neurons").iterdir()) == [f"neuron_{n:05d}" for n in range(3)]


@one_ray_at_a_time
def test_a_ray_task_that_fails_keeps_the_neurons_it_finished(tmp_path):
    """One task for neurons 0-3; neuron 3 fails after 0, 1 and 2 are done. Locally those three are kept; on
    Ray the task returned all or nothing, and the run ended with no folder at all."""

    class BreaksOnNeuron3(GaborSimpleCell):  # defined here, so that Ray ships it by value
        """Four cells; asked for neuron 3 alone (its pixel MEI, after the group's 3D-MEIs), it raises."""

        def __init__(self):
            super().__init__(orientation=[0.0, 0.5, 1.0, 1.5])

        def respond(self, z, idx):
            if idx.tolist() == [3]:
                raise RuntimeError("the model broke on neuron 3")
            return super().respond(z, idx)

    kw = dict(settings=MEISettings(**{**SMALL, "seeds": (0,)}), batch_size=4, pixel_steps=2, progress=False)
    for cluster in (None, "ray"):
        out = tmp_path / str(cluster)
        with pytest.raises(Exception, match="the model broke on neuron 3"):
            run_population(BreaksOnNeuron3(), [0, 1, 2, 3], out, cluster=cluster, **kw)
        assert sorted(p.name for p in (out / "neurons").iterdir()) == [f"neuron_{n:05d}" for n in range(3)], cluster
        assert [r["neuron"] for r in read_table(out)] == [0, 1, 2]
    assert not ray.is_initialized()


@one_ray_at_a_time
def test_an_encoder_that_cannot_reach_the_workers_is_refused_before_the_folder(tmp_path):
    """A model holding a lock cannot be pickled and has no file to be rebuilt from: it failed once Ray had
    started and the folder was written, with a message about load_run."""
    import threading

    unit, lock = GaborSimpleCell(orientation=[0.0, 0.5]), threading.Lock()

    def model(x):
        with lock:
            return unit(x, preprocessed=True)

    enc = encoder_from_model(model, mean=0.5, std=0.2, image_size=16)
    with pytest.raises(MEIError, match="cannot reach Ray's workers: it cannot be pickled"):
        run_population(enc, [0, 1], tmp_path / "pop", settings=MEISettings(**SMALL), pixel_steps=0, cluster="ray",
                       progress=False)
    assert not (tmp_path / "pop").exists() and not ray.is_initialized()


@one_ray_at_a_time
@pytest.mark.skipif(torch.cuda.is_available(), reason="the local Ray instance would have this machine's GPUs")
def test_cuda_on_a_ray_cluster_without_gpus_is_refused_before_any_task(tmp_path):
    """The driver checks the device's name only (a login node has no GPU; the workers do); the cluster's
    resources decide, once Ray is up, before any task is sent."""
    with pytest.raises(MEIError, match="'cuda' asked for, but the Ray cluster has no GPU"):
        run_population(cells(), [0, 1], tmp_path / "pop", settings=MEISettings(**SMALL), pixel_steps=0,
                       cluster="ray", device="cuda", progress=False)
    assert not ray.is_initialized()
    assert not list((tmp_path / "pop" / "neurons").glob("neuron_*"))
