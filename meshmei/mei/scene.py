"""The learnable scene of one 3D-MEI seed: RBF offsets (and scales), optionally the light and the object pose."""

from __future__ import annotations

import math

import numpy as np
import torch

from ..optim import Lookahead
from ..regularizers import albedo_roughness, texture_roughness
from ..render import axis_angle_to_matrix, render
from .settings import MEISettings, make_deformer

__all__ = ["SeedScene", "sheet_uv", "robust_turns", "albedo_penalty"]


class SeedScene:
    """The learnable scene of one seed: RBF offsets (and scales), optionally the light and the pose."""

    def __init__(self, V0, settings: MEISettings, seed: int, uv=None, n_weights: int | None = None):
        """``n_weights``: the vertex count the weights scale to (the start's own when None), which also sets
        the offsets' learning rate (:meth:`MEISettings.offset_lr`)."""
        dtype, device = V0.dtype, V0.device
        g = torch.Generator().manual_seed(int(seed))  # drawn on the CPU: the same start on every device
        self.rbf = make_deformer(V0, settings)
        # the objective's vertices: a guarded step's check of the candidate and the next objective share one map
        self.vertices = Lookahead(self.rbf, (self.rbf.offsets, self.rbf.log_sigma))
        with torch.no_grad():
            self.rbf.offsets.copy_(settings.init_noise * torch.randn(self.rbf.offsets.shape, generator=g,
                                                                     dtype=torch.float64, device="cpu"))
        lr = settings.offset_lr(V0.shape[0] if n_weights is None else n_weights)
        self.groups = [{"params": [self.rbf.offsets], "lr": lr}]
        if settings.lr_scales > 0:
            self.groups.append({"params": [self.rbf.log_sigma], "lr": settings.lr_scales})
        given = settings.light is not None
        light0 = settings.light if given else (0.0, 0.0, float(settings.camera_distance))
        self.light = torch.tensor(light0, dtype=dtype, device=device) if (settings.optimize_light or given) else None
        self.rotation, self.translation = V0.new_zeros(3), V0.new_zeros(3)
        if settings.optimize_light:
            self.light.requires_grad_(True)
            self.groups.append({"params": [self.light], "lr": settings.lr_light})
        self.albedo_logit, self.uv = None, None
        if settings.albedo:  # a texture over the start's own grid when it has one (uv), else per vertex
            a0 = math.log(settings.albedo_init / (1 - settings.albedo_init))
            R = settings.albedo_resolution
            self.uv = uv if R else None
            shape = (R, R) if self.uv is not None else (V0.shape[0],)
            self.albedo_logit = torch.nn.Parameter(torch.full(shape, a0, dtype=dtype, device=device))
            self.groups.append({"params": [self.albedo_logit], "lr": settings.lr_albedo})
        self.camera, self.render_settings = settings.camera(), settings.render_settings()  # built once per seed
        self.robust = robust_turns(settings, dtype, device=device)
        self.settings, self.widened = settings, 1.0
        self.light0 = torch.tensor(light0, dtype=dtype, device=device)
        self.pose = settings.optimize_pose
        if self.pose:
            self.rotation.requires_grad_(True)
            self.translation.requires_grad_(True)
            self.groups.append({"params": [self.rotation, self.translation], "lr": settings.lr_pose})

    def image(self, V, F, *, pose: bool | None = None) -> torch.Tensor:
        kw = {}
        if self.pose if pose is None else pose:
            kw = dict(rotation=axis_angle_to_matrix(self.rotation), translation=self.translation)
        return render(V, F, camera=self.camera, light=self.light, settings=self.render_settings,
                      albedo=self.albedo(), uv=self.uv, **kw)

    def views(self, V, F) -> torch.Tensor:
        """What the objective averages: the plain image ``(1, 1, S, S)``, or with ``robust_pose`` /
        ``robust_light`` the K images of the quadrature of object turns and light positions ``(K, 1, S, S)``
        (weighted by :meth:`expected`)."""
        if self.robust is None:
            return self.image(V, F)
        turns, lights, _ = self.robust
        kw = {}
        if turns is not None or self.pose:
            R = turns if turns is not None else torch.eye(3, dtype=V.dtype, device=V.device).unsqueeze(0)
            if self.pose:
                R = R @ axis_angle_to_matrix(self.rotation)
                kw["translation"] = self.translation
            kw["rotation"] = R
        light = self.light
        if lights is not None:  # the light (optimised or not) turned about the object
            light = (lights @ (self.light if self.light is not None else self.light0)).reshape(-1, 3)
        return render(V, F, camera=self.camera, light=light, settings=self.render_settings, albedo=self.albedo(),
                      uv=self.uv, **kw)

    def widen(self, fraction: float) -> None:
        """Set the robust ranges for a step at ``fraction`` of the run: ``min(1, fraction / robust_widen)``
        of their full size (full at once when ``robust_widen`` is 0; nothing to do without a robust
        objective)."""
        if self.robust is None:
            return
        w = self.settings.robust_widen
        scale = 1.0 if w <= 0 else min(1.0, max(fraction, 0.0) / w)
        if scale != self.widened:
            self.robust = robust_turns(self.settings, self.robust[2].dtype, scale, device=self.robust[2].device)
            self.widened = scale

    def expected(self, responses: torch.Tensor) -> torch.Tensor:
        """The objective's response from the responses ``(K,)`` to :meth:`views`: the one response, or the
        quadrature's weighted sum, the mean over the uniform distribution of turns."""
        if self.robust is None:
            return responses.mean()
        return (responses * self.robust[2]).sum()

    def albedo(self) -> torch.Tensor | None:
        """The albedo in [0, 1] (per vertex, or a texture over :attr:`uv`), or None (shape only)."""
        return None if self.albedo_logit is None else torch.sigmoid(self.albedo_logit)

    def albedo_roughness(self, F) -> torch.Tensor:
        return albedo_penalty(self.albedo(), self.uv, F)


def albedo_penalty(a, uv, F) -> torch.Tensor:
    """The albedo's smoothness penalty: :func:`~meshmei.regularizers.texture_roughness` for a texture
    (``uv`` given), else :func:`~meshmei.regularizers.albedo_roughness` over the mesh; () or (B,)."""
    return texture_roughness(a) if uv is not None else albedo_roughness(a, F)


def sheet_uv(V0: torch.Tensor) -> torch.Tensor:
    """Texture coordinates of a sheet's rest vertices: its x and y spans mapped onto [0, 1]^2 (v down the
    image, as rows)."""
    xy = V0[:, :2]
    lo, hi = xy.min(0).values, xy.max(0).values
    uv = (xy - lo) / (hi - lo).clamp_min(torch.finfo(V0.dtype).tiny)
    return torch.stack([uv[:, 0], 1 - uv[:, 1]], 1)


def _turns(degrees: float, points: int, dtype, device) -> tuple[torch.Tensor, torch.Tensor]:
    """Rotations ``(points^2, 3, 3)`` and their weights ``(points^2,)`` (summing to 1): azimuth about y times
    elevation about x at the Gauss-Legendre nodes of ``[-d, d]`` with their weights, so that the weighted
    sum is the mean over the uniform distribution on the square, exact for polynomials in the two angles
    up to degree ``2 * points - 1`` in each."""
    x, w = np.polynomial.legendre.leggauss(points)
    a = torch.deg2rad(torch.as_tensor(x * degrees, dtype=torch.float64, device="cpu"))
    w1 = torch.as_tensor(w / 2, dtype=torch.float64, device="cpu")
    az, el = torch.meshgrid(a, a, indexing="ij")
    zero = torch.zeros_like(az)
    Ry = axis_angle_to_matrix(torch.stack([zero, az, zero], -1).reshape(-1, 3))
    Rx = axis_angle_to_matrix(torch.stack([el, zero, zero], -1).reshape(-1, 3))
    return (Ry @ Rx).to(device, dtype), torch.outer(w1, w1).reshape(-1).to(device, dtype)


def robust_turns(settings: MEISettings, dtype, scale: float = 1.0, device="cpu"):
    """``(object turns, light turns, weights)`` for the robust objective: the quadrature of
    :func:`_turns` for each axis that is on (the other None), every (turn, light) pair with the product
    of their weights when both are; None when neither is. ``scale`` shrinks both ranges (the widening of
    ``robust_widen``; 0: every node at the plain view)."""
    k = settings.robust_points
    turns = _turns(scale * settings.robust_pose, k, dtype, device) if settings.robust_pose > 0 else None
    lights = _turns(scale * settings.robust_light, k, dtype, device) if settings.robust_light > 0 else None
    if turns is None and lights is None:
        return None
    if lights is None:
        return turns[0], None, turns[1]
    if turns is None:
        return None, lights[0], lights[1]
    (T, wt), (L, wl) = turns, lights
    K, J = T.shape[0], L.shape[0]  # every (turn, light) pair
    return T.repeat_interleave(J, 0), L.repeat(K, 1, 1), (wt[:, None] * wl[None, :]).reshape(-1)
