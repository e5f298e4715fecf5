"""View- and light-robust 3D-MEIs: the objective averages the response over a grid of object turns and
light positions; the result is reported, saved and re-rendered in the plain scene."""

from __future__ import annotations

import math

import pytest
import torch

from meshmei.encoders import GaborComplexCell, GaborSimpleCell
from meshmei.errors import MEIError
from meshmei.mei import MEISettings, optimize_mei
from meshmei.mei.scene import SeedScene, robust_turns
from meshmei.mei.optimize import initial


def test_the_turns_are_rotations_whose_weights_give_the_mean_over_the_uniform_square():
    d = 20.0
    turns, lights, w = robust_turns(MEISettings(robust_pose=d, robust_points=3), torch.float64)
    assert turns.shape == (9, 3, 3) and lights is None and w.shape == (9,)
    eye = torch.eye(3, dtype=torch.float64)
    torch.testing.assert_close(turns @ turns.transpose(1, 2), eye.expand(9, 3, 3))
    assert any(torch.allclose(t, eye) for t in turns)  # the plain view is a node (odd points)
    assert bool((w > 0).all()) and float(w.sum()) == pytest.approx(1.0, abs=1e-14)
    # recover the two angles (R = Ry(az) Rx(el)) and integrate az^4 el^2 (degree 5 or less per angle:
    # exact for 3 Gauss-Legendre nodes): the mean over [-d, d]^2 is (d^4 / 5) (d^2 / 3)
    az = torch.atan2(-turns[:, 2, 0], turns[:, 0, 0])
    el = torch.atan2(-turns[:, 1, 2], turns[:, 1, 1])
    r = math.radians(d)
    assert float((w * az ** 4 * el ** 2).sum()) == pytest.approx(r ** 4 / 5 * r ** 2 / 3, rel=1e-12)
    assert float((w * az ** 3 * el).sum()) == pytest.approx(0.0, abs=1e-15)
    assert float(az.abs().max()) < r  # Gauss nodes lie inside the range
    T, L, wb = robust_turns(MEISettings(robust_pose=10.0, robust_light=30.0, robust_points=2), torch.float64)
    assert T.shape == L.shape == (16, 3, 3) and wb.shape == (16,)  # every (turn, light) pair
    assert float(wb.sum()) == pytest.approx(1.0, abs=1e-14)
    assert robust_turns(MEISettings(), torch.float64) is None


def test_the_ranges_widen_linearly_over_the_first_share_of_the_run():
    s = MEISettings(image_size=24, n_vertices=60, robust_pose=20.0, robust_light=10.0, robust_widen=0.5)
    V0, F, _ = initial("sheet", s)
    scene = SeedScene(V0, s, 0)
    full = robust_turns(s, torch.float32)

    def largest(turns):  # the largest azimuth and elevation of the turns (R = Ry(az) Rx(el))
        az = torch.atan2(-turns[:, 2, 0], turns[:, 0, 0])
        el = torch.atan2(-turns[:, 1, 2], turns[:, 1, 1])
        return float(az.abs().max()), float(el.abs().max())

    scene.widen(0.0)
    eye = torch.eye(3).expand(81, 3, 3)
    torch.testing.assert_close(scene.robust[0], eye)
    torch.testing.assert_close(scene.robust[1], eye)
    torch.testing.assert_close(scene.robust[2], full[2])  # the weights do not change
    scene.widen(0.25)
    for got, want in zip(scene.robust[:2], full[:2]):
        assert largest(got) == pytest.approx(tuple(0.5 * a for a in largest(want)), rel=1e-5)
    for f in (0.5, 0.9):
        scene.widen(f)
        for got, want in zip(scene.robust, full):
            torch.testing.assert_close(got, want)
    with pytest.raises(MEIError, match="robust_widen"):
        MEISettings(robust_widen=1.0)


def test_the_objective_is_the_mean_over_the_views_and_the_result_is_the_plain_scene():
    s = MEISettings(steps=3, seeds=(0,), image_size=24, n_vertices=60, robust_pose=15.0, robust_light=15.0,
                    robust_points=2, dtype="float64")
    cell = GaborSimpleCell()
    V0, F, _ = initial("sheet", s)
    scene = SeedScene(V0, s, 0)
    with torch.no_grad():
        views = scene.views(scene.rbf(), F)
    assert views.shape == (16, 1, 24, 24)
    assert float((views - views[:1]).abs().max()) > 1e-3  # the views differ
    res = optimize_mei(cell, 0, "sheet", s)
    torch.testing.assert_close(res.render(), res.image)
    assert res.activation == pytest.approx(float(cell(res.image)[0, 0]), rel=1e-12)


def test_a_complex_cell_keeps_its_response_under_a_pose_robust_objective():
    """A complex cell is phase-invariant, so turning the object (which moves the grating's phase) costs
    it little: the pose-robust 3D-MEI keeps at least 0.8 of the plain one's response at the original view."""
    s = dict(steps=120, seeds=(0,), image_size=32, n_vertices=120)
    cell = GaborComplexCell()
    plain = optimize_mei(cell, 0, "sheet", **s)
    robust = optimize_mei(cell, 0, "sheet", robust_pose=10.0, **s)
    assert robust.activation >= 0.8 * plain.activation, (robust.activation, plain.activation)


def test_bad_robust_settings_are_refused():
    with pytest.raises(MEIError, match="robust_pose"):
        MEISettings(robust_pose=-1.0)
    with pytest.raises(MEIError, match="robust_points"):
        MEISettings(robust_points=0)


def test_keep_best_with_no_iterate_offered_refuses_a_non_finite_final_one():
    # one step, ranges widening over the first half: keep-best is offered nothing but the final iterate,
    # which lr 1e37 overflows; it used to come back as the result, NaN response and all
    with pytest.raises(MEIError, match="the loss became nan at step 1 of seed 0"):
        optimize_mei(GaborSimpleCell(), 0, "sheet", seeds=(0,), steps=1, image_size=16, n_vertices=40, lr=1e37,
                     valid_steps=False, robust_pose=10.0)
