"""The main job end to end (quick preset), its outputs, and its refusals."""

import json
import math

import pytest

from meshmei.cli import main
from meshmei.encoders import EncoderError, make_encoder
from meshmei.mei import load_run
from meshmei.story import QUICK, run_story
from meshmei.tuning import load_sweep


@pytest.fixture(scope="module")
def cell():
    return make_encoder("gabor-simple", orientation=math.pi / 6, frequency=3.0, sigma=0.3)


def test_story_writes_every_artifact_and_they_reload(tmp_path, cell):
    lines = []
    s = run_story(tmp_path / "out", encoder=cell, preset=QUICK, log=lines.append)
    out = tmp_path / "out"
    for name in ("summary.png", "summary.pdf", "story.json"):
        assert (out / name).is_file()
    run = load_run(out / "mei")
    assert run.activation == pytest.approx(s["mei_activation"])
    assert run.extra["pixel_mei_activation"] == pytest.approx(s["pixel_mei_activation"])
    pose, light = load_sweep(out / "mei" / "tuning_pose"), load_sweep(out / "mei" / "tuning_light")
    assert pose.shape == (QUICK["pose"], QUICK["pose"]) and light.shape == QUICK["light"]
    # the simple cell's 3D-MEI: strongest at its own view; the pixel MEI beats it in its own image space
    assert s["pose_best"] == {"elevation": 0.0, "azimuth": 0.0}
    # the summary's peaks are the saved sweeps' (a minimum in their place passed before)
    assert (s["pose_best_response"], s["light_best_response"]) == (float(pose.of(0).max()), float(light.of(0).max()))
    assert (s["pose_best"], s["light_best"]) == (pose.argmax(0), light.argmax(0))
    assert s["mei_activation"] > 0.6 and s["pixel_mei_activation"] > s["mei_activation"]
    assert json.loads((out / "story.json").read_text())["neuron"] == 0
    assert any("files:" in line for line in lines)
    # the result's health, in story.json and in the closing line, is the saved mesh's
    h = json.loads((out / "story.json").read_text())["mei_health"]
    assert h == run.health() and h["self_intersections"] == 0 and h["flipped_faces"] == 0
    assert any(f"{h['self_intersections']} self-intersecting pairs, 0 flipped faces" in line for line in lines)


def test_story_refuses_bad_neuron_and_nonempty_output(tmp_path, cell, monkeypatch):
    with pytest.raises(EncoderError, match="out of range"):
        run_story(tmp_path / "a", encoder=cell, neuron=4, preset=QUICK)
    assert not (tmp_path / "a").exists()  # refused before its folder is made (an empty one was left before)
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "keep.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="not empty"):
        run_story(tmp_path / "b", encoder=cell, preset=QUICK)
    assert (tmp_path / "b" / "keep.txt").read_text() == "mine"
    # with overwrite, a mei/ folder of files meshmei did not write is refused before the 3D-MEI and the pixel
    # MEI (it was refused when the run was saved, after both)
    (tmp_path / "b" / "mei").mkdir()
    (tmp_path / "b" / "mei" / "notes.txt").write_text("mine")
    import meshmei.story as story

    def fail(*a, **k):
        pytest.fail("optimised before refusing")

    monkeypatch.setattr(story, "optimize_mei", fail)
    with pytest.raises(FileExistsError, match=r"mei holds files meshmei did not write .* not replaced, even with"):
        run_story(tmp_path / "b", encoder=cell, preset=QUICK, overwrite=True)
    assert (tmp_path / "b" / "mei" / "notes.txt").read_text() == "mine"


def test_demo_cli_reports_an_occupied_output_without_traceback(tmp_path, capsys):
    (tmp_path / "keep.txt").write_text("mine")
    assert main(["demo", "--quick", "--out", str(tmp_path)]) == 2
    assert "not empty" in capsys.readouterr().err
    # found by fuzzing: a file as --out (errno 20), and a folder where none can be made (errno 2 after the run)
    for out, says in ((tmp_path / "keep.txt", "keep.txt is a file, not a folder; choose another output path"),
                      (tmp_path / "keep.txt" / "sub", "keep.txt is a file, not a folder; choose another output path")):
        assert main(["demo", "--quick", "--out", str(out), "--overwrite"]) == 2
        err = capsys.readouterr().err.strip()
        assert err.endswith(says) and "\n" not in err
    assert (tmp_path / "keep.txt").read_text() == "mine"


def test_demo_cli_quick_on_the_shipped_model(tmp_path, capsys):
    from meshmei.encoders import DEMO_MODEL_PATH

    if not DEMO_MODEL_PATH.is_file():
        pytest.fail(f"the demo model must ship with the package: {DEMO_MODEL_PATH} is missing")
    assert main(["demo", "--quick", "--out", str(tmp_path / "demo")]) == 0
    s = json.loads((tmp_path / "demo" / "story.json").read_text())
    run = load_run(tmp_path / "demo" / "mei")
    assert s["mei_activation"] == run.activation > 0 and s["neuron"] == run.neuron
    light = load_sweep(tmp_path / "demo" / "mei" / "tuning_light")
    assert s["light_best_response"] == float(light.of(run.neuron).max())
    assert "3D-MEI response" in capsys.readouterr().out


def test_an_interrupted_overwrite_leaves_no_story_of_another_neuron(tmp_path, cell, monkeypatch):
    """Interrupted after the new run folder was in place (during the sweeps), an overwrite left story.json and
    summary.png of the earlier neuron beside mei/ of the new one. story.json is now removed first and written
    last: a folder without it holds no finished story."""
    import meshmei.story as story

    two = make_encoder("gabor-simple", orientation=[0.0, 1.0], frequency=3.0, sigma=0.3)
    run_story(tmp_path, encoder=two, neuron=0, preset=QUICK, log=lambda line: None)
    assert (tmp_path / "story.json").is_file()

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(story, "_sweep", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_story(tmp_path, encoder=two, neuron=1, preset=QUICK, overwrite=True, log=lambda line: None)
    assert load_run(tmp_path / "mei").neuron == 1
    assert not (tmp_path / "story.json").exists() and not (tmp_path / "summary.png").exists()
