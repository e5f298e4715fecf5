"""The main job, end to end on built-in data: a 3D-MEI for a demo neuron, its pose and light tuning, plots.

``meshmei demo`` runs it offline in a few minutes on a laptop CPU and prints where everything went.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ._files import check_output
from .encoders import DEMO_MODEL_PATH, is_demo_model, load_demo_model
from .mei import MEISettings, optimize_mei, pixel_image_size, pixel_mei, save_run
from .plots import summary_sheet
from .quality import health_line
from .tuning import example_renders, light_sweep, pose_sweep, save_sweep, turned_views

__all__ = ["run_story", "QUICK", "FULL"]

# Sizes of the two presets: the full job (the README's) and a quick one for tests and smoke runs.
FULL = dict(image_size=64, n_vertices=600, steps=200, seeds=(0, 1), pixel_steps=200, pose=37, light=(10, 36))
QUICK = dict(image_size=32, n_vertices=150, steps=25, seeds=(0,), pixel_steps=30, pose=5, light=(3, 6))


def _default_neuron(encoder) -> int:
    """The shipped demo model's best-predicted neuron (highest test correlation with ground truth), else 0."""
    info = DEMO_MODEL_PATH.with_suffix(".json")
    if is_demo_model(encoder) and info.is_file():
        corr = json.loads(info.read_text()).get("test_correlation_with_ground_truth")
        if isinstance(corr, list) and corr:
            return int(np.nanargmax(np.asarray(corr, dtype=np.float64)))
    return 0


def run_story(out, *, encoder=None, neuron: int | None = None, init: str = "sheet", preset: dict | None = None,
              overwrite: bool = False, log=print) -> dict:
    """3D-MEI, pixel MEI, pose sweep, light sweep and the summary sheet, written under ``out``.

    Parameters
    ----------
    out : path
        Output directory (``mei/``, ``mei/tuning_pose/``, ``mei/tuning_light/``, ``summary.png|pdf``,
        ``story.json``). ``story.json`` is written last: a folder without it holds no finished story (an
        interrupted run, or an interrupted ``overwrite``, which removes the earlier story's ``story.json`` and
        summary sheet before it replaces ``mei/``).
    encoder : Encoder, optional
        Default: the shipped demo model (:func:`meshmei.encoders.load_demo_model`).
    neuron : int, optional
        Default: the demo model's best-predicted neuron.
    init : str
        Initial mesh of the 3D-MEI.
    preset : dict, optional
        :data:`FULL` (default) or :data:`QUICK`, or a dict with the same keys.

    Returns
    -------
    dict with the activations, the sweep maxima and the paths written.
    """
    p = dict(FULL if preset is None else preset)
    out = Path(out)
    if out.is_dir() and any(out.iterdir()) and not overwrite:  # a file there: refused by check_output below
        raise FileExistsError(f"{out} exists and is not empty; pass --overwrite to replace its contents")
    # the run folder is replaced after the 3D-MEI and the pixel MEI: a folder there that meshmei did not
    # write must stop the story before that work, not after it
    check_output(out / "mei", overwrite=True, error=FileExistsError)
    t0 = time.perf_counter()
    encoder = load_demo_model() if encoder is None else encoder
    neuron = _default_neuron(encoder) if neuron is None else int(neuron)
    encoder.neuron_index(neuron)  # clear error for an out-of-range neuron before any work (and any folder)
    out.mkdir(parents=True, exist_ok=True)
    res, pix = _optimise(encoder, neuron, init, p, log)
    # story.json, written last, says the folder holds a whole story: an earlier story's goes (with its sheet)
    # before its run folder is replaced, so that an interrupted --overwrite leaves a folder without it, not
    # one whose story.json and summary sheet describe another neuron than mei/
    for name in ("story.json", "summary.png", "summary.pdf"):
        (out / name).unlink(missing_ok=True)
    run_dir = save_run(res, out / "mei", overwrite=True)
    pose, light = _sweep(res, encoder, run_dir, p, log)
    log("[5/5] summary sheet")
    pix_img = pix.image[0, 0].detach().cpu().numpy()
    sheet = summary_sheet(res, out / "summary", turned_views(res), pixel_image=pix_img,
                          pixel_activation=float(pix.activation))
    best_pose, best_light = pose.argmax(neuron), light.argmax(neuron)
    summary = {
        "neuron": neuron,
        "mei_activation": res.activation,
        "mei_health": res.health(),
        "pixel_mei_activation": float(pix.activation),
        "pose_best": best_pose,
        "pose_best_response": float(pose.of(neuron).max()),
        "pose_sweep_seconds": pose.meta["seconds"],
        "light_best": best_light,
        "light_best_response": float(light.of(neuron).max()),
        "light_sweep_seconds": light.meta["seconds"],
        "total_seconds": time.perf_counter() - t0,
        "files": {"run": str(run_dir), "pose": str(run_dir / "tuning_pose"), "light": str(run_dir / "tuning_light"),
                  "summary": [str(s) for s in sheet]},
    }
    partial = out / ".story.json.partial"
    partial.write_text(json.dumps(summary, indent=1))
    os.replace(partial, out / "story.json")
    _report(summary, pose, out, run_dir, log)
    return summary


def _optimise(encoder, neuron, init, p, log):
    """Steps 1 and 2: the 3D-MEI (carrying the pixel MEI's activation in its ``extra``) and the pixel MEI."""
    size = pixel_image_size(encoder, p["image_size"])  # a lab's model renders at its own size
    h, w = (size, size) if isinstance(size, int) else tuple(size)
    log(f"[1/5] 3D-MEI of neuron {neuron} from a {init} ({p['steps']} steps x {len(p['seeds'])} seeds, "
        f"{h}x{w} px)")
    st = MEISettings(image_size=p["image_size"], n_vertices=p["n_vertices"], steps=p["steps"], seeds=tuple(p["seeds"]))
    res = optimize_mei(encoder, neuron, init=init, settings=st, progress=True)
    log(f"      response {res.activation:.4f} in {res.wall_time:.1f} s")
    log("[2/5] pixel MEI in the same image space")
    pix = pixel_mei(encoder, neuron, image_size=size, steps=p["pixel_steps"], seeds=tuple(p["seeds"]))
    log(f"      response {pix.activation:.4f}")
    res = replace(res, extra={**res.extra, "pixel_mei_activation": float(pix.activation)})
    return res, pix


def _sweep(res, encoder, run_dir, p, log):
    """Steps 3 and 4: the pose and light sweeps of the 3D-MEI, saved inside its run directory."""
    n_pose = p["pose"]
    log(f"[3/5] pose sweep, {n_pose} x {n_pose} (azimuth x elevation, -90..90 deg)")
    pose = pose_sweep(res, encoder, elevation=np.linspace(-90, 90, n_pose), azimuth=np.linspace(-90, 90, n_pose))
    save_sweep(pose, run_dir / "tuning_pose", overwrite=True)
    n_el, n_az = p["light"]
    log(f"[4/5] light sweep, {n_el} elevations x {n_az} azimuths over the camera-facing hemisphere")
    light = light_sweep(res, encoder, elevation=np.linspace(0, 90, n_el),
                        azimuth=np.linspace(0, 360, n_az, endpoint=False))
    save_sweep(light, run_dir / "tuning_light", overwrite=True,
               images={n: example_renders(res, light, n) for n in light.neurons})
    return pose, light


def _report(summary, pose, out, run_dir, log):
    """The closing lines: responses, tuning maxima and where the files went."""
    best_pose, best_light = summary["pose_best"], summary["light_best"]
    log("")
    h = summary["mei_health"]
    log(f"neuron {summary['neuron']}: 3D-MEI response {summary['mei_activation']:.4f} ({health_line(h)}), "
        f"pixel MEI {summary['pixel_mei_activation']:.4f}")
    log(f"pose tuning: best {summary['pose_best_response']:.4f} at azimuth {best_pose['azimuth']:.0f}, "
        f"elevation {best_pose['elevation']:.0f} (original view {pose.reference['responses'][0]:.4f}); "
        f"{pose.meta['renders']} renders in {pose.meta['seconds']:.1f} s")
    log(f"light tuning: best {summary['light_best_response']:.4f} with the light at azimuth "
        f"{best_light['azimuth']:.0f}, elevation {best_light['elevation']:.0f}")
    log(f"files: {out}/summary.png, {run_dir} (mesh.obj, renders, summary.json), tuning_pose/, tuning_light/")
    log(f"total {summary['total_seconds']:.0f} s")
