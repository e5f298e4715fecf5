"""Reconstruction outputs on disk: the mesh, the history and settings as JSON, and the figures."""

from __future__ import annotations

import json
import os
from pathlib import Path

from .._checks import non_finite_entry
from .._files import atomic_directory
from ..errors import ReconstructionError
from ..mesh import save_mesh
from ..plots import reconstruction_figures
from .settings import ReconstructionResult

__all__ = ["save_reconstruction"]


def save_reconstruction(result: ReconstructionResult, directory, *, overwrite: bool = False, **record) -> Path:
    """Write ``mesh.obj``, ``history.json`` (:meth:`ReconstructionResult.to_json` plus ``record``, e.g. the
    start and target names), ``loss.png`` and ``metrics.png`` as the folder ``directory``, all at once
    (:func:`meshmei._files.atomic_directory`): a save that fails leaves no folder, and a folder that exists
    (another run's, another command's) is replaced only with ``overwrite``.

    Raises
    ------
    ReconstructionError
        ``directory`` exists and ``overwrite`` is False; a number of the result or of ``record`` is NaN or Inf
        (standard JSON has neither; the message names its key), before anything is written.
    """
    record = {k: os.fspath(v) if isinstance(v, os.PathLike) else v for k, v in record.items()}  # target=Path(...)
    own = result.to_json()
    clash = sorted(set(record) & set(own))
    if clash:  # final={...} replaced the result's own final metrics in history.json
        raise ReconstructionError(f"the record's {clash} would replace the result's own fields in history.json; "
                                  "rename them")
    bad = non_finite_entry(record)
    if bad is not None:  # written as NaN or Infinity, which JSON does not have
        raise ReconstructionError(f"the record's {bad[0]} is {bad[1]}: JSON has no NaN or Infinity; give a finite "
                                  "number or None")
    # fails, if it must, before anything is written; allow_nan=False: never NaN or Infinity in the file
    history = json.dumps({**own, **record}, indent=1, allow_nan=False)

    def write(tmp: Path) -> None:
        save_mesh(tmp / "mesh.obj", result.V, result.F)
        (tmp / "history.json").write_text(history)
        reconstruction_figures(result, tmp)

    return atomic_directory(directory, write, overwrite=overwrite, error=ReconstructionError)
