"""Shape reconstruction by Chamfer minimisation: settings, schedules, sources and targets, the fit, outputs."""

from .fit import reconstruct, stage_weights
from .runs import save_reconstruction
from .schedule import (
    FOUR_LEVEL_MIN_VERTICES,
    NAMED_SCHEDULES,
    RBF_FOUR_LEVEL_OVERRIDES,
    RBF_THREE_LEVEL_OVERRIDES,
    THREE_LEVEL_MIN_VERTICES,
    default_schedule,
    default_stages,
    schedule_from_text,
)
from .settings import (
    DEFAULT_STEPS,
    DEFAULTS,
    METHODS,
    STAGE_FIELDS,
    ReconstructionResult,
    ReconstructionSettings,
    ReconstructionWarning,
)
from .openings import find_opening, torus_through_opening
from .sources import SOURCE_NAMES, resolve_source, source_mesh, target_surface

__all__ = [
    "reconstruct",
    "ReconstructionSettings",
    "ReconstructionResult",
    "ReconstructionWarning",
    "METHODS",
    "STAGE_FIELDS",
    "DEFAULTS",
    "DEFAULT_STEPS",
    "stage_weights",
    "default_stages",
    "default_schedule",
    "RBF_THREE_LEVEL_OVERRIDES",
    "RBF_FOUR_LEVEL_OVERRIDES",
    "THREE_LEVEL_MIN_VERTICES",
    "FOUR_LEVEL_MIN_VERTICES",
    "schedule_from_text",
    "NAMED_SCHEDULES",
    "SOURCE_NAMES",
    "source_mesh",
    "resolve_source",
    "target_surface",
    "find_opening",
    "torus_through_opening",
    "save_reconstruction",
]
