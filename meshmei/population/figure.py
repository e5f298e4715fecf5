"""The population's summary figure: 3D-MEI against pixel-MEI responses, and their ratio."""

from __future__ import annotations

import math
from pathlib import Path

from ..plots import new_figure

__all__ = ["population_figure"]


def population_figure(out, rows: list[dict]) -> Path:
    """Write ``population.png``: a scatter of 3D-MEI against pixel-MEI response per neuron (with the
    diagonal) and a histogram of their ratio; without pixel MEIs, the 3D-MEI responses by neuron."""
    path = Path(out) / "population.png"
    paired = [r for r in rows if r.get("pixel_mei_response") is not None]
    fig = new_figure(figsize=(9, 4))  # no pyplot, no backend switch in the caller's session (meshmei.plots)
    axes = fig.subplots(1, 2)
    if paired:
        x = [r["pixel_mei_response"] for r in paired]
        y = [r["mei_response"] for r in paired]
        lo, hi = min(x + y + [0.0]), max(x + y)
        axes[0].plot([lo, hi], [lo, hi], color="0.6", lw=1, label="3D-MEI = pixel MEI")
        axes[0].scatter(x, y, s=14)
        axes[0].set_xlabel("pixel-MEI response")
        axes[0].set_ylabel("3D-MEI response")
        axes[0].legend(loc="upper left", frameon=False)
        ratios = [r["ratio"] for r in paired if r["ratio"] is not None and math.isfinite(r["ratio"])]
        axes[1].hist(ratios, bins=max(5, min(30, len(ratios))), color="C1")
        axes[1].set_xlabel("3D-MEI / pixel-MEI response")
        axes[1].set_ylabel("neurons")
    else:
        axes[0].bar([r["neuron"] for r in rows], [r["mei_response"] for r in rows])
        axes[0].set_xlabel("neuron")
        axes[0].set_ylabel("3D-MEI response")
        axes[1].axis("off")
    fig.suptitle(f"{len(rows)} neurons")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path
