"""A compact differentiable rasterizer in torch with the paper's scene (see ``docs/rendering.md``).

Pure torch, CPU and CUDA, float32 and float64: a hard z-buffer over bounded (face, pixel) pairs for
visibility, perspective-correct barycentric interpolation for interior gradients, and a soft coverage
``sigmoid(s / sigma)`` of the signed pixel distance to the silhouette for outline gradients.
"""

from .camera import DEFAULT_DISTANCE, DEFAULT_FOV_DEGREES, Camera, camera_from_angles
from .raster import Fragments, rasterize
from .renderer import Renderer, render
from .settings import RenderError, RenderSettings
from .shading import lambert
from .transforms import apply_pose, axis_angle_to_matrix

__all__ = [
    "Camera",
    "camera_from_angles",
    "DEFAULT_DISTANCE",
    "DEFAULT_FOV_DEGREES",
    "Fragments",
    "rasterize",
    "render",
    "Renderer",
    "RenderError",
    "RenderSettings",
    "lambert",
    "apply_pose",
    "axis_angle_to_matrix",
]
