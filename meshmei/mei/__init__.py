"""3D maximally exciting inputs: settings, the optimisation, baselines, run directories, and the pixel MEI."""

from .baselines import grid_search, random_deformations, random_mesh_responses
from .batch import mei_batches, optimize_mei_batch
from .diverse import DiverseMEIs, diverse_meis
from .optimize import optimize_mei
from .pixel import PixelMEIResult, gaussian_blur, pixel_image_size, pixel_mei
from .runs import RUN_FORMAT, load_run, save_run
from .settings import (ALBEDO_MIN_STEPS, DEFAULT_CONTACT_WEIGHT, DEFAULT_SIGMA_FACTOR, DEFAULT_STEPS, MEIResult,
                       MEISettings)

__all__ = [
    "MEISettings",
    "MEIResult",
    "DEFAULT_CONTACT_WEIGHT",
    "DEFAULT_SIGMA_FACTOR",
    "DEFAULT_STEPS",
    "ALBEDO_MIN_STEPS",
    "optimize_mei",
    "optimize_mei_batch",
    "mei_batches",
    "diverse_meis",
    "DiverseMEIs",
    "grid_search",
    "random_deformations",
    "random_mesh_responses",
    "save_run",
    "load_run",
    "RUN_FORMAT",
    "pixel_mei",
    "pixel_image_size",
    "PixelMEIResult",
    "gaussian_blur",
]
