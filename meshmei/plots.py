"""Figures for tuning sweeps and MEI runs (matplotlib, written as PNG and PDF)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["plot_pose_heatmap", "plot_light_polar", "summary_sheet"]


def _mpl():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, stem: Path):
    stem = Path(stem)
    paths = []
    for ext in (".png", ".pdf"):
        p = stem.with_suffix(ext)
        fig.savefig(p, dpi=120, bbox_inches="tight")
        paths.append(p)
    _mpl().close(fig)
    return paths


def _edges(v):
    """Cell edges for pcolormesh from cell centres."""
    v = np.asarray(v, dtype=np.float64)
    if len(v) == 1:
        return np.array([v[0] - 0.5, v[0] + 0.5])
    mid = (v[1:] + v[:-1]) / 2
    return np.concatenate([[2 * v[0] - mid[0]], mid, [2 * v[-1] - mid[-1]]])


def plot_pose_heatmap(sweep, neuron: int, stem) -> list[Path]:
    """Azimuth x elevation heatmap of one neuron's responses, the original view marked (roll averaged out)."""
    plt = _mpl()
    r = sweep.of(neuron)
    if r.ndim == 3:  # a roll axis: show its mean, and the roll curve beside it
        fig, (ax, ax2) = plt.subplots(1, 2, figsize=(10, 4.2))
        roll = sweep.axis("roll")
        curve = r.mean(axis=(0, 1))
        ax2.plot(roll, curve, "o-", ms=3)
        ax2.set_xlabel("roll (deg)")
        ax2.set_ylabel("response (mean over the pose grid)")
        ax2.set_title("in-plane rotation")
        r = r.mean(axis=2)
    else:
        fig, ax = plt.subplots(figsize=(5.4, 4.2))
    az, el = sweep.axis("azimuth"), sweep.axis("elevation")
    m = ax.pcolormesh(_edges(az), _edges(el), r, shading="flat", cmap="viridis")
    fig.colorbar(m, ax=ax, label="response")
    ax.plot([0], [0], marker="x", color="w", ms=10, mew=2, label="original view")
    best = sweep.argmax(neuron)
    ax.plot([best["azimuth"]], [best["elevation"]], marker="o", mfc="none", mec="r", ms=10, mew=2, label="maximum")
    ax.set_xlabel("azimuth (deg)")
    ax.set_ylabel("elevation (deg)")
    ax.set_title(f"pose tuning, neuron {neuron}")
    ax.legend(loc="lower right", fontsize=7)
    return _save(fig, stem)


def plot_light_polar(sweep, neuron: int, stem, images: dict | None = None) -> list[Path]:
    """Polar heatmap over the light hemisphere (centre: light at the camera's axis; rim: grazing),
    with the example renders of the high, mid and low response groups when ``images`` is given."""
    plt = _mpl()
    r = sweep.of(neuron)
    az, el = sweep.axis("azimuth"), sweep.axis("elevation")
    ncol = 1 + (3 if images else 0)
    fig = plt.figure(figsize=(5.0 + 2.6 * (ncol - 1), 4.4), layout="constrained")
    ax = fig.add_subplot(1, ncol, 1, projection="polar")
    theta = np.radians(_edges(az))
    rad = 90.0 - np.clip(_edges(el), 0.0, 90.0)  # radius: angle away from the camera axis
    m = ax.pcolormesh(theta, rad, r, shading="flat", cmap="magma")
    ax.set_ylim(0, 90)
    ax.set_yticks([30, 60, 90])
    ax.set_yticklabels(["el 60", "el 30", "el 0"], fontsize=7)
    fig.colorbar(m, ax=ax, label="response", pad=0.1, shrink=0.8)
    ax.set_title(f"light tuning, neuron {neuron}\n(azimuth 0 = light from image right)", fontsize=9)
    if images:
        for k, label in enumerate(("high", "mid", "low")):
            img, ex = images[label]
            a = fig.add_subplot(1, ncol, 2 + k)
            a.imshow(img, cmap="gray", vmin=0, vmax=1)
            a.set_title(f"{label}: az {ex['azimuth']:.0f}, el {ex['elevation']:.0f}\nresponse {ex['response']:.3f}", fontsize=8)
            a.axis("off")
            ax.plot([np.radians(ex["azimuth"])], [90 - ex["elevation"]], "o", mfc="none", mec="c", ms=8)
    return _save(fig, stem)


def summary_sheet(run, stem, *, pixel_image=None, pixel_activation=None, views=((45, 20), (90, 0), (-45, -30))) -> list[Path]:
    """One page for an MEI run: the rendered MEI, three 3D views of the mesh, the activation curve, the
    pixel MEI and the activation bars (3D-MEI versus pixel MEI)."""
    import torch

    from .tuning import pose_rotations

    plt = _mpl()
    fig = plt.figure(figsize=(13, 6.2))
    gs = fig.add_gridspec(2, 4)
    ax = fig.add_subplot(gs[0, 0])
    ax.imshow(run.image[0, 0].cpu().numpy(), cmap="gray", vmin=0, vmax=1)
    ax.set_title(f"3D-MEI render\nneuron {run.neuron}, response {run.activation:.3f}", fontsize=9)
    ax.axis("off")
    import math

    from .render import Camera

    scene = run.scene()
    base = scene["rotation"]
    # frame the whole mesh: camera distance from its bounding sphere and the field of view, light at the camera
    cam = scene["camera"]
    radius = float((run.V - run.V.mean(0)).norm(dim=1).max())
    half = math.radians(cam.fov_degrees) / 2
    dist = max(float(torch.as_tensor(cam.eye).reshape(-1, 3)[0].norm()), 1.15 * radius / math.sin(half))
    view_cam = Camera(eye=(0.0, 0.0, dist), fov_degrees=cam.fov_degrees, znear=cam.znear, zfar=max(cam.zfar, 4 * dist))
    light = torch.tensor([0.0, 0.0, dist], dtype=run.V.dtype)
    for k, (azi, ele) in enumerate(views):
        R = pose_rotations([ele], [azi], dtype=run.V.dtype).reshape(3, 3) @ base.to(run.V.dtype)
        with torch.no_grad():
            img = run.render(rotation=R[None], camera=view_cam, light=light, translation=-(run.V.mean(0) @ R.T))
        a = fig.add_subplot(gs[0, 1 + k])
        a.imshow(img[0, 0].cpu().numpy(), cmap="gray", vmin=0, vmax=1)
        a.set_title(f"mesh, azimuth {azi}, elevation {ele}", fontsize=9)
        a.axis("off")
    a = fig.add_subplot(gs[1, 0:2])
    a.plot(np.arange(1, len(run.history) + 1), run.history, lw=1.5)
    a.set_xlabel("step")
    a.set_ylabel("response")
    a.set_title(f"activation during optimisation (seed {run.seed})", fontsize=9)
    if pixel_image is not None:
        a = fig.add_subplot(gs[1, 2])
        a.imshow(np.asarray(pixel_image), cmap="gray")
        a.set_title("pixel MEI", fontsize=9)
        a.axis("off")
    a = fig.add_subplot(gs[1, 3])
    names, vals = ["3D-MEI"], [run.activation]
    if pixel_activation is not None:
        names.append("pixel MEI")
        vals.append(pixel_activation)
    a.bar(names, vals, color=["tab:blue", "tab:gray"][: len(vals)])
    for i, v in enumerate(vals):
        a.text(i, v, f"{v:.3f}", ha="center", va="bottom", fontsize=8)
    a.set_ylabel("response")
    a.set_title("activation", fontsize=9)
    fig.tight_layout()
    return _save(fig, stem)
