"""Checks shared by several modules: of scalar arguments, each raising a ``ValueError`` (or the caller's
subclass) whose message names the argument and what arrived, and whether a tensor is finite."""

from __future__ import annotations

import argparse
import math
import numbers

import numpy as np
import torch

__all__ = ["check_positive", "check_non_negative", "check_distinct_seeds", "check_seed", "seed_twin", "SEED_RANGE",
           "positive_int", "all_finite", "is_integral", "non_finite_entry"]


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


# The seeds meshmei takes, lowest and highest: those that give distinct runs. torch's CPU generator
# (torch.Generator.manual_seed, a Mersenne Twister) keeps a seed's low 32 bits, so every other integer torch
# takes repeats one of these runs: reconstruct(seed=0), 2**32, 2**63 and -2**63 were one run, bit for bit, and
# -1 was the run of 2**32 - 1 (a GPU's generator keeps all 64 bits; in this range both give distinct runs).
# Seeds in the range run as they did.
SEED_RANGE = (0, 2 ** 32 - 1)


def seed_twin(seed: int) -> int:
    """The seed in :data:`SEED_RANGE` whose run an integer seed gives on torch's CPU generator: its low 32 bits."""
    return int(seed) % (SEED_RANGE[1] + 1)


def _out_of_range(name: str, got) -> str:
    lo, hi = SEED_RANGE
    twins = [s for s in (got if isinstance(got, list) else [got]) if -(2 ** 63) <= s < 2 ** 64]
    same = (f"; {', '.join(f'{s} gives the run of {seed_twin(s)}' for s in twins[:3])}" if twins else "")
    return (f"{name} must lie in [{lo}, {hi}], the seeds of distinct runs (torch's CPU generator keeps a seed's "
            f"low 32 bits{same}), got {got!r}")


def check_seed(name: str, seed, *, error: type[ValueError] = ValueError) -> int:
    """``seed`` as an int, or ``error`` naming ``name``: an integer (NumPy's too, not a bool) in
    :data:`SEED_RANGE`; a seed beyond it that torch takes is named with the seed whose run it would give."""
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)):
        raise error(f"{name} must be an integer in [{SEED_RANGE[0]}, {SEED_RANGE[1]}], got {seed!r}")
    if not SEED_RANGE[0] <= seed <= SEED_RANGE[1]:
        raise error(_out_of_range(name, int(seed)))
    return int(seed)


def check_distinct_seeds(seeds, *, error: type[ValueError] = ValueError) -> None:
    """Raise ``error`` unless the integers ``seeds`` lie in :data:`SEED_RANGE` (where every seed gives a run of
    its own: beyond it torch repeats these runs) and none is repeated (a seed's run would only be repeated)."""
    bad = [s for s in seeds if not SEED_RANGE[0] <= s <= SEED_RANGE[1]]
    if bad:
        raise error(_out_of_range("seeds", bad))
    if len(set(seeds)) != len(seeds):
        twice = sorted({s for s in seeds if seeds.count(s) > 1})
        raise error(f"seeds must be distinct; {twice} repeated (a seed's run would only be repeated)")


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
