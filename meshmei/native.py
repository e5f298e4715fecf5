"""meshmei's compiled kernels: four small C files built on first use into one shared library, with the torch
(and NumPy) code as their reference and fallback.

- ``render/_raster.c``: the renderer's CPU kernels (:mod:`meshmei.render.native`);
- ``_contact.c``: the contact barrier's broad phase and its energy with the gradient
  (:class:`meshmei.contact.ContactBarrier`) and the certificates' rules (:mod:`meshmei.certify`);
- ``_guard.c``: the step guard's float64 face frame with its quality and turn rules, and its barrier with
  the gradient (:class:`meshmei.validity.StepGuard`);
- ``_regularizers.c``: the uniform Laplacian, edge and area losses with their gradients
  (:mod:`meshmei.regularizers`).

They are compiled once per source version with the system's C compiler (``$CC``, else ``cc``, ``gcc`` or
``clang``) into the cache directory (``$MESHMEI_CACHE_DIR``, else ``$XDG_CACHE_HOME/meshmei`` or
``~/.cache/meshmei``; the temporary directory where that cannot be written), in about two seconds, keyed by
a hash of the sources, the compiler, its flags and the machine's architecture, and loaded with
:mod:`ctypes` (which releases the GIL for the call). Where no compiler works, or with ``MESHMEI_NATIVE=0``,
the torch and NumPy code runs instead, unchanged, with one warning; :func:`native_status` says which is in
use and why. CUDA tensors always run the torch code.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
import warnings
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch
from torch.autograd.function import once_differentiable

__all__ = ["native_status", "torch_reference", "available", "enabled", "library", "kernel_buffers", "with_gradient"]

_HERE = Path(__file__).parent
# each file's ABI version, which its ``meshmei_<name>_abi()`` returns
_SOURCES = {"raster": (_HERE / "render" / "_raster.c", 5), "contact": (_HERE / "_contact.c", 6),
            "guard": (_HERE / "_guard.c", 2), "regularizers": (_HERE / "_regularizers.c", 1)}
_FLAGS = ["-O3", "-std=c99", "-shared", "-fPIC", "-ffp-contract=off", "-fno-fast-math"]

_i64, _p, _dbl = ctypes.c_int64, ctypes.c_void_p, ctypes.c_double
_SIGNATURES = {
    **{f"front_{t}": [_i64, _i64, _i64, _p, _p, _p, _p, _p, _p, _i64, _dbl, _dbl] + [_p] * 22 for t in ("f32", "f64")},
    **{f"sample_fwd_{t}": [_i64, _p, _p, _p, _p, _i64, _p, _p, _i64, _p, _p, _p, _p, _i64, _p, _i64, _dbl, _dbl, _p,
                           _p, _p, _p] for t in ("f32", "f64")},
    **{f"sample_bwd_{t}": [_i64, _p, _p, _i64, _i64, _p, _p, _i64, _p, _p, _p, _p, _i64, _p, _i64, _dbl, _dbl, _p, _p,
                           _p, _p, _p, _p, _p, _p] for t in ("f32", "f64")},
    **{f"shade_fwd_{t}": [_i64, _i64, _p, _p, _p, _p, _dbl, _dbl, _dbl, _dbl, _p] for t in ("f32", "f64")},
    **{f"shade_bwd_{t}": [_i64, _i64, _p, _p, _p, _p, _dbl, _dbl, _dbl, _dbl, _p, _p, _p, _p, _p]
       for t in ("f32", "f64")},
    **{f"normals_fwd_{t}": [_i64, _i64, _i64, _p, _p, _dbl, _p, _p] for t in ("f32", "f64")},
    **{f"normals_bwd_{t}": [_i64, _i64, _i64, _p, _p, _dbl, _p, _p, _p, _p] for t in ("f32", "f64")},
    "contact_vertex_face": [_i64, _p, _i64, _p, _dbl, _i64, _p, _p, _p],
    "contact_edge_edge": [_i64, _p, _i64, _p, _p, _dbl, _i64, _p, _p, _p],
    "contact_vertex_face_distances": [_p, _p, _i64, _p, _p, _p],
    "contact_edge_edge_distances": [_p, _p, _i64, _p, _p, _p],
    "contact_energy": [_i64, _p, _p, _p, _p, ctypes.c_int, _i64, _i64, _dbl, _dbl, _p, _p, _p],
    "separation_fans": [_i64, _p, _i64, _p, _p, _p, _p],
    "guard_frame_parts": [_i64, _i64, _p, _p, ctypes.c_int, _p, _p, _p],
    "guard_frame_finish": [_i64, _p, _p, _p, _dbl, _dbl, _p, _dbl, _p, _p, _p, _p],
    "guard_barrier": [_i64, _i64, _i64, _p, _p, _p, _p, _dbl, _dbl, _dbl, _dbl, _dbl, _dbl, _dbl, _p, _p],
    "graph_holds": [_i64, _p, _i64, _p, _p, _p, _p, _p, _p, _i64, _p, _p, _p, _p, _dbl, _dbl, _p],
    "star_holds": [_i64, _p, _i64, _p, _p, _p, _dbl, _p],
    "reg_losses": [_i64, _i64, _i64, _i64, _p, _p, _p, _p, _p, ctypes.c_int, _p, _p],
}
_RETURNS = {"contact_vertex_face": _i64, "contact_edge_edge": _i64, "guard_frame_parts": ctypes.c_int,
            "guard_barrier": ctypes.c_int,
            "graph_holds": ctypes.c_int, "star_holds": ctypes.c_int, "reg_losses": ctypes.c_int}

_lock = threading.Lock()
_state: dict = {"lib": None, "reason": None, "tried": False}
_local = threading.local()  # torch_reference() in this thread


def _compiler() -> str | None:
    for name in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def _cache_dir() -> Path:
    if os.environ.get("MESHMEI_CACHE_DIR"):
        return Path(os.environ["MESHMEI_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "meshmei"


def _build() -> ctypes.CDLL:
    """Compile (unless a build of these sources and flags is cached) and load; raises OSError or
    RuntimeError with the reason."""
    cc = _compiler()
    if cc is None:
        raise RuntimeError("no C compiler found (set $CC, or install cc, gcc or clang)")
    sources = [path for path, _ in _SOURCES.values()]
    # keyed by the sources, the compiler and its flags, and the platform: a home directory shared by the nodes
    # of a cluster may hold builds for several architectures
    key = " ".join([cc, *_FLAGS, sys.platform, platform.machine()]).encode()
    tag = hashlib.sha256(b"".join(p.read_bytes() for p in sources) + key).hexdigest()[:16]
    out = _cache_dir() / f"kernels-{tag}.so"
    if not out.exists():
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
            writable = os.access(out.parent, os.W_OK)
        except OSError:
            writable = False
        if not writable:  # a read-only home: the temporary directory, one folder per user
            out = Path(tempfile.gettempdir()) / f"meshmei-{os.getuid() if hasattr(os, 'getuid') else 0}" / out.name
            out.parent.mkdir(parents=True, exist_ok=True)
    if not out.exists():
        # a private temporary name, then an atomic rename: parallel processes (test workers) may build at once
        fd, tmp = tempfile.mkstemp(suffix=".so", dir=out.parent)
        os.close(fd)
        try:
            r = subprocess.run([cc, *_FLAGS, "-o", tmp, *map(str, sources), "-lm"], capture_output=True, text=True,
                               timeout=120)
            if r.returncode != 0:
                raise RuntimeError(f"{cc} failed: {(r.stderr or r.stdout).strip()[:500]}")
            os.replace(tmp, out)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
    lib = ctypes.CDLL(str(out))
    for name, (path, abi) in _SOURCES.items():
        if getattr(lib, f"meshmei_{name}_abi")() != abi:
            raise RuntimeError(f"{out} is a build of another version of {path.name}")
    for name, argtypes in _SIGNATURES.items():
        getattr(lib, name).argtypes = argtypes
        getattr(lib, name).restype = _RETURNS.get(name)
    return lib


def library():
    """The loaded kernels (a :class:`ctypes.CDLL`), built on the first call; None where they cannot be
    (:func:`native_status` says why)."""
    if _state["tried"]:
        return _state["lib"]
    with _lock:
        if not _state["tried"]:
            if os.environ.get("MESHMEI_NATIVE", "1").strip().lower() in ("0", "false", "no", "off"):
                _state["reason"] = "disabled by MESHMEI_NATIVE"
            else:
                try:
                    _state["lib"] = _build()
                except (OSError, RuntimeError, subprocess.SubprocessError) as e:
                    _state["reason"] = f"{type(e).__name__}: {e}"
                    warnings.warn(f"meshmei: the compiled kernels are not available ({_state['reason']}); the "
                                  "torch and NumPy code runs instead (results equal to rounding, slower on CPU)",
                                  RuntimeWarning, stacklevel=3)
            _state["tried"] = True
    return _state["lib"]


def native_status() -> dict:
    """``{"compiled": bool, "reason": str | None}``: whether the compiled kernels are in use (CPU renders,
    the contact barrier's search and energy, the step guard's check and barrier, three regularizers), and why
    not."""
    lib = library()
    return {"compiled": lib is not None, "reason": _state["reason"]}


@contextmanager
def torch_reference():
    """Within this block (in this thread) the compiled kernels are not used: renders run the torch code
    throughout, the contact barrier searches with its NumPy and SciPy code and measures in torch, the step
    guard checks with its torch and NumPy code and its barrier is torch's, and so are the regularizers. The
    reference the kernels are tested against, and what CUDA tensors always run. A render's backward follows
    its forward; a contact search started here in a worker thread
    (:meth:`~meshmei.contact.ContactBarrier.prefetch`) follows the thread that started it."""
    before = getattr(_local, "off", False)
    _local.off = True
    try:
        yield
    finally:
        _local.off = before


def enabled() -> bool:
    """Whether this thread may use the compiled kernels now (built, and not within :func:`torch_reference`)."""
    return not getattr(_local, "off", False) and library() is not None


def available(t: torch.Tensor) -> bool:
    """Whether the compiled kernels take this tensor's device and dtype here and now."""
    return t.device.type == "cpu" and t.dtype in (torch.float32, torch.float64) and enabled()


class _WithGradient(torch.autograd.Function):
    """:func:`with_gradient`'s node: its forward copies the value, its backward scales the kept gradient (and
    sums it over the functions, where there are several)."""

    @staticmethod
    def forward(ctx, V, value, G):
        ctx.save_for_backward(G)
        ctx.several = G.ndim > V.ndim
        return value.clone()

    @staticmethod
    @once_differentiable
    def backward(ctx, g):
        (G,) = ctx.saved_tensors
        out = g.reshape(g.shape + (1,) * (G.ndim - g.ndim)) * G
        return out.sum(0) if ctx.several else out, None, None


def kernel_buffers(V: torch.Tensor, functions: int | None = None):
    """For a kernel that writes one value per item of ``V (B, n, 3)`` and, where autograd wants it, their
    gradient: ``(Vd, value, grad)``, ``V``'s coordinates as a contiguous float64 array ``(B, n, 3)``, ``(B,)``
    zeros, and zeros of ``Vd``'s shape (None where no gradient is wanted: grad mode off, or ``V`` without
    one). With ``functions`` k, for a kernel that writes k such functions: values ``(k, B)`` and gradients
    ``(k,)`` plus ``Vd``'s shape. One mesh ``V (n, 3)`` is a batch of one for the kernel (``B`` 1), and
    :func:`with_gradient` hands its values back without the batch axis. Hand them back with
    :func:`with_gradient` after the kernel has filled them."""
    Vd = np.ascontiguousarray(V.detach().numpy(), dtype=np.float64)
    if V.ndim == 2:
        Vd = Vd[None]  # (1, n, 3), still contiguous
    wanted = torch.is_grad_enabled() and V.requires_grad
    lead = () if functions is None else (functions,)
    return Vd, np.zeros(lead + Vd.shape[:1]), np.zeros(lead + Vd.shape) if wanted else None


def with_gradient(V: torch.Tensor, value: np.ndarray, grad: np.ndarray | None) -> torch.Tensor:
    """A kernel's values ``(B,)`` (one per item of ``V (B, n, 3)``), or ``(k, B)`` for k functions, as a tensor
    of ``V``'s dtype, with a graph to ``V`` whose gradient is ``grad`` (``(k,)`` and ``V``'s size) per unit of
    each value, or without one where ``grad`` is None (:func:`kernel_buffers`): what a kernel that writes a
    function and its gradient in one pass hands to autograd (the contact energy, the guard's barrier, the
    regularizers). The backward only scales ``grad`` (and sums over the functions). For one mesh ``V (n,
    3)`` (a batch of one in :func:`kernel_buffers`) the values come back as ``()``, or ``(k,)``: one node
    on ``V`` itself, where adding a batch axis and taking it off again would put two more in the graph."""
    if V.ndim == 2:  # the batch of one's axis off both
        value, grad = value[..., 0], None if grad is None else grad[..., 0, :, :]
    out = torch.from_numpy(value).to(V.dtype)
    if grad is None:
        return out
    return _WithGradient.apply(V, out, torch.from_numpy(grad).to(V.dtype).reshape(grad.shape[:-V.ndim] + V.shape))
