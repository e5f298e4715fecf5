"""Batched 3D-MEIs: several (neuron, seed) items in one render and one model call per step, with the
results of running each alone."""

from __future__ import annotations

import pytest
import torch

from meshmei.encoders import GaborComplexCell, GaborSimpleCell
from meshmei.errors import MEIError
from meshmei.mei import MEISettings, mei_batches, optimize_mei, optimize_mei_batch
from meshmei.quality import count_flipped_faces, count_self_intersections

from conftest import shipped_demo


def _two_cell_encoder():
    """Two Gabor cells as one model's neurons (a simple cell, and a complex cell at another orientation)."""
    from meshmei.encoders import encoder_from_model

    simple, complex_ = GaborSimpleCell(), GaborComplexCell(orientation=0.7)

    def model(x):
        return torch.cat([simple(x, preprocessed=True), complex_(x, preprocessed=True)], 1)

    return encoder_from_model(model, mean=0.5, std=0.2, image_size=24)


@pytest.mark.parametrize("batch_size", [3, 8])
def test_batched_items_equal_their_runs_alone(batch_size):
    """float64, light and pose optimised, 12 steps: per neuron the same winning seed, histories, mesh and
    per-seed responses as optimize_mei, whether the items of a neuron share a batch or are split (3)."""
    enc = _two_cell_encoder()
    s = MEISettings(steps=12, seeds=(0, 1), image_size=24, n_vertices=60, dtype="float64", optimize_light=True,
                    optimize_pose=True)
    batched = optimize_mei_batch(enc, [1, 0], "sheet", s, batch_size=batch_size)
    assert list(batched) == [1, 0]
    for n in (0, 1):
        solo, b = optimize_mei(enc, n, "sheet", s), batched[n]
        assert b.seed == solo.seed and b.neuron == n
        torch.testing.assert_close(torch.tensor(b.history), torch.tensor(solo.history), rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(b.V, solo.V, rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(b.light, solo.light, rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(b.rotation, solo.rotation, rtol=1e-9, atol=1e-9)
        for seed in s.seeds:
            assert b.seed_activations[seed] == pytest.approx(solo.seed_activations[seed], rel=1e-9)
        for k in b.deformer_state:
            torch.testing.assert_close(b.deformer_state[k], solo.deformer_state[k], rtol=1e-9, atol=1e-9)
        # the result is a complete run: its response is that of its mesh rendered in its scene
        torch.testing.assert_close(enc(b.render(), n)[0, 0], torch.tensor(b.activation, dtype=torch.float64))


def test_batches_yield_each_neuron_once_as_its_seeds_finish():
    enc = _two_cell_encoder()
    s = MEISettings(steps=2, seeds=(0, 1, 2), image_size=24, n_vertices=40)
    seen = []
    for n, res in mei_batches(enc, [1, 0], "sheet", s, batch_size=4):  # batches (1,0..2)+(0,0), then (0,1..2)
        seen.append(n)
        assert sorted(res.seed_activations) == [0, 1, 2] and res.neuron == n
    assert seen == [1, 0]


def test_batch_callbacks_see_every_step_with_its_items():
    """A batched run's ``callbacks`` get each step's record with ``items``, the batch's (neuron, seed) pairs,
    each value per item in that order, and leave the run as it is. Under a robust objective every neuron runs
    alone: its records are optimize_mei's (one value, their seed), with their one item. A callback that is
    not callable is refused before any step."""
    enc = _two_cell_encoder()
    s = MEISettings(steps=2, seeds=(0, 1), image_size=24, n_vertices=40)
    seen = []
    res = optimize_mei_batch(enc, [1, 0], "sheet", s, batch_size=3, callbacks=seen.append)
    first, second = [(1, 0), (1, 1), (0, 0)], [(0, 1)]
    assert [(r["step"], r["items"]) for r in seen] == [(1, first), (2, first), (1, second), (2, second)]
    assert all(len(r["response"]) == len(r["loss"]) == len(r["items"]) for r in seen)
    plain = optimize_mei_batch(enc, [1, 0], "sheet", s, batch_size=3)
    for n in (0, 1):
        torch.testing.assert_close(res[n].V, plain[n].V, atol=1e-5, rtol=0)  # rounding, as optimize_mei's test
    robust = []
    optimize_mei_batch(enc, [1, 0], "sheet", s, robust_pose=0.2, callbacks=robust.append)
    assert [(r["step"], r["seed"], r["items"]) for r in robust] == [
        (1, 0, [(1, 0)]), (2, 0, [(1, 0)]), (1, 1, [(1, 1)]), (2, 1, [(1, 1)]),
        (1, 0, [(0, 0)]), (2, 0, [(0, 0)]), (1, 1, [(0, 1)]), (2, 1, [(0, 1)])]
    assert all(isinstance(r["response"], float) for r in robust)
    with pytest.raises(MEIError, match=r"callbacks\[0\] is not callable"):
        optimize_mei_batch(enc, [0], "sheet", s, callbacks=[3], progress=False)


def test_guarded_items_equal_their_guarded_runs_alone():
    """valid_steps (the default) in float64 at ten times the default rate: each item's guard refuses and
    halves its own steps, and every item ends where its guarded run alone ends, with the same step scales."""
    enc = _two_cell_encoder()
    s = MEISettings(steps=15, seeds=(0, 1), image_size=24, n_vertices=60, dtype="float64", lr=3e-2)
    assert s.valid_steps
    batched = optimize_mei_batch(enc, [0, 1], "sheet", s, batch_size=3)
    for n in (0, 1):
        solo = optimize_mei(enc, n, "sheet", s)
        assert batched[n].seed == solo.seed and batched[n].extra["guard"] == {**solo.extra["guard"], "seconds":
                                                                               batched[n].extra["guard"]["seconds"]}
        assert solo.extra["guard"]["refused"] > 0  # the rate does make the guard refuse steps
        torch.testing.assert_close(batched[n].V, solo.V, rtol=1e-9, atol=1e-9)
        # the responses come from the float32 cells: a last-bit difference of V (summation order of the batched
        # regularizers, whose weights are scaled to the 60-vertex mesh) may move them by a float32 ulp
        torch.testing.assert_close(torch.tensor(batched[n].history), torch.tensor(solo.history), rtol=1e-6, atol=1e-9)
        assert count_self_intersections(batched[n].V, batched[n].F) == 0
        assert count_flipped_faces(batched[n].V, batched[n].V0, batched[n].F) == 0


def test_bad_batches_fail_before_any_step():
    enc = _two_cell_encoder()
    with pytest.raises(MEIError, match="out of range"):
        optimize_mei_batch(enc, [0, 2], "sheet", steps=2)
    with pytest.raises(MEIError, match="twice"):
        optimize_mei_batch(enc, [0, 1, 0], "sheet", steps=2)
    with pytest.raises(MEIError, match="batch_size"):
        optimize_mei_batch(enc, [0], "sheet", steps=2, batch_size=0)


def test_demo_model_batch_matches_alone():
    """The shipped demo model (a CNN core with a readout) in float32: 5 steps, two neurons, two seeds."""
    _, model = shipped_demo()
    from meshmei.encoders import make_encoder

    enc = make_encoder("demo")
    s = MEISettings(steps=5, seeds=(0, 1), image_size=32, n_vertices=80)
    batched = optimize_mei_batch(enc, [3, 6], "sheet", s)
    for n in (3, 6):
        solo = optimize_mei(enc, n, "sheet", s)
        torch.testing.assert_close(torch.tensor(batched[n].history), torch.tensor(solo.history), rtol=1e-4, atol=1e-4)
