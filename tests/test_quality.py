"""Mesh health and triangle quality: self-intersections, degenerate and flipped faces."""

from __future__ import annotations

import math

import pytest
import torch

from meshmei.errors import MeshError
from meshmei.quality import mesh_health, mesh_quality, triangle_quality

from conftest import grid_sheet


def test_mesh_health_counts():
    # two triangles crossing each other, one degenerate triangle, none sharing vertices
    V = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0],
                      [0.2, 0.2, -0.5], [0.2, 0.2, 0.5], [0.8, -0.5, 0.0],
                      [5, 5, 5], [6, 5, 5], [7, 5, 5]], dtype=torch.float64)
    F = torch.tensor([[0, 1, 2], [3, 4, 5], [6, 7, 8]])
    h = mesh_health(V, F)
    assert h.self_intersections == 1
    assert h.degenerate_faces == 1
    assert h.flipped_faces is None
    Vs, Fs = grid_sheet(4, 4)
    W = Vs.clone()
    W[:, 0] *= -1  # mirror the flat sheet in x: every normal turns from +z to -z
    assert mesh_health(W, Fs, Vs).flipped_faces == Fs.shape[0]
    assert mesh_health(Vs, Fs, Vs).as_dict() == {"self_intersections": 0, "degenerate_faces": 0, "flipped_faces": 0}
    with pytest.raises(MeshError):
        mesh_health(Vs, Fs, Vs[:5])


def test_triangle_quality():
    V = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0.5, math.sqrt(3) / 2, 0], [2, 0, 0]], dtype=torch.float64)
    F = torch.tensor([[0, 1, 2], [0, 1, 3]])
    q = triangle_quality(V, F)
    torch.testing.assert_close(q, torch.tensor([1.0, 0.0], dtype=torch.float64))
    assert mesh_quality(V, F)["min_quality"] == 0.0
