"""What tells two lab models apart (the fingerprint a population folder and a saved run are checked against),
and the model's side of the boundary: its dtype, its channels, the images it is given."""

from __future__ import annotations

import functools
import math
import os
import subprocess
import sys

import pytest
import torch

import meshmei
from meshmei.encoders import Encoder, Preprocess, encoder_from_model, encoder_identity, model_fingerprint
from meshmei.errors import EncoderError, MEIError
from meshmei.population.store import config_hash

SIZE = 16
MESHMEI_ROOT = os.path.dirname(os.path.dirname(meshmei.__file__))  # the meshmei under test, for subprocesses


def _weights(seed, n=4):
    return torch.randn(n, SIZE * SIZE, generator=torch.Generator().manual_seed(seed))


def _closure(seed):
    w = _weights(seed)
    return lambda x: x.flatten(1) @ w.T  # the weights live in the closure, not in a module


def _scaled(x, scale):
    return scale * x.flatten(1)[:, :3]


class Gain(torch.nn.Module):
    """A module whose plain attribute (not a parameter or buffer) changes its responses."""

    def __init__(self, g):
        super().__init__()
        self.g = g
        self.conv = torch.nn.Conv2d(1, 3, 3)
        with torch.no_grad():
            self.conv.weight.copy_(torch.linspace(-1, 1, 27).reshape(3, 1, 3, 3))
            self.conv.bias.zero_()

    def forward(self, x):
        return self.g * self.conv(x).mean((2, 3))


class Lin(Encoder):
    """A user's own Encoder subclass."""

    def __init__(self, seed):
        super().__init__(Preprocess(0.5, 0.2))
        self.w = torch.nn.Parameter(_weights(seed))

    @property
    def n_neurons(self):
        return 4

    def respond(self, z, idx):
        return (z.flatten(1) @ self.w.T).index_select(1, idx)


def _enc(model, **kw):
    return encoder_from_model(model, mean=0.5, std=0.2, image_size=SIZE, **kw)


def _two_heads(x):
    return x.flatten(1)[:, :3], -x.flatten(1)[:, :3]


def _kw_model(x, scale):
    return scale * x.flatten(1)[:, :3]


PAIRS = {  # two encoders that answer differently, in each way a review found them taken for one another
    "closure weights": lambda: (_enc(_closure(0)), _enc(_closure(1))),
    "partial argument": lambda: (_enc(functools.partial(_scaled, scale=1.0)), _enc(functools.partial(_scaled, scale=-1.0))),
    "module attribute": lambda: (_enc(Gain(1.0)), _enc(Gain(-1.0))),
    "custom encoder": lambda: (Lin(0), Lin(1)),
    "output picked": lambda: (_enc(_two_heads, output=0), _enc(_two_heads, output=1)),
    "tensor keyword": lambda: (_enc(_kw_model, forward_kwargs={"scale": torch.tensor(1.0)}),
                               _enc(_kw_model, forward_kwargs={"scale": torch.tensor(-1.0)})),
}


@pytest.mark.parametrize("case", list(PAIRS))
def test_encoders_that_answer_differently_have_different_identities_and_equal_ones_the_same(case):
    a, b = PAIRS[case]()
    a2, _ = PAIRS[case]()  # built again the same way: the same model
    x = torch.rand(2, 1, SIZE, SIZE, generator=torch.Generator().manual_seed(0))
    assert not torch.allclose(a(x), b(x))
    assert config_hash(encoder_identity(a)) != config_hash(encoder_identity(b))
    torch.testing.assert_close(a(x), a2(x), rtol=0, atol=0)
    assert config_hash(encoder_identity(a)) == config_hash(encoder_identity(a2))


class Recorder(torch.nn.Module):
    """A model that records as it runs: a list and a dict of what it saw, a private call counter."""

    def __init__(self):
        super().__init__()
        self.conv = torch.nn.Conv2d(1, 3, 3)
        self.seen, self.acts, self._calls = [], {}, 0

    def forward(self, x):
        self._calls += 1
        self.seen.append(tuple(x.shape))
        out = self.conv(x).mean((2, 3))
        self.acts["out"] = out.detach()
        return out


def test_what_a_model_records_as_it_runs_does_not_change_its_fingerprint():
    """Only settings count (numbers, strings, tuples of them): a fingerprint that moved with every forward would
    refuse to resume the model's own population folder."""
    torch.manual_seed(0)
    enc = _enc(Recorder())
    before = model_fingerprint(enc)
    for _ in range(3):
        enc(torch.rand(2, 1, SIZE, SIZE))
    assert model_fingerprint(enc) == before
    w = _weights(0)
    log = []

    def logged(x):  # a closure over its weights and a log it fills
        log.append(1)
        return x.flatten(1) @ w.T

    enc = _enc(logged)
    before = model_fingerprint(enc)
    enc(torch.rand(2, 1, SIZE, SIZE))
    assert model_fingerprint(enc) == before


def test_models_without_held_values_keep_the_fingerprint_they_had():
    """The fingerprint grew to cover held values; models that hold none (most) keep their old fingerprint, so
    their population folders resume: the values here are the fingerprints before the change."""
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Conv2d(1, 4, 3), torch.nn.ReLU(), torch.nn.AdaptiveAvgPool2d(1),
                              torch.nn.Flatten())
    assert model_fingerprint(_enc(net)) == "4dae3dcd64fbc24d"
    assert model_fingerprint(_enc(net, forward_kwargs={})) == "4dae3dcd64fbc24d"
    assert model_fingerprint(_enc([net, net])) == "7c1190be5c33aeb8"


def test_a_population_folder_refuses_another_model_with_the_same_code(tmp_path):
    """A closure over other weights resumed a folder and mixed its results into the table."""
    from meshmei.population.run import run_population

    kw = dict(steps=2, seeds=(0,), image_size=SIZE, n_vertices=64, pixel_steps=0, progress=False, batch_size=2)
    run_population(_enc(_closure(0)), [0], tmp_path / "pop", **kw)
    with pytest.raises(MEIError):
        run_population(_enc(_closure(1)), [0, 1], tmp_path / "pop", **kw)
    rows = run_population(_enc(_closure(0)), [0, 1], tmp_path / "pop", **kw)  # the same model resumes
    assert [r["neuron"] for r in rows] == [0, 1]


class Net(torch.nn.Module):
    def __init__(self, channels=1):
        super().__init__()
        torch.manual_seed(0)
        self.c = torch.nn.Conv2d(channels, 4, 3)

    def forward(self, x):
        return self.c(x).mean((2, 3))


def test_a_float64_run_feeds_a_float32_model_in_its_dtype_and_a_float64_model_is_taken():
    from meshmei.mei import optimize_mei

    enc = _enc(Net())
    x = torch.rand(2, 1, SIZE, SIZE, generator=torch.Generator().manual_seed(0))
    x64 = x.double().requires_grad_()
    out = enc(x64)
    assert out.dtype == torch.float64
    torch.testing.assert_close(out, enc(x).double(), rtol=1e-5, atol=1e-6)
    out.sum().backward()
    assert bool(torch.isfinite(x64.grad).all()) and float(x64.grad.abs().sum()) > 0
    res = optimize_mei(enc, 0, "sheet", steps=2, image_size=SIZE, seeds=(0,), n_vertices=64, dtype="float64")
    assert res.V.dtype == torch.float64 and math.isfinite(res.activation)
    torch.testing.assert_close(enc(res.render())[0, 0].double(), torch.tensor(res.activation, dtype=torch.float64),
                               rtol=1e-5, atol=1e-6)  # the reported response is the model's for the returned render
    enc64 = _enc(Net().double())  # refused at the probe before (float32 gray images)
    assert enc64(x).dtype == torch.float32
    torch.testing.assert_close(enc64(x), enc(x), rtol=1e-5, atol=1e-6)


class Inplace(torch.nn.Module):
    def __init__(self):
        super().__init__()
        torch.manual_seed(0)
        self.c = torch.nn.Conv2d(3, 4, 3)

    def forward(self, x):
        x = x.sub_(0.1)  # an in-place normalisation, as exported models do
        return self.c(x).mean((2, 3))


def test_a_three_channel_model_may_edit_its_input_in_place():
    enc = encoder_from_model(Inplace(), mean=0.5, std=0.2, image_size=SIZE, channels=3)
    x = torch.rand(2, 1, SIZE, SIZE, generator=torch.Generator().manual_seed(0))
    ref = Inplace()
    with torch.no_grad():
        want = ref(enc.preprocess(x).repeat(1, 3, 1, 1))
    torch.testing.assert_close(enc(x), want)


@pytest.mark.parametrize("dtype", [torch.int64, torch.bool, torch.uint8])
def test_images_that_are_not_float_are_refused_at_any_size(dtype):
    enc = _enc(Net())
    for size in (SIZE, 20):  # 20: resized first, which failed inside torch's interpolate
        with pytest.raises(EncoderError, match=r"^images must be a float tensor"):
            enc(torch.ones(2, 1, size, size).to(dtype))
    with pytest.raises(EncoderError, match=r"^images must have shape \(B, 1, H, W\) with B, H, W >= 1"):
        enc(torch.ones(2, 1, 0, 20))


def test_an_image_size_given_as_a_string_is_named_whole():
    with pytest.raises(EncoderError, match=r"^image_size must be an int or \(H, W\), got '16'$"):
        encoder_from_model(Net(), mean=0.5, std=0.2, image_size="16")


def test_functions_that_call_other_methods_have_other_fingerprints():
    """The same bytecode with another attribute name (relu against sigmoid) hashed alike: a population folder
    took the second model's neurons beside the first's."""
    def relu(x):
        return x.flatten(1)[:, :3].relu()

    def sigmoid(x):
        return x.flatten(1)[:, :3].sigmoid()

    sigmoid.__qualname__ = relu.__qualname__  # the same function name, as in two versions of one file
    a, b = (model_fingerprint(encoder_from_model(f, mean=0.5, std=0.2, image_size=8)) for f in (relu, sigmoid))
    assert a != b


_LAB_MODEL = '''
import torch


class Core(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.conv = torch.nn.Conv2d(1, 2, 3)

    def forward(self, x):
        return self.conv(x).relu()


class Readout(torch.nn.Module):
    def __init__(self, n):
        super().__init__()
        self.gain = 2.0
        self.lin = torch.nn.Linear(2 * 14 * 14, n)

    def forward(self, x):
        return self.gain * self.lin(x.flatten(1))


class Net(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.core, self.readout = Core(), Readout(3)

    def forward(self, x):
        return self.readout(self.core(x))


def plain(x, mode="sum"):
    # a comprehension, a lambda and a set literal: constants whose repr holds an address or a hash order
    cols = [x.flatten(1)[:, i] for i in range(3)]
    pick = (lambda c: c * 2.0) if mode in {"sum", "mean", "max"} else (lambda c: c)
    return torch.stack([pick(c) for c in cols], 1)


def fingerprints():
    from meshmei.encoders import encoder_from_model, model_fingerprint
    torch.manual_seed(0)
    a = model_fingerprint(encoder_from_model(Net(), mean=0.5, std=0.2, image_size=16))
    b = model_fingerprint(encoder_from_model(plain, mean=0.5, std=0.2, image_size=16))
    return a + " " + b
'''


def test_a_fingerprint_is_the_same_in_every_process(tmp_path):
    """The fingerprint of a model with several module classes of its own (a core and a readout), and of a
    function with a comprehension, a lambda and a set literal, is the same in fresh processes with other
    string hashing: it ordered the classes as a set (by address) and hashed code constants by their repr
    (a nested code object's holds its address), so the same command refused its own population folder."""
    (tmp_path / "labmodel.py").write_text(_LAB_MODEL)
    code = "import labmodel; print(labmodel.fingerprints())"
    seen = set()
    for seed in ("0", "1", "2", "3"):
        path = os.pathsep.join([str(tmp_path), MESHMEI_ROOT, os.environ.get("PYTHONPATH", "")])
        env = {**os.environ, "PYTHONHASHSEED": seed, "PYTHONPATH": path}
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env,
                             cwd=tmp_path)
        assert out.returncode == 0, out.stderr[-2000:]
        seen.add(out.stdout.strip().splitlines()[-1])
    assert len(seen) == 1, seen
