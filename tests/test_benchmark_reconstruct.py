"""The reconstruction benchmark's curve comparison (pure functions; the benchmark itself is not a test)."""

from __future__ import annotations

import pytest

from meshmei.benchmarks.reconstruct import (_teapot_piece_names, best_of_runs, on_checkpoints, slower_levels,
                                            time_to_reach)


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


def test_best_of_runs_takes_the_lowest_value_reached_by_each_time():
    # the 100 s run's curve, and a 30 s run that ended lower than the long run was at 30 s
    entry = {"curve": [(0.0, 1.0), (10.2, 0.5), (30.1, 0.3), (50.0, 0.2), (100.3, 0.05)],
             "budgets": {"10.0": {"chamfer_l2": 0.6}, "30.0": {"chamfer_l2": 0.1}, "100.0": {"chamfer_l2": 0.05}}}
    assert best_of_runs(entry, (10.0, 30.0, 100.0)) == [(0.0, 1.0), (10.0, 0.5), (30.0, 0.1), (50.0, 0.1),
                                                         (100.0, 0.05)]
    # the short run is what makes 0.1 reachable at 30 s; the long run alone gets there at 100 s
    assert time_to_reach(best_of_runs(entry, (10.0, 30.0, 100.0)), 0.1) == 30.0
    assert time_to_reach(on_checkpoints(entry["curve"]), 0.1) == 100.0


def test_teapot_pieces_are_named_by_their_boxes():
    parts = [
        {"area_share": 0.73, "bbox_min": [-0.27, -0.24, -0.19], "bbox_max": [0.22, 0.24, 0.11]},
        {"area_share": 0.13, "bbox_min": [-0.18, -0.16, 0.10], "bbox_max": [0.13, 0.16, 0.19]},
        {"area_share": 0.08, "bbox_min": [0.18, -0.06, -0.12], "bbox_max": [0.39, 0.06, 0.11]},
        {"area_share": 0.06, "bbox_min": [-0.39, -0.03, -0.12], "bbox_max": [-0.21, 0.03, 0.08]},
    ]
    named = _teapot_piece_names(parts)
    assert [named[k]["area_share"] for k in ("body", "lid", "spout", "handle")] == [0.73, 0.13, 0.08, 0.06]



def test_bad_resolutions_are_refused_before_any_run(capsys):
    from meshmei.benchmarks.reconstruct import main

    for bad in ("2500,abc", "5000"):
        with pytest.raises(SystemExit) as exc:
            main(["--resolutions", bad])
        assert exc.value.code == 2
        assert "--resolutions" in capsys.readouterr().err
