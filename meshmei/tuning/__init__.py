"""Tuning in 3D: sweep an optimised mesh's pose and its light over physical axes and record responses.

:mod:`.grids` defines the axes (object rotations, light positions on the camera-facing hemisphere),
:mod:`.sweeps` renders and records the responses over them, :mod:`.views` renders the example conditions
for figures, :mod:`.files` saves and loads sweeps, and :mod:`.run` sweeps a saved run (``meshmei tune``).
"""

from ..errors import TuningError
from .files import SWEEP_FORMAT, load_sweep, save_sweep
from .grids import check_angles, light_positions, parse_range, pose_rotations
from .run import run_tuning
from .sweeps import Sweep, camera_distance, light_sweep, pose_sweep, response_groups
from .views import example_renders, turned_views

__all__ = [
    "TuningError",
    "Sweep",
    "check_angles",
    "pose_rotations",
    "light_positions",
    "camera_distance",
    "pose_sweep",
    "light_sweep",
    "response_groups",
    "example_renders",
    "turned_views",
    "SWEEP_FORMAT",
    "save_sweep",
    "load_sweep",
    "run_tuning",
    "parse_range",
]
