"""Reconstruction outputs on disk: the mesh, the history and settings as JSON, and the figures."""

from __future__ import annotations

import json
from pathlib import Path

from ..mesh import save_mesh
from ..plots import reconstruction_figures
from .settings import ReconstructionResult

__all__ = ["save_reconstruction"]


def save_reconstruction(result: ReconstructionResult, directory, **record) -> Path:
    """Write ``mesh.obj``, ``history.json`` (:meth:`ReconstructionResult.to_json` plus ``record``, e.g. the
    start and target names), ``loss.png`` and ``metrics.png`` into ``directory`` (created if needed)."""
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    save_mesh(out / "mesh.obj", result.V, result.F)
    (out / "history.json").write_text(json.dumps({**result.to_json(), **record}, indent=1))
    reconstruction_figures(result, out)
    return out
