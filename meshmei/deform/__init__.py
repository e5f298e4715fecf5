"""Parameterisations of a mesh's vertices: Gaussian RBF offsets and scales, raw vertex offsets, large steps."""

from .largesteps import AdamUniform, DifferentialSolver, system_matrix
from .params import (
    MIN_COARSE_KERNELS,
    PARAMETERISATIONS,
    LargeStepsParameterisation,
    Parameterisation,
    RBFParameterisation,
    VertexParameterisation,
)
from .rbf import MAX_LR_SCALE, NarrowKernelError, RBFDeformer, farthest_point_sampling, rbf_dense

__all__ = [
    "RBFDeformer",
    "NarrowKernelError",
    "farthest_point_sampling",
    "rbf_dense",
    "MAX_LR_SCALE",
    "system_matrix",
    "DifferentialSolver",
    "AdamUniform",
    "Parameterisation",
    "RBFParameterisation",
    "VertexParameterisation",
    "LargeStepsParameterisation",
    "PARAMETERISATIONS",
    "MIN_COARSE_KERNELS",
]
