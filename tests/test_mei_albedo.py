"""Shape + albedo 3D-MEIs: a texture over the sheet's grid (per-vertex albedo on other starts), kept in
[0, 1], saved and reloaded, batched like the shape, and raising the response where shape alone cannot."""

from __future__ import annotations

import pytest
import torch

from meshmei.encoders import GaborSimpleCell, encoder_from_model
from meshmei.errors import MEIError
from meshmei.mei import MEISettings, load_run, optimize_mei, optimize_mei_batch, save_run

TINY = dict(steps=8, seeds=(0,), image_size=24, n_vertices=60, albedo=True, albedo_resolution=16)


def test_a_sheet_gets_a_texture_in_the_unit_interval_that_reproduces_its_image(tmp_path):
    cell = GaborSimpleCell()
    res = optimize_mei(cell, 0, "sheet", **TINY)
    assert res.albedo.shape == (16, 16) and res.albedo_uv.shape == (res.V.shape[0], 2)
    assert float(res.albedo.min()) >= 0.0 and float(res.albedo.max()) <= 1.0
    assert float(res.albedo.std()) > 0  # it was optimised, not left at its start
    # the smoothness term weighs in the loss, so it is in the regularizers' history (it was left out)
    assert len(res.reg_history["albedo_roughness"]) == len(res.history) and res.reg_history["albedo_roughness"][-1] > 0
    torch.testing.assert_close(res.render(), res.image)
    back = load_run(save_run(res, tmp_path / "run", figures=False))
    torch.testing.assert_close(back.albedo, res.albedo)
    torch.testing.assert_close(back.render(), res.image)


def test_a_sphere_gets_a_per_vertex_albedo():
    res = optimize_mei(GaborSimpleCell(), 0, "sphere", **TINY)
    assert res.albedo.shape == (res.V.shape[0],) and res.albedo_uv is None
    torch.testing.assert_close(res.render(), res.image)


@pytest.mark.parametrize("init", ["sheet", "sphere"])
def test_the_albedo_figure_shows_the_albedo_the_camera_sees(init, tmp_path):
    """albedo.png's "albedo alone" panel renders with ambient light 1 and no point light: there the render
    shows the reflectance itself (a constant albedo of 0.3 reads 0.3 on the covered pixels). save_run
    writes the figure for an albedo run and not for a shape-only one."""
    import dataclasses

    from meshmei.plots import albedo_figure
    from meshmei.render import rasterize

    res = optimize_mei(GaborSimpleCell(), 0, init, **TINY)
    flat = dataclasses.replace(res.settings.render_settings(), ambient=1.0, light_intensity=0.0)
    img = dataclasses.replace(res, albedo=torch.full_like(res.albedo, 0.3)).render(settings=flat)[0, 0]
    # the pixels the surface covers fully (the rest are soft edges, blended with the background)
    sc = res.scene()
    full = rasterize(res.V, res.F, camera=sc["camera"], settings=flat).coverage[0] > 0.999
    assert int(full.sum()) > 20 and float((img[full] - 0.3).abs().max()) < 1e-3
    assert albedo_figure(res, tmp_path / "a.png").stat().st_size > 0
    assert (save_run(res, tmp_path / "run") / "albedo.png").is_file()
    shape_only = optimize_mei(GaborSimpleCell(), 0, init, **dict(TINY, albedo=False, steps=2))
    assert not (save_run(shape_only, tmp_path / "shape") / "albedo.png").exists()


def test_the_texture_panel_is_drawn_the_way_the_camera_sees_it(tmp_path, monkeypatch):
    """A texture with its first rows bright: the camera view shows them in its top half, and so must the
    texture panel (it was drawn flipped, bright at the bottom)."""
    import dataclasses

    import meshmei.plots as plots

    res = optimize_mei(GaborSimpleCell(), 0, "sheet", **TINY)
    T = torch.full_like(res.albedo, 0.1)
    T[:4] = 0.9
    res = dataclasses.replace(res, albedo=T)
    res = dataclasses.replace(res, image=res.render().detach())
    shown, draw = {}, plots._gray
    monkeypatch.setattr(plots, "_gray", lambda ax, img, title, **kw: (shown.__setitem__(title.split(" ")[0], img),
                                                                      draw(ax, img, title, **kw))[1])
    plots.albedo_figure(res, tmp_path / "a.png")

    def top_brighter(img):
        img = torch.as_tensor(img)
        return float(img[: img.shape[0] // 2].mean()) > float(img[img.shape[0] // 2:].mean())

    assert top_brighter(shown["albedo"]) and top_brighter(shown["texture"])


def test_shape_only_stays_the_default_and_bad_albedo_settings_are_refused():
    assert MEISettings().albedo is False
    assert optimize_mei(GaborSimpleCell(), 0, "sheet", steps=2, seeds=(0,), image_size=16, n_vertices=40).albedo is None
    with pytest.raises(MEIError, match="albedo_resolution"):
        MEISettings(albedo=True, albedo_resolution=1)
    with pytest.raises(MEIError, match=r"^albedo_resolution must be at most 8192 \(the largest image side\), got 10+$"):
        MEISettings(albedo=True, albedo_resolution=10**9)  # reached the allocator and its RuntimeError
    assert MEISettings(albedo=True, albedo_resolution=8192).albedo_resolution == 8192
    with pytest.raises(MEIError, match="albedo_init"):
        MEISettings(albedo=True, albedo_init=1.0)


def test_batched_albedo_runs_equal_their_runs_alone():
    cells = [GaborSimpleCell(), GaborSimpleCell(orientation=1.0)]
    enc = encoder_from_model(lambda x: torch.cat([c(x, preprocessed=True) for c in cells], 1), mean=0.5, std=0.2,
                             image_size=24)
    s = MEISettings(**{**TINY, "dtype": "float64", "seeds": (0, 1)})
    batched = optimize_mei_batch(enc, [0, 1], "sheet", s, batch_size=3)
    for n in (0, 1):
        solo = optimize_mei(enc, n, "sheet", s)
        torch.testing.assert_close(batched[n].albedo, solo.albedo, rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(torch.tensor(batched[n].history), torch.tensor(solo.history), rtol=1e-9, atol=1e-9)
