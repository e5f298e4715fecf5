"""Meshes to start from and to reconstruct: primitives, targets, isotropic remeshing, unit-diagonal normalisation."""

from .primitives import DEFAULT_N_VERTICES, INITIAL_KINDS, initial_mesh
from .remeshing import remesh
from .targets import TARGET_NAMES, bunny_path, normalize_unit_diagonal, target_mesh

__all__ = [
    "DEFAULT_N_VERTICES",
    "INITIAL_KINDS",
    "TARGET_NAMES",
    "bunny_path",
    "initial_mesh",
    "normalize_unit_diagonal",
    "remesh",
    "target_mesh",
]
