"""Every figure meshmei writes: 3D-MEI runs, reconstructions, pose and light tuning, and the summary sheet.

Figures take results, sweeps and arrays and draw them; they compute nothing that a caller needs. Drawing
uses matplotlib's object-oriented API (:class:`matplotlib.figure.Figure`): no pyplot state, and no backend
switch in the caller's session.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from .render import camera_from_angles, render

__all__ = ["mei_figures", "diverse_figure", "albedo_figure", "reconstruction_figures", "plot_pose_heatmap", "plot_light_polar",
           "summary_sheet", "new_figure"]

# the three extra views of a 3D-MEI run's mesh: the camera orbits the origin at these angles (degrees)
ORBIT_AZIMUTHS = (0, 45, 90)
ORBIT_ELEVATION = 30


def new_figure(**kwargs):
    """A :class:`matplotlib.figure.Figure` with no pyplot state and no backend switch (every figure of
    meshmei's is one); matplotlib is imported only when a figure is drawn: importing meshmei stays quick
    and needs no display."""
    from matplotlib.figure import Figure

    return Figure(**kwargs)


def _save(fig, stem) -> list[Path]:
    """Write ``fig`` as ``stem.png`` and ``stem.pdf``; returns both paths."""
    stem = Path(stem)
    if stem.suffix.lower() in (".png", ".pdf"):  # "fig.png" names the pair fig.png and fig.pdf
        stem = stem.with_suffix("")
    paths = []
    for ext in (".png", ".pdf"):
        p = stem.with_name(stem.name + ext)  # with_suffix cut a stem's last dotted part: run.a and run.b wrote run.png
        fig.savefig(p, dpi=120, bbox_inches="tight")
        paths.append(p)
    return paths


def _gray(ax, image, title, **title_kw):
    """Show an ``(H, W)`` image in gray levels 0 to 1, titled, without axes."""
    ax.imshow(image, cmap="gray", vmin=0, vmax=1)
    ax.set_title(title, **title_kw)
    ax.axis("off")


def _edges(v):
    """Cell edges for pcolormesh from cell centres."""
    v = np.asarray(v, dtype=np.float64)
    if len(v) == 1:
        return np.array([v[0] - 0.5, v[0] + 0.5])
    mid = (v[1:] + v[:-1]) / 2
    return np.concatenate([[2 * v[0] - mid[0]], mid, [2 * v[-1] - mid[-1]]])


# ------------------------------------------------------------------------------------------- 3D-MEI runs


def mei_figures(result, out) -> None:
    """Write ``render.png``, ``views.png`` and ``activation.png`` of a 3D-MEI run into the folder ``out``.

    Parameters
    ----------
    result : MEIResult
        The run (:func:`meshmei.mei.optimize_mei` or :func:`meshmei.mei.load_run`).
    out : Path
        An existing folder.
    """
    import matplotlib.image  # deferred with the rest of matplotlib (see new_figure)

    out = Path(out)
    image = result.image[0, 0].detach().cpu().numpy()  # (H, W)
    matplotlib.image.imsave(out / "render.png", image, cmap="gray", vmin=0, vmax=1)
    fig = new_figure(figsize=(12, 3.2))
    axes = fig.subplots(1, 4)
    axes[0].imshow(image, cmap="gray", vmin=0, vmax=1)
    axes[0].set_title(f"MEI render, response {result.activation:.3f}")
    for ax, az in zip(axes[1:], ORBIT_AZIMUTHS):
        ax.imshow(_orbit_view(result, az), cmap="gray", vmin=0, vmax=1)
        ax.set_title(f"azimuth {az}, elevation {ORBIT_ELEVATION}")
    for ax in axes:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(out / "views.png", dpi=100)
    fig = new_figure(figsize=(5, 3.2))
    ax = fig.subplots()
    ub = result.encoder.get("upper_bound")
    y = [h / ub for h in result.history] if ub else result.history
    ax.plot(range(1, len(y) + 1), y)
    ax.set_xlabel("step")
    ax.set_ylabel("fraction of upper bound" if ub else "response")
    ax.set_title(f"neuron {result.neuron}, seed {result.seed}")
    fig.tight_layout()
    fig.savefig(out / "activation.png", dpi=100)
    if result.albedo is not None:
        albedo_figure(result, out / "albedo.png")


def albedo_figure(result, path) -> Path:
    """The albedo of a shape + albedo 3D-MEI: its render, the albedo alone as the camera sees it (ambient
    light only), the shading alone (albedo 1 everywhere), and, for a texture, the texture map itself."""
    import dataclasses

    s = result.settings.render_settings()
    with torch.no_grad():
        flat = result.render(settings=dataclasses.replace(s, ambient=1.0, light_intensity=0.0))
        shading = result.render(albedo=None, uv=None)
    panels = [(result.image, f"render, response {result.activation:.3f}"), (flat, "albedo (camera view)"),
              (shading, "shading alone (albedo 1)")]
    if result.albedo.ndim == 2:  # a texture over the sheet's grid, v down the image (sheet_uv): row 0 on top
        panels.append((result.albedo[None, None], f"texture {result.albedo.shape[0]} x {result.albedo.shape[1]}"))
    fig = new_figure(figsize=(2.6 * len(panels), 2.8))
    for ax, (img, title) in zip(fig.subplots(1, len(panels)), panels):
        _gray(ax, img[0, 0].detach().cpu().numpy(), title, fontsize=9)
    path = Path(path)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    return path


def diverse_figure(diverse, path) -> Path:
    """The K diverse 3D-MEIs' renders side by side, with their responses, and their dissimilarity matrix."""
    results = diverse.results
    k = len(results)
    fig = new_figure(figsize=(2.2 * (k + 1), 2.6))
    axes = fig.subplots(1, k + 1)
    for ax, r in zip(axes, results):
        _gray(ax, r.image[0, 0].detach().cpu().numpy(), f"seed {r.seed}: {r.activation:.3f}", fontsize=9)
    im = axes[-1].imshow(diverse.dissimilarity.cpu().numpy(), vmin=0, vmax=1, cmap="viridis")
    axes[-1].set_title("dissimilarity", fontsize=9)
    axes[-1].set_xticks(range(k))
    axes[-1].set_yticks(range(k))
    fig.colorbar(im, ax=axes[-1], fraction=0.046)
    path = Path(path)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    return path


def _orbit_view(result, azimuth) -> np.ndarray:
    """The run's mesh seen by a camera turned about the vertical axis by ``azimuth`` degrees, ``(H, W)``."""
    s = result.settings
    cam = camera_from_angles(float(azimuth), float(ORBIT_ELEVATION), s.camera_distance, fov_degrees=s.fov_degrees)
    with torch.no_grad():
        img = render(result.V, result.F, camera=cam, settings=s.render_settings(), albedo=result.albedo,
                     uv=result.albedo_uv)
    return img[0, 0].cpu().numpy()


# ----------------------------------------------------------------------------------------- reconstructions


def reconstruction_figures(result, out_dir) -> list[Path]:
    """Write ``loss.png`` (loss against time) and ``metrics.png`` (Chamfer-L2, F-score, normal consistency
    against time) of a reconstruction into ``out_dir`` (made if missing); returns the paths.

    Parameters
    ----------
    result : ReconstructionResult
        With ``history`` (one dict per step: ``time``, ``loss``) and ``metrics`` (one dict per evaluation:
        ``time``, ``chamfer_l2``, ``fscore``, ``normal_consistency``).
    out_dir : str or Path
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    h = result.history
    fig = new_figure(figsize=(5, 3.5))
    ax = fig.subplots()
    ax.semilogy([r["time"] for r in h], [r["loss"] for r in h], lw=0.8)
    ax.set_xlabel("optimisation time (s)")
    ax.set_ylabel("loss")
    ax.set_title(f"{result.settings.method}: training loss")
    fig.tight_layout()
    p1 = out_dir / "loss.png"
    fig.savefig(p1, dpi=120)
    m = result.metrics
    fig = new_figure(figsize=(12, 3.5))
    axs = fig.subplots(1, 3)
    t = [r["time"] for r in m]
    axs[0].semilogy(t, [r["chamfer_l2"] for r in m], "o-")
    axs[0].set_ylabel("Chamfer-L2")
    axs[1].plot(t, [r["fscore"] for r in m], "o-")
    axs[1].set_ylabel("F-score @ 1%")
    axs[2].plot(t, [r["normal_consistency"] for r in m], "o-")
    axs[2].set_ylabel("normal consistency")
    for a in axs:
        a.set_xlabel("optimisation time (s)")
    fig.tight_layout()
    p2 = out_dir / "metrics.png"
    fig.savefig(p2, dpi=120)
    return [p1, p2]


# ------------------------------------------------------------------------------------------------ tuning


def plot_pose_heatmap(sweep, neuron: int, stem) -> list[Path]:
    """Azimuth x elevation heatmap of one neuron's responses, the original view marked (roll averaged out).

    Parameters
    ----------
    sweep : Sweep
        A pose sweep (:func:`meshmei.tuning.pose_sweep`), with or without a roll axis.
    neuron : int
    stem : str or Path
        Written as ``stem.png`` and ``stem.pdf``.
    """
    r = sweep.of(neuron)
    if r.ndim == 3:  # a roll axis: show its mean, and the roll curve beside it
        fig = new_figure(figsize=(10, 4.2))
        ax, ax2 = fig.subplots(1, 2)
        curve = r.mean(axis=(0, 1))
        ax2.plot(sweep.axis("roll"), curve, "o-", ms=3)
        ax2.set_xlabel("roll (deg)")
        ax2.set_ylabel("response (mean over the pose grid)")
        ax2.set_title("in-plane rotation")
        r = r.mean(axis=2)
    else:
        fig = new_figure(figsize=(5.4, 4.2))
        ax = fig.subplots()
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
    with the example renders of the high, mid and low response groups when ``images`` is given.

    Parameters
    ----------
    sweep : Sweep
        A light sweep (:func:`meshmei.tuning.light_sweep`).
    neuron : int
    stem : str or Path
        Written as ``stem.png`` and ``stem.pdf``.
    images : dict, optional
        ``{"high" | "mid" | "low": ((H, W) array, example)}`` as :func:`meshmei.tuning.example_renders`
        returns, ``example`` a dict with the condition's ``azimuth``, ``elevation`` and ``response``.
    """
    if images and not {"high", "mid", "low"} <= set(images):  # a KeyError halfway through the figure before
        raise ValueError(f"images needs 'high', 'mid' and 'low' (as example_renders returns them), got "
                         f"{sorted(map(str, images))}")
    r = sweep.of(neuron)
    az, el = sweep.axis("azimuth"), sweep.axis("elevation")
    ncol = 1 + (3 if images else 0)
    fig = new_figure(figsize=(5.0 + 2.6 * (ncol - 1), 4.4), layout="constrained")
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
            title = f"{label}: az {ex['azimuth']:.0f}, el {ex['elevation']:.0f}\nresponse {ex['response']:.3f}"
            _gray(fig.add_subplot(1, ncol, 2 + k), img, title, fontsize=8)
            ax.plot([np.radians(ex["azimuth"])], [90 - ex["elevation"]], "o", mfc="none", mec="c", ms=8)
    return _save(fig, stem)


# ------------------------------------------------------------------------------------------ summary sheet


def summary_sheet(run, stem, views, *, pixel_image=None, pixel_activation=None) -> list[Path]:
    """One page for an MEI run: the rendered MEI, three 3D views of the mesh, the activation curve, the
    pixel MEI and the activation bars (3D-MEI versus pixel MEI).

    Parameters
    ----------
    run : MEIResult
    stem : str or Path
        Written as ``stem.png`` and ``stem.pdf``.
    views : sequence of (azimuth, elevation, (H, W) array)
        Three renders of the mesh and the pose angles (degrees) they were taken at, e.g. from
        :func:`meshmei.tuning.turned_views`.
    pixel_image : (H, W) array, optional
        The pixel MEI.
    pixel_activation : float, optional
        Its response, drawn as a second bar.
    """
    views = list(views)
    if len(views) > 3:  # the page has three places for them (a fourth was matplotlib's IndexError)
        raise ValueError(f"summary_sheet draws at most 3 views, got {len(views)}")
    fig = new_figure(figsize=(13, 6.2))
    gs = fig.add_gridspec(2, 4)
    _gray(fig.add_subplot(gs[0, 0]), run.image[0, 0].cpu().numpy(),
          f"3D-MEI render\nneuron {run.neuron}, response {run.activation:.3f}", fontsize=9)
    for k, (azi, ele, img) in enumerate(views):
        _gray(fig.add_subplot(gs[0, 1 + k]), img, f"mesh, azimuth {azi}, elevation {ele}", fontsize=9)
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
