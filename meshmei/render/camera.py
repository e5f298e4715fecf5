"""Perspective pinhole cameras: placement (look-at or azimuth/elevation/distance) and projection to pixels.

Conventions
-----------
World space is right-handed. A camera at ``eye`` looks at ``at``; its frame has ``right``, ``up`` and
``forward`` unit vectors (rows of the view rotation), so view coordinates are
``x = right . (p - eye)``, ``y = up . (p - eye)`` and the depth ``z = forward . (p - eye)`` (> 0 in front).
Pixel coordinates are continuous with the origin at the top-left image corner, ``u`` to the right and
``v`` downwards; pixel ``(row i, column j)`` has its centre at ``(u, v) = (j + 0.5, i + 0.5)``:

    u = S / 2 + f * x / z,    v = S / 2 - f * y / z,    f = (S / 2) / tan(fov / 2)

for an ``S x S`` image. The default camera sits overhead on the +z axis at ``(0, 0, 2.5)`` looking at the
origin with ``up = +y`` (the paper's set-up), so world +x points right and world +y up in the image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from .settings import RenderError, finite_float
from .transforms import check_batch, real_numbers, unit

__all__ = ["Camera", "camera_from_angles", "DEFAULT_DISTANCE", "DEFAULT_FOV_DEGREES"]

DEFAULT_DISTANCE = 2.5
DEFAULT_FOV_DEGREES = 30.0


def _vec3(name, x, dtype, device):
    """``x`` as a ``(B, 3)`` tensor (B >= 1) on ``device`` in ``dtype``, keeping its autograd graph."""
    t = real_numbers(name, x, torch.float64)  # text failed inside torch.as_tensor
    if not t.is_floating_point() and t.dtype not in (torch.int32, torch.int64):
        raise RenderError(f"{name} must hold real numbers, got dtype {t.dtype}")
    if t.ndim not in (1, 2) or t.shape[-1] != 3 or t.shape[0] == 0:
        raise RenderError(f"{name} must have shape (3,) or (B, 3), got {tuple(t.shape)}")
    t = t.to(dtype=dtype, device=device).reshape(-1, 3)
    if not bool(torch.isfinite(t).all()):
        raise RenderError(f"{name} holds NaN or Inf: {t.detach().cpu().tolist()}")
    return t


@dataclass(frozen=True)
class Camera:
    """A perspective camera, or a batch of them sharing field of view and clipping depths.

    Attributes
    ----------
    eye : (3,) or (B, 3) float tensor or sequence
        Camera centre in world coordinates (differentiable when a tensor requiring grad).
    at : (3,) or (B, 3) float tensor or sequence
        Point looked at.
    up : (3,) or (B, 3) float tensor or sequence
        Approximate up direction; it is made orthogonal to the viewing direction. Must not be parallel to
        ``at - eye``.
    fov_degrees : float
        Full field of view of the square image, in degrees, in (0, 180).
    znear, zfar : float
        Clipping depths along the viewing direction, ``0 < znear < zfar``. Faces with a vertex outside
        ``[znear, zfar]`` are dropped (see ``docs/rendering.md``).

    Examples
    --------
    >>> cam = Camera()  # overhead at (0, 0, 2.5), looking at the origin, +y up
    >>> cam.batch_size
    1
    """

    eye: Any = (0.0, 0.0, DEFAULT_DISTANCE)
    at: Any = (0.0, 0.0, 0.0)
    up: Any = (0.0, 1.0, 0.0)
    fov_degrees: float = DEFAULT_FOV_DEGREES
    znear: float = 0.1
    zfar: float = 100.0

    def __post_init__(self):
        fov = finite_float("fov_degrees", self.fov_degrees)
        if not 0 < fov < 180:
            raise RenderError(f"fov_degrees must lie in (0, 180), got {self.fov_degrees!r}")
        near, far = finite_float("znear", self.znear), finite_float("zfar", self.zfar)
        if not 0 < near < far:
            raise RenderError(f"need 0 < znear < zfar, got znear={self.znear!r}, zfar={self.zfar!r}")
        for name, value in (("fov_degrees", fov), ("znear", near), ("zfar", far)):  # kept as checked: "30" was
            object.__setattr__(self, name, value)  # accepted here and failed inside the renderer
        sizes = {_batch_of(name, getattr(self, name)) for name in ("eye", "at", "up")}
        sizes.discard(1)
        if len(sizes) > 1:
            raise RenderError(f"eye, at and up have incompatible batch sizes {sorted(sizes)}")

    @property
    def batch_size(self) -> int:
        return max(_batch_of(name, getattr(self, name)) for name in ("eye", "at", "up"))

    def focal_pixels(self, image_size: int) -> float:
        """Focal length in pixels for an ``image_size``-pixel square image."""
        return 0.5 * image_size / math.tan(math.radians(self.fov_degrees) / 2)

    def frame(self, dtype=torch.float32, device=None, *, eps: float = 1e-12):
        """Camera centres and view rotations.

        Returns
        -------
        eye : (B, 3) tensor
        R : (B, 3, 3) tensor
            Rows ``right``, ``up``, ``forward``; view coordinates are ``(p - eye) @ R.T``.
        """
        # tuples cannot change under the camera: their frame is reused; tensors, arrays and lists can be
        # edited in place (an array edited after the camera was made gave the old view), so are read anew
        fixed = all(_immutable(getattr(self, k)) for k in ("eye", "at", "up"))
        key = (dtype, torch.device(device) if device is not None else torch.device("cpu"), eps)
        if fixed and key in self.__dict__.get("_frames", {}):  # sequences cannot change: reuse their frame
            return self._frames[key]
        eye = _vec3("eye", self.eye, dtype, device)
        at = _vec3("at", self.at, dtype, device)
        up = _vec3("up", self.up, dtype, device)
        eye, at, up = torch.broadcast_tensors(eye, at, up)  # (B, 3) each
        d = at - eye
        if bool((torch.linalg.vector_norm(d, dim=-1) <= eps).any()):
            raise RenderError("camera eye and at coincide; the viewing direction is undefined")
        fwd = unit(d, eps)
        side = torch.linalg.cross(fwd, up, dim=-1)
        if bool((torch.linalg.vector_norm(side, dim=-1) <= 1e-6 * torch.linalg.vector_norm(up, dim=-1)).any()):
            raise RenderError("camera up is parallel to the viewing direction (at - eye); choose another up")
        right = unit(side, eps)
        upo = torch.linalg.cross(right, fwd, dim=-1)
        frame = eye, torch.stack([right, upo, fwd], dim=-2)  # (B, 3), (B, 3, 3)
        if fixed:
            self.__dict__.setdefault("_frames", {})[key] = frame
        return frame


def _immutable(x) -> bool:
    """A tuple of numbers, or of tuples of numbers: values that cannot change after the camera is made."""
    return isinstance(x, tuple) and all(isinstance(v, (int, float)) or _immutable(v) for v in x)


def _batch_of(name, x):
    t = real_numbers(name, x, torch.float64)
    if t.ndim not in (1, 2) or t.shape[-1] != 3 or t.shape[0] == 0:
        raise RenderError(f"{name} must have shape (3,) or (B, 3), got {tuple(t.shape)}")
    return 1 if t.ndim == 1 else t.shape[0]


def camera_from_angles(azimuth, elevation, distance=DEFAULT_DISTANCE, *, at=(0.0, 0.0, 0.0), degrees=True,
                       fov_degrees=DEFAULT_FOV_DEGREES, znear=0.1, zfar=100.0) -> Camera:
    """Cameras on a sphere around ``at``, for pose sweeps; differentiable in the angles and distance.

    ``eye = at + distance * (cos(el) sin(az), sin(el), cos(el) cos(az))``: azimuth turns about the world
    y axis, elevation lifts towards +y, and ``(0, 0)`` is the default overhead camera on +z. The up vector
    is the derivative of the eye direction with respect to elevation, so it is never parallel to the
    viewing direction, even at the poles.

    Parameters
    ----------
    azimuth, elevation : float or (B,) tensor
        Angles, in degrees unless ``degrees=False``.
    distance : float or (B,) tensor
        Distance from ``at`` (> znear).

    Returns
    -------
    Camera with ``(B, 3)`` eye, at and up.

    Examples
    --------
    >>> cam = camera_from_angles(torch.tensor([0.0, 90.0]), 0.0)
    >>> cam.eye.shape
    torch.Size([2, 3])
    """
    ts = [real_numbers(name, a, torch.float64)
          for name, a in (("azimuth", azimuth), ("elevation", elevation), ("distance", distance))]
    dtype = next((t.dtype for t in ts if t.is_floating_point()), torch.float64)
    for name, t in zip(("azimuth", "elevation", "distance"), ts):
        if t.ndim > 1:
            raise RenderError(f"{name} must be a scalar or a (B,) tensor, got shape {tuple(t.shape)}")
        if not bool(torch.isfinite(t).all()):
            raise RenderError(f"{name} holds NaN or Inf")
    znear = finite_float("znear", znear)  # a string failed in the comparison below
    if bool((ts[2] <= znear).any()):  # a camera that close sees the object's centre clipped away
        raise RenderError(f"distance must be > znear ({znear}), got {ts[2].tolist()}")
    sizes = {t.numel() for t in ts} - {1}
    if len(sizes) > 1:
        raise RenderError("azimuth, elevation and distance have incompatible batch sizes "
                          f"{[t.numel() for t in ts]} (each one value or B)")
    az, el, dist = torch.broadcast_tensors(*[t.to(dtype).reshape(-1) for t in ts])
    if degrees:
        az, el = torch.deg2rad(az), torch.deg2rad(el)
    ce, se, ca, sa = torch.cos(el), torch.sin(el), torch.cos(az), torch.sin(az)
    direction = torch.stack([ce * sa, se, ce * ca], dim=-1)  # (B, 3)
    up = torch.stack([-se * sa, ce, -se * ca], dim=-1)
    centre = _vec3("at", at, dtype, az.device)
    check_batch("at", centre.shape[0], direction.shape[0])
    eye = centre + dist.unsqueeze(-1) * direction
    return Camera(eye=eye, at=centre.expand_as(eye), up=up, fov_degrees=fov_degrees, znear=znear, zfar=zfar)
