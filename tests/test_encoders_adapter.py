"""A lab's own model as an encoder: models built the way the ecosystem builds them (neuralpredictors readouts,
multi-session data keys, ensembles, a 3-channel ResNet-style core, TorchScript, a Python factory), the
pixel-unit rule, eval mode, and clear errors before the first step."""

from __future__ import annotations

import json
import math
import textwrap
from pathlib import Path

import pytest
import torch

from meshmei.cli import main
from meshmei.encoders import (ModelEncoder, aspect_crop, encoder_from_model, encoder_spec, fit_to_size, frozen_encoder,
                              load_model)
from meshmei.errors import EncoderError, MEIError
from meshmei.mei import load_run, optimize_mei, pixel_mei
from meshmei.tuning import pose_sweep

try:
    from neuralpredictors.layers import readouts
except ImportError:  # without it only the tests of its readouts skip (a module-level importorskip skipped all)
    readouts = None
needs_neuralpredictors = pytest.mark.skipif(readouts is None, reason="neuralpredictors is not installed (the 'test' "
                                            "extra)")
pytestmark = pytest.mark.filterwarnings("ignore:Readout is NOT initialized with mean activity")

SMALL = dict(steps=3, seeds=(0,), n_vertices=100)


class Bottleneck(torch.nn.Module):
    """ResNet's bottleneck block (1x1, 3x3, 1x1 with a projected shortcut), as torchvision builds it."""

    def __init__(self, cin, width, cout, stride):
        super().__init__()
        self.body = torch.nn.Sequential(
            torch.nn.Conv2d(cin, width, 1, bias=False), torch.nn.BatchNorm2d(width), torch.nn.ReLU(),
            torch.nn.Conv2d(width, width, 3, stride, 1, bias=False), torch.nn.BatchNorm2d(width), torch.nn.ReLU(),
            torch.nn.Conv2d(width, cout, 1, bias=False), torch.nn.BatchNorm2d(cout))
        self.short = torch.nn.Sequential(torch.nn.Conv2d(cin, cout, 1, stride, bias=False), torch.nn.BatchNorm2d(cout))

    def forward(self, x):
        return torch.relu(self.body(x) + self.short(x))


if readouts is not None:  # models built from its readouts
    class ResNetV4(torch.nn.Module):
        """A small ResNet-style core on 3-channel 100 x 100 images with a Gaussian readout (an nnvision-like V4
        model), ELU + 1 output."""

        def __init__(self, n_neurons=6, width=8):
            super().__init__()
            self.core = torch.nn.Sequential(
                torch.nn.Conv2d(3, width, 7, 2, 3, bias=False), torch.nn.BatchNorm2d(width), torch.nn.ReLU(),
                torch.nn.MaxPool2d(3, 2, 1), Bottleneck(width, width, 4 * width, 1), Bottleneck(4 * width, width, 4 * width, 2))
            self.readout = readouts.FullGaussian2d((4 * width, 13, 13), n_neurons, bias=True)
            self.seen = []  # (training flag, input shape, whether all channels were equal) per call

        def forward(self, x):
            self.seen.append((self.training, tuple(x.shape), bool((x[:, :1] == x).all())))
            return torch.nn.functional.elu(self.readout(self.core(x))) + 1


    class MultiSession(torch.nn.Module):
        """One core, one Gaussian readout per recording session, picked by ``data_key`` (neuralpredictors style)."""

        class Readouts(readouts.MultiReadoutBase):
            _base_readout = readouts.FullGaussian2d

        def __init__(self):
            super().__init__()
            self.core = torch.nn.Sequential(torch.nn.Conv2d(1, 8, 5, 2, 2), torch.nn.ELU(), torch.nn.Conv2d(8, 8, 3, 2, 1))
            self.readout = self.Readouts({"s1": (8, 25, 25), "all_sessions": (8, 25, 25)},
                                         {"s1": 4, "all_sessions": 9}, bias=True)

        def forward(self, x, data_key=None):
            return torch.nn.functional.elu(self.readout(self.core(x), data_key=data_key)) + 1


def _seeded(cls, seed, *args):
    torch.manual_seed(seed)
    return cls(*args)


@needs_neuralpredictors
def test_a_multi_session_model_answers_for_the_session_its_data_key_names():
    model = _seeded(MultiSession, 0)
    enc = encoder_from_model(model, mean=124.5, std=70.3, pixel_range=(0, 255), forward_kwargs={"data_key": "all_sessions"})
    assert enc.n_neurons == 9  # the probe found the session's count
    x = torch.rand(2, 1, 100, 100)
    z = (255 * x - 124.5) / 70.3
    z = 25 * z / z.flatten(1).norm(dim=1).view(-1, 1, 1, 1)
    model.eval()
    with torch.no_grad():
        torch.testing.assert_close(enc(x, [2, 7]), model(z, data_key="all_sessions")[:, [2, 7]])
    s1 = encoder_from_model(model, mean=124.5, std=70.3, pixel_range=(0, 255), forward_kwargs={"data_key": "s1"})
    assert s1.n_neurons == 4
    res = optimize_mei(enc, 8, "sheet", **SMALL)
    assert res.image.shape == (1, 1, 100, 100) and math.isfinite(res.activation)


@needs_neuralpredictors
def test_an_ensemble_is_the_mean_of_its_members():
    members = [_seeded(MultiSession, s) for s in (1, 2, 3)]
    enc = encoder_from_model(members, mean=0.5, std=0.2, forward_kwargs={"data_key": "s1"})
    x = torch.rand(3, 1, 100, 100)
    z = enc.preprocess(x)
    for m in members:
        m.eval()
    with torch.no_grad():
        torch.testing.assert_close(enc(x), torch.stack([m(z, data_key="s1") for m in members]).mean(0))


@needs_neuralpredictors
def test_a_three_channel_resnet_core_at_100_px_runs_in_eval_mode_and_is_restored():
    model = _seeded(ResNetV4, 0)
    model.train()
    enc = encoder_from_model(model, mean=124.5, std=70.3, channels=3, image_size=100, pixel_range=(0, 255))
    model.seen.clear()
    res = optimize_mei(enc, 3, "sphere", **SMALL)
    assert res.image.shape == (1, 1, 100, 100)  # rendered at the model's size, not the default 64
    assert model.seen and all(not training for training, _, _ in model.seen)  # eval mode throughout
    assert all(shape[1:] == (3, 100, 100) and same for _, shape, same in model.seen)  # gray repeated into 3
    assert model.training and all(p.requires_grad for p in model.parameters())  # restored afterwards
    assert all(p.grad is None for p in model.parameters())  # and its parameters got no gradient
    pm = pixel_mei(enc, 3, steps=3, seeds=(0,))
    assert pm.image.shape == (1, 1, 100, 100) and math.isfinite(pm.activation)


def test_the_pixel_rule_maps_the_renderers_range_onto_the_models():
    enc = encoder_from_model(lambda x: x.flatten(1)[:, :4], mean=100.0, std=50.0, pixel_range=(0, 255), clip=True,
                             norm=None, image_size=8)
    x = torch.tensor([0.0, 0.5, 1.0, 1.4]).view(1, 1, 2, 2).expand(1, 1, 2, 2)
    pre = enc.preprocess
    torch.testing.assert_close(pre.standardise(x).flatten(), (torch.tensor([0.0, 127.5, 255.0, 255.0]) - 100) / 50)
    inside = x[..., :1, :]  # intensities 0 and 0.5, which the clip leaves alone
    torch.testing.assert_close(pre.to_image(pre(inside)), inside)
    normed = encoder_from_model(lambda x: x.flatten(1)[:, :4], mean=100.0, std=50.0, pixel_range=(0, 255), image_size=8)
    z = normed.preprocess(torch.rand(1, 1, 8, 8))
    for contrast in (0.5, 1.0):
        torch.testing.assert_close(normed.preprocess(normed.preprocess.to_image(z, contrast)), z)
    # norm=None keeps the standardised image: the response is the model on (p - mean) / std itself
    img = torch.full((1, 1, 8, 8), 0.5)
    torch.testing.assert_close(enc(img), torch.full((1, 4), (127.5 - 100) / 50))
    # another render size is resized to the model's (anti-aliased); a constant image stays constant
    torch.testing.assert_close(enc(torch.full((1, 1, 32, 32), 0.5)), enc(img))


class _Recording(torch.nn.Module):
    """Keeps the images it is given; responds with their mean (one neuron)."""

    def __init__(self):
        super().__init__()
        self._seen = []

    def forward(self, x):
        self._seen.append(x.detach().clone())
        return x.mean((1, 2, 3)).unsqueeze(1)


def test_a_wide_model_sees_a_centre_crop_of_the_square_render_not_a_stretched_one():
    # a 36 x 64 model (a mouse V1 digital twin's input) given a square image of a disc: it gets the middle 36
    # rows at full resolution, so the disc stays round (square pixels); stretched, it was 1.78x wider than tall
    model = _Recording()
    enc = encoder_from_model(model, mean=0.5, std=0.2, norm=None, image_size=(36, 64))
    yy, xx = torch.meshgrid(torch.arange(64) + 0.5, torch.arange(64) + 0.5, indexing="ij")
    disc = (((yy - 32) ** 2 + (xx - 32) ** 2) <= 12.0 ** 2).double()
    model._seen.clear()
    enc(disc.view(1, 1, 64, 64))
    seen = model._seen[-1][0, 0]
    assert seen.shape == (36, 64)
    torch.testing.assert_close(seen, (disc[14:50] - 0.5) / 0.2)  # exactly the middle rows, no resampling
    inside = seen > 0
    rows, cols = inside.any(1).nonzero().squeeze(1), inside.any(0).nonzero().squeeze(1)
    assert rows.numel() == cols.numel() == 24  # as tall as wide
    # an image of another aspect and size: cropped to the model's aspect first, then resized
    assert aspect_crop(100, 100, (36, 64)) == (22, 0, 56, 100)
    assert aspect_crop(30, 100, (36, 64)) == (0, 23, 30, 53)
    assert aspect_crop(64, 64, (64, 64)) == (0, 0, 64, 64)
    out = fit_to_size(torch.rand(2, 1, 100, 100, dtype=torch.float64), (36, 64))
    assert out.shape == (2, 1, 36, 64) and out.dtype == torch.float64
    # a 3D-MEI run renders at the model's longer side, and the model gets its own size
    model._seen.clear()
    res = optimize_mei(enc, 0, "sheet", **SMALL)
    assert res.settings.image_size == 64 and res.image.shape[-2:] == (64, 64)
    assert model._seen and all(x.shape[-2:] == (36, 64) for x in model._seen)


@needs_neuralpredictors
def test_outputs_are_picked_from_tuples_and_dicts():
    core = _seeded(MultiSession, 4)

    def as_tuple(x):
        return ("features", core(x, data_key="s1"))

    def as_dict(x):
        return {"responses": core(x, data_key="s1")}

    a = encoder_from_model(as_tuple, mean=0.5, std=0.2, output=1)
    b = encoder_from_model(as_dict, mean=0.5, std=0.2, output="responses")
    c = encoder_from_model(as_dict, mean=0.5, std=0.2, output=lambda out: out["responses"] * 2)
    x = torch.rand(2, 1, 100, 100)
    core.eval()
    with torch.no_grad():
        torch.testing.assert_close(a(x), b(x))
        torch.testing.assert_close(c(x), 2 * b(x))
    with pytest.raises(EncoderError, match="returned a tuple, not a tensor of responses"):
        encoder_from_model(as_tuple, mean=0.5, std=0.2)
    with pytest.raises(EncoderError, match="output='rates' cannot pick the response from a dict"):
        encoder_from_model(as_dict, mean=0.5, std=0.2, output="rates")


@pytest.mark.parametrize("model, message", [
    (lambda x: x.mean((2, 3)).unsqueeze(-1), r"shape \(B, N\); for a batch of 2 it returned \(2, 1, 1\)"),
    (lambda x: torch.full((1, 3), 1.0), r"returned \(1, 3\)"),
    (lambda x: torch.full((x.shape[0], 3), math.nan), "non-finite responses"),
    (lambda x: 1 / 0, "ZeroDivisionError"),
    (lambda x: torch.ones(x.shape[0], 2, dtype=torch.long), "float responses"),
    (lambda x: x.flatten(1)[:, :2].to_sparse(), "dense tensor of responses, got layout torch.sparse_coo"),
    (lambda x: torch.ones(x.shape[0], 2, device="meta"), "on device meta, its images were on cpu"),
    # every image of a batch answered with the first one's: a pose sweep gave one value for every condition
    (lambda x: x.flatten(1)[:1, :3].expand(x.shape[0], 3), "depend on the other images in its batch"),
])
def test_a_model_that_misbehaves_is_named_before_any_step(model, message):
    with pytest.raises(EncoderError, match=message):
        encoder_from_model(model, mean=0.5, std=0.2, image_size=16)


@pytest.mark.parametrize("model", [lambda x: x.flatten(1)[:, :2].detach(), lambda x: torch.ones(x.shape[0], 2)])
def test_a_model_whose_responses_carry_no_gradient_is_named_at_the_first_step(model):
    """Found by fuzzing: the pixel MEI's backward failed deep in torch, and a 3D-MEI climbed nothing."""
    enc = encoder_from_model(model, mean=0.5, std=0.2, image_size=16)
    with pytest.raises(EncoderError, match="carry no gradient back to the image"):
        pixel_mei(enc, 0, steps=2, seeds=(0,))
    with pytest.raises(EncoderError, match="carry no gradient back to the image"):
        optimize_mei(enc, 0, "sheet", **SMALL)
    with torch.no_grad():  # a sweep needs no gradient
        assert enc(torch.rand(1, 1, 16, 16), 0).shape == (1, 1)


@pytest.mark.parametrize("options", [dict(image_size=(10**9, 10**9)), dict(image_size=64, channels=10**9)])
def test_a_model_whose_images_cannot_be_allocated_is_named_before_any_step(options):
    """Found by fuzzing: the allocator's RuntimeError came out of the probe as a traceback."""
    with pytest.raises(EncoderError, match="do not fit in memory on cpu: check image_size and channels"):
        encoder_from_model(lambda x: x.flatten(1)[:, :2], mean=0.5, std=0.2, **options)


def test_bad_options_and_neurons_are_refused_before_the_first_step():
    ok = lambda x: x.flatten(1)[:, :3]  # noqa: E731
    for kwargs, message in [(dict(channels=0), "channels must be positive and finite, got 0"),
                            (dict(image_size=(16,)), "image_size must be an int or"),
                            (dict(pixel_range=(1, 1)), "hi > lo"),
                            (dict(std=0.0), "std must be positive and finite"),
                            (dict(forward_kwargs=["data_key"]), "forward_kwargs must be a dict")]:
        with pytest.raises(EncoderError, match=message):
            encoder_from_model(ok, **{"mean": 0.5, "std": 0.2, "image_size": 16, **kwargs})
    with pytest.raises(EncoderError, match="at least one model"):
        encoder_from_model([], mean=0.5, std=0.2)
    enc = encoder_from_model(ok, mean=0.5, std=0.2, image_size=16)
    with pytest.raises(MEIError, match=r"neuron index out of range for 3 neurons: got \[3\]"):
        optimize_mei(enc, 3, "sheet", **SMALL)


def _write_factory(tmp_path, body):
    path = tmp_path / "lab_model.py"
    path.write_text(textwrap.dedent(body))
    return path


FACTORY = """
    import torch

    class Model(torch.nn.Module):
        def __init__(self):
            super().__init__()
            torch.manual_seed(0)
            self.conv = torch.nn.Conv2d(3, 5, 9, stride=4)

        def forward(self, x, data_key=None):
            assert data_key == "all_sessions"
            return torch.nn.functional.elu(self.conv(x).mean((2, 3))) + 1

    def build():
        return {"model": Model(), "mean": 124.5, "std": 70.3, "channels": 3, "image_size": 40,
                "pixel_range": (0, 255)}

    def broken():
        raise RuntimeError("checkpoint not found")
"""


def test_the_cli_runs_a_python_factory_and_tune_reloads_it(tmp_path, capsys):
    path = _write_factory(tmp_path, FACTORY)
    out = tmp_path / "run"
    rc = main(["mei", "--model", f"{path}:build", "--data-key", "all_sessions", "--neuron", "4", "--out", str(out),
               "--steps", "3", "--seeds", "0", "--n-vertices", "100", "--quiet"])
    assert rc == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["encoder"]["kind"] == "model" and summary["encoder"]["n_neurons"] == 5
    assert summary["settings"]["image_size"] == 40  # the model's size
    run = load_run(out, rebuild_encoder=True)
    with torch.no_grad():
        again = float(run.encoder_module(run.image, run.neuron)[0, 0])
    assert again == pytest.approx(run.activation, rel=1e-5)
    rc = main(["tune", "pose", "--mei", str(out), "--out", str(tmp_path / "tune"), "--elevation=-5:5:3",
               "--azimuth=-5:5:3"])
    assert rc == 0 and (tmp_path / "tune").is_dir()


def test_the_cli_names_a_failing_factory_in_one_line(tmp_path, capsys):
    path = _write_factory(tmp_path, FACTORY)
    for spec, message in [(f"{path}:broken", "broken() failed: RuntimeError: checkpoint not found"),
                          (f"{path}:missing", "has no callable 'missing'"),
                          (str(tmp_path / "nope.ts"), "no model file at")]:
        rc = main(["mei", "--model", spec, "--out", str(tmp_path / "x"), "--steps", "1", "--quiet"])
        err = capsys.readouterr().err.strip()
        assert rc == 2 and message in err and "\n" not in err and "Traceback" not in err
    rc = main(["mei", "--model", f"{path}:build", "--neuron", "5", "--data-key", "all_sessions",
               "--out", str(tmp_path / "y"), "--steps", "1", "--quiet"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "neuron index out of range for 5 neurons" in err
    rc = main(["mei", "--mean", "3", "--out", str(tmp_path / "z"), "--steps", "1", "--quiet"])
    assert rc == 2 and "--mean applies to --model only" in capsys.readouterr().err
    for command in (["mei"], ["population", "--neurons", "0"]):  # --encoder was ignored without a word
        rc = main([*command, "--model", f"{path}:build", "--encoder", "demo", "--out", str(tmp_path / "w"),
                   "--steps", "1", "--quiet"])
        err = capsys.readouterr().err.strip()
        assert rc == 2 and err.endswith("--model and --encoder demo each name the model: give one of them")
        assert "\n" not in err and not (tmp_path / "w").exists()


class ScriptableV4(torch.nn.Module):
    """A 3-channel core with a point readout at learned positions (grid_sample), written so that
    ``torch.jit.script`` compiles it with a free batch size, as labs export models for deployment."""

    def __init__(self, n_neurons: int = 6):
        super().__init__()
        torch.manual_seed(2)
        self.core = torch.nn.Sequential(torch.nn.Conv2d(3, 8, 7, 4, 3), torch.nn.ELU(), torch.nn.Conv2d(8, 16, 3, 2, 1))
        self.mu = torch.nn.Parameter(0.5 * torch.rand(n_neurons, 2) - 0.25)
        self.features = torch.nn.Parameter(torch.randn(16, n_neurons) / 4)

    def forward(self, x):
        f = self.core(x)
        grid = self.mu.unsqueeze(0).unsqueeze(2).expand(x.shape[0], -1, 1, 2)
        y = torch.nn.functional.grid_sample(f, grid, align_corners=True)[..., 0]  # (B, C, N)
        return torch.nn.functional.elu((y * self.features.unsqueeze(0)).sum(1)) + 1


def test_a_torchscript_export_runs_from_the_cli_with_its_statistics(tmp_path, capsys):
    path = tmp_path / "v4.ts"
    torch.jit.script(ScriptableV4().eval()).save(str(path))
    with pytest.raises(EncoderError, match="needs its training statistics: give mean, std"):
        load_model(str(path))
    out = tmp_path / "run"
    rc = main(["mei", "--model", str(path), "--mean", "124.5", "--std", "70.3", "--channels", "3",
               "--pixel-range", "0,255", "--neuron", "2", "--out", str(out), "--steps", "2", "--seeds", "0",
               "--n-vertices", "100", "--image-size", "100", "--quiet"])
    assert rc == 0
    run = load_run(out, rebuild_encoder=True)
    assert isinstance(run.encoder_module, ModelEncoder) and run.encoder_module.n_neurons == 6
    spec = encoder_spec(run.encoder_module)
    assert spec["source"]["options"]["mean"] == 124.5 and spec["channels"] == 3
    with frozen_encoder(run.encoder_module), torch.no_grad():
        assert float(run.encoder_module(run.image, 2)[0, 0]) == pytest.approx(run.activation, rel=1e-5)


@needs_neuralpredictors
def test_a_model_run_sweeps_pose_like_a_built_in_cell():
    model = _seeded(MultiSession, 5)
    enc = encoder_from_model(model, mean=0.5, std=0.2, forward_kwargs={"data_key": "s1"}, image_size=48)
    res = optimize_mei(enc, 1, "sheet", **SMALL)
    sweep = pose_sweep(res, enc, elevation=[0.0], azimuth=[-5.0, 0.0, 5.0], roll=[0.0])
    r = torch.as_tensor(sweep.responses, dtype=torch.float64).flatten()
    # at the MEI's own pose the sweep gives back its response (as for the built-in cells), and the pose matters
    assert torch.isfinite(r).all() and float(r[1]) == pytest.approx(res.activation, rel=1e-5)
    assert float(r.max() - r.min()) > 0


def test_the_main_job_runs_on_a_labs_model(tmp_path):
    path = _write_factory(tmp_path, FACTORY)
    out = tmp_path / "demo"
    rc = main(["demo", "--quick", "--model", f"{path}:build", "--data-key", "all_sessions", "--neuron", "2",
               "--out", str(out)])
    assert rc == 0
    story = json.loads((out / "story.json").read_text())
    assert story["neuron"] == 2
    summary = json.loads((out / "mei" / "summary.json").read_text())
    assert summary["encoder"]["kind"] == "model" and summary["settings"]["image_size"] == 40
    assert (out / "summary.png").is_file()


class Normed(torch.nn.Module):
    """A conv, a batch norm and a pooled linear readout; records its training flags per call."""

    def __init__(self, n_neurons=3):
        super().__init__()
        torch.manual_seed(4)
        self.conv, self.bn = torch.nn.Conv2d(1, 4, 5, 4), torch.nn.BatchNorm2d(4)
        self.head = torch.nn.Linear(4, n_neurons)
        self.seen = []

    def forward(self, x, data_key=None):
        self.seen.append((self.training, self.bn.training))
        return self.head(torch.relu(self.bn(self.conv(x))).mean((2, 3)))


def _modes(model):
    return [m.training for m in model.modules()]


def test_the_models_own_modes_are_kept_and_restored_submodule_by_submodule():
    frozen_bn = Normed()
    frozen_bn.train()
    frozen_bn.bn.eval()  # a model fine-tuned with its batch norm frozen
    for model in (Normed().eval(), frozen_bn):
        before, stats = _modes(model), model.bn.running_mean.clone()
        enc = encoder_from_model(model, mean=0.5, std=0.2, image_size=32)
        assert _modes(model) == before  # wrapping changes no mode
        optimize_mei(enc, 1, "sheet", **SMALL, image_size=32)
        assert _modes(model) == before and torch.equal(model.bn.running_mean, stats)
        assert model.seen and all(seen == (False, False) for seen in model.seen)


def test_pose_and_light_sweeps_run_the_model_in_eval_mode():
    from meshmei.tuning import light_sweep

    model = Normed()
    enc = encoder_from_model(model, mean=0.5, std=0.2, image_size=32)
    res = optimize_mei(enc, 0, "sheet", **SMALL, image_size=32)
    model.train()
    model.seen.clear()
    stats = model.bn.running_mean.clone()
    pose_sweep(res, enc, elevation=[-5.0, 5.0], azimuth=[0.0])
    light_sweep(res, enc, elevation=[30.0], azimuth=[0.0, 90.0])
    assert model.seen and all(seen == (False, False) for seen in model.seen)
    assert model.training and torch.equal(model.bn.running_mean, stats)


@pytest.mark.parametrize("wrap", [lambda m: __import__("functools").partial(m, data_key="s1"),
                                  lambda m: m.forward, lambda m: (lambda x: m(x, data_key="s1"))],
                         ids=["partial", "bound-forward", "closure"])
def test_a_callable_that_holds_a_model_is_frozen_like_the_model(wrap):
    model = Normed().train()
    enc = encoder_from_model(wrap(model), mean=0.5, std=0.2, image_size=32)
    model.seen.clear()
    optimize_mei(enc, 2, "sheet", **SMALL, image_size=32)
    assert model.seen and all(seen == (False, False) for seen in model.seen)
    assert model.training and all(p.requires_grad and p.grad is None for p in model.parameters())


def test_wrong_shapes_and_failures_during_a_run_are_named():
    with pytest.raises(EncoderError, match=r"for a batch of 1 it returned \(3,\), expected \(1, 3\)"):
        encoder_from_model(lambda x: x.flatten(1)[:, :3].squeeze(), mean=0.5, std=0.2, image_size=16)
    calls = []

    def flaky(x):
        calls.append(1)
        if len(calls) > 4:
            raise RuntimeError("CUDA error: an illegal memory access\nmore detail")
        return x.flatten(1)[:, :3]

    enc = encoder_from_model(flaky, mean=0.5, std=0.2, image_size=16)
    with pytest.raises(EncoderError, match=r"the model failed on images of shape \(1, 1, 16, 16\) with no keyword "
                                           r"arguments: RuntimeError: CUDA error: an illegal memory access more detail"):
        optimize_mei(enc, 0, "sheet", **SMALL, image_size=16)
    with pytest.raises(EncoderError, match="the ensemble's models return different shapes"):
        encoder_from_model([lambda x: x.flatten(1)[:, :3], lambda x: x.flatten(1)[:, :4]], mean=0.5, std=0.2,
                           image_size=16)


FACTORIES = """
    import torch
    from helper_beside import make  # a module next to the factory

    def build():
        return {"model": make(), "mean": 0.5, "std": 0.2, "image_size": 24, "forward_kwargs": {"multiplex": False}}

    def unknown_key():
        return {"model": make(), "mean": 0.5, "std": 0.2, "data_key": "s1"}

    def bad_checkpoint():
        m = make()
        m.load_state_dict({"weight": torch.zeros(1)})
"""

HELPER = """
    import torch

    class Net(torch.nn.Module):
        def __init__(self):
            super().__init__()
            torch.manual_seed(3)
            self.lin = torch.nn.Linear(24 * 24, 4)

        def forward(self, x, multiplex=True, data_key=None):
            assert multiplex is False
            return self.lin(x.flatten(1)) + (0.0 if data_key is None else 1.0)

    def make():
        return Net()
"""


def test_a_factorys_dict_and_the_options_are_merged_and_checked(tmp_path):
    (tmp_path / "helper_beside.py").write_text(textwrap.dedent(HELPER))
    path = _write_factory(tmp_path, FACTORIES)
    enc = load_model(f"{path}:build", forward_kwargs={"data_key": "s1"}, norm=None)
    assert enc.forward_kwargs == {"multiplex": False, "data_key": "s1"}  # merged key by key
    assert not enc.preprocess.renorm  # norm=None: no rescaling, as encoder_from_model's
    for options, message in [(dict(mean=3.0), "sets mean=0.5 and the options give mean=3.0"),
                             (dict(image_size=32), "sets image_size=24 and the options give image_size=32"),
                             (dict(forward_kwargs={"multiplex": True}), "passes forward_kwargs"),
                             (dict(data_key="s1"), r"unknown adapter options \['data_key'\]")]:
        with pytest.raises(EncoderError, match=message):
            load_model(f"{path}:build", **options)
    assert load_model(f"{path}:build", image_size=24, mean=0.5).image_size == (24, 24)  # the same value: fine
    with pytest.raises(EncoderError, match=r"returned unknown keys \['data_key'\]"):
        load_model(f"{path}:unknown_key")
    with pytest.raises(EncoderError) as err:
        load_model(f"{path}:bad_checkpoint")
    assert "Missing key(s)" in str(err.value) and "\n" not in str(err.value)


def test_a_run_with_an_option_json_cannot_hold_is_saved_and_says_so(tmp_path):
    from meshmei.mei import save_run

    (tmp_path / "helper_beside.py").write_text(textwrap.dedent(HELPER))
    path = _write_factory(tmp_path, FACTORIES)
    enc = load_model(f"{path}:build", output=lambda out: out)  # an option JSON cannot hold
    res = optimize_mei(enc, 0, "sheet", **SMALL)
    save_run(res, tmp_path / "run", figures=False)
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["encoder"]["source"]["unrecorded"] == ["output"]
    with pytest.raises(MEIError, match=r"options that a run folder cannot record \(output\)"):
        load_run(tmp_path / "run", rebuild_encoder=True)
    assert load_run(tmp_path / "run", encoder=enc).activation == res.activation


def test_a_changed_model_is_told_apart_from_the_runs(tmp_path):
    from meshmei.encoders import model_fingerprint

    a, b = Normed(), Normed()
    ea = encoder_from_model(a, mean=0.5, std=0.2, image_size=32)
    assert model_fingerprint(ea) == model_fingerprint(encoder_from_model(b, mean=0.5, std=0.2, image_size=32))
    with torch.no_grad():
        b.head.bias[0] += 1e-6
    assert model_fingerprint(ea) != model_fingerprint(encoder_from_model(b, mean=0.5, std=0.2, image_size=32))
    path = _write_factory(tmp_path, FACTORY)
    out = tmp_path / "run"
    assert main(["mei", "--model", f"{path}:build", "--data-key", "all_sessions", "--out", str(out), "--steps", "2",
                 "--seeds", "0", "--n-vertices", "100", "--quiet"]) == 0
    path.write_text(path.read_text().replace("torch.manual_seed(0)", "torch.manual_seed(1)"))
    with pytest.raises(MEIError, match="is not the run's any more"):
        load_run(out, rebuild_encoder=True)


def test_the_cli_gives_a_torchscript_model_its_input_size_and_the_pixel_mei_its_size(tmp_path, capsys):
    path = tmp_path / "fixed.ts"
    torch.manual_seed(0)
    torch.jit.script(torch.nn.Sequential(torch.nn.Flatten(), torch.nn.Linear(32 * 32, 3))).save(str(path))
    out = tmp_path / "run"
    rc = main(["mei", "--model", str(path), "--mean", "0.5", "--std", "0.2", "--image-size", "32", "--pixel-mei",
               "--out", str(out), "--steps", "2", "--seeds", "0", "--n-vertices", "100", "--quiet"])
    assert rc == 0, capsys.readouterr().err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["settings"]["image_size"] == 32 and summary["encoder"]["image_size"] == [32, 32]
    assert math.isfinite(summary["pixel_mei_activation"])
    rc = main(["mei", "--model", str(path), "--mean", "0.5", "--std", "0.2", "--out", str(tmp_path / "other"),
               "--steps", "1", "--quiet"])  # at the default 100 the model cannot run: one line, code 2
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "mat1 and mat2 shapes cannot be multiplied" in err and "\n" not in err


def test_a_model_that_turns_nan_during_a_run_is_blamed_not_the_learning_rate():
    calls = []

    def unstable(x):
        calls.append(1)
        out = x.flatten(1)[:, :3].clone()
        return out if len(calls) <= 4 else out * math.nan

    enc = encoder_from_model(unstable, mean=0.5, std=0.2, image_size=16)
    with pytest.raises(EncoderError, match=r"returned non-finite responses to finite images of shape \(1, 1, 16, 16\)"):
        optimize_mei(enc, 0, "sheet", **SMALL, image_size=16)


def test_statistics_beyond_float32_are_named_and_large_pixel_values_keep_their_images_apart():
    # the squared norm of images standardised by std 1e-20 overflowed float32: every image was rescaled by
    # norm / inf = 0, the model saw zeros, and every image got the same response
    def model(x):
        return x.flatten(1)[:, :4] * torch.arange(1.0, 5.0)

    enc = encoder_from_model(model, mean=0.5, std=1e-20, image_size=8)
    x = torch.rand(2, 1, 8, 8, generator=torch.Generator().manual_seed(0))
    z = enc.preprocess(x)
    assert bool(torch.isfinite(z).all())
    torch.testing.assert_close(z.flatten(1).norm(dim=1), torch.full((2,), enc.preprocess.norm))
    torch.testing.assert_close(z, encoder_from_model(model, mean=0.5, std=1.0, image_size=8).preprocess(x))  # scale-free
    with pytest.raises(EncoderError, match="a gray image is not finite after preprocessing .* do not fit in"):
        encoder_from_model(model, mean=0.5, std=1e-300, image_size=8)


def test_a_model_that_edits_its_input_in_place_leaves_the_callers_images_alone():
    # one channel: the model got the caller's tensor, and the pixel MEI's leaf failed in torch's autograd
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.ReLU(inplace=True), torch.nn.Flatten(), torch.nn.Linear(256, 3))
    enc = encoder_from_model(net, mean=0.5, std=0.2, image_size=16)
    z = torch.randn(2, 1, 16, 16, generator=torch.Generator().manual_seed(1))
    kept = z.clone()
    enc(z, preprocessed=True)
    assert torch.equal(z, kept)
    pm = pixel_mei(enc, 1, steps=3, seeds=(0,))
    torch.testing.assert_close(enc(pm.image, 1, preprocessed=True)[0, 0], torch.tensor(pm.activation))


def test_option_types_a_caller_might_pass_are_taken_or_named(tmp_path):
    # found by fuzzing: clip="no" clipped, output=True picked a tuple's element 1, np.int64(16) was refused as a
    # size and a dict's keys were taken as one, and load_model(Path) was an AttributeError
    import numpy as np

    from meshmei.encoders import load_model

    def model(x):
        return x.flatten(1)[:, :3]

    a = encoder_from_model(model, mean=0.5, std=0.2, image_size=np.int64(16))
    assert a.image_size == (16, 16)
    for options, says in ((dict(clip="no"), "clip must be True or False"),
                          (dict(output=True), "output must be None, an index, a key or a callable"),
                          (dict(image_size={16: 0, 20: 1}), "image_size must be an int or"),
                          (dict(image_size={16, 20}), "image_size must be an int or")):
        with pytest.raises(EncoderError, match=says):
            encoder_from_model(model, mean=0.5, std=0.2, **options)
    factory = tmp_path / "m.py"
    factory.write_text("def build():\n    return {'model': lambda x: x.flatten(1)[:, :3], 'mean': 0.5, 'std': 0.2, "
                       "'image_size': 16}\n")
    assert load_model(f"{factory}:build").image_size == load_model(Path(f"{factory}:build")).image_size == (16, 16)
    with pytest.raises(EncoderError, match="a model spec is"):
        load_model(None)
    with pytest.raises(EncoderError, match=r"image_size must be the model's input size \(16, 16\)"):
        pixel_mei(a, 0, image_size=(15, 9), steps=2, seeds=(0,))  # failed at its first step, naming no option


def test_an_ensemble_of_members_in_different_dtypes_is_named():
    # its members were all fed the first one's dtype: torch's "expected ... but found Double"
    def member(dtype):
        torch.manual_seed(0)
        return torch.nn.Sequential(torch.nn.Flatten(), torch.nn.Linear(256, 3)).to(dtype)

    with pytest.raises(EncoderError, match=r"members hold weights of different dtypes \(float32, float64\)"):
        encoder_from_model([member(torch.float32), member(torch.float64)], mean=0.5, std=0.2, image_size=16)
    both = encoder_from_model([member(torch.float64), member(torch.float64)], mean=0.5, std=0.2, image_size=16)
    assert both.n_neurons == 3
