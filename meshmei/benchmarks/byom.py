"""Bring your own model (issue 17): what meshmei adds to a step against a lab-sized model's own cost.

Run: ``python -m meshmei.benchmarks.byom [--steps 30]``; writes the "byom" section of ``docs/benchmarks.md``.

The model is the size of the cores labs use for macaque V4: ResNet-50 up to ``layer3`` (1,024 channels,
stride 16, 3 input channels, batch norm in eval mode) with a Gaussian readout (neuralpredictors'
``FullGaussian2d`` when installed, else a point readout by ``grid_sample``) for 100 neurons, at 100 x 100
pixels, wrapped with :func:`meshmei.encoders.encoder_from_model` (statistics in 0-255 units). Weights are
random: only the cost matters here.

Measured in one process, alternating: (a) the model's own forward and backward on a ``(1, 3, 100, 100)``
image that requires a gradient (parameters frozen, as in a 3D-MEI step); (b) a 3D-MEI step with that model
(``optimize_mei``, sheet, default settings otherwise); and the parts of (b) meshmei owns, each on its own:
the RBF deformation, the render at 100 px, the regularizers (forward and backward), and the adapter's
preprocessing. meshmei's share is ``(b - a) / a``. Nothing is saved for an interrupted run to resume: its units
are timings in alternated rounds, and taking some from another run would mix two machine states in one table.
"""

from __future__ import annotations

import os
import time

import torch

from meshmei.benchmarks._report import benchmark_parser, machine_line, markdown_table, median, step_intervals, timings, write_section
from meshmei.encoders import encoder_from_model, frozen_encoder
from meshmei.mei import MEISettings, optimize_mei
from meshmei.mei.optimize import initial
from meshmei.mei.settings import make_deformer
from meshmei.regularizers import regularizer_values, scale_weights
from meshmei.render import render
from meshmei.render.native import native_status, torch_reference


class Bottleneck(torch.nn.Module):
    def __init__(self, cin, width, stride):
        super().__init__()
        cout = 4 * width
        self.body = torch.nn.Sequential(
            torch.nn.Conv2d(cin, width, 1, bias=False), torch.nn.BatchNorm2d(width), torch.nn.ReLU(inplace=True),
            torch.nn.Conv2d(width, width, 3, stride, 1, bias=False), torch.nn.BatchNorm2d(width),
            torch.nn.ReLU(inplace=True), torch.nn.Conv2d(width, cout, 1, bias=False), torch.nn.BatchNorm2d(cout))
        self.short = None
        if stride != 1 or cin != cout:
            self.short = torch.nn.Sequential(torch.nn.Conv2d(cin, cout, 1, stride, bias=False), torch.nn.BatchNorm2d(cout))

    def forward(self, x):
        return torch.relu(self.body(x) + (x if self.short is None else self.short(x)))


def resnet50_layer3() -> torch.nn.Sequential:
    """ResNet-50's stem and layers 1-3 (3, 4 and 6 bottlenecks; 1,024 output channels, stride 16)."""
    layers = [torch.nn.Conv2d(3, 64, 7, 2, 3, bias=False), torch.nn.BatchNorm2d(64), torch.nn.ReLU(inplace=True),
              torch.nn.MaxPool2d(3, 2, 1)]
    cin = 64
    for width, blocks, stride in ((64, 3, 1), (128, 4, 2), (256, 6, 2)):
        for b in range(blocks):
            layers.append(Bottleneck(cin, width, stride if b == 0 else 1))
            cin = 4 * width
    return torch.nn.Sequential(*layers)


class PointReadout(torch.nn.Module):
    def __init__(self, channels, n_neurons):
        super().__init__()
        self.mu = torch.nn.Parameter(0.5 * torch.rand(n_neurons, 2) - 0.25)
        self.features = torch.nn.Parameter(torch.randn(channels, n_neurons) / channels ** 0.5)

    def forward(self, x):
        grid = self.mu.unsqueeze(0).unsqueeze(2).expand(x.shape[0], -1, 1, 2)
        y = torch.nn.functional.grid_sample(x, grid, align_corners=True)[..., 0]
        return (y * self.features.unsqueeze(0)).sum(1)


class V4Model(torch.nn.Module):
    def __init__(self, n_neurons=100, size=100):
        super().__init__()
        self.core = resnet50_layer3()
        with torch.no_grad():
            shape = self.core(torch.zeros(1, 3, size, size)).shape[1:]
        try:
            from neuralpredictors.layers.readouts import FullGaussian2d

            self.readout = FullGaussian2d(tuple(shape), n_neurons, bias=True)
            self.readout_name = "FullGaussian2d (neuralpredictors)"
        except ImportError:
            self.readout = PointReadout(shape[0], n_neurons)
            self.readout_name = "point readout (grid_sample)"
        self.shape = tuple(shape)

    def forward(self, x):
        return torch.nn.functional.elu(self.readout(self.core(x))) + 1


# the same step with parts of valid steps off, measured in the same rounds: how much of meshmei's share they are;
# and with the renderer's torch code in place of its compiled kernels (meshmei.render.native)
VARIANTS = {"guard, no barriers": dict(barrier_weight=0.0, contact_weight=0.0),
            "valid steps off": dict(valid_steps=False, contact_weight=0.0),
            "renderer's torch code": None}


class NullModel(torch.nn.Module):
    """A model that costs next to nothing (a linear readout of each channel's mean): a step with it is
    meshmei's own part of a step, measured directly rather than as the difference of two noisy times."""

    def __init__(self, n_neurons=100):
        super().__init__()
        self.w = torch.nn.Parameter(torch.randn(3, n_neurons))

    def forward(self, x):
        return torch.nn.functional.elu(x.mean((2, 3)) @ self.w) + 1


def measure(steps: int = 40, repeats: int = 20, n_rounds: int = 5) -> dict:
    torch.manual_seed(0)
    model = V4Model().eval()
    enc = encoder_from_model(model, mean=124.5, std=70.3, channels=3, image_size=100, pixel_range=(0, 255))
    null = encoder_from_model(NullModel().eval(), mean=124.5, std=70.3, channels=3, image_size=100,
                              pixel_range=(0, 255))
    settings = MEISettings(steps=steps, seeds=(0,), image_size=100)
    V0, F, _ = initial("sheet", settings)
    rbf = make_deformer(V0, settings)
    weights = {k: w for k, w in scale_weights(settings.weights, settings.n_vertices, settings.reg_ref_vertices).items()
               if w > 0}
    img = torch.rand(1, 3, 100, 100, requires_grad=True)

    def model_only():
        img.grad = None
        model(img)[0, 7].backward()

    def deform():
        V = rbf()
        V.sum().backward()
        rbf.offsets.grad = None

    def draw():
        V = rbf().detach().requires_grad_()
        render(V, F, camera=settings.camera(), settings=settings.render_settings()).sum().backward()

    def regularize():
        V = rbf().detach().requires_grad_()
        sum(weights[k] * r for k, r in regularizer_values(V, V0, F, weights).items()).backward()

    x = torch.rand(1, 1, 100, 100, requires_grad=True)

    def preprocess():
        enc.preprocess(x).expand(-1, 3, -1, -1).sum().backward()

    def draw_torch():
        with torch_reference():
            draw()

    parts = {}
    with frozen_encoder(enc):
        for name, fn in (("model forward + backward", model_only), ("RBF deformation", deform),
                         ("render 100 px", draw), ("render 100 px, torch code", draw_torch),
                         ("regularizers", regularize), ("preprocessing", preprocess)):
            parts[name] = timings(fn, repeat=repeats)[0]
    def step_times(s, e=enc):
        d = step_intervals(optimize_mei(e, 7, "sheet", s).time_history, 3)
        return median(d), min(d)

    rounds, variants, direct = [], {name: [] for name in VARIANTS}, []
    for _ in range(n_rounds):  # alternate, so that all see the same machine state
        with frozen_encoder(enc):
            m_med, m_best = timings(model_only, repeat=repeats)
        s_med, s_best = step_times(settings)
        rounds.append((s_med, m_med, s_best, m_best))
        direct.append(step_times(settings, null)[0] / m_med)
        for name, kw in VARIANTS.items():
            if kw is None:
                with torch_reference():
                    variants[name].append(step_times(settings)[0] - m_med)
            else:
                variants[name].append(step_times(MEISettings.with_overrides(settings, kw))[0] - m_med)
    shares = sorted((s - m) / m for s, m, _, _ in rounds)
    best_shares = sorted((s - m) / m for _, _, s, m in rounds)
    step, m = median([r[0] for r in rounds]), median([r[1] for r in rounds])
    return {"parts": parts, "step": step, "model": m, "shares": shares, "best_shares": best_shares,
            "direct": sorted(direct),
            "variants": {k: median(v) for k, v in variants.items()},
            "readout": model.readout_name, "shape": model.shape}


def run(steps: int, rounds: int = 5):
    load = os.getloadavg()[0]
    r = measure(steps, n_rounds=rounds)
    shares = r["shares"]
    share = median(shares)
    rows = [[name, f"{1000 * t:.1f}"] for name, t in r["parts"].items()]
    rows.append(["3D-MEI step (everything)", f"{1000 * r['step']:.1f}"])
    rows.append(["meshmei's share: step - model", f"{1000 * (r['step'] - r['model']):.1f}"])
    for name, extra in r["variants"].items():
        rows.append([f"meshmei's share, {name}", f"{1000 * extra:.1f} ({100 * extra / r['model']:.0f} %)"])
    body = "\n".join([
        "## Bring your own model (`python -m meshmei.benchmarks.byom`)",
        "",
        f"Machine: {machine_line()}; 1-minute load average at the start {load:.1f}; "
        f"{torch.get_num_threads()} torch threads.",
        "",
        f"A ResNet-50 core up to layer3 (features {r['shape']}) with a {r['readout']} for 100 neurons, at "
        "100 x 100 px with 3 channels, statistics in 0-255 units (`encoder_from_model`). Median milliseconds; "
        "each part on its own (forward and backward), then a whole 3D-MEI step (sheet, 400 vertices, "
        "default settings), the model's own cost measured alternately with it in rounds of "
        f"{steps} steps; in the same rounds, the step with the guard's and contact barriers off, with "
        "valid steps off, and with the renderer's torch code in place of its compiled kernels (their share: "
        "step - model, median over rounds). Compiled kernels: "
        f"{'in use' if native_status()['compiled'] else 'not available (' + str(native_status()['reason']) + ')'}.",
        "",
        markdown_table(["part", "ms"], rows),
        "",
        f"meshmei's share of a step, (step - model) / model, per round, from median times: "
        f"{', '.join(f'{100 * x:.0f} %' for x in shares)}; median {100 * share:.0f} %. From each round's "
        f"best times (the least disturbed by other jobs on this shared machine): "
        f"{', '.join(f'{100 * x:.0f} %' for x in r['best_shares'])}; median {100 * median(r['best_shares']):.0f} %.",
        "",
        "Measured directly, as the time of the same step with a model that costs next to nothing (a linear "
        "readout of the channel means, the same adapter and statistics; its mesh follows another path) over "
        "the model's own time in the same round: "
        f"{', '.join(f'{100 * x:.0f} %' for x in r['direct'])}; median {100 * median(r['direct']):.0f} %.",
        "",
        f"Target (issue 17): meshmei's share at most 20 % of the model's forward and backward: "
        f"{'met' if share <= 0.20 else 'not met'} by step - model (median of {len(shares)} rounds: "
        f"{100 * share:.0f} %); measured directly, {100 * median(r['direct']):.0f} % "
        f"({'within' if median(r['direct']) <= 0.20 else 'above'} the target).",
    ])
    return write_section("byom", body)


def main(argv=None):
    ap = benchmark_parser(__file__, __doc__)
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--rounds", type=int, default=5, help="alternated rounds (the share is their median)")
    args = ap.parse_args(argv)
    t = time.perf_counter()
    print(f"wrote {run(args.steps, args.rounds)} in {time.perf_counter() - t:.0f} s")


if __name__ == "__main__":
    main()
