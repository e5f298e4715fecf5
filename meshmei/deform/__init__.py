"""Parameterisations of a mesh's vertices: Gaussian RBF offsets, and large steps."""

from .rbf import *  # noqa: F401,F403
from .rbf import __all__ as _rbf_all
from .largesteps import *  # noqa: F401,F403
from .largesteps import __all__ as _ls_all

__all__ = list(_rbf_all) + list(_ls_all)
