"""Shared meshes for the tests: small analytic meshes, libigl validation meshes and adversarial cases."""

from __future__ import annotations

import numpy as np
import pytest
import torch

# The tests are about correctness. Many small tensor ops run faster on one thread than on a pool that
# stalls on each of them (measured: the render tests take 13 s single-threaded, 100 s with 2 threads on
# a shared 2-core machine). Benchmarks set their own thread counts.
torch.set_num_threads(1)

MAX_TEST_PROCESSES = 8  # each imports torch and the stack (about 0.5 GB): enough to fill a workstation


def usable_cores() -> int:
    """Cores this process may run on: its CPU affinity, and the cgroup's CPU quota where one is set (a
    container may see every core of its host but be allowed two)."""
    import os

    n = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    try:
        quota, period = open("/sys/fs/cgroup/cpu.max").read().split()[:2]
        if quota != "max":
            n = min(n, max(1, int(quota) // int(period)))
    except (OSError, ValueError):
        pass
    return max(1, n)


def pytest_xdist_auto_num_workers(config):
    """``-n auto``: one test process per usable core, at most :data:`MAX_TEST_PROCESSES`."""
    return min(usable_cores(), MAX_TEST_PROCESSES)


def grid_sheet(nx: int = 6, ny: int = 5, *, dtype=torch.float64):
    """A regular right-triangle grid in z=0 (boundary, normals +z): (V, F)."""
    xs, ys = np.meshgrid(np.linspace(0, 1, nx), np.linspace(0, 1, ny), indexing="xy")
    V = np.stack([xs.ravel(), ys.ravel(), np.zeros(nx * ny)], 1)
    F = []
    for j in range(ny - 1):
        for i in range(nx - 1):
            a, b, c, d = j * nx + i, j * nx + i + 1, (j + 1) * nx + i, (j + 1) * nx + i + 1
            F += [[a, b, d], [a, d, c]]
    return torch.tensor(V, dtype=dtype), torch.tensor(F, dtype=torch.int64)


def equilateral_sheet(nx: int = 6, ny: int = 5, *, dtype=torch.float64):
    """A triangulated patch of the equilateral lattice: every edge and every face the same size."""
    V, F = [], []
    for j in range(ny):
        for i in range(nx):
            V.append([i + 0.5 * (j % 2), j * np.sqrt(3) / 2, 0.0])
    for j in range(ny - 1):
        for i in range(nx - 1):
            a, b, c, d = j * nx + i, j * nx + i + 1, (j + 1) * nx + i, (j + 1) * nx + i + 1
            F += [[a, b, d], [a, d, c]] if j % 2 else [[a, b, c], [b, d, c]]
    return torch.tensor(V, dtype=dtype), torch.tensor(F, dtype=torch.int64)


def icosphere(subdiv: int = 1, *, dtype=torch.float64):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdiv)
    return torch.tensor(m.vertices, dtype=dtype), torch.tensor(m.faces, dtype=torch.int64)


def perturbed_sphere(subdiv: int = 3, scale: float = 0.05, seed: int = 0):
    V, F = icosphere(subdiv)
    g = torch.Generator().manual_seed(seed)
    return V + scale * torch.randn(V.shape, generator=g, dtype=V.dtype), F


def random_rotation(seed: int = 0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    Q, R = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=dtype))
    Q = Q * torch.sign(torch.diagonal(R))
    return Q if torch.det(Q) > 0 else -Q


def hard_cases(dtype=torch.float64) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
    """Adversarial but valid meshes: every operator and regularizer must stay finite on them."""
    Vs, Fs = icosphere(1, dtype=dtype)
    n = Vs.shape[0]
    cases = {}
    # three collinear vertices forming a face (zero area, non-zero edges)
    V = torch.cat([Vs, torch.tensor([[2.0, 0, 0], [2.5, 0, 0], [3.0, 0, 0]], dtype=dtype)])
    cases["collinear_face"] = (V, torch.cat([Fs, torch.tensor([[n, n + 1, n + 2]])]))
    # a face that repeats a vertex index
    cases["repeated_index"] = (Vs.clone(), torch.cat([Fs, Fs[:1, [0, 0, 1]]]))
    # duplicate vertex: a face whose two corners coincide in space (zero-length edge)
    V = torch.cat([Vs, Vs[Fs[0, 0]].unsqueeze(0)])
    cases["duplicate_vertex"] = (V, torch.cat([Fs, torch.tensor([[Fs[0, 0].item(), n, Fs[0, 1].item()]])]))
    # needle (one tiny edge) and cap (one angle near 180 degrees)
    V = torch.tensor([[0, 0, 0], [1, 0, 0], [1, 1e-9, 0], [0, 1, 0], [0.5, 1e-9, 0.0], [1, 1, 0]], dtype=dtype)
    cases["needle_and_cap"] = (V, torch.tensor([[0, 1, 2], [0, 4, 1], [0, 1, 3], [1, 5, 3]]))
    # unreferenced vertices, in the middle and at the end
    V = torch.cat([Vs, torch.full((3, 3), 7.0, dtype=dtype)])
    F = Fs.clone()
    F[F >= 5] += 1  # vertex 5 becomes unreferenced; vertex 5 is a copy shifted out
    V = torch.cat([Vs[:5], torch.tensor([[9.0, 9, 9]], dtype=dtype), Vs[5:], torch.full((2, 3), 7.0, dtype=dtype)])
    cases["unreferenced_vertices"] = (V, F)
    # non-manifold edge: three faces on one edge
    V = torch.tensor([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0, 1]], dtype=dtype)
    cases["nonmanifold_edge"] = (V, torch.tensor([[0, 1, 2], [1, 0, 3], [0, 1, 4]]))
    # a mesh with boundary
    cases["sheet_boundary"] = grid_sheet(5, 4, dtype=dtype)
    # extreme coordinate scales
    cases["scale_1e-6"] = (Vs * 1e-6, Fs.clone())
    cases["scale_1e6"] = (Vs * 1e6, Fs.clone())
    # all three corners of a face at one point
    V = torch.cat([Vs, Vs[:1].repeat(3, 1)])
    cases["point_face"] = (V, torch.cat([Fs, torch.tensor([[n, n + 1, n + 2]])]))
    return cases


@pytest.fixture(scope="session")
def bunny64():
    from meshmei.shapes import target_mesh

    V, F = target_mesh("bunny", dtype=torch.float64)
    return V, F


@pytest.fixture(scope="session")
def teapot64():
    from meshmei.shapes import target_mesh

    V, F = target_mesh("teapot", dtype=torch.float64)
    return V, F


def shipped_demo():
    """The shipped demo model's path and the model. It ships with the package (pyproject's package-data): a
    missing file fails the test (it was skipped, so a package without it passed)."""
    from meshmei.encoders import DEMO_MODEL_PATH, load_demo_model

    if not DEMO_MODEL_PATH.is_file():
        pytest.fail(f"the demo model must ship with the package: {DEMO_MODEL_PATH} is missing "
                    "(python data_gen/make_demo_model.py builds it)")
    return DEMO_MODEL_PATH, load_demo_model()
