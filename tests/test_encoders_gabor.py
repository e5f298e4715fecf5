"""Gabor cells: the exact bounds of simple and complex cells, neuron selection, the orientation convention."""

from __future__ import annotations

import math

import pytest
import torch

from meshmei.encoders import GaborComplexCell, GaborSimpleCell, gabor_filters

CELL_PARAMS = [
    {},
    dict(x0=0.2, y0=-0.1, orientation=1.1, frequency=6.0, sigma=0.2, aspect=1.5, phase=0.7),
]


@pytest.mark.parametrize("params", CELL_PARAMS)
@pytest.mark.parametrize("size", [(32, 32), (40, 56)])
def test_simple_cell_bound_reached_by_the_filter_itself(params, size):
    H, W = size
    cell = GaborSimpleCell(mean=0.0, std=1.0, **params)
    g = cell.filters(H, W)[0]  # (1, H, W) unit-norm, zero-mean
    torch.testing.assert_close(g.sum(), torch.tensor(0.0, dtype=torch.float64), atol=1e-12, rtol=0)
    torch.testing.assert_close(g.norm(), torch.tensor(1.0, dtype=torch.float64))
    r = cell(g.view(1, 1, H, W))
    assert abs(float(r) - 1.0) < 1e-12
    # any image of the form mean + c * filter reaches it under other statistics too
    cell = GaborSimpleCell(**params)
    assert abs(float(cell(cell.optimal_image(0, H, W, contrast=0.2))) - 1.0) < 1e-12
    # the negative filter gives exactly -1; random images stay inside [-1, 1]
    assert abs(float(cell(cell.optimal_image(0, H, W, contrast=-0.2))) + 1.0) < 1e-12
    r = cell(torch.rand(64, 1, H, W, dtype=torch.float64))
    assert r.abs().max() < 1


@pytest.mark.parametrize("params", CELL_PARAMS)
def test_complex_cell_quadrature_pair_and_phase_invariance(params):
    H = W = 48
    cell = GaborComplexCell(**params)
    G = cell.filters(H, W)[0].flatten(1)  # (2, H*W)
    torch.testing.assert_close(G @ G.T, torch.eye(2, dtype=torch.float64), atol=1e-12, rtol=0)
    torch.testing.assert_close(G.sum(1), torch.zeros(2, dtype=torch.float64), atol=1e-12, rtol=0)
    # exact optima for every phase
    for phi in torch.linspace(0, 2 * math.pi, 9):
        r = cell(cell.optimal_image(0, H, W, phase=float(phi)))
        assert abs(float(r) - 1.0) < 1e-12
        assert abs(math.remainder(float(cell.phase_of(cell.optimal_image(0, H, W, phase=float(phi)))) - float(phi),
                                  2 * math.pi)) < 1e-9
    # mean-free raw Gabors of any phase (same other parameters) give the same response: the pair spans them
    p = dict(x0=0.0, y0=0.0, orientation=0.0, frequency=4.0, sigma=0.35, aspect=1.0)
    p.update({k: v for k, v in params.items() if k != "phase"})
    raw = torch.stack([gabor_filters(H, W, phase=ph, **p)[0] for ph in (0.0, 0.4, 1.9, 3.0, 5.5)])
    imgs = 0.5 + 0.1 * (raw - raw.mean((1, 2), keepdim=True))
    r = cell(imgs.unsqueeze(1))
    assert float(r.max() - r.min()) < 1e-12
    assert abs(float(r.max()) - 1.0) < 1e-12
    # bounded on random images
    assert float(cell(torch.rand(64, 1, H, W, dtype=torch.float64)).max()) < 1


def test_gabor_bank_evaluates_only_requested_neurons():
    cell = GaborComplexCell(orientation=[0.0, 0.5, 1.0], frequency=[3.0, 4.0, 5.0])
    assert cell.n_neurons == 3
    x = torch.rand(4, 1, 32, 32)
    full = cell(x)
    torch.testing.assert_close(cell(x, neurons=[2, 0]), full[:, [2, 0]])
    torch.testing.assert_close(cell(x, neurons=1), full[:, [1]])


def test_orientation_convention():
    # orientation 0: wave vector along +x, vertical stripes (constant down each column)
    g = gabor_filters(16, 16, x0=0, y0=0, orientation=0.0, frequency=2.0, sigma=100.0, aspect=1.0, phase=0.0)[0]
    torch.testing.assert_close(g, g[:1].expand(16, 16), atol=1e-3, rtol=0)
    # orientation pi/2: horizontal stripes
    g = gabor_filters(16, 16, x0=0, y0=0, orientation=math.pi / 2, frequency=2.0, sigma=100.0, aspect=1.0, phase=0.0)[0]
    torch.testing.assert_close(g, g[:, :1].expand(16, 16), atol=1e-3, rtol=0)
