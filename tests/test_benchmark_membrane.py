"""Tests for the reconstruction benchmark's membrane floor (what blocking a target's opening costs)."""

import math

import numpy as np
import pytest
import torch

from meshmei.shapes import initial_mesh


def test_membrane_floor_of_a_torus_is_the_closed_form_from_below():
    from meshmei.benchmarks.reconstruct import membrane_floor

    # Torus R = 0.35, r = 0.15 about z: the hole is the disc of radius a = 0.2, the line through a point at
    # radius rho comes closest to the torus (a - rho) in the plane z = 0, so a blocking surface pays at
    # least 2 * integral of (a - rho)^2 over the disc = pi a^4 / 3.
    V, F = initial_mesh("torus", n_vertices=3000, dtype=torch.float64)
    exact = math.pi * 0.2**4 / 3
    coarse = membrane_floor(V, F, spacing=0.01)
    fine = membrane_floor(V, F, spacing=0.004)
    # a lower bound that tightens as the spacing falls (0.79 and 0.91 of the closed form here)
    assert 0.75 * exact < coarse.integral < fine.integral < 1.01 * exact and fine.integral > 0.88 * exact
    assert fine.opening_area == pytest.approx(math.pi * 0.2**2, rel=0.03)
    assert fine.target_area == pytest.approx(4 * math.pi**2 * 0.35 * 0.15, rel=0.01)
    assert fine.accuracy() == pytest.approx(fine.integral / fine.target_area, rel=1e-12)
    assert fine.accuracy(2 * fine.target_area) == pytest.approx(fine.accuracy() / 2, rel=1e-12)
    assert np.array_equal(fine.axis, [0, 0, 1]) and fine.clearance == pytest.approx(0.2, abs=0.01)


def test_membrane_floor_is_the_same_for_a_turned_moved_torus_and_in_float32():
    from scipy.spatial.transform import Rotation

    from meshmei.benchmarks.reconstruct import membrane_floor

    V, F = initial_mesh("torus", n_vertices=1500, dtype=torch.float64)
    base = membrane_floor(V, F, spacing=0.01)
    R = torch.from_numpy(Rotation.random(random_state=4).as_matrix())
    W = V @ R.T + torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)
    # the opening found on the turned torus, and the original one carried along: the same floor up to the
    # grid's placement (cells are laid out in the plane of each)
    turned = membrane_floor(W, F, spacing=0.01)
    carried = membrane_floor(W, F, (base.centre @ R.numpy().T + [0.3, -0.2, 0.1], base.axis @ R.numpy().T, 0.2),
                             spacing=0.01)
    assert turned.integral == pytest.approx(base.integral, rel=0.01)  # 0.9993 of it
    assert carried.integral == pytest.approx(base.integral, rel=1e-3)  # 0.999997
    assert turned.target_area == pytest.approx(base.target_area, rel=1e-9)
    assert membrane_floor(V.float(), F, spacing=0.01).integral == pytest.approx(base.integral, rel=1e-5)


def test_membrane_floor_bounds_the_convex_hull_which_blocks_the_hole():
    from scipy.spatial import ConvexHull

    from meshmei.metrics import surface_metrics
    from meshmei.benchmarks.reconstruct import membrane_floor

    V, F = initial_mesh("torus", n_vertices=3000, dtype=torch.float64)
    hull = ConvexHull(V.numpy())
    H = torch.from_numpy(hull.points[hull.vertices])
    remap = -np.ones(len(hull.points), dtype=np.int64)
    remap[hull.vertices] = np.arange(len(hull.vertices))
    FH = torch.from_numpy(remap[hull.simplices])
    m = surface_metrics(H, FH, V, F, n_samples=200_000, health=False)
    floor = membrane_floor(V, F, spacing=0.004)
    hull_area = m.area_ratio * floor.target_area
    # the hull caps the hole with two flat discs at z = +-0.15, farther from the torus than the plane z = 0
    # (and flat annuli over the tube's inner half): 2.7x the floor
    assert m.accuracy > floor.accuracy(hull_area) > 0


def test_membrane_floor_says_why_it_cannot():
    from meshmei.errors import MeshError
    from meshmei.benchmarks.reconstruct import membrane_floor

    S, FS = initial_mesh("sphere", n_vertices=400, dtype=torch.float64)
    with pytest.raises(MeshError, match="no through-hole"):
        membrane_floor(S, FS)
    V, F = initial_mesh("torus", n_vertices=600, dtype=torch.float64)
    z = np.array([0.0, 0.0, 1.0])
    with pytest.raises(MeshError, match="inside"):
        membrane_floor(V, F, (np.array([0.35, 0.0, 0.0]), z, 0.1), spacing=0.02)
    with pytest.raises(MeshError, match="not enclosed"):
        membrane_floor(V, F, (np.array([0.7, 0.0, 0.0]), z, 0.1), spacing=0.02)
    for spacing in (0, -0.1, float("nan"), float("inf"), True, "0.1"):
        with pytest.raises(ValueError, match="spacing"):
            membrane_floor(V, F, (np.zeros(3), z, 0.2), spacing=spacing)
    with pytest.raises(ValueError, match="at most 4 million"):
        membrane_floor(V, F, (np.zeros(3), z, 0.2), spacing=1e-4)
    for bad in ((np.zeros(3), np.zeros(3), 0.2), (np.zeros(3), z), (np.full(3, np.nan), z, 0.2), (np.zeros(3), z, "x")):
        with pytest.raises(ValueError, match="opening"):
            membrane_floor(V, F, bad, spacing=0.02)
