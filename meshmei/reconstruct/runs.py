"""Reconstruction outputs on disk: the mesh, the history and settings as JSON, and the figures."""

from __future__ import annotations

import json
from pathlib import Path

from ..mesh import save_mesh
from .settings import ReconstructionResult

__all__ = ["save_reconstruction", "plot_history"]


def save_reconstruction(result: ReconstructionResult, directory, **record) -> Path:
    """Write ``mesh.obj``, ``history.json`` (:meth:`ReconstructionResult.to_json` plus ``record``, e.g. the
    start and target names), ``loss.png`` and ``metrics.png`` into ``directory`` (created if needed)."""
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    save_mesh(out / "mesh.obj", result.V, result.F)
    (out / "history.json").write_text(json.dumps({**result.to_json(), **record}, indent=1))
    plot_history(result, out)
    return out


# MERGE: plot_history moves to meshmei.plots
def plot_history(result: ReconstructionResult, out_dir) -> list[Path]:
    """Write ``loss.png`` (loss against time) and ``metrics.png`` (Chamfer-L2, F-score, normal consistency
    against time) into ``out_dir``; returns the paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    h = result.history
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.semilogy([r["time"] for r in h], [r["loss"] for r in h], lw=0.8)
    ax.set_xlabel("optimisation time (s)")
    ax.set_ylabel("loss")
    ax.set_title(f"{result.settings.method}: training loss")
    fig.tight_layout()
    p1 = out_dir / "loss.png"
    fig.savefig(p1, dpi=120)
    plt.close(fig)
    m = result.metrics
    fig, axs = plt.subplots(1, 3, figsize=(12, 3.5))
    t = [r["time"] for r in m]
    axs[0].semilogy(t, [r["chamfer_l2"] for r in m], "o-")
    axs[0].set_ylabel("Chamfer-L2")
    axs[1].plot(t, [r["fscore"] for r in m], "o-")
    axs[1].set_ylabel("F-score @ 1%")
    axs[2].plot(t, [r["normal_consistency"] for r in m], "o-")
    axs[2].set_ylabel("normal consistency")
    for a in axs:
        a.set_xlabel("optimisation time (s)")
    fig.tight_layout()
    p2 = out_dir / "metrics.png"
    fig.savefig(p2, dpi=120)
    plt.close(fig)
    return [p1, p2]
