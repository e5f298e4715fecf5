"""Figures: each writes the files it names, from results, sweeps and arrays, without touching pyplot."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import matplotlib.image
import numpy as np
import pytest

from meshmei.encoders import GaborSimpleCell
from meshmei.mei import optimize_mei
from meshmei.plots import mei_figures, plot_light_polar, plot_pose_heatmap, reconstruction_figures, summary_sheet
from meshmei.tuning import Sweep

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tiny_run():
    return optimize_mei(GaborSimpleCell(), 0, "sheet", image_size=32, n_vertices=80, steps=3, seeds=(0,))


def _sweep(kind, roll=False):
    el, az = np.linspace(0, 90, 3), np.linspace(0, 300, 6)
    axes = [("elevation", el), ("azimuth", az)] + ([("roll", np.array([-10.0, 0.0, 10.0]))] if roll else [])
    shape = tuple(len(v) for _, v in axes)
    r = np.random.default_rng(0).random((1, *shape))
    return Sweep(kind, r, tuple(axes), (0,))


def test_mei_figures_write_the_render_views_and_activation(tmp_path, tiny_run):
    mei_figures(tiny_run, tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["activation.png", "render.png", "views.png"]
    render = matplotlib.image.imread(tmp_path / "render.png")
    assert render.shape[:2] == (32, 32)  # the render itself, pixel for pixel (gray: R = G = B), the right way up
    # (the gray colormap has 256 levels: within two of them)
    np.testing.assert_allclose(render[..., 0], tiny_run.image[0, 0].clamp(0, 1).numpy(), atol=2 / 255)


def test_reconstruction_figures_plot_loss_and_metrics(tmp_path):
    history = [{"time": 0.1 * k, "loss": 1.0 / (k + 1)} for k in range(10)]
    metrics = [{"time": t, "chamfer_l2": 1e-3 / (t + 1), "fscore": t / 2, "normal_consistency": 0.5 + t / 4}
               for t in (0.0, 0.5, 1.0)]
    result = SimpleNamespace(history=history, metrics=metrics, settings=SimpleNamespace(method="rbf"))
    paths = reconstruction_figures(result, tmp_path / "new")
    assert paths == [tmp_path / "new" / "loss.png", tmp_path / "new" / "metrics.png"]
    assert all(p.is_file() for p in paths)


@pytest.mark.parametrize("roll", [False, True])
def test_pose_heatmap_with_and_without_roll(tmp_path, roll):
    paths = plot_pose_heatmap(_sweep("pose", roll), 0, tmp_path / "pose")
    assert [p.name for p in paths] == ["pose.png", "pose.pdf"] and all(p.is_file() for p in paths)


def test_light_polar_with_example_renders(tmp_path):
    img = np.full((8, 8), 0.5)
    ex = {"azimuth": 60.0, "elevation": 45.0, "response": 0.5}
    images = {label: (img, ex) for label in ("high", "mid", "low")}
    paths = plot_light_polar(_sweep("light"), 0, tmp_path / "light", images=images)
    assert all(p.is_file() for p in paths)
    wide = matplotlib.image.imread(paths[0]).shape[1]
    narrow = matplotlib.image.imread(plot_light_polar(_sweep("light"), 0, tmp_path / "alone")[0]).shape[1]
    assert wide > 2 * narrow  # the three examples sit beside the polar plot
    with pytest.raises(ValueError, match="images needs 'high', 'mid' and 'low'"):  # a KeyError mid-figure before
        plot_light_polar(_sweep("light"), 0, tmp_path / "part", images={"high": (img, ex)})
    assert not list(tmp_path.glob("part*"))


def test_summary_sheet_takes_rendered_views(tmp_path, tiny_run):
    views = [(az, 0, np.full((16, 16), 0.5)) for az in (0, 90, 180)]
    paths = summary_sheet(tiny_run, tmp_path / "summary", views, pixel_image=np.zeros((32, 32)), pixel_activation=0.9)
    assert [p.name for p in paths] == ["summary.png", "summary.pdf"] and all(p.is_file() for p in paths)
    with pytest.raises(ValueError, match="summary_sheet draws at most 3 views, got 4"):  # matplotlib's IndexError
        summary_sheet(tiny_run, tmp_path / "four", views + views[:1])


def test_figures_leave_pyplot_and_the_backend_alone(tmp_path):
    code = (
        "import sys, matplotlib, numpy as np\n"
        "raw = lambda: dict.__getitem__(matplotlib.rcParams, 'backend')  # get_backend() would load pyplot\n"
        "backend = raw()\n"
        "from meshmei.plots import plot_pose_heatmap\n"
        "from meshmei.tuning import Sweep\n"
        "s = Sweep('pose', np.ones((1, 2, 2)), (('elevation', np.zeros(2)), ('azimuth', np.arange(2.0))), (0,))\n"
        f"plot_pose_heatmap(s, 0, {str(tmp_path / 'p')!r})\n"
        "assert 'matplotlib.pyplot' not in sys.modules\n"
        "assert raw() == backend, (backend, raw())\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert out.returncode == 0, out.stderr


def test_a_dotted_stem_keeps_its_dots(tmp_path):
    """with_suffix cut a stem's last dotted part: pose.v1 and pose.v2 both wrote pose.png, the second over
    the first. A stem ending in .png or .pdf names the pair."""
    first = plot_pose_heatmap(_sweep("pose"), 0, tmp_path / "pose.v1")
    second = plot_pose_heatmap(_sweep("pose"), 0, tmp_path / "pose.v2")
    assert [p.name for p in first + second] == ["pose.v1.png", "pose.v1.pdf", "pose.v2.png", "pose.v2.pdf"]
    assert all(p.is_file() for p in first + second)
    assert [p.name for p in plot_pose_heatmap(_sweep("pose"), 0, tmp_path / "fig.png")] == ["fig.png", "fig.pdf"]
