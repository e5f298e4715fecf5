"""Pose and light sweeps: known tuning of simulated cells, saved sweeps, bad input."""

import json
import math

import numpy as np
import pytest
import torch

from meshmei.cli import main
from meshmei.encoders import make_encoder
from meshmei.mei import MEISettings, load_run, optimize_mei, save_run
from meshmei.render import RenderSettings
from meshmei.shapes import initial_mesh
from meshmei.tuning import (
    TuningError,
    light_positions,
    light_sweep,
    load_sweep,
    pose_rotations,
    pose_sweep,
    response_groups,
    run_tuning,
    save_sweep,
    turned_views,
)

FREQ, SIGMA, ORIENT = 3.0, 0.3, math.pi / 6


@pytest.fixture(scope="module")
def simple_cell():
    return make_encoder("gabor-simple", orientation=ORIENT, frequency=FREQ, sigma=SIGMA)


@pytest.fixture(scope="module")
def sheet_mei(simple_cell):
    st = MEISettings(image_size=40, n_vertices=250, steps=100, seeds=(0,))
    res = optimize_mei(simple_cell, 0, init="sheet", settings=st, progress=False)
    assert res.activation > 0.85  # the optimisation itself is tested in test_mei.py
    return res


def test_rotations_are_proper_and_compose_in_order():
    R = pose_rotations([-30, 0, 45], [-90, 10], [0, 120], dtype=torch.float64)
    assert R.shape == (3, 2, 2, 3, 3)
    torch.testing.assert_close(R @ R.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand_as(R))
    assert torch.allclose(torch.linalg.det(R), torch.ones(3, 2, 2, dtype=torch.float64))
    front = torch.tensor([0.0, 0, 1], dtype=torch.float64)
    # azimuth turns the front to image right (+x); elevation tilts it up (+y)
    Ra = pose_rotations([0], [30], dtype=torch.float64)[0, 0]
    torch.testing.assert_close(Ra @ front, torch.tensor([0.5, 0, math.sqrt(3) / 2], dtype=torch.float64))
    Re = pose_rotations([30], [0], dtype=torch.float64)[0, 0]
    torch.testing.assert_close(Re @ front, torch.tensor([0, 0.5, math.sqrt(3) / 2], dtype=torch.float64))


def test_angles_beyond_a_turn_are_the_same_rotations_and_stay_finite():
    """1e308 degrees overflowed float32 in radians: a NaN rotation, refused deep in the renderer."""
    for dtype in (torch.float32, torch.float64):
        R = pose_rotations([370.0, -725.0, 1e308], [1e308, 0.0], [-1e308], dtype=dtype)
        assert torch.isfinite(R).all()
        same = pose_rotations([10.0, -5.0, math.fmod(1e308, 360.0)], [math.fmod(1e308, 360.0), 0.0],
                              [math.fmod(-1e308, 360.0)], dtype=dtype)
        torch.testing.assert_close(R, same, rtol=0, atol=1e-6 if dtype == torch.float32 else 1e-12)
    with pytest.raises(TuningError, match=r"^light distance must be at most 1e\+06, got 1e\+308$"):
        light_positions([0.0], [0.0], 1e308)  # its position overflowed: "light holds NaN or Inf"
    assert torch.isfinite(light_positions([0.0], [0.0], 1e6)).all()


def test_sweeps_refuse_bad_arguments_in_one_line(sheet_mei, simple_cell):
    """Found by fuzzing: neurons='12' swept neurons (1, 2) and [0.7, 1.9] swept (0, 1); a batch size of 0 or 2.5,
    a range's text as the angles, an encoder or result of None failed inside the sweep."""
    V, F = sheet_mei.V, sheet_mei.F
    for sweep, args, kw, says in [
            (pose_sweep, (sheet_mei, simple_cell), dict(neurons="12"), "neurons must be None, a neuron index or a "
                                                                        "sequence of them, got '12'"),
            (pose_sweep, (sheet_mei, simple_cell), dict(neurons=[0.7, 1.9]), r"got \[0.7, 1.9\]"),
            (light_sweep, (sheet_mei, simple_cell), dict(batch_size=0), "batch_size must be a positive integer, got 0"),
            (pose_sweep, (sheet_mei, simple_cell), dict(batch_size=2.5), "batch_size must be a positive integer"),
            (pose_sweep, (sheet_mei, simple_cell), dict(elevation="0:10:2"), r"elevation must be angles in degrees, "
                                                                              r"got '0:10:2' \(parse_range reads"),
            (light_sweep, (None, simple_cell), {}, "result must be an MEIResult, or a"),
            (pose_sweep, (sheet_mei, None), {}, "encoder must be a meshmei Encoder"),
            (pose_sweep, ((V, F, None), simple_cell), {}, "a bare mesh's scene must be a dict")]:
        with pytest.raises(TuningError, match=says) as err:
            sweep(*args, **{"elevation": [0], "azimuth": [0], **kw})
        assert "\n" not in str(err.value)
    np_neuron = pose_sweep(sheet_mei, simple_cell, neurons=np.int64(0), elevation=[0], azimuth=[0])
    assert tuple(np_neuron.neurons) == (0,)


def test_a_range_is_ascii_numbers_and_never_gives_nan():
    # found by fuzzing: -1e308:1e308:3 gave [nan, inf, 1e308], and other scripts' digits, '1_0' and None were
    # read or ended in an AttributeError
    from meshmei.tuning import parse_range

    np.testing.assert_array_equal(parse_range(" -90 : 90 : 3 "), [-90.0, 0.0, 90.0])
    np.testing.assert_array_equal(parse_range(".5:1e2:2"), [0.5, 100.0])
    for bad in ("0:10:\u0663", "\uff10:10:2", "0:10:1_0", "+2", "1:2:3:4", "x:1:3", None, 5):
        with pytest.raises(TuningError, match="a range is 'lo:hi:n'"):
            parse_range(bad)
    for bad in ("-1e308:1e308:3", "1e400:0:2", "nan:1:3", "0:-Inf:2"):
        with pytest.raises(TuningError, match="bounds must be finite degrees"):
            parse_range(bad)


def test_bare_meshes_and_neurons_of_any_sequence_type_are_taken_or_named(sheet_mei, simple_cell):
    # found by fuzzing: a NumPy V and a camera of text were AttributeErrors, a scene key's typo render()'s
    # TypeError, a rotation of (2, 3, 3) torch's size mismatch; a generator of neurons was "empty", a 0-d
    # tensor failed in iteration, np.float32(3) was not a distance and True was one
    V, F = sheet_mei.V, sheet_mei.F
    grid = dict(elevation=[0], azimuth=[0, 10])
    alone = pose_sweep((V, F), simple_cell, **grid)
    np.testing.assert_array_equal(pose_sweep((V.numpy(), F.numpy()), simple_cell, **grid).responses, alone.responses)
    for scene, says in (({"lite": 1}, r"scene takes camera, .*; got \['lite'\]"),
                        ({"rotation": torch.eye(3).expand(2, 3, 3)}, r"rotation must be a \(3, 3\) tensor"),
                        ({"camera": "x"}, "camera must be a Camera, got str")):
        with pytest.raises(TuningError, match=says):
            pose_sweep((V, F, scene), simple_cell, **grid)
    for neurons in ((n for n in [0]), torch.tensor(0), torch.tensor([0]), np.array([0])):
        assert tuple(pose_sweep(sheet_mei, simple_cell, neurons=neurons, **grid).neurons) == (0,)
    with pytest.raises(TuningError, match="got a dict"):
        pose_sweep(sheet_mei, simple_cell, neurons={0: 1}, **grid)
    with pytest.raises(TuningError, match="elevation must be angles in degrees, got None"):
        pose_sweep(sheet_mei, simple_cell, elevation=None, azimuth=[0])
    light = [light_sweep(sheet_mei, simple_cell, elevation=[30], azimuth=[0], distance=d).responses
             for d in (3.0, np.float32(3), np.int64(3), torch.tensor(3.0))]
    assert all(np.array_equal(r, light[0]) for r in light)
    with pytest.raises(TuningError, match="light distance must be a positive number, got True"):
        light_sweep(sheet_mei, simple_cell, elevation=[30], azimuth=[0], distance=True)


def test_light_positions_on_the_hemisphere():
    P = light_positions([0, 45, 90], [0, 90, 180], 2.0, dtype=torch.float64)
    torch.testing.assert_close(P.norm(dim=-1), torch.full((3, 3), 2.0, dtype=torch.float64))
    torch.testing.assert_close(P[0, 2], torch.tensor([-2.0, 0, 0], dtype=torch.float64), atol=1e-12, rtol=0)
    torch.testing.assert_close(P[2, 1], torch.tensor([0, 0, 2.0], dtype=torch.float64), atol=1e-12, rtol=0)


def test_pose_sweep_peaks_at_the_original_view_and_falls_off(sheet_mei, simple_cell):
    ang = np.linspace(-90, 90, 13)
    sw = pose_sweep(sheet_mei, simple_cell, elevation=ang, azimuth=ang)
    r = sw.of(0)
    assert r.shape == (13, 13) and sw.neurons == (0,)
    assert sw.argmax(0) == {"elevation": 0.0, "azimuth": 0.0}
    assert r[6, 6] == pytest.approx(sheet_mei.activation, abs=1e-5)
    assert r[6, 6] == pytest.approx(sw.reference["responses"][0], abs=1e-6)
    far = np.abs(ang) >= 45
    assert np.abs(r[6, far]).max() < 0.5 * r[6, 6] and np.abs(r[far, 6]).max() < 0.5 * r[6, 6]


def test_roll_sweep_reproduces_the_gabor_orientation_tuning(sheet_mei, simple_cell):
    roll = np.linspace(-180, 180, 37)
    sw = pose_sweep(sheet_mei, simple_cell, elevation=[0], azimuth=[0], roll=roll)
    curve = sw.of(0)[0, 0]
    # analytic tuning of an isotropic even Gabor to its own rotation: the overlap of the rotated spectra,
    # <g_0, g_theta> / <g_0, g_0> with wave number k = pi f and envelope sigma (image half-widths)
    k, th = math.pi * FREQ, np.radians(roll)
    pred = (np.exp(-(SIGMA * k) ** 2 * (1 - np.cos(th)) / 2) + np.exp(-(SIGMA * k) ** 2 * (1 + np.cos(th)) / 2))
    pred /= 1 + np.exp(-(SIGMA * k) ** 2)
    measured = curve / curve[18]
    assert np.argmax(curve) in (0, 18, 36)
    assert np.abs(measured - pred).max() < 0.1
    assert np.corrcoef(measured, pred)[0, 1] > 0.98


def test_light_sweep_on_a_sphere_finds_the_left_light():
    # an odd Gabor of half a cycle across the image: prefers bright on the left, dark on the right
    cell = make_encoder("gabor-simple", orientation=0.0, frequency=0.5, sigma=0.6, phase=math.pi / 2)
    V, F = initial_mesh("sphere", n_vertices=600)
    sw = light_sweep((V, F, {"settings": RenderSettings(image_size=48)}), cell, elevation=np.linspace(0, 90, 4), azimuth=np.linspace(0, 330, 12),
                     distance=2.5)
    best = sw.argmax(0)
    assert abs(best["azimuth"] - 180) <= 30
    r = sw.of(0)
    # off the camera axis, the mirror light (from the right) drives it the opposite way; on the axis
    # (elevation 90) the shading is left-right symmetric and the response vanishes
    assert r[:-1, 0].max() < 0 < r[:-1, 6].min()
    assert np.abs(r[-1]).max() < 1e-2 * r.max()
    groups = response_groups(sw)
    assert len(groups["high"]) + len(groups["mid"]) + len(groups["low"]) == r.size
    assert groups["high_example"]["response"] == pytest.approx(r.max())
    assert min(g["response"] for g in groups["high"]) >= max(g["response"] for g in groups["low"])


def test_sweep_saves_and_reloads_exactly(tmp_path, sheet_mei, simple_cell):
    sw = pose_sweep(sheet_mei, simple_cell, elevation=[-20, 0, 20], azimuth=[-10, 0, 10])
    out = save_sweep(sw, tmp_path / "pose")
    back = load_sweep(out)
    assert np.array_equal(back.responses, sw.responses)
    assert all(a == b and np.array_equal(u, v) for (a, u), (b, v) in zip(back.axes, sw.axes))
    assert back.neurons == sw.neurons and back.kind == "pose"
    assert (out / "pose_neuron0.png").is_file() and (out / "pose_neuron0.pdf").is_file()
    with pytest.raises(TuningError, match="exists"):
        save_sweep(sw, out)


@pytest.mark.parametrize("damage", ["list", "axes", "neurons", "reference", "npz"])
def test_a_damaged_sweep_is_one_tuning_error(tmp_path, sheet_mei, simple_cell, damage):
    """Hand-edited or truncated sweep files gave TypeErrors, KeyErrors and BadZipFile tracebacks."""
    import shutil

    out = save_sweep(pose_sweep(sheet_mei, simple_cell, elevation=[0], azimuth=[0, 10]), tmp_path / "ok", figures=False)
    bad = shutil.copytree(out, tmp_path / damage)
    meta = json.loads((bad / "sweep.json").read_text())
    edited = {"list": [meta], "axes": {**meta, "axes": 3}, "reference": {**meta, "reference": [1]},
              "neurons": {k: v for k, v in meta.items() if k != "neurons"}}.get(damage)
    if edited is None:
        data = (bad / "sweep.npz").read_bytes()
        (bad / "sweep.npz").write_bytes(data[:len(data) // 2])
    else:
        (bad / "sweep.json").write_text(json.dumps(edited))
    with pytest.raises(TuningError, match="no complete sweep|not a readable sweep"):
        load_sweep(bad)


def test_save_sweep_refuses_a_sweep_load_sweep_would_refuse_and_writes_numpy_numbers(tmp_path, sheet_mei, simple_cell):
    # found by fuzzing: a shape mismatch was written (then refused by load_sweep, or failed in matplotlib), and
    # an np.float32 in meta was the JSON encoder's TypeError
    from meshmei.tuning import Sweep

    sw = pose_sweep(sheet_mei, simple_cell, elevation=[0], azimuth=[0, 10])
    sw.meta["scale"] = np.float32(1.5)
    assert load_sweep(save_sweep(sw, tmp_path / "ok", figures=False)).meta["scale"] == 1.5
    bad = Sweep(sw.kind, sw.responses[:, :, :1], sw.axes, sw.neurons, sw.reference, sw.meta)
    with pytest.raises(TuningError, match=r"has responses of shape \(1, 1, 2\), got \(1, 1, 1\)"):
        save_sweep(bad, tmp_path / "bad")
    assert not (tmp_path / "bad").exists()


def test_load_sweep_names_a_directory_that_is_not_a_path():
    with pytest.raises(TuningError, match="a sweep directory is a path, got NoneType"):
        load_sweep(None)


@pytest.mark.parametrize("edit, match", [
    ({"neurons": "0"}, "neurons must be a list"), ({"neurons": [0.7]}, "neurons must be a list"),
    ({"neurons": [True]}, "neurons must be a list"), ({"neurons": [0, 0]}, "neurons must be a list"),
    ({"kind": "bogus"}, "kind must be one of"), ({"kind": "light", "axes": ["elevation", "azimuth", "roll"]},
                                                 "a light sweep has the axes"),
    ("nan", "responses must be finite real numbers"), ("complex", "responses must be finite real numbers"),
    ("0-d axis", "axis azimuth must be a non-empty list of finite angles"),
])
def test_an_edited_sweep_is_refused_not_read_as_another(tmp_path, sheet_mei, simple_cell, edit, match):
    # found by fuzzing: NaN responses loaded (argmax named the NaN cell), "0" and [0.7] were read as neuron 0,
    # a kind of "bogus" loaded and failed in matplotlib when saved again, complex responses lost their
    # imaginary part with a warning, and a 0-d axis ended in "len() of unsized object"
    import shutil

    sw = pose_sweep(sheet_mei, simple_cell, elevation=[0], azimuth=[0, 10], roll=[0, 5])
    bad = shutil.copytree(save_sweep(sw, tmp_path / "ok", figures=False), tmp_path / "bad")
    if isinstance(edit, dict):
        meta = json.loads((bad / "sweep.json").read_text())
        (bad / "sweep.json").write_text(json.dumps({**meta, **edit}))
    else:
        arrays = dict(np.load(bad / "sweep.npz"))
        if edit == "nan":
            arrays["responses"][0, 0, 0, 0] = np.nan
        elif edit == "complex":
            arrays["responses"] = arrays["responses"] + 1j
        else:
            arrays["axis_azimuth"] = np.array(0.0)
        np.savez(bad / "sweep.npz", **arrays)
    with pytest.raises(TuningError, match=match):
        load_sweep(bad)


def test_overwrite_replaces_only_what_meshmei_wrote(tmp_path, sheet_mei, simple_cell):
    """overwrite=True (CLI --overwrite) removed whatever folder was there: --out ~/data by mistake lost the
    data. Now only an empty folder or one of meshmei's results is replaced."""
    sw = pose_sweep(sheet_mei, simple_cell, elevation=[0], azimuth=[0, 10])
    mine = tmp_path / "data"
    mine.mkdir()
    (mine / "precious.txt").write_text("keep")
    a_file = tmp_path / "notes.txt"
    a_file.write_text("keep")
    for target, match in ((mine, "holds files meshmei did not write"), (a_file, "is a file, not a result folder")):
        with pytest.raises(TuningError, match=match):
            save_sweep(sw, target, overwrite=True, figures=False)
    assert (mine / "precious.txt").read_text() == "keep" and a_file.read_text() == "keep"
    first = save_sweep(sw, tmp_path / "sweep", figures=False)
    (tmp_path / "empty").mkdir()
    for target in (first, tmp_path / "empty"):  # an earlier sweep, and an empty folder, are replaced
        assert load_sweep(save_sweep(sw, target, overwrite=True, figures=False)).neurons == sw.neurons
    # a 3D-MEI run is never replaced by a sweep (found by fuzzing: tune --mei SET/member_0 --out SET/member_1
    # --overwrite replaced a member of a diverse set), nor taken for a result by a look-alike file name
    run = save_run(sheet_mei, tmp_path / "run", figures=False)
    with pytest.raises(TuningError, match=r"run holds another kind of meshmei result \(summary.json, where this "
                                          r"command writes sweep.json\); it is not replaced, even with overwrite"):
        save_sweep(sw, run, overwrite=True, figures=False)
    assert load_run(run).activation == sheet_mei.activation
    sibling = save_run(sheet_mei, tmp_path / "sibling", figures=False)
    assert main(["tune", "pose", "--mei", str(run), "--out", str(sibling), "--overwrite", "--elevation", "0:0:1",
                 "--azimuth", "0:0:1"]) == 2
    assert load_run(sibling).activation == sheet_mei.activation
    (tmp_path / "fake").mkdir()
    (tmp_path / "fake" / "history.json").write_text("{}")
    with pytest.raises(TuningError, match=r"\(no result file of meshmei's: .*; its history.json is not one meshmei "
                                          r"wrote\)"):
        save_sweep(sw, tmp_path / "fake", overwrite=True, figures=False)


def test_half_written_sweep_is_not_taken_for_a_finished_one(tmp_path, sheet_mei, simple_cell):
    sw = pose_sweep(sheet_mei, simple_cell, elevation=[0], azimuth=[0, 10])

    class Boom(RuntimeError):
        pass

    import meshmei.plots as plots

    orig = plots.plot_pose_heatmap
    plots.plot_pose_heatmap = lambda *a, **k: (_ for _ in ()).throw(Boom())
    try:
        with pytest.raises(Boom):
            save_sweep(sw, tmp_path / "pose")
    finally:
        plots.plot_pose_heatmap = orig
    assert not (tmp_path / "pose").exists()
    assert not list(tmp_path.iterdir())  # the temporary directory is cleaned up too
    # a directory with a sweep.json that never got marked complete is refused
    bad = tmp_path / "bad"
    bad.mkdir()
    np.savez(bad / "sweep.npz", responses=np.zeros((1, 1)), axis_elevation=np.zeros(1))
    (bad / "sweep.json").write_text(json.dumps({"format": "meshmei-sweep-1", "kind": "pose", "neurons": [0],
                                                "axes": ["elevation"]}))
    with pytest.raises(TuningError, match="no complete sweep"):
        load_sweep(bad)


def test_bad_input(tmp_path, sheet_mei, simple_cell):
    with pytest.raises(TuningError, match="elevation range is empty"):
        pose_sweep(sheet_mei, simple_cell, elevation=[], azimuth=[0])
    with pytest.raises(TuningError, match=r"neuron index out of range for an encoder of 1 neurons: \[3\]"):
        pose_sweep(sheet_mei, simple_cell, neurons=[3], elevation=[0], azimuth=[0])
    with pytest.raises(TuningError, match=r"elevation must lie in \[0.0, 90.0\]"):
        light_sweep(sheet_mei, simple_cell, elevation=[-10], azimuth=[0])
    with pytest.raises(TuningError, match="NaN"):
        pose_sweep(sheet_mei, simple_cell, elevation=[float("nan")], azimuth=[0])
    with pytest.raises(TuningError, match="no sweep directory"):
        load_sweep(tmp_path / "nothing")
    corrupt = tmp_path / "corrupt"
    corrupt.mkdir()
    (corrupt / "sweep.json").write_text("{not json")
    with pytest.raises(TuningError, match="not a readable sweep"):
        load_sweep(corrupt)


def test_cli_tune_pose_and_light(tmp_path, sheet_mei, capsys):
    run = save_run(sheet_mei, tmp_path / "run", figures=False)
    # a negative range as the help writes it, with a space (argparse took '-30:30:3' for an option)
    assert main(["tune", "pose", "--mei", str(run), "--elevation", "-30:30:3", "--azimuth=-30:30:3"]) == 0
    sw = load_sweep(run / "tuning_pose")
    assert sw.shape == (3, 3) and sw.argmax(0) == {"elevation": 0.0, "azimuth": 0.0}
    assert main(["tune", "light", "--mei", str(run), "--elevation", "0:90:2", "--azimuth", "0:270:4"]) == 0
    light = load_sweep(run / "tuning_light")
    assert light.shape == (2, 4)
    assert (run / "tuning_light" / "light_neuron0.png").is_file()
    meta = json.loads((run / "tuning_light" / "sweep.json").read_text())
    assert set(meta["groups"]["0"]) == {"high_example", "mid_example", "low_example"}
    capsys.readouterr()
    # bad input through the CLI: a clear message and exit code 2, no traceback
    assert main(["tune", "pose", "--mei", str(tmp_path / "missing")]) == 2
    assert "no MEI run directory" in capsys.readouterr().err
    assert main(["tune", "pose", "--mei", str(run), "--neurons", "5", "--overwrite"]) == 2
    assert "out of range" in capsys.readouterr().err
    assert main(["tune", "pose", "--mei", str(run), "--azimuth", "0:10:0", "--overwrite"]) == 2
    assert "a range gives 1 to 3601 angles, got n=0" in capsys.readouterr().err
    assert main(["tune", "pose", "--mei", str(run), "--elevation=0:1:1000000000000", "--overwrite"]) == 2  # 7 TiB
    assert "got n=1000000000000" in capsys.readouterr().err
    assert main(["tune", "pose", "--mei", str(run), "--elevation=inf:1:3", "--overwrite"]) == 2
    assert "bounds must be finite" in capsys.readouterr().err


def test_each_neurons_light_plot_shows_its_own_examples(tmp_path, monkeypatch):
    import meshmei.tuning.files as files
    from meshmei.encoders import GaborSimpleCell
    from meshmei.mei import optimize_mei
    from meshmei.tuning import response_groups

    cells = GaborSimpleCell(orientation=[0.0, 1.6], phase=[0.0, 2.0])  # two neurons that like different lights
    run = save_run(optimize_mei(cells, 0, "sphere", steps=3, seeds=(0,), image_size=24, n_vertices=80),
                   tmp_path / "run", figures=False)
    shown = {}
    monkeypatch.setattr(files.plots, "plot_light_polar",
                        lambda sweep, nrn, stem, images=None: shown.update({nrn: (sweep, images)}))
    run_tuning("light", run, neurons=[0, 1], elevation=[0.0, 45.0, 90.0], azimuth=[0.0, 90.0, 180.0, 270.0])
    assert sorted(shown) == [0, 1]
    for nrn, (sweep, images) in shown.items():
        groups = response_groups(sweep, nrn)
        assert all(images[label][1] == groups[f"{label}_example"] for label in ("high", "mid", "low"))
    assert shown[0][1]["high"][1] != shown[1][1]["high"][1]  # the two neurons' examples differ here


def test_run_tuning_refuses_an_unknown_sweep(tmp_path):
    with pytest.raises(TuningError, match="what must be 'pose' or 'light', got 'colour'"):
        run_tuning("colour", tmp_path)


def test_each_sweep_refuses_the_others_option_before_any_work(tmp_path, capsys):
    """tune light --roll and tune pose --distance were silently ignored; now a clear error (exit code 2)."""
    from meshmei.cli import main

    with pytest.raises(TuningError, match="roll is a pose sweep's axis"):
        run_tuning("light", tmp_path / "no-run", roll=[0.0, 10.0])
    with pytest.raises(TuningError, match="distance places the light of a light sweep"):
        run_tuning("pose", tmp_path / "no-run", distance=3.0)
    assert main(["tune", "light", "--mei", str(tmp_path), "--roll", "0:10:2"]) == 2
    err = capsys.readouterr().err
    assert "roll is a pose sweep's axis" in err and len(err.splitlines()) == 1


def test_turned_views_frame_the_whole_mesh(sheet_mei):
    views = turned_views(sheet_mei, views=((0, 0), (90, 0), (360, 0)))
    assert [(a, e) for a, e, _ in views] == [(0, 0), (90, 0), (360, 0)]
    S = sheet_mei.settings.image_size
    for _, _, img in views:
        assert img.shape == (S, S)
        # framed: the whole mesh lies inside the image, so its border is background
        border = np.concatenate([img[0], img[-1], img[:, 0], img[:, -1]])
        assert np.allclose(border, border[0]) and (np.abs(img - border[0]) > 1e-3).any()
    assert np.abs(views[0][2] - views[1][2]).max() > 0.1  # turned a quarter: another picture
    np.testing.assert_allclose(views[2][2], views[0][2], atol=1e-3)  # turned all the way round: the same


def test_a_bare_scene_keeps_its_own_light_as_the_reference(sheet_mei, simple_cell):
    """The reference of a (V, F, scene) sweep was taken under the default light, not the scene's."""
    from meshmei.render import render

    scene = sheet_mei.scene()
    scene["light"] = torch.tensor([2.0, 0.0, 1.0])
    with torch.no_grad():
        own = float(simple_cell(render(sheet_mei.V, sheet_mei.F, **scene), [0])[0, 0])
        scene.pop("light")
        default = float(simple_cell(render(sheet_mei.V, sheet_mei.F, **scene), [0])[0, 0])
        scene["light"] = torch.tensor([2.0, 0.0, 1.0])
    assert abs(own - default) > 1e-3  # the two lights differ in what the cell sees
    sw = light_sweep((sheet_mei.V, sheet_mei.F, scene), simple_cell, neurons=[0], elevation=[90], azimuth=[0])
    assert sw.reference["responses"][0] == pytest.approx(own, rel=1e-6)
    assert torch.equal(scene["light"], torch.tensor([2.0, 0.0, 1.0]))  # the caller's scene is left alone


def test_tune_refuses_an_output_that_holds_the_run_and_checks_existing_output_first(tmp_path, sheet_mei, capsys,
                                                                                     monkeypatch):
    import meshmei.tuning.run as tr

    run = save_run(sheet_mei, tmp_path / "run", figures=False)
    before = sorted(p.name for p in run.iterdir())
    # --out the run itself, or its parent, with --overwrite: the sweep replaced the run it swept
    for out in (run, tmp_path):
        assert main(["tune", "pose", "--mei", str(run), "--out", str(out), "--overwrite", "--elevation=0:0:1",
                     "--azimuth=0:0:1"]) == 2
        err = capsys.readouterr().err
        assert "is the run being swept" in err and "replacing it would delete it" in err and err.count("\n") == 1
        assert sorted(p.name for p in run.iterdir()) == before
    # an existing output is refused before the sweep (it was refused after about 40 s of rendering)
    (run / "tuning_pose").mkdir()
    (run / "tuning_pose" / "sweep.json").write_text("{}")
    monkeypatch.setattr(tr, "pose_sweep", lambda *a, **k: pytest.fail("swept before refusing"))
    assert main(["tune", "pose", "--mei", str(run)]) == 2
    assert "tuning_pose exists; pass --overwrite to replace it" in capsys.readouterr().err


def test_a_grid_of_too_many_conditions_is_one_line_before_any_work(tmp_path, sheet_mei, capsys):
    from meshmei.tuning.grids import MAX_GRID_CONDITIONS

    with pytest.raises(TuningError, match=r"^the grid has 3601 x 3601 x 2 = 25,934,402 conditions; at most"):
        pose_rotations(np.zeros(3601), np.zeros(3601), np.zeros(2))
    assert pose_rotations(np.zeros(3601), np.zeros(3601)).shape[:2] == (3601, 3601)  # the bound itself passes
    assert MAX_GRID_CONDITIONS == 3601 * 3601
    run = save_run(sheet_mei, tmp_path / "run", figures=False)
    rc = main(["tune", "pose", "--mei", str(run), "--elevation=0:1:3601", "--azimuth=0:1:3601", "--roll=0:1:3601"])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("meshmei tune: error: the grid has 3601 x 3601 x 3601") and err.count("\n") == 1
