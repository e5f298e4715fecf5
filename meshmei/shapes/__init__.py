"""Meshes to start from and to reconstruct: primitives, targets, isotropic remeshing, unit-diagonal normalisation."""

import sys
import threading
import warnings

# pymeshlab is imported here, with meshmei (meshmei.shapes.remeshing says why). meshmei imported first in a
# worker thread brings pymeshlab in there, and such a process aborted at exit (3 of 3 tries: a thread that
# imported meshmei and ran a 3D-MEI; 1 of 1 that only imported it): only the caller can move the import
if "pymeshlab" not in sys.modules and threading.current_thread() is not threading.main_thread():
    warnings.warn(f"meshmei is imported in the thread {threading.current_thread().name!r}, not the main thread: "
                  "pymeshlab, which comes with it, has aborted such processes at exit (a corrupted heap, "
                  "'malloc_consolidate'); import meshmei at the top of your program, in the main thread",
                  RuntimeWarning, stacklevel=2)

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
