"""Diverse 3D-MEIs: K members of one neuron pushed apart in image space under a floor on their response."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

from meshmei.encoders import GaborComplexCell, GaborSimpleCell
from meshmei.errors import MEIError
from meshmei.mei import diverse_meis

SMALL = dict(steps=120, image_size=32, n_vertices=120)


def _circular_gaps(phases):
    p = sorted(x % (2 * math.pi) for x in phases)
    return [b - a for a, b in zip(p, p[1:])] + [p[0] + 2 * math.pi - p[-1]]


def test_a_complex_cells_members_span_distinct_phases():
    """The complex cell is phase-invariant: its diverse members take phases spread over the circle, each
    keeping most of the best member's response, and are further apart than undriven runs."""
    cell = GaborComplexCell()
    d = diverse_meis(cell, 0, k=3, diversity=0.5, **SMALL)
    plain = diverse_meis(cell, 0, k=3, diversity=0.0, **SMALL)
    phases = [float(cell.phase_of(r.image)[0]) for r in d.results]
    assert min(_circular_gaps(phases)) > 0.5, phases
    assert min(d.responses) >= 0.8 * max(d.responses)
    off = ~torch.eye(3, dtype=torch.bool)
    assert float(d.dissimilarity[off].mean()) > float(plain.dissimilarity[off].mean())
    for r in d.results:  # each member is a complete result
        torch.testing.assert_close(r.render(), r.image)


def test_a_simple_cells_members_stay_near_its_one_optimum():
    cell = GaborSimpleCell()
    d = diverse_meis(cell, 0, k=3, diversity=0.5, floor=0.8, **SMALL)
    best = max(d.responses)
    assert min(d.responses) >= 0.8 * best and best >= 0.85 * cell.upper_bound  # none drifted off the optimum


def test_no_diversity_and_no_floor_are_independent_runs_even_below_zero():
    """The floor used |best|: where every response was negative (a sphere's start), every member paid
    10 |best| (floor + 1)^2, even with floor 0, and the members were not the independent runs promised."""
    from meshmei.mei import optimize_mei

    cell = GaborSimpleCell(orientation=0.5, frequency=3.0)
    kw = dict(steps=15, image_size=32, n_vertices=100, dtype="float64", seeds=(0,))
    d = diverse_meis(cell, 0, k=np.int64(2), init="sphere", diversity=0.0, floor=0.0, **kw)  # numpy's int: refused
    assert len(d.results) == 2 and max(r.history[0] for r in d.results) < 0  # the case that went wrong: no positive response yet
    for member in d.results:
        alone = optimize_mei(cell, 0, "sphere", keep="last", **{**kw, "seeds": (member.seed,)})
        torch.testing.assert_close(member.V, alone.V, rtol=1e-9, atol=1e-9)
        assert member.loss_history[0] == pytest.approx(alone.loss_history[0], rel=1e-12)


def test_an_encoder_that_does_not_rescale_its_images_measures_distances_as_a_share_too():
    from meshmei.encoders import encoder_from_model
    from meshmei.mei.diverse import image_distances

    cell = GaborSimpleCell(orientation=0.4, frequency=3.0)
    enc = encoder_from_model(lambda x: cell(x, preprocessed=True) * 50, mean=0.5, std=0.01, norm=None, image_size=32)
    d = diverse_meis(enc, 0, k=3, init="sheet", steps=8, seeds=(0,), n_vertices=100)
    z = torch.cat([enc.preprocess(r.image) for r in d.results])
    assert float(z[0].norm()) > 100  # far from the norm of 25 the share was taken against (9.5 to 12.7 came out)
    sizes = z.reshape(3, -1).norm(dim=1)
    share = torch.cdist(z.reshape(3, -1), z.reshape(3, -1)) / (sizes[:, None] + sizes[None, :])
    torch.testing.assert_close(d.dissimilarity, share)
    assert 0 < float(d.dissimilarity.max()) <= 1 and torch.equal(image_distances(enc, z), d.dissimilarity)


def test_bad_diverse_settings_are_refused():
    with pytest.raises(MEIError, match="k must be"):
        diverse_meis(GaborSimpleCell(), 0, k=1, steps=2)
    with pytest.raises(MEIError, match="floor"):
        diverse_meis(GaborSimpleCell(), 0, k=2, floor=1.5, steps=2)
    for robust in (dict(robust_pose=10.0), dict(robust_light=5.0)):  # not silently dropped
        with pytest.raises(MEIError, match="robust"):
            diverse_meis(GaborSimpleCell(), 0, k=2, steps=2, **robust)


def test_the_cli_refuses_diverse_and_robust_together_in_one_line(tmp_path, capsys):
    from meshmei.cli import main

    rc = main(["mei", "--encoder", "gabor-simple", "--diverse", "2", "--robust-pose", "10", "--steps", "2",
               "--out", str(tmp_path / "x"), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "robust" in err and len(err.splitlines()) == 1


def test_the_cli_writes_the_members_and_tune_sweeps_each(tmp_path, capsys):
    """meshmei mei --diverse 2 writes member_0, member_1, diversity.json and diverse.png; meshmei tune on
    that folder sweeps every member into its own folder, and each member's response is its summary's."""
    import json

    from meshmei.cli import main

    out = tmp_path / "div"
    assert main(["mei", "--encoder", "gabor-complex", "--diverse", "2", "--steps", "3", "--image-size", "16",
                 "--n-vertices", "40", "--out", str(out), "--quiet"]) == 0
    d = json.loads((out / "diversity.json").read_text())
    assert len(d["responses"]) == 2 and (out / "diverse.png").is_file()
    # the set's own settings are recorded, and each member says how it ran: its own seed, its last iterate
    # (members said keep='best' and seeds=(0,), and nothing recorded K, the reward or the floor)
    assert (d["k"], d["seeds"], d["diversity"], d["floor"]) == (2, [0, 1], 0.5, 0.8)
    clean = 0
    for i, r in enumerate(d["responses"]):
        summary = json.loads((out / f"member_{i}" / "summary.json").read_text())
        assert summary["activation"] == pytest.approx(r, rel=1e-6)
        assert summary["settings"]["seeds"] == [i] and summary["settings"]["keep"] == "last"
        assert summary["diverse"]["member"] == i
        clean += summary["quality"]["self_intersections"] == 0 and summary["quality"]["flipped_faces"] == 0
    assert f"{clean} of 2 free of self-intersections and flipped faces" in capsys.readouterr().out  # its health
    assert main(["tune", "pose", "--mei", str(out), "--elevation", "0:0:1", "--azimuth=-10:10:3"]) == 0
    for i in range(2):
        assert (out / f"member_{i}" / "tuning_pose").is_dir()
    assert capsys.readouterr().out.count("pose sweep, neuron 0") == 2


def test_overwriting_a_diverse_set_leaves_no_member_of_the_old_one(tmp_path, capsys):
    import json

    from meshmei.cli import main

    out, common = tmp_path / "div", ["--encoder", "gabor-complex", "--steps", "2", "--image-size", "16",
                                     "--n-vertices", "40", "--quiet"]
    assert main(["mei", "--diverse", "3", "--out", str(out), *common]) == 0
    assert main(["mei", "--diverse", "2", "--out", str(out), "--overwrite", "--seeds", "7", *common]) == 0
    assert sorted(p.name for p in out.glob("member_*")) == ["member_0", "member_1"]  # member_2 is gone
    assert len(json.loads((out / "diversity.json").read_text())["responses"]) == 2
    for member in ("member_0", "member_1"):  # saved without a graph (it made the sweep below warn)
        state = torch.load(out / member / "state.pt", weights_only=True)
        assert not any(v.requires_grad for v in state.values() if isinstance(v, torch.Tensor))
    capsys.readouterr()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the UserWarning of a scalar taken from a tensor with a graph
        assert main(["tune", "pose", "--mei", str(out), "--elevation", "0:0:1", "--azimuth", "0:0:1"]) == 0
    assert capsys.readouterr().out.count("pose sweep, neuron 0") == 2
    for k in ("0", "-3", "1025", "1" + "0" * 400):  # 10**400 had grown a list of seeds until memory ran out
        assert main(["mei", "--diverse", k, "--out", str(tmp_path / f"d{len(k)}{k[0]}"), *common]) == 2
        err = capsys.readouterr().err
        assert "--diverse K needs 1 <= K <= 1024" in err and len(err.splitlines()) == 1
        assert not (tmp_path / f"d{len(k)}{k[0]}").exists()
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "diversity.json").write_text("{}")
    assert main(["tune", "pose", "--mei", str(empty)]) == 2
    assert "diversity.json is damaged" in capsys.readouterr().err


def test_the_cli_adds_the_pixel_mei_to_a_diverse_set(tmp_path, capsys):
    """--diverse K --pixel-mei ran no pixel MEI (the option was silently dropped); now one baseline for the
    neuron, printed and recorded with every member and in diversity.json."""
    import json

    from meshmei.cli import main

    out = tmp_path / "div"
    assert main(["mei", "--encoder", "gabor-complex", "--diverse", "2", "--steps", "2", "--image-size", "16",
                 "--n-vertices", "40", "--out", str(out), "--quiet", "--pixel-mei"]) == 0
    pm = json.loads((out / "diversity.json").read_text())["pixel_mei_activation"]
    assert pm > 0.9  # the pixel MEI of a complex cell nearly reaches its bound of 1
    for i in range(2):
        assert json.loads((out / f"member_{i}" / "summary.json").read_text())["pixel_mei_activation"] == pm
    assert f"pixel MEI {pm:.4f}" in capsys.readouterr().out


def test_members_seeds_past_the_seed_range_are_refused_before_any_work(monkeypatch):
    """The members run seeds s, s+1, ...: from 2**32 - 1, the second member's 2**32 is seed 0 to torch's CPU
    generator (it keeps a seed's low 32 bits), a run that seeds (0,) gives too."""
    from meshmei.mei import diverse

    monkeypatch.setattr(diverse, "initial", lambda *a: pytest.fail("the start was built"))
    with pytest.raises(MEIError, match=r"^the members' seeds 4294967295\.\.4294967296 \(the first of seeds, then one "
                                       r"more each\) must lie in \[0, 4294967295\], the seeds of distinct runs; start "
                                       r"from a seed of at most 4294967294$"):
        diverse_meis(GaborSimpleCell(), 0, k=2, seeds=(2 ** 32 - 1,), **SMALL)
