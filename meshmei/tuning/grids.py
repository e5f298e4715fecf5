"""The grids of a tuning sweep: object rotations over elevation x azimuth (x roll), light positions.

The scene is the paper's: the camera on +z looking at the origin with +y up, so image right is +x and
image up is +y. Angles are in degrees.

- Pose: the object turns about its own centre. Azimuth turns its front (the face seen by the camera)
  towards image right (a rotation about +y), elevation tilts the front up (about -x), and roll
  (optional) turns the image plane counter-clockwise as seen by the camera (about +z, the view axis).
  They apply in that order, on top of the run's own pose. (0, 0, 0) is the original view.
- Light: a point light at ``distance`` from the origin on the hemisphere facing the camera, at
  ``d * (cos(el) cos(az), cos(el) sin(az), sin(el))``: elevation 90 is at the camera's axis, elevation 0
  grazes in the image plane, azimuth 0 lights from image right, 90 from above, 180 from the left.
"""

from __future__ import annotations

import math
import numbers
import re

import numpy as np
import torch

from ..errors import TuningError
from ..render import axis_angle_to_matrix

__all__ = ["check_angles", "pose_rotations", "light_positions", "parse_range"]


def check_angles(name, values, lo=None, hi=None) -> np.ndarray:
    """Angles in degrees as a flat float64 array ``(g,)``; raise TuningError if empty, not finite or outside
    ``[lo, hi]``."""
    if values is None or isinstance(values, (bool, np.bool_)):  # None was "holds NaN or Inf: [nan]"
        raise TuningError(f"{name} must be angles in degrees, got {values!r}")
    try:
        a = np.asarray(values, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):  # '0:10:2' is a range's text: parse_range reads it
        raise TuningError(f"{name} must be angles in degrees, got {values!r} (parse_range reads 'lo:hi:n')") from None
    if a.size == 0:
        raise TuningError(f"{name} range is empty; give at least one angle")
    if not np.isfinite(a).all():
        raise TuningError(f"{name} holds NaN or Inf: {a.tolist()[:8]}")
    if lo is not None and (a.min() < lo or a.max() > hi):
        raise TuningError(f"{name} must lie in [{lo}, {hi}] degrees, got [{a.min()}, {a.max()}]")
    return a


def _rot(axis, deg, dtype, device):
    # beyond a turn, the angle less its whole turns (exact in float64; within a turn nothing changes): 1e308
    # degrees overflowed the dtype in radians and made the rotation NaN
    deg = np.where(np.abs(deg) > 360.0, np.fmod(deg, 360.0), deg)
    aa = torch.zeros(len(deg), 3, dtype=dtype, device=device)
    aa[:, axis] = torch.as_tensor(np.radians(deg), dtype=dtype, device=device)
    return axis_angle_to_matrix(aa)


def pose_rotations(elevation, azimuth, roll=None, *, dtype=torch.float32, device="cpu") -> torch.Tensor:
    """Rotation matrices ``(E, A[, R], 3, 3)`` for a grid of elevation x azimuth (x roll), degrees.

    ``R = R_roll(z) @ R_elevation(-x) @ R_azimuth(y)``: azimuth first, then elevation, then roll.
    """
    el, az = check_angles("elevation", elevation), check_angles("azimuth", azimuth)
    rl = np.zeros(1) if roll is None else check_angles("roll", roll)
    check_grid_size(len(el), len(az), len(rl))
    Ry = _rot(1, az, dtype, device)  # (A, 3, 3)
    Rx = _rot(0, -el, dtype, device)  # (E, 3, 3)
    Rz = _rot(2, rl, dtype, device)  # (R, 3, 3)
    R = Rz[None, None] @ Rx[:, None, None] @ Ry[None, :, None]  # (E, A, R, 3, 3)
    return R if roll is not None else R[:, :, 0]


def light_positions(elevation, azimuth, distance: float, *, dtype=torch.float32, device="cpu") -> torch.Tensor:
    """Light positions ``(E, A, 3)`` on the camera-facing hemisphere (see the module docstring)."""
    el = np.radians(check_angles("elevation", elevation, 0.0, 90.0))
    az = np.radians(check_angles("azimuth", azimuth))
    if isinstance(distance, torch.Tensor) and distance.numel() == 1:
        distance = distance.item()
    # NumPy's numbers too (np.float32(3) was refused), not a bool (True was swept at 1.0)
    if isinstance(distance, bool) or not (isinstance(distance, numbers.Real) and math.isfinite(distance)
                                          and distance > 0):
        raise TuningError(f"light distance must be a positive number, got {distance!r}")
    distance = float(distance)
    if distance > MAX_LIGHT_DISTANCE:  # 1e308 overflowed the light's position ("light holds NaN or Inf")
        raise TuningError(f"light distance must be at most {MAX_LIGHT_DISTANCE:g}, got {distance!r}")
    check_grid_size(len(el), len(az))
    E, A = np.meshgrid(el, az, indexing="ij")
    P = distance * np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1)
    return torch.as_tensor(P, dtype=dtype, device=device)


# the farthest light of a light sweep: from there the light's direction turns by under a microradian across an
# object of unit size, so a farther one is the same light; its squared distance stays well within float32
MAX_LIGHT_DISTANCE = 1e6
_NUMBER = re.compile(r"[+-]?((\d+\.?\d*|\.\d+)([eE][+-]?\d+)?|inf|infinity|nan)", re.ASCII | re.IGNORECASE)
_COUNT = re.compile(r"\d{1,18}", re.ASCII)

# the most conditions (renders per neuron) of one grid: two full axes at a tenth of a degree
MAX_GRID_CONDITIONS = 3601 * 3601


def check_grid_size(*counts: int) -> None:
    """Raise TuningError when a grid of these axis lengths has more than :data:`MAX_GRID_CONDITIONS`
    conditions (three axes of 3,601 angles asked for 1.7 TB of rotations and failed inside torch)."""
    total = math.prod(counts)
    if total > MAX_GRID_CONDITIONS:
        raise TuningError(f"the grid has {' x '.join(map(str, counts))} = {total:,} conditions; at most "
                          f"{MAX_GRID_CONDITIONS:,} (each is a render): use coarser ranges")


# the most angles one range may give (a 3,601-step axis is a tenth of a degree over a full turn); a grid's
# renders are the product of its axes' counts
MAX_RANGE_ANGLES = 3601


def parse_range(text: str) -> np.ndarray:
    """``"lo:hi:n"`` -> n angles from lo to hi inclusive (finite bounds, 1 to :data:`MAX_RANGE_ANGLES`)."""
    parts = text.split(":") if isinstance(text, str) else ()
    # ASCII numbers only, as parse_neurons: float() and int() also read other scripts' digits and '1_0' (10)
    if (len(parts) != 3 or not all(_NUMBER.fullmatch(p.strip()) for p in parts[:2])
            or not _COUNT.fullmatch(parts[2].strip())):
        raise TuningError(f"a range is 'lo:hi:n' (degrees, count), got {text!r}")
    lo, hi, n = float(parts[0]), float(parts[1]), int(parts[2])
    if not (math.isfinite(lo) and math.isfinite(hi) and math.isfinite(hi - lo)):  # -1e308:1e308 gave NaN angles
        raise TuningError(f"a range's bounds must be finite degrees, got {text!r}")
    if not 1 <= n <= MAX_RANGE_ANGLES:
        raise TuningError(f"a range gives 1 to {MAX_RANGE_ANGLES} angles, got n={n} in {text!r}")
    return np.linspace(lo, hi, n)
