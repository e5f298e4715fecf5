"""Building encoders by name, describing them as JSON and rebuilding them; the shipped demo model's record."""

from __future__ import annotations

import json
import math

import pytest
import torch

from meshmei.encoders import (
    CoreReadoutModel,
    GaborComplexCell,
    GaborSimpleCell,
    encoder_from_spec,
    encoder_spec,
    is_demo_model,
    make_encoder,
)
from meshmei.errors import MEIError

from conftest import shipped_demo


@pytest.mark.parametrize("kind, cls", [("gabor-simple", GaborSimpleCell), ("gabor-complex", GaborComplexCell)])
def test_gabor_spec_round_trip_rebuilds_the_same_cell(kind, cls):
    cell = make_encoder(kind, orientation=[0.2, 1.0], frequency=3.0, sigma=0.3, mean=0.4, std=0.1)
    assert isinstance(cell, cls)
    spec = encoder_spec(cell)
    assert json.loads(json.dumps(spec)) == spec  # JSON-able as it stands
    assert spec["kind"] == kind and spec["class"] == cls.__name__ and spec["n_neurons"] == 2
    assert spec["upper_bound"] == 1.0 and spec["mean"] == pytest.approx(0.4)
    back = encoder_from_spec(spec)
    assert isinstance(back, cls) and encoder_spec(back) == spec
    x = torch.rand(3, 1, 24, 24, dtype=torch.float64)
    torch.testing.assert_close(back(x), cell(x), rtol=0, atol=0)


def test_custom_encoder_is_described_but_not_rebuilt():
    model = CoreReadoutModel(3, mean=0.2, std=0.5)
    spec = encoder_spec(model)
    assert spec["kind"] == "custom" and spec["class"] == "CoreReadoutModel" and spec["upper_bound"] is None
    assert not is_demo_model(model)
    with pytest.raises(MEIError, match="cannot rebuild a CoreReadoutModel encoder"):
        encoder_from_spec(spec)


def test_a_demo_model_with_other_weights_is_not_rebuilt_as_the_shipped_one(tmp_path):
    """A model from load_demo_model(another file), or the shipped one changed in place, was recorded as
    kind "demo" alone and rebuilt as the shipped model: another encoder, silently (0.52 for 3.81)."""
    from meshmei.encoders import DEMO_MODEL_PATH, load_demo_model

    shipped_demo()
    spec = encoder_spec(load_demo_model())
    assert spec["kind"] == "demo" and encoder_spec(encoder_from_spec(spec)) == spec  # the shipped one rebuilds
    blob = torch.load(DEMO_MODEL_PATH, map_location="cpu", weights_only=True)
    key = next(k for k in blob["state_dict"] if k.startswith("readout.features"))
    blob["state_dict"][key] = blob["state_dict"][key] + 0.3
    torch.save(blob, tmp_path / "mine.pt")
    changed = load_demo_model()
    with torch.no_grad():
        next(changed.parameters()).add_(0.1)
    for model in (load_demo_model(tmp_path / "mine.pt"), changed):
        other = encoder_spec(model)
        assert other["kind"] == "demo" and other["weights"] != spec["weights"]
        with pytest.raises(MEIError, match=r"^the run's demo model had other weights than the shipped one"):
            encoder_from_spec(other)
    old = {k: v for k, v in spec.items() if k != "weights"}  # a run saved before weights were recorded
    assert encoder_spec(encoder_from_spec(old)) == spec
    # the shipped model's identity (a population folder's hash) is the one it had before: old folders resume
    from meshmei.encoders.registry import encoder_identity

    assert encoder_identity(load_demo_model()) == old and encoder_identity(changed)["weights"] == encoder_spec(changed)["weights"]


def test_unknown_encoder_name_raises_mei_error():
    with pytest.raises(MEIError, match="unknown encoder 'gabor'; expected 'gabor-simple', 'gabor-complex' or 'demo'"):
        make_encoder("gabor", orientation=math.pi)
    # the demo model's keywords were dropped without a word (path= too: another file loaded the shipped one)
    with pytest.raises(MEIError, match=r"the demo encoder takes no parameters but path=..., got \['orientation'\]"):
        make_encoder("demo", orientation=math.pi)


# ---------------------------------------------------------------------------------------------- demo model

def test_demo_model_ships_small_with_its_correlations():
    path, model = shipped_demo()
    info = json.loads(path.with_suffix(".json").read_text())
    assert path.stat().st_size < 400_000
    assert model.n_neurons == info["n_neurons"] == len(info["test_correlation_with_ground_truth"])
    assert "SIMULATED" in info["what"] and not model.training
    assert float(model.preprocess.mean) == pytest.approx(info["training_mean"])
    assert info["mean_test_correlation_with_ground_truth"] >= 0.5
    assert make_encoder_demo_kind(model) == "demo"


def make_encoder_demo_kind(model):
    return encoder_spec(model)["kind"]


def test_demo_model_is_rebuilt_by_name():
    _, model = shipped_demo()
    assert is_demo_model(model) and is_demo_model(make_encoder("demo"))
    back = encoder_from_spec(encoder_spec(model))
    assert is_demo_model(back)
    x = torch.rand(2, 1, 32, 32)
    torch.testing.assert_close(back(x), model(x), rtol=0, atol=0)
