"""The reconstruction benchmark's curve comparison (pure functions; the benchmark itself is not a test)."""

from __future__ import annotations

from meshmei.benchmarks.reconstruct import _teapot_piece_names, on_checkpoints, slower_levels, time_to_reach


def test_checkpoints_absorb_the_step_after_each_evaluation_time():
    curve = [(0.0, 1.0), (1.04, 0.5), (2.3, 0.2), (5.01, 0.1), (100.2, 0.01)]
    assert on_checkpoints(curve) == [(0.0, 1.0), (1.0, 0.5), (2.0, 0.2), (5.0, 0.1), (100.0, 0.01)]


def test_slower_levels_lists_exactly_the_levels_reached_later():
    ref = [(0.0, 1.0), (1.0, 0.5), (2.0, 0.2), (5.0, 0.1), (100.0, 0.05)]
    same_but_jittered = [(0.0, 1.0), (1.09, 0.5), (2.05, 0.2), (5.3, 0.1), (100.1, 0.05)]
    assert slower_levels(same_but_jittered, ref) == []
    faster = [(0.0, 1.0), (1.0, 0.1), (2.0, 0.05), (5.0, 0.04), (100.0, 0.01)]
    assert slower_levels(faster, ref) == []
    # late in the middle: 0.2 is reached at 5 s instead of 2 s; 0.05 never (inf)
    late = [(0.0, 1.0), (1.0, 0.45), (2.0, 0.3), (5.0, 0.09), (100.0, 0.06)]
    assert slower_levels(late, ref) == [(0.2, 5.0, 2.0), (0.05, float("inf"), 100.0)]
    assert time_to_reach(late, 0.3) == 2.0 and time_to_reach(late, 1e-9) == float("inf")


def test_teapot_pieces_are_named_by_their_boxes():
    parts = [
        {"area_share": 0.73, "bbox_min": [-0.27, -0.24, -0.19], "bbox_max": [0.22, 0.24, 0.11]},
        {"area_share": 0.13, "bbox_min": [-0.18, -0.16, 0.10], "bbox_max": [0.13, 0.16, 0.19]},
        {"area_share": 0.08, "bbox_min": [0.18, -0.06, -0.12], "bbox_max": [0.39, 0.06, 0.11]},
        {"area_share": 0.06, "bbox_min": [-0.39, -0.03, -0.12], "bbox_max": [-0.21, 0.03, 0.08]},
    ]
    named = _teapot_piece_names(parts)
    assert [named[k]["area_share"] for k in ("body", "lid", "spout", "handle")] == [0.73, 0.13, 0.08, 0.06]


def test_torus_through_handle_is_centred_on_the_handle_with_axis_y():
    import torch

    from meshmei.benchmarks.reconstruct import torus_through_handle
    from meshmei.metrics import face_components
    from meshmei.shapes import initial_mesh, target_mesh

    Vt, Ft = target_mesh("teapot")
    V, F = torus_through_handle(600, Vt, Ft)
    V0, F0 = initial_mesh("torus", n_vertices=600)
    assert torch.equal(F, F0)
    # The centre sits in the handle's opening: left of the body, in the handle's plane (y = 0), and in
    # empty space (generalised winding number of the teapot below 1/2 there), with handle on both sides.
    centre = 0.5 * (V.min(0).values + V.max(0).values)
    assert float(centre[0]) < -0.25 and abs(float(centre[1])) < 1e-3
    import igl
    import numpy as np

    Vn, Fn = Vt.double().numpy(), Ft.numpy()
    assert abs(igl.fast_winding_number(Vn, Fn, centre.double().numpy()[None])[0]) < 0.5
    handle = face_components(Ft, Vt.shape[0]) == face_components(Ft, Vt.shape[0])[
        int(np.argmin(Vn[Fn].max(1)[:, 0]))]  # the piece holding the face furthest to -x
    H = Vn[Fn[handle].ravel()]
    assert H[:, 0].min() < float(centre[0]) < H[:, 0].max() and H[:, 2].min() < float(centre[2]) < H[:, 2].max()
    # axis y: thickness 2 * 0.15 * 0.5 along y, diameter 0.5 in x and z; the hole (radius 0.1) is empty
    ext = V.max(0).values - V.min(0).values
    torch.testing.assert_close(ext, torch.tensor([0.5, 0.15, 0.5]), atol=5e-3, rtol=0)
    assert float((V - centre).norm(dim=1).min()) > 0.095
