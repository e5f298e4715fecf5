"""Checks shared by several modules: of scalar arguments, each raising a ``ValueError`` (or the caller's
subclass) whose message names the argument and what arrived, and whether a tensor is finite."""

from __future__ import annotations

import argparse
import math
import numbers

import numpy as np
import torch

__all__ = ["check_positive", "check_non_negative", "check_distinct_seeds", "positive_int", "all_finite", "is_integral",
           "non_finite_entry"]


def all_finite(x: torch.Tensor) -> bool:
    """Whether every entry of ``x`` is finite (an integer or empty tensor: True), by one reduction: the largest
    ``|x|`` is NaN or Inf exactly where some entry is (``amax`` propagates NaN). On the small tensors of a
    step (a mesh's vertices, a gradient) about a fifth of ``isfinite(x).all()``'s cost, which runs six
    operations. No graph is recorded (``x`` may require a gradient)."""
    if not (x.is_floating_point() or x.is_complex()) or x.numel() == 0:
        return True
    return math.isfinite(float(x.detach().abs().amax()))


def non_finite_entry(value, where: str = "") -> tuple[str, float] | None:
    """The first float in ``value`` (dicts, lists and tuples of them, as JSON holds) that is NaN or Inf, as
    ``(path, number)`` with the path written as Python reads it (``info['stages'][0]['sigma_median']``);
    None when there is none. Python's ``json`` writes such a number as ``NaN`` or ``Infinity``, which JSON does
    not have (strict readers refuse the file)."""
    if isinstance(value, float):
        return None if math.isfinite(value) else (where or "the value", value)
    if isinstance(value, dict):
        items = value.items()
    elif isinstance(value, (list, tuple)):
        items = enumerate(value)
    else:
        return None
    for key, item in items:
        found = non_finite_entry(item, f"{where}[{key!r}]" if where else str(key))
        if found is not None:
            return found
    return None


def is_finite_real(x) -> bool:
    """A real number (NumPy's too) that is finite as a float, not a bool: NaN, Inf and an int beyond a float's
    range (on which ``math.isfinite`` raises OverflowError) are not."""
    if isinstance(x, (bool, np.bool_)) or not isinstance(x, numbers.Real):
        return False
    try:
        return math.isfinite(float(x))
    except OverflowError:
        return False


def is_int(x) -> bool:
    """A Python int, not a bool (what JSON reads a count or an index as)."""
    return isinstance(x, int) and not isinstance(x, bool)


def is_integral(x) -> bool:
    """An integer of any size (NumPy's too), or a finite float of integer value (``3.0``), not a bool. (An int
    beyond a float's range made ``math.isfinite`` raise OverflowError in the checks that used it.)"""
    if isinstance(x, (bool, np.bool_)) or not isinstance(x, numbers.Real):
        return False
    return isinstance(x, numbers.Integral) or (math.isfinite(x) and int(x) == x)


def check_positive(name, value, *, integer=False, error: type[ValueError] = ValueError):
    """Raise ``error`` unless ``value`` is a positive finite number (an integer with ``integer=True``)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise error(f"{name} must be a positive {'integer' if integer else 'number'}, got {value!r}")
    if not (value > 0 and (isinstance(value, numbers.Integral) or math.isfinite(value))):
        raise error(f"{name} must be positive and finite, got {value!r}")
    if integer and int(value) != value:
        raise error(f"{name} must be a positive integer, got {value!r}")


def check_non_negative(name, value, *, unit: str = "", error: type[ValueError] = ValueError):
    """Raise ``error`` unless ``value`` is a finite number >= 0 (``unit``, e.g. ``" of pixels"``, is named
    in the message)."""
    if (isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating))
            or not (value >= 0 and (isinstance(value, numbers.Integral) or math.isfinite(value)))):
        raise error(f"{name} must be a finite non-negative number{unit}, got {value!r}")


def check_distinct_seeds(seeds, *, error: type[ValueError] = ValueError) -> None:
    """Raise ``error`` unless the integers ``seeds`` are seeds torch takes (``torch.Generator.manual_seed``:
    ``[-2**63, 2**64 - 1]``; beyond, its own overflow error at the first seed) and give distinct runs: no
    seed repeated, and no two that torch takes as one (it takes seeds modulo ``2**64``: -1 is ``2**64 - 1``)."""
    bad = [s for s in seeds if not -(2 ** 63) <= s < 2 ** 64]
    if bad:
        raise error(f"seeds must lie in [-2**63, 2**64 - 1] (torch's seed range), got {bad}")
    if len(set(seeds)) != len(seeds):
        twice = sorted({s for s in seeds if seeds.count(s) > 1})
        raise error(f"seeds must be distinct; {twice} repeated (a seed's run would only be repeated)")
    same = sorted({s for s in seeds if sum((t - s) % 2 ** 64 == 0 for t in seeds) > 1})
    if same:
        raise error(f"seeds {same} are the same seed to torch (it takes seeds modulo 2**64); give distinct ones")


def positive_int(text: str) -> int:
    """An argparse type: a positive integer (argparse's one-line error otherwise)."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def float_dtype(dtype, *, error: type[ValueError] = ValueError) -> torch.dtype:
    """``dtype`` as a torch floating dtype (its name, "float64", is taken too), or ``error``: an int dtype
    truncated or zeroed every vertex, and a name reached torch as a device string."""
    named = getattr(torch, dtype, None) if isinstance(dtype, str) else dtype
    if not isinstance(named, torch.dtype) or not named.is_floating_point:
        raise error(f"dtype must be a torch floating dtype such as torch.float32 or torch.float64 (or its name), "
                    f"got {dtype!r}")
    return named
