"""Rasterize a mesh into per-pixel :class:`Fragments`: checked inputs in, the passes of
:mod:`meshmei.render.passes` run, fragments out (see ``docs/rendering.md``)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..mesh import check_mesh
from .camera import Camera
from .passes import run_passes
from .settings import RenderError, RenderSettings
from .transforms import apply_pose, check_batch

__all__ = ["Fragments", "rasterize", "RenderInputs", "prepare_inputs"]


@dataclass(frozen=True)
class Fragments:
    """What each pixel sees. Float fields carry gradients to the vertices, pose and camera.

    Attributes
    ----------
    face_id : (B, H, W) int64 tensor
        Index into ``F`` of the nearest face whose projection contains the pixel centre; -1 for background.
    bary : (B, H, W, 3) float tensor
        Perspective-correct barycentric coordinates of the pixel centre's surface point in the face's
        corners ``F[face_id]``; zero on background.
    depth : (B, H, W) float tensor
        View depth (distance along the viewing direction) of that point; zero on background.
    coverage : (B, H, W) float tensor
        Soft coverage in [0, 1]: ``sigmoid(s / sigma)`` of the signed distance ``s`` (pixels, positive
        inside) to the silhouette within ``settings.soft_margin`` of it, else 1 on covered and 0 on
        background pixels.
    """

    face_id: torch.Tensor
    bary: torch.Tensor
    depth: torch.Tensor
    coverage: torch.Tensor


# --------------------------------------------------------------------------------------------------
# inputs

@dataclass(frozen=True)
class RenderInputs:
    """The checked inputs of one :func:`rasterize` or :func:`~meshmei.render.render` call.

    Attributes
    ----------
    V : (n, 3) or (B, n, 3) float tensor
        The vertices as given (checked).
    F : (m, 3) int64 tensor
    posed : (Bv, n, 3) float tensor
        World vertices after the object pose.
    eye : (Bc, 3) float tensor
        Camera centres.
    R : (Bc, 3, 3) float tensor
        View rotations (rows right, up, forward).
    camera : Camera
    settings : RenderSettings
    """

    V: torch.Tensor
    F: torch.Tensor
    posed: torch.Tensor
    eye: torch.Tensor
    R: torch.Tensor
    camera: Camera
    settings: RenderSettings

    @property
    def n_vertices(self) -> int:
        return self.V.shape[-2]

    @property
    def batch_size(self) -> int:
        """Broadcast batch size of the poses and the cameras."""
        return max(self.posed.shape[0], self.eye.shape[0])

    def expanded(self, B: int):
        """World vertices ``(B, n, 3)``, camera centres ``(B, 3)`` and view rotations ``(B, 3, 3)``."""
        return self.posed.expand(B, *self.posed.shape[1:]), self.eye.expand(B, 3), self.R.expand(B, 3, 3)


_DEFAULT_CAMERA = Camera()  # frozen, with tuple fields: its frame is cached on it


def prepare_inputs(V, F, camera, rotation, translation, settings) -> RenderInputs:
    """Check the mesh, settings and camera (defaults for None), pose the vertices and place the cameras.

    Raises
    ------
    MeshError
        Malformed ``V`` / ``F``.
    RenderError
        Bad settings, camera, pose or incompatible batch sizes.
    """
    if settings is None:
        settings = RenderSettings()
    if not isinstance(settings, RenderSettings):
        raise RenderError(f"settings must be a RenderSettings, got {type(settings).__name__}")
    if camera is None:
        camera = _DEFAULT_CAMERA  # one instance, so that its view frame is computed once (a loop of renders)
    if not isinstance(camera, Camera):
        raise RenderError(f"camera must be a Camera, got {type(camera).__name__}")
    V, F = check_mesh(V, F, batched=None)
    posed = apply_pose(V, rotation, translation)  # (Bv, n, 3)
    eye, R = camera.frame(V.dtype, V.device)
    check_batch("camera", eye.shape[0], posed.shape[0])
    return RenderInputs(V=V, F=F, posed=posed, eye=eye, R=R, camera=camera, settings=settings)


# --------------------------------------------------------------------------------------------------
def rasterize(V, F, *, camera: Camera | None = None, rotation=None, translation=None,
              settings: RenderSettings | None = None) -> Fragments:
    """Rasterize a mesh (or a batch of poses / cameras of it) into per-pixel fragments.

    Parameters
    ----------
    V : (n, 3) or (B, n, 3) float tensor
        Vertex positions in object coordinates; dtype and device of the outputs follow ``V``.
    F : (m, 3) int64 tensor
    camera : Camera, optional
        Default: overhead at (0, 0, 2.5) looking at the origin. A batch of B cameras is allowed.
    rotation : (3, 3) or (B, 3, 3) float tensor, optional
        Rotation matrix; :func:`~meshmei.render.axis_angle_to_matrix` makes one from axis-angle vectors.
    translation : (3,) or (B, 3) tensor, optional
        Object pose ``V @ R.T + t`` (rotation about the object origin, then translation).
    settings : RenderSettings, optional

    Returns
    -------
    Fragments
        ``(B, S, S)`` fields with B the broadcast batch size and S = ``settings.image_size``.

    Raises
    ------
    MeshError
        Malformed ``V`` / ``F`` (shapes, NaN, indices).
    RenderError
        Bad settings, camera, pose or incompatible batch sizes.
    """
    inp = prepare_inputs(V, F, camera, rotation, translation, settings)
    V, F = inp.V, inp.F
    Vw, eye, R = inp.expanded(inp.batch_size)
    r = run_passes(Vw, F, eye, R, inp.camera, inp.settings, inp.n_vertices)
    B, S = r.B, r.S
    bary_in, depth_in = r.perspective_correct(r.inside)
    zero = 0.0 * (r.Vc.sum())  # keeps every output connected to the inputs, with zero gradient
    bary = torch.zeros(B * S * S, 3, dtype=V.dtype, device=V.device).index_put((r.inside.pix,), bary_in) + zero
    depth = torch.zeros(B * S * S, dtype=V.dtype, device=V.device).index_put((r.inside.pix,), depth_in) + zero
    return Fragments(face_id=r.face_id, bary=bary.view(B, S, S, 3), depth=depth.view(B, S, S),
                     coverage=(r.coverage + zero).view(B, S, S))
