"""Tests for meshmei.reconstruct.openings: a target's through-hole, and the torus started through it."""

import numpy as np
import pytest
import torch

from meshmei.shapes import initial_mesh, target_mesh


def test_find_opening_finds_a_torus_hole_whatever_its_axis_and_place():
    from meshmei.reconstruct.openings import find_opening

    V, F = initial_mesh("torus", n_vertices=1500, dtype=torch.float64)
    centre, axis, clearance = find_opening(V, F)
    assert np.array_equal(axis, [0, 0, 1])  # within a degree of a coordinate axis: snapped to it
    np.testing.assert_allclose(centre, [0, 0, 0], atol=0.02)
    assert clearance == pytest.approx(0.2, abs=0.01)  # hole radius 0.35 - 0.15
    # turned to axis x and moved: the same hole, found there
    shift = np.array([0.3, -0.2, 0.1])
    W = V[:, [2, 0, 1]] + torch.from_numpy(shift)
    centre, axis, clearance = find_opening(W, F)
    assert np.array_equal(axis, [1, 0, 0])
    np.testing.assert_allclose(centre, shift, atol=0.02)
    assert clearance == pytest.approx(0.2, abs=0.01)


@pytest.mark.parametrize("size", [1e-2, 1e-6, 1e3])
def test_find_opening_is_the_same_at_any_size(size):
    # libigl's ray caster missed every hit on a mesh 1e-2 across, so a small mesh had no opening at all
    from meshmei.reconstruct.openings import find_opening

    V, F = initial_mesh("torus", n_vertices=800, dtype=torch.float64)
    c1, a1, r1 = find_opening(V, F, grid=12, directions=8)
    found = find_opening(V * size, F, grid=12, directions=8)
    assert found is not None
    centre, axis, clearance = found
    assert np.array_equal(axis, a1)
    assert clearance == pytest.approx(r1 * size, rel=1e-6)
    np.testing.assert_allclose(centre, c1 * size, rtol=0, atol=1e-3 * size)


@pytest.mark.parametrize("seed", [0, 4])
def test_find_opening_finds_a_tilted_hole_and_its_axis(seed):
    from scipy.spatial.transform import Rotation

    from meshmei.reconstruct.openings import find_opening

    # a torus with a ball beside it (so that no principal axis of the vertices is the hole's axis), turned
    # so that the axis is far from every coordinate axis: only the spread candidate directions can find it
    V, F = initial_mesh("torus", n_vertices=1500, dtype=torch.float64)
    S, G = initial_mesh("sphere", n_vertices=300, dtype=torch.float64)
    V, F = torch.cat([V, 0.4 * S + torch.tensor([0.7, 0.0, 0.45], dtype=torch.float64)]), torch.cat([F, G + len(V)])
    R = Rotation.random(random_state=seed).as_matrix()
    shift = np.array([0.3, -0.2, 0.1])
    W = (V @ torch.from_numpy(R).T + torch.from_numpy(shift)).numpy()
    principal = np.linalg.eigh(np.cov((W - W.mean(0)).T))[1].T
    assert np.abs(principal @ R[:, 2]).max() < np.cos(np.deg2rad(20))
    assert np.abs(R[:, 2]).max() < np.cos(np.deg2rad(30))
    centre, axis, clearance = find_opening(W, F)
    assert np.linalg.norm(axis) == pytest.approx(1.0) and axis[np.argmax(np.abs(axis))] > 0
    assert abs(axis @ R[:, 2]) > np.cos(np.deg2rad(2.0))
    np.testing.assert_allclose(centre, shift, atol=0.005)
    assert clearance == pytest.approx(0.2, abs=0.01)


def test_torus_through_a_turned_teapots_opening_turns_with_it():
    from scipy.spatial.transform import Rotation

    from meshmei.reconstruct.openings import find_opening, torus_through_opening

    Vt, Ft = target_mesh("teapot", dtype=torch.float64)
    c0, a0, r0 = find_opening(Vt, Ft)
    R = Rotation.from_euler("xyz", [35, -20, 50], degrees=True).as_matrix()
    Vr = Vt @ torch.from_numpy(R).T
    centre, axis, clearance = find_opening(Vr, Ft)
    assert np.linalg.norm(centre - R @ c0) < 0.005
    assert abs(axis @ (R @ a0)) > np.cos(np.deg2rad(2.0))
    assert clearance == pytest.approx(r0, rel=0.05)
    V, _ = torus_through_opening(Vr, Ft, n_vertices=800)
    Vd = V.double().numpy()
    # centred on the opening, the hole twice the clearance, thin (tube diameter 0.3 * scale) along the axis
    scale = 2 * clearance / 0.2
    np.testing.assert_allclose(Vd.mean(0), centre, atol=2e-3)
    along = (Vd - centre) @ axis
    assert along.max() - along.min() == pytest.approx(0.3 * scale, rel=0.02)
    radial = np.linalg.norm((Vd - centre) - along[:, None] * axis, axis=1)
    assert radial.max() == pytest.approx(0.5 * scale, rel=0.02) and radial.min() == pytest.approx(2 * clearance, rel=0.02)


def test_find_opening_on_a_sphere_is_none_and_the_placed_torus_says_why():
    from meshmei.errors import MeshError
    from meshmei.reconstruct.openings import find_opening, torus_through_opening

    V, F = initial_mesh("sphere", n_vertices=800, dtype=torch.float64)
    assert find_opening(V, F) is None
    with pytest.raises(MeshError, match="no through-hole"):
        torus_through_opening(V, F)


def test_torus_through_the_teapots_opening_goes_through_the_handle():
    import igl

    from meshmei.reconstruct.openings import find_opening, torus_through_opening

    Vt, Ft = target_mesh("teapot", dtype=torch.float64)
    centre, axis, clearance = find_opening(Vt, Ft)
    # the handle's opening: left of the body, in the handle's plane y = 0, axis y, empty space
    assert np.array_equal(axis, [0, 1, 0]) and centre[0] < -0.25 and abs(centre[1]) < 0.01 and 0.03 < clearance < 0.06
    assert abs(igl.fast_winding_number(Vt.numpy(), Ft.numpy(), centre[None])[0]) < 0.5
    V, F = torus_through_opening(Vt, Ft, n_vertices=800)
    assert V.dtype == torch.float32 and F.shape == initial_mesh("torus", n_vertices=800)[1].shape
    Vd = V.double().numpy()
    np.testing.assert_allclose(0.5 * (Vd.min(0) + Vd.max(0)), centre, atol=2e-3)
    # axis y: the torus is thin along y (tube diameter 0.3 * scale) and its hole has radius 2 * clearance
    scale = 2 * clearance / 0.2
    np.testing.assert_allclose(Vd.max(0) - Vd.min(0), [scale, 0.3 * scale, scale], atol=5e-3)
    assert np.linalg.norm(Vd - centre, axis=1).min() == pytest.approx(2 * clearance, rel=0.02)


def test_find_opening_ignores_dents_closed_along_the_axis():
    from meshmei.reconstruct.openings import find_opening

    # The bunny (closed, genus 0) has dents that are surrounded in a plane but closed along its normal.
    assert find_opening(*target_mesh("bunny")) is None


def test_find_opening_rejects_an_invalid_mesh():
    from meshmei.errors import MeshError
    from meshmei.reconstruct.openings import find_opening

    V, F = initial_mesh("torus", n_vertices=600, dtype=torch.float64)
    V = V.clone()
    V[5, 0] = float("nan")
    with pytest.raises(MeshError, match="NaN"):
        find_opening(V, F)
    with pytest.raises(MeshError):
        find_opening(V[:, :2], F)


@pytest.mark.parametrize("kwargs, match", [({"grid": 3}, "grid"), ({"rays": 4}, "rays"), ({"directions": -1}, "directions"),
                                           ({"grid": 10.5}, "grid"), ({"directions": True}, "directions")])
def test_find_opening_rejects_bad_settings(kwargs, match):
    from meshmei.reconstruct.openings import find_opening

    V, F = initial_mesh("torus", n_vertices=600, dtype=torch.float64)
    with pytest.raises(ValueError, match=match):
        find_opening(V, F, **kwargs)


def test_torus_through_a_given_opening_equals_the_found_one_and_checks_it():
    from meshmei.reconstruct.openings import find_opening, torus_through_opening

    Vt, Ft = target_mesh("teapot", dtype=torch.float64)
    found = find_opening(Vt, Ft)
    V0, F0 = torus_through_opening(Vt, Ft, n_vertices=400)
    V1, F1 = torus_through_opening(Vt, Ft, n_vertices=400, opening=found)
    assert torch.equal(V0, V1) and torch.equal(F0, F1)
    # the axis either way round, or not of unit length, gives the same torus
    centre, axis, clearance = found
    V2, _ = torus_through_opening(Vt, Ft, n_vertices=400, opening=(centre, -3.0 * axis, clearance))
    torch.testing.assert_close(V2, V0, rtol=0, atol=1e-6)
    for bad in [(centre, np.zeros(3), clearance), (centre, axis, 0.0), (centre, axis, float("nan")),
                (np.array([np.nan, 0, 0]), axis, clearance), (centre[:2], axis, clearance), (centre, axis)]:
        with pytest.raises(ValueError, match="opening"):
            torus_through_opening(Vt, Ft, n_vertices=400, opening=bad)


def test_the_opening_is_found_past_stray_vertices_and_at_any_scale():
    """A vertex no face uses widened the search lattice until the hole fell between its points (None); the
    diagonal's square underflowed below 1e-154 (None) and overflowed above 1e154 (OverflowError)."""
    from meshmei.reconstruct.openings import find_opening

    V, F = initial_mesh("torus", n_vertices=300, dtype=torch.float64)[:2]
    centre, axis, clearance = find_opening(V, F)
    stray = torch.cat([V, torch.tensor([[10.0, 10.0, 10.0]], dtype=torch.float64)])
    c2, a2, d2 = find_opening(stray, F)
    assert np.array_equal(c2, centre) and np.array_equal(a2, axis) and d2 == clearance
    for scale in (2.0 ** -700, 2.0 ** 540):  # powers of two: the search is exact at any of them
        c3, a3, d3 = find_opening(V * scale, F)
        assert np.array_equal(c3 / scale, centre) and np.array_equal(a3, axis) and d3 / scale == clearance


def test_the_placed_torus_takes_float_dtypes_only():
    """An int dtype truncated the torus's coordinates; a dtype's name reached torch as a device string."""
    from meshmei.reconstruct.openings import torus_through_opening

    V, F = initial_mesh("torus", n_vertices=300, dtype=torch.float64)[:2]
    assert torus_through_opening(V, F, n_vertices=200, dtype="float64")[0].dtype == torch.float64
    for dtype in (torch.int64, "cuda"):
        with pytest.raises(ValueError, match="dtype must be a torch floating dtype"):
            torus_through_opening(V, F, dtype=dtype)


def test_the_search_sizes_have_floors_and_ceilings():
    """grid=300 ran for minutes and grid=1000 or rays=100000 ran out of memory inside numpy or libigl."""
    from meshmei.reconstruct.openings import SEARCH_LIMITS, find_opening

    V, F = initial_mesh("torus", n_vertices=300, dtype=torch.float64)[:2]
    for name, least in (("grid", 4), ("rays", 8), ("directions", 0)):
        with pytest.raises(ValueError, match=f"{name} must be at most {SEARCH_LIMITS[name]:,}, got "):
            find_opening(V, F, **{name: SEARCH_LIMITS[name] + 1})
        with pytest.raises(ValueError, match=f"{name} must be an integer of at least {least}"):
            find_opening(V, F, **{name: least - 1})

