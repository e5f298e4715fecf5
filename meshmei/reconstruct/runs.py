"""Reconstruction outputs on disk: the mesh, the history and settings as JSON, and the figures."""

from __future__ import annotations

import json
import os
from pathlib import Path

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
        ``directory`` exists and ``overwrite`` is False.
    """
    record = {k: os.fspath(v) if isinstance(v, os.PathLike) else v for k, v in record.items()}  # target=Path(...)
    own = result.to_json()
    clash = sorted(set(record) & set(own))
    if clash:  # final={...} replaced the result's own final metrics in history.json
        raise ReconstructionError(f"the record's {clash} would replace the result's own fields in history.json; "
                                  "rename them")
    history = json.dumps({**own, **record}, indent=1)  # fails, if it must, before anything is written

    def write(tmp: Path) -> None:
        save_mesh(tmp / "mesh.obj", result.V, result.F)
        (tmp / "history.json").write_text(history)
        reconstruction_figures(result, tmp)

    return atomic_directory(directory, write, overwrite=overwrite, error=ReconstructionError)
