"""meshmei's compiled kernels as a library (``meshmei.native``): built once and cached, per machine; where
no compiler works, or they are disabled, the torch and NumPy code gives the same images and contact pairs."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest
import torch

from meshmei import native
from meshmei.contact import ContactBarrier, mean_edge_length
from meshmei.native import native_status, torch_reference
from meshmei.render import RenderSettings, render
from meshmei.shapes import initial_mesh

HAS_CC = any(shutil.which(c) for c in ("cc", "gcc", "clang"))
needs_cc = pytest.mark.skipif(not HAS_CC, reason="no C compiler on this machine: the torch code runs")


@needs_cc
def test_this_machine_compiles_the_kernels():
    st = native_status()
    assert st["compiled"], st["reason"]
    assert native.available(torch.zeros(1)) and native.available(torch.zeros(1, dtype=torch.float64))
    assert not native.available(torch.zeros(1, dtype=torch.float16))
    with torch_reference():
        assert not native.available(torch.zeros(1)) and not native.enabled()
    assert native.available(torch.zeros(1)) and native.enabled()


def _crumpled_sphere():
    V, F = initial_mesh("sphere", n_vertices=300, dtype=torch.float64)
    h = mean_edge_length(V, F)
    return V + 0.35 * h * torch.randn(V.shape, generator=torch.Generator().manual_seed(3), dtype=V.dtype), F, h


_PROBE = """
import warnings, torch
warnings.simplefilter("always")
from meshmei.contact import ContactBarrier
from meshmei.render import render, RenderSettings
from meshmei.native import native_status
from meshmei.shapes import initial_mesh
from test_native import _crumpled_sphere
V, F = initial_mesh("sphere", n_vertices=300)
with warnings.catch_warnings(record=True) as w:
    img = render(V, F, settings=RenderSettings(image_size=24))
    Vc, Fc, h = _crumpled_sphere()
    pairs = ContactBarrier(Fc, h / 3, edges=True).candidates(Vc)
    st = native_status()
torch.save({"img": img, "pairs": pairs, "st": st, "warnings": [str(x.message) for x in w]}, OUT)
"""


@pytest.mark.parametrize("how", ["no compiler", "compiler fails", "disabled"])
def test_without_a_compiler_the_torch_code_renders_the_image_and_finds_the_pairs(tmp_path, how):
    out = tmp_path / "probe.pt"
    env = {k: v for k, v in os.environ.items() if k != "CC"}
    env["MESHMEI_CACHE_DIR"] = str(tmp_path / "cache")  # nothing cached: a compiler would be needed
    env["PYTHONPATH"] = os.pathsep.join([os.path.dirname(__file__), env.get("PYTHONPATH", "")])
    if how == "no compiler":
        env["PATH"] = str(tmp_path)  # finds no cc, gcc or clang
    elif how == "compiler fails":
        if not shutil.which("false"):
            pytest.skip("no 'false' program to stand in for a failing compiler")
        env["CC"] = "false"  # found, exits 1
    else:
        env["MESHMEI_NATIVE"] = "0"
    r = subprocess.run([sys.executable, "-c", _PROBE.replace("OUT", repr(str(out)))], env=env, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    got = torch.load(out)
    assert not got["st"]["compiled"]
    if how != "disabled":
        assert ("no C compiler" if how == "no compiler" else "failed") in got["st"]["reason"]
        assert sum("compiled kernels are not available" in m for m in got["warnings"]) == 1
    else:
        assert got["st"]["reason"] == "disabled by MESHMEI_NATIVE" and not got["warnings"]
    V, F = initial_mesh("sphere", n_vertices=300)
    Vc, Fc, h = _crumpled_sphere()
    with torch_reference():
        torch.testing.assert_close(got["img"], render(V, F, settings=RenderSettings(image_size=24)), rtol=0, atol=0)
        want = ContactBarrier(Fc, h / 3, edges=True).candidates(Vc)
    assert len(want[0]) > 0 and len(want[2]) > 0
    assert all(torch.equal(a, b) for a, b in zip(got["pairs"], want))


@needs_cc
def test_a_build_is_cached_and_reused(tmp_path):
    """A second process finds the first one's build and compiles nothing."""
    env = {**os.environ, "MESHMEI_CACHE_DIR": str(tmp_path)}
    code = "from meshmei.native import native_status; print(native_status())"
    for _ in range(2):
        r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
        assert r.returncode == 0 and "'compiled': True" in r.stdout, r.stderr[-2000:]
    builds = list(tmp_path.glob("kernels-*.so"))
    assert len(builds) == 1 and sorted(tmp_path.iterdir()) == builds  # no temporary left behind


@needs_cc
def test_a_cache_directory_that_cannot_be_made_builds_in_the_temporary_directory(tmp_path):
    env = {**os.environ, "MESHMEI_CACHE_DIR": "/dev/null/meshmei", "TMPDIR": str(tmp_path)}
    code = "from meshmei.native import native_status; print(native_status())"
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and "'compiled': True" in r.stdout, r.stderr[-2000:]
    assert len(list(tmp_path.glob("meshmei-*/kernels-*.so"))) == 1


@pytest.mark.parametrize("functions", [None, 2])
def test_one_mesh_is_a_batch_of_one_for_the_kernel_and_its_node_is_on_the_mesh(functions):
    """kernel_buffers takes V (n, 3) as a batch of one; with_gradient hands the values back without that axis
    and its node's gradient has V's own shape (not one autograd would have to reduce)."""
    from meshmei.native import kernel_buffers, with_gradient

    V = torch.randn(5, 3, dtype=torch.float64, requires_grad=True)
    Vd, value, grad = kernel_buffers(V, functions)
    lead = () if functions is None else (functions,)
    assert Vd.shape == (1, 5, 3) and value.shape == lead + (1,) and grad.shape == lead + (1, 5, 3)
    value[...] = 3.0
    for k in range(functions or 1):
        grad[(k,) if functions else ()] = k + 1.0
    out = with_gradient(V, value, grad)
    assert out.shape == lead and torch.equal(out, torch.full(lead, 3.0, dtype=torch.float64))
    raw = out.grad_fn.apply(torch.ones(lead, dtype=torch.float64))[0]
    assert raw.shape == V.shape and torch.equal(raw, torch.full((5, 3), 3.0 if functions else 1.0, dtype=torch.float64))
