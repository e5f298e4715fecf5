"""The learnable scene of one 3D-MEI seed: RBF offsets (and scales), optionally the light and the object pose."""

from __future__ import annotations

import torch

from ..render import axis_angle_to_matrix, render
from .settings import MEISettings, make_deformer

__all__ = ["SeedScene"]


class SeedScene:
    """The learnable scene of one seed: RBF offsets (and scales), optionally the light and the pose."""

    def __init__(self, V0, settings: MEISettings, seed: int):
        dtype = V0.dtype
        g = torch.Generator().manual_seed(int(seed))
        self.rbf = make_deformer(V0, settings)
        with torch.no_grad():
            self.rbf.offsets.copy_(settings.init_noise * torch.randn(self.rbf.offsets.shape, generator=g,
                                                                     dtype=torch.float64))
        self.groups = [{"params": [self.rbf.offsets], "lr": settings.lr}]
        if settings.lr_scales > 0:
            self.groups.append({"params": [self.rbf.log_sigma], "lr": settings.lr_scales})
        given = settings.light is not None
        light0 = settings.light if given else (0.0, 0.0, float(settings.camera_distance))
        self.light = torch.tensor(light0, dtype=dtype) if (settings.optimize_light or given) else None
        self.rotation, self.translation = torch.zeros(3, dtype=dtype), torch.zeros(3, dtype=dtype)
        if settings.optimize_light:
            self.light.requires_grad_(True)
            self.groups.append({"params": [self.light], "lr": settings.lr_light})
        self.camera, self.render_settings = settings.camera(), settings.render_settings()  # built once per seed
        self.pose = settings.optimize_pose
        if self.pose:
            self.rotation.requires_grad_(True)
            self.translation.requires_grad_(True)
            self.groups.append({"params": [self.rotation, self.translation], "lr": settings.lr_pose})

    def image(self, V, F, *, pose: bool | None = None) -> torch.Tensor:
        kw = {}
        if self.pose if pose is None else pose:
            kw = dict(rotation=axis_angle_to_matrix(self.rotation), translation=self.translation)
        return render(V, F, camera=self.camera, light=self.light, settings=self.render_settings, **kw)
