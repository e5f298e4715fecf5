"""Make the shipped demo model: a core + Gaussian readout fitted to *simulated* neurons on rendered meshes.

    python data_gen/make_demo_model.py [--n-images 6000] [--epochs 30] [--out meshmei/data/demo_model.pt]

1. Renders random smooth deformations of the sheet, sphere and torus with meshmei's own renderer, under
   random object rotations and random point-light positions on the forward hemisphere (64 x 64 pixels).
2. Computes the responses of a population of ground-truth model neurons on the preprocessed images
   (standardised with the data set's pixel mean / std, rescaled to norm 25): Gabor energy units (complex
   cells), Gabor simple cells, curvature units (the geometric mean of two Gabor energies at neighbouring
   positions and different orientations: a bent contour) and shading units (a centre-surround blob and a
   broad luminance gradient). Each ground-truth response goes through a softplus and gets Gaussian noise.
3. Trains a :class:`meshmei.encoders.CoreReadoutModel` (strided default core, Gaussian readout, ELU + 1)
   with a Poisson loss on 80 % of the images, and reports the Pearson correlation with the noise-free
   ground truth and with the noisy responses on the held-out 20 %.
4. Saves the weights (a few tens of KB) and a JSON with the correlations, the ground-truth definitions and
   the data-set statistics beside them.

This is a digital twin of simulated neurons, not of recorded V4 data.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from meshmei.encoders import CoreReadoutModel, DefaultCore, GaborComplexCell, GaborSimpleCell, Preprocess  # noqa: E402
from meshmei.mei import random_deformations  # noqa: E402
from meshmei.render import DEFAULT_DISTANCE, Camera, RenderSettings, axis_angle_to_matrix, render  # noqa: E402
from meshmei.shapes import initial_mesh  # noqa: E402

IMAGE_SIZE = 64
CORE = {"channels": 16, "kernel_sizes": [9, 5, 5], "strides": [2, 1, 1]}


def render_dataset(n_images: int, seed: int, batch: int = 50):
    """Random deformed meshes under random rotations and lights: images ``(N, 1, S, S)`` and meta data."""
    g = torch.Generator().manual_seed(seed)
    meshes = {k: initial_mesh(k, n_vertices=400) for k in ("sheet", "sphere", "torus")}
    st = RenderSettings(image_size=IMAGE_SIZE)
    cam = Camera()
    images, kinds = [], []
    for start in range(0, n_images, batch):
        b = min(batch, n_images - start)
        kind = ("sheet", "sphere", "torus")[(start // batch) % 3]
        V0, F = meshes[kind]
        Vb = random_deformations(V0, b, generator=g, n_bumps=5, amplitude=0.2, width=(0.08, 0.3))
        Vb = Vb * (0.7 + 0.6 * torch.rand(b, 1, 1, generator=g))  # random size
        aa = torch.randn(b, 3, generator=g) * 0.8  # random rotation, about 45 degrees rms
        R = axis_angle_to_matrix(aa)
        t = torch.cat([0.25 * torch.randn(b, 2, generator=g), torch.zeros(b, 1)], 1)
        # light on the forward hemisphere at the camera's distance
        az = 2 * math.pi * torch.rand(b, generator=g)
        el = torch.acos(torch.rand(b, generator=g))  # polar angle from +z, uniform over the hemisphere
        direction = torch.stack([torch.sin(el) * torch.cos(az), torch.sin(el) * torch.sin(az), torch.cos(el)], 1)
        light = DEFAULT_DISTANCE * direction
        with torch.no_grad():
            images.append(render(Vb, F, camera=cam, light=light, rotation=R, translation=t, settings=st))
        kinds += [kind] * b
    return torch.cat(images), kinds


def ground_truth_population():
    """Definitions of the simulated neurons (JSON-able) and a function computing their noise-free rates."""
    defs = []
    cx = [(-0.25, -0.2), (0.2, 0.25), (0.0, 0.0), (0.3, -0.1), (-0.15, 0.3), (0.05, -0.3)]
    for i, (x0, y0) in enumerate(cx):  # Gabor energy units
        defs.append({"type": "complex", "x0": x0, "y0": y0, "orientation": i * math.pi / 6,
                     "frequency": 4.0 + (i % 3), "sigma": 0.22})
    for i, (x0, y0) in enumerate([(0.0, 0.0), (-0.2, 0.1), (0.25, 0.2)]):  # simple cells
        defs.append({"type": "simple", "x0": x0, "y0": y0, "orientation": 0.4 + i, "frequency": 4.0,
                     "sigma": 0.25, "phase": i * math.pi / 2})
    for i, (x0, y0) in enumerate([(0.0, 0.0), (-0.2, -0.2), (0.2, 0.0), (0.0, 0.25)]):  # curvature units
        th = i * math.pi / 4
        d = 0.12
        defs.append({"type": "curvature", "x0": x0, "y0": y0, "orientation": th, "bend": math.pi / 3,
                     "offset": d, "frequency": 5.0, "sigma": 0.12})
    defs.append({"type": "blob", "x0": 0.0, "y0": 0.0, "sigma": 0.15})
    defs.append({"type": "gradient", "orientation": math.pi / 4, "sigma": 0.6})
    return defs


def _unit_filter(img):
    img = img - img.mean()
    return img / img.norm()


def make_rates(defs, S=IMAGE_SIZE):
    """A function ``z (B, 1, S, S) preprocessed -> noise-free rates (B, n)`` for the population ``defs``."""
    parts = []
    xs = (torch.arange(S, dtype=torch.float64) + 0.5) / S * 2 - 1
    Y, X = torch.meshgrid(xs, xs, indexing="ij")
    for d in defs:
        if d["type"] == "complex":
            cell = GaborComplexCell(x0=d["x0"], y0=d["y0"], orientation=d["orientation"], frequency=d["frequency"],
                                    sigma=d["sigma"])
            parts.append(lambda z, c=cell: 4.0 * c(z, preprocessed=True)[:, 0])
        elif d["type"] == "simple":
            cell = GaborSimpleCell(x0=d["x0"], y0=d["y0"], orientation=d["orientation"], frequency=d["frequency"],
                                   sigma=d["sigma"], phase=d["phase"])
            parts.append(lambda z, c=cell: 4.0 * c(z, preprocessed=True)[:, 0])
        elif d["type"] == "curvature":
            cells = []
            for sgn in (-1, 1):
                ang = d["orientation"] + sgn * d["bend"] / 2
                # the two arms sit on either side along the contour direction (perpendicular to the wave vector)
                px = d["x0"] + sgn * d["offset"] * -math.sin(d["orientation"])
                py = d["y0"] + sgn * d["offset"] * math.cos(d["orientation"])
                cells.append(GaborComplexCell(x0=px, y0=py, orientation=ang, frequency=d["frequency"], sigma=d["sigma"]))
            parts.append(lambda z, a=cells[0], b=cells[1]: 4.0 * torch.sqrt(
                a(z, preprocessed=True)[:, 0] * b(z, preprocessed=True)[:, 0] + 1e-12))
        elif d["type"] == "blob":
            r2 = (X - d["x0"]) ** 2 + (Y - d["y0"]) ** 2
            s = d["sigma"]
            dog = _unit_filter(torch.exp(-r2 / (2 * s * s)) - 0.5 * torch.exp(-r2 / (8 * s * s)))
            parts.append(lambda z, f=dog: 4.0 * (z[:, 0].double() * f).sum((1, 2)) / 25.0)
        elif d["type"] == "gradient":
            u = X * math.cos(d["orientation"]) - Y * math.sin(d["orientation"])
            f = _unit_filter(u * torch.exp(-(X**2 + Y**2) / (2 * d["sigma"] ** 2)))
            parts.append(lambda z, f=f: 4.0 * (z[:, 0].double() * f).sum((1, 2)) / 25.0)

    def rates(z):
        lin = torch.stack([p(z) for p in parts], 1).float()
        return torch.nn.functional.softplus(3.0 * (lin - 0.5)) / 3.0 * 4.0

    return rates


def pearson(a, b):
    a = a - a.mean(0)
    b = b - b.mean(0)
    return (a * b).sum(0) / (a.norm(dim=0) * b.norm(dim=0)).clamp_min(1e-12)


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n-images", type=int, default=6000)
    ap.add_argument("--epochs", type=int, default=30)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--noise", type=float, default=0.15, help="Gaussian noise std relative to each neuron's rate std")
    ap.add_argument("--out", default=str(ROOT / "meshmei" / "data" / "demo_model.pt"))
    return ap.parse_args(argv)


def fit(model, z, noisy, clean, train, test, epochs, g, t0):
    """Train ``model`` with a Poisson loss on the ``train`` images, reporting the test correlation every 5 epochs."""
    with torch.no_grad():  # start each readout where its neuron's input sits and at the right output level
        model.readout.bias.copy_(torch.log(noisy[train].mean(0)).clamp(-2, 2))
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, epochs)
    for epoch in range(epochs):
        model.train()
        order = train[torch.randperm(len(train), generator=g)]
        total = 0.0
        for i in range(0, len(order), 64):
            idx = order[i:i + 64]
            pred = model(z[idx], preprocessed=True)
            y = noisy[idx]
            loss = (pred - y * torch.log(pred + 1e-8)).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(idx)
        sched.step()
        if epoch % 5 == 4 or epoch == epochs - 1:
            model.eval()
            with torch.no_grad():
                pt = model(z[test], preprocessed=True)
            r = pearson(pt, clean[test])
            print(f"epoch {epoch + 1}: train loss {total / len(order):.4f}, test correlation with ground truth "
                  f"mean {float(r.mean()):.3f} min {float(r.min()):.3f} ({time.perf_counter() - t0:.0f} s)")
    return model.eval()


def save(model, out: Path, info: dict):
    """Write the weights (float32, the preprocessing statistics in float64) and ``info`` as JSON beside them."""
    out.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().clone().float() if v.is_floating_point() and k not in ("preprocess.mean", "preprocess.std")
             else v.detach().clone() for k, v in model.state_dict().items()}
    torch.save({"state_dict": state, "core": json.dumps(CORE)}, out)
    out.with_suffix(".json").write_text(json.dumps(info, indent=1))


def main(argv=None):
    args = parse_args(argv)
    torch.manual_seed(args.seed)
    t0 = time.perf_counter()
    images, kinds = render_dataset(args.n_images, args.seed)
    mean, std = float(images.mean()), float(images.std())
    pre = Preprocess(mean, std)
    z = pre(images)
    defs = ground_truth_population()
    with torch.no_grad():
        clean = make_rates(defs)(z)
    g = torch.Generator().manual_seed(args.seed + 1)
    noisy = (clean + args.noise * clean.std(0) * torch.randn(clean.shape, generator=g)).clamp_min(0)
    print(f"rendered {len(images)} images in {time.perf_counter() - t0:.1f} s; pixel mean {mean:.3f}, std {std:.3f}")
    perm = torch.randperm(len(images), generator=g)
    n_test = len(images) // 5
    test, train = perm[:n_test], perm[n_test:]
    n = clean.shape[1]
    model = fit(CoreReadoutModel(n, DefaultCore(**CORE), mean=mean, std=std), z, noisy, clean, train, test,
                args.epochs, g, t0)
    with torch.no_grad():
        pt = model(z[test], preprocessed=True)
    r_clean = pearson(pt, clean[test])
    r_noisy = pearson(pt, noisy[test])
    ceiling = pearson(clean[test], noisy[test])
    info = {
        "what": "core + Gaussian readout fitted to SIMULATED neurons (a digital twin of model neurons, not of "
                "recorded V4 data)",
        "script": "data_gen/make_demo_model.py",
        "arguments": vars(args),
        "image_size": IMAGE_SIZE,
        "n_images": {"train": len(train), "test": len(test)},
        "training_mean": mean,
        "training_std": std,
        "norm": pre.norm,
        "core": CORE,
        "n_neurons": n,
        "ground_truth": defs,
        "test_correlation_with_ground_truth": [round(float(x), 4) for x in r_clean],
        "test_correlation_with_noisy_responses": [round(float(x), 4) for x in r_noisy],
        "noise_ceiling_correlation": [round(float(x), 4) for x in ceiling],
        "mean_test_correlation_with_ground_truth": round(float(r_clean.mean()), 4),
        "seconds": round(time.perf_counter() - t0, 1),
        "torch": torch.__version__,
    }
    out = Path(args.out)
    save(model, out, info)
    print(f"wrote {out} ({out.stat().st_size / 1024:.0f} KB) and {out.with_suffix('.json').name}; "
          f"test correlation with ground truth per neuron: {[round(float(x), 2) for x in r_clean]}")


if __name__ == "__main__":
    main()
