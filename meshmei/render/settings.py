"""Render settings (a frozen dataclass) and the exception raised for bad render input."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np

from ..errors import RenderError

__all__ = ["RenderError", "RenderSettings", "SOFT_MARGIN_SIGMAS", "MAX_IMAGE_SIZE", "finite_float"]

# Soft coverage is evaluated only within this many sigmas of the silhouette: beyond it the logistic
# differs from 0 or 1 by less than 1e-3 (sigmoid(-7) = 9.1e-4), the size of the jump we accept there.
SOFT_MARGIN_SIGMAS = 7.0
# the widest fringe (pixels) and the largest intensity a setting may take: beyond them an image is meaningless,
# and a fringe of 1e30 pixels overflowed the pixel boxes (an OverflowError) while 1e300 made the image inf
MAX_SIGMA = 1000.0
MAX_INTENSITY = 1e6
# the widest image side (pixels): 8192 x 8192 is 67 million pixels; also the bound of every other image-sized
# grid (a pixel MEI, an albedo texture), so that a size of 10**6 is refused, not handed to the allocator
MAX_IMAGE_SIZE = 8192


def finite_float(name: str, value) -> float:
    """``value`` as a float, or a RenderError naming ``name`` when it is not a finite real number."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise RenderError(f"{name} must be a real number, got {value!r}") from None
    if not math.isfinite(v):
        raise RenderError(f"{name} must be finite, got {value!r}")
    return v


@dataclass(frozen=True)
class RenderSettings:
    """How an image is formed, independent of where the camera, object and light are.

    Attributes
    ----------
    image_size : int
        Width and height of the square image in pixels (1 to ``MAX_IMAGE_SIZE``, 8192).
    sigma : float
        Softness of the silhouette in pixels: coverage is ``sigmoid(s / sigma)`` of the signed distance
        ``s`` (pixels, positive inside) from the pixel centre to the silhouette. ``0.2`` about minimises the
        coverage error against area sampling (see ``docs/rendering.md``); larger values spread silhouette
        gradients over more pixels at the price of a blurrier outline.
    background : float
        Uniform gray level behind the object.
    ambient : float
        Ambient term added to every surface point (>= 0).
    light_intensity : float
        Intensity of the point light (>= 0); the Lambertian term is ``light_intensity * max(0, n . l)``
        with unit normal ``n`` and unit direction ``l`` to the light (no distance falloff).
    albedo : float
        Gray reflectance of the surface (>= 0); surface shade is ``albedo * (ambient + Lambertian)``.
    shading : str
        ``"smooth"`` (interpolated area-weighted vertex normals) or ``"flat"`` (face normals).
    two_sided : bool
        Light faces seen from behind with their normal flipped towards the camera (open meshes such as
        the sheet or the teapot); with ``False`` their Lambertian term uses the stored normal.
    chunk_size : int
        Most (face, pixel) candidate pairs formed at once; bounds the rasterizer's working memory to about
        ``chunk_size * 150`` bytes (>= 1024).
    eps : float
        Guard for divisions that can meet zero: normal lengths, light distances and edge lengths (in
        pixels) are held above it.
    """

    image_size: int = 128
    sigma: float = 0.2
    background: float = 0.5
    ambient: float = 0.2
    light_intensity: float = 0.8
    albedo: float = 1.0
    shading: str = "smooth"
    two_sided: bool = True
    chunk_size: int = 1 << 19
    eps: float = 1e-9

    def __post_init__(self):
        size = self.image_size
        if (isinstance(size, (bool, np.bool_)) or not isinstance(size, numbers.Integral)
                or not 1 <= size <= MAX_IMAGE_SIZE):
            raise RenderError(f"image_size must be an integer in [1, {MAX_IMAGE_SIZE}], got {size!r}")
        object.__setattr__(self, "image_size", int(size))
        sigma = finite_float("sigma", self.sigma)
        if not 0 < sigma <= MAX_SIGMA:
            raise RenderError(f"sigma must lie in (0, {MAX_SIGMA:g}] pixels, got {self.sigma!r}")
        if abs(finite_float("background", self.background)) > MAX_INTENSITY:
            raise RenderError(f"background must lie within +-{MAX_INTENSITY:g}, got {self.background!r}")
        for name in ("ambient", "light_intensity", "albedo"):
            if not 0 <= finite_float(name, getattr(self, name)) <= MAX_INTENSITY:
                raise RenderError(f"{name} must lie in [0, {MAX_INTENSITY:g}], got {getattr(self, name)!r}")
        if self.shading not in ("smooth", "flat"):
            raise RenderError(f"shading must be 'smooth' or 'flat', got {self.shading!r}")
        if not isinstance(self.two_sided, bool):
            raise RenderError(f"two_sided must be a bool, got {self.two_sided!r}")
        cs = self.chunk_size
        if isinstance(cs, (bool, np.bool_)) or not isinstance(cs, numbers.Integral) or cs < 1024:
            raise RenderError(f"chunk_size must be an integer >= 1024, got {cs!r}")
        object.__setattr__(self, "chunk_size", int(cs))
        eps = finite_float("eps", self.eps)
        if not 0 < eps < 1e-2:
            raise RenderError(f"eps must lie in (0, 1e-2), got {self.eps!r}")

    @property
    def soft_margin(self) -> float:
        """Distance in pixels beyond which coverage is taken as exactly 0 or 1."""
        return SOFT_MARGIN_SIGMAS * float(self.sigma)
