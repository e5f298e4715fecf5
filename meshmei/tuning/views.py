"""Renders of an MEI run for figures: the light sweep's example conditions, the mesh turned to other poses."""

from __future__ import annotations

import math

import torch

from ..render import Camera
from .grids import light_positions, pose_rotations
from .sweeps import Sweep, camera_distance, response_groups

__all__ = ["example_renders", "turned_views"]


def example_renders(run, sweep: Sweep, neuron: int | None = None) -> dict:
    """Renders of the light sweep's high / mid / low example conditions: ``{label: ((H, W) array, example)}``.

    ``example`` is the condition of :func:`response_groups` (``azimuth``, ``elevation``, ``response``).
    """
    groups = response_groups(sweep, neuron)
    d = sweep.meta["distance"]
    out = {}
    for label in ("high", "mid", "low"):
        ex = groups[f"{label}_example"]
        P = light_positions([ex["elevation"]], [ex["azimuth"]], d, dtype=run.V.dtype).reshape(1, 3)
        with torch.no_grad():
            out[label] = (run.render(light=P)[0, 0].cpu().numpy(), ex)
    return out


def turned_views(run, views=((45, 20), (90, 0), (-45, -30))) -> list:
    """Renders of a run's whole mesh turned by pose angles about its centre, framed and lit from the camera.

    The camera stays on +z, moved back until the mesh's bounding sphere fits the field of view (never
    closer than the run's camera); the light sits at the camera.

    Parameters
    ----------
    run : MEIResult
    views : sequence of (azimuth, elevation)
        Degrees, applied on top of the run's pose as in :func:`pose_rotations`.

    Returns
    -------
    list of (azimuth, elevation, (H, W) array)
    """
    scene = run.scene()
    base, cam = scene["rotation"], scene["camera"]
    radius = float((run.V - run.V.mean(0)).norm(dim=1).max())
    half = math.radians(cam.fov_degrees) / 2
    dist = max(camera_distance(scene), 1.15 * radius / math.sin(half))
    view_cam = Camera(eye=(0.0, 0.0, dist), fov_degrees=cam.fov_degrees, znear=cam.znear, zfar=max(cam.zfar, 4 * dist))
    light = torch.tensor([0.0, 0.0, dist], dtype=run.V.dtype, device=run.V.device)
    out = []
    for azi, ele in views:
        R = pose_rotations([ele], [azi], dtype=run.V.dtype, device=run.V.device).reshape(3, 3) @ base.to(run.V)
        with torch.no_grad():
            img = run.render(rotation=R[None], camera=view_cam, light=light, translation=-(run.V.mean(0) @ R.T))
        out.append((azi, ele, img[0, 0].cpu().numpy()))
    return out
