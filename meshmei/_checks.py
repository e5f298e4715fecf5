"""Checks of scalar arguments shared by several modules; each raises a ``ValueError`` (or the caller's
subclass) whose message names the argument and what arrived."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["check_positive", "check_non_negative"]


def check_positive(name, value, *, integer=False, error: type[ValueError] = ValueError):
    """Raise ``error`` unless ``value`` is a positive finite number (an integer with ``integer=True``)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise error(f"{name} must be a positive {'integer' if integer else 'number'}, got {value!r}")
    if not (math.isfinite(float(value)) and value > 0):
        raise error(f"{name} must be positive and finite, got {value!r}")
    if integer and int(value) != value:
        raise error(f"{name} must be a positive integer, got {value!r}")


def check_non_negative(name, value, *, unit: str = "", error: type[ValueError] = ValueError):
    """Raise ``error`` unless ``value`` is a finite number >= 0 (``unit``, e.g. ``" of pixels"``, is named
    in the message)."""
    if (isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating))
            or not (math.isfinite(float(value)) and value >= 0)):
        raise error(f"{name} must be a finite non-negative number{unit}, got {value!r}")
