"""The compiled half of the rasterizer's no-grad passes: a small C file built on first use, with the torch
code as its reference and fallback.

The two enumeration passes (the z-buffer over (face, pixel) pairs and the nearest-segment buffer over
(segment, pixel) pairs) are, in torch, a sequence of some twenty tensor operations per chunk of pairs: at
the image sizes of a 3D-MEI most of their time is spent dispatching operations, not computing. Their loop
bodies in C (``_raster.c``) compute the same keys bit for bit (same operations, same order, same dtype, no
fused multiply-add), on CPU tensors, in a single pass over the pairs and without materialising them.

The C file is compiled once per source version with the system's C compiler (``$CC``, else ``cc``, ``gcc``
or ``clang``) into the cache directory (``$MESHMEI_CACHE_DIR``, else ``$XDG_CACHE_HOME/meshmei`` or
``~/.cache/meshmei``), in well under a second, and loaded with :mod:`ctypes` (which releases the GIL for the
call). Where no compiler works, or with ``MESHMEI_NATIVE=0``, the torch passes run instead, unchanged, with
one warning; :func:`native_status` says which is in use and why. CUDA tensors always take the torch path.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import warnings
from contextlib import contextmanager
from pathlib import Path

import torch

__all__ = ["native_status", "zbuffer", "segment_buffer", "available", "torch_passes"]

_SOURCE = Path(__file__).with_name("_raster.c")
_FLAGS = ["-O2", "-std=c99", "-shared", "-fPIC", "-ffp-contract=off", "-fno-fast-math"]
_ABI = 1

_lock = threading.Lock()
_state: dict = {"lib": None, "reason": None, "tried": False}
_local = threading.local()  # torch_passes() in this thread


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
    """Compile (unless a build of this source and these flags is cached) and load; raises OSError or
    RuntimeError with the reason."""
    cc = _compiler()
    if cc is None:
        raise RuntimeError("no C compiler found (set $CC, or install cc, gcc or clang)")
    src = _SOURCE.read_bytes()
    tag = hashlib.sha256(src + " ".join([cc] + _FLAGS).encode() + sys.platform.encode()).hexdigest()[:16]
    out = _cache_dir() / f"raster-{tag}.so"
    if not out.exists():
        out.parent.mkdir(parents=True, exist_ok=True)
        # a private temporary name, then an atomic rename: parallel processes (test workers) may build at once
        fd, tmp = tempfile.mkstemp(suffix=".so", dir=out.parent)
        os.close(fd)
        try:
            r = subprocess.run([cc, *_FLAGS, "-o", tmp, str(_SOURCE), "-lm"], capture_output=True, text=True,
                               timeout=120)
            if r.returncode != 0:
                raise RuntimeError(f"{cc} failed: {(r.stderr or r.stdout).strip()[:500]}")
            os.replace(tmp, out)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
    lib = ctypes.CDLL(str(out))
    if lib.meshmei_raster_abi() != _ABI:
        raise RuntimeError(f"{out} is a build of another version of {_SOURCE.name}")
    i64, p, dbl = ctypes.c_int64, ctypes.c_void_p, ctypes.c_double
    for name in ("zbuffer_f32", "zbuffer_f64"):
        getattr(lib, name).argtypes = [i64, p, p, p, p, i64, p]
        getattr(lib, name).restype = None
    for name in ("segbuffer_f32", "segbuffer_f64"):
        getattr(lib, name).argtypes = [i64, p, p, p, p, i64, dbl, dbl, p]
        getattr(lib, name).restype = None
    return lib


def _lib():
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
                    warnings.warn(f"meshmei: the compiled rasterizer passes are not available ({_state['reason']}); "
                                  "the torch passes run instead (the same images, slower on CPU)", RuntimeWarning,
                                  stacklevel=3)
            _state["tried"] = True
    return _state["lib"]


def native_status() -> dict:
    """``{"compiled": bool, "reason": str | None}``: whether CPU renders use the compiled passes, and why not."""
    lib = _lib()
    return {"compiled": lib is not None, "reason": _state["reason"]}


@contextmanager
def torch_passes():
    """Within this block (in this thread) renders take the torch passes: the reference the compiled ones are
    tested against, and what CUDA tensors always take."""
    before = getattr(_local, "off", False)
    _local.off = True
    try:
        yield
    finally:
        _local.off = before


def available(t: torch.Tensor) -> bool:
    """Whether the compiled passes take this tensor's device and dtype here and now."""
    return (t.device.type == "cpu" and t.dtype in (torch.float32, torch.float64) and not getattr(_local, "off", False)
            and _lib() is not None)


def _ptr(t: torch.Tensor, dtype) -> int:
    assert t.dtype == dtype and t.is_contiguous() and t.device.type == "cpu", (t.dtype, t.shape)
    return t.data_ptr()


def zbuffer(table, lo, hi, pix0, S: int, zkey) -> None:
    """Pass 1 into ``zkey`` (in place): ``table`` ``(15, K)``, ``lo``/``hi`` ``(K, 2)``, ``pix0`` ``(K,)``."""
    lib = _lib()
    K = table.shape[1]
    table, lo, hi, pix0 = table.contiguous(), lo.contiguous(), hi.contiguous(), pix0.contiguous()
    assert table.shape == (15, K) and lo.shape == hi.shape == (K, 2) and pix0.shape == (K,)
    fn = lib.zbuffer_f32 if table.dtype == torch.float32 else lib.zbuffer_f64
    fn(K, _ptr(table, table.dtype), _ptr(lo, torch.int64), _ptr(hi, torch.int64), _ptr(pix0, torch.int64), S,
       _ptr(zkey, torch.int64))


def segment_buffer(table, lo, hi, pix0, S: int, margin: float, eps: float, skey) -> None:
    """Pass 2 into ``skey`` (in place): ``table`` ``(Q, 4)`` segment ends, ``lo``/``hi`` ``(Q, 2)``, ``pix0`` ``(Q,)``."""
    lib = _lib()
    Q = table.shape[0]
    table, lo, hi, pix0 = table.contiguous(), lo.contiguous(), hi.contiguous(), pix0.contiguous()
    assert table.shape == (Q, 4) and lo.shape == hi.shape == (Q, 2) and pix0.shape == (Q,)
    fn = lib.segbuffer_f32 if table.dtype == torch.float32 else lib.segbuffer_f64
    fn(Q, _ptr(table, table.dtype), _ptr(lo, torch.int64), _ptr(hi, torch.int64), _ptr(pix0, torch.int64), S,
       float(margin), float(eps), _ptr(skey, torch.int64))
