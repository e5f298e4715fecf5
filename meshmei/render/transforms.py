"""Rigid object pose (rotations from axis-angle vectors, applied to vertex batches) and the scene's vector checks."""

from __future__ import annotations

import numpy as np
import torch

from ..operators import scaled_norm
from .settings import RenderError

__all__ = ["axis_angle_to_matrix", "apply_pose", "check_batch", "as_points", "unit"]


def axis_angle_to_matrix(aa: torch.Tensor) -> torch.Tensor:
    """Rotation matrices from axis-angle vectors (Rodrigues), differentiable everywhere including at zero.

    Parameters
    ----------
    aa : (..., 3) float tensor
        Rotation axis times angle in radians.

    Returns
    -------
    (..., 3, 3) tensor, ``R @ x`` rotates ``x``.

    Examples
    --------
    >>> import math
    >>> R = axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.pi / 2]))
    >>> torch.allclose(R @ torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 1.0, 0.0]), atol=1e-6)
    True
    """
    if aa.shape[-1:] != (3,):
        raise RenderError(f"axis-angle vectors must have shape (..., 3), got {tuple(aa.shape)}")
    theta2 = (aa * aa).sum(-1, keepdim=True).unsqueeze(-1)  # (..., 1, 1)
    small = theta2 < 1e-8
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = t2.sqrt()
    # sin(t)/t and (1 - cos(t))/t^2, with their Taylor series near zero so the gradient stays finite
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / t2)
    x, y, z = aa.unbind(-1)
    zero = torch.zeros_like(x)
    K = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*aa.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device)
    return eye + a * K + b * (K @ K)


def real_numbers(name: str, x, dtype=None) -> torch.Tensor:
    """``x`` (a tensor, array or sequence) as a tensor (a sequence in ``dtype``, rounded once), or a
    RenderError when it holds no real numbers: complex or bool values cast to float would lose the
    imaginary part, or read True as 1, silently."""
    if isinstance(x, torch.Tensor):
        if x.is_complex() or x.dtype == torch.bool:
            raise RenderError(f"{name} must hold real numbers, got dtype {x.dtype}")
        return x
    try:
        a = np.asarray(x)
    except (TypeError, ValueError) as err:
        raise RenderError(f"{name} must be a tensor or a rectangular sequence of numbers: {err}") from None
    if a.dtype.kind not in "fiu":
        raise RenderError(f"{name} must hold real numbers, got {a.dtype} values")
    return torch.as_tensor(a, dtype=dtype, device="cpu")  # then moved to the mesh's device by the caller


def _rotation(rotation, dtype, device):
    R = real_numbers("rotation", rotation, dtype).to(dtype=dtype, device=device)
    if R.shape[-2:] != (3, 3) or R.ndim not in (2, 3):
        raise RenderError(f"rotation must be a (3, 3) or (B, 3, 3) matrix (use axis_angle_to_matrix for "
                          f"axis-angle vectors), got shape {tuple(R.shape)}")
    R = R.reshape(-1, 3, 3)
    if R.shape[0] == 0 or not bool(torch.isfinite(R).all()):
        raise RenderError(f"rotation must be non-empty and finite, got shape {tuple(R.shape)}")
    return R


def apply_pose(V: torch.Tensor, rotation=None, translation=None) -> torch.Tensor:
    """Rotate about the origin, then translate: ``V @ R.T + t``, broadcast over a batch.

    Parameters
    ----------
    V : (n, 3) or (B, n, 3) float tensor
    rotation : None, (3, 3) or (B, 3, 3) float tensor
        Rotation matrix (see :func:`axis_angle_to_matrix`). Not checked for orthogonality: a general
        linear map is applied as given.
    translation : None, (3,) or (B, 3) tensor

    Returns
    -------
    (B, n, 3) tensor (B = 1 when nothing is batched).
    """
    Vb = V if V.ndim == 3 else V.unsqueeze(0)
    if rotation is not None:
        R = _rotation(rotation, V.dtype, V.device)
        check_batch("rotation", R.shape[0], Vb.shape[0])
        Vb = torch.matmul(Vb, R.transpose(-1, -2))
    if translation is not None:
        t = as_points("translation", translation, V.dtype, V.device)
        check_batch("translation", t.shape[0], Vb.shape[0])
        Vb = Vb + t.unsqueeze(1)
    return Vb


def check_batch(name: str, b: int, B: int) -> None:
    """Raise RenderError unless batch sizes ``b`` (of ``name``) and ``B`` broadcast: equal, or one of them 1."""
    if b != 1 and B != 1 and b != B:
        raise RenderError(f"{name} has batch size {b}, incompatible with batch size {B}")


def as_points(name: str, x, dtype, device) -> torch.Tensor:
    """``x`` (a (3,) or (B, 3) tensor or sequence) as a finite ``(B, 3)`` tensor, keeping its autograd graph.

    Raises
    ------
    RenderError
        Wrong shape (the message names ``name`` and the shape), or NaN / Inf.
    """
    t = real_numbers(name, x, dtype).to(dtype=dtype, device=device)
    if t.ndim not in (1, 2) or t.shape[-1] != 3 or t.shape[0] == 0:
        raise RenderError(f"{name} must have shape (3,) or (B, 3), got {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise RenderError(f"{name} holds NaN or Inf")
    return t.reshape(-1, 3)


def unit(x: torch.Tensor, eps: float) -> torch.Tensor:
    """``x / max(|x|, eps)`` along the last axis, right where ``|x|^2`` overflows (a light 1e20 away in float32)."""
    length = torch.linalg.vector_norm(x, dim=-1, keepdim=True)
    if length.numel() and not float(length.detach().amax()) < float("inf"):
        length = scaled_norm(x, -1, keepdim=True)
    return x / length.clamp_min(eps)
