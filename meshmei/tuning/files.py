"""Sweeps on disk: ``sweep.npz`` (responses, axes), ``sweep.json`` (metadata) and the figures, written atomically."""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path

import numpy as np

from .. import plots  # the module: each figure is looked up when drawn (a test swaps one out)
from .._checks import is_int
from .._files import atomic_directory
from ..errors import TuningError
from .sweeps import Sweep, response_groups

__all__ = ["SWEEP_FORMAT", "SWEEP_KINDS", "save_sweep", "load_sweep"]

SWEEP_FORMAT = "meshmei-sweep-1"
# the result files a sweep folder may replace with --overwrite: a sweep, never a 3D-MEI run (`tune --mei RUN/member_0
# --out RUN/member_1 --overwrite` replaced a member of a diverse set, which then no longer loaded); the other
# commands replace any result meshmei wrote
SWEEP_KINDS = ("sweep.json",)
# each kind's axes, as pose_sweep and light_sweep make them
SWEEP_AXES = {"pose": (("elevation", "azimuth"), ("elevation", "azimuth", "roll")),
              "light": (("elevation", "azimuth"),)}


def save_sweep(sweep: Sweep, directory, *, overwrite: bool = False, figures: bool = True, images=None) -> Path:
    """Write ``sweep.npz`` (responses and axes), ``sweep.json`` (metadata) and plots, atomically.

    ``images`` (optional): each neuron's example renders for its light plot, ``{neuron: {label: render}}``
    (:func:`~meshmei.tuning.views.example_renders` per neuron).
    """
    if not isinstance(sweep, Sweep):
        raise TuningError(f"sweep must be a Sweep (pose_sweep, light_sweep, load_sweep), got {type(sweep).__name__}")
    shape = (len(sweep.neurons), *[len(v) for _, v in sweep.axes])
    if sweep.kind not in SWEEP_AXES or np.shape(sweep.responses) != shape:  # written, then refused by load_sweep
        raise TuningError(f"a {sweep.kind!r} sweep of {len(sweep.neurons)} neuron(s) over the axes "
                          f"{[n for n, _ in sweep.axes]} has responses of shape {shape}, got "
                          f"{np.shape(sweep.responses)}")

    def write(tmp: Path):
        np.savez(tmp / "sweep.npz", responses=sweep.responses, **{f"axis_{n}": v for n, v in sweep.axes})
        if figures:
            for nrn in sweep.neurons:
                stem = tmp / f"{sweep.kind}_neuron{nrn}"
                if sweep.kind == "pose":
                    plots.plot_pose_heatmap(sweep, nrn, stem)
                else:
                    plots.plot_light_polar(sweep, nrn, stem, images=None if images is None else images.get(nrn))
        meta = {"format": SWEEP_FORMAT, "complete": True, "kind": sweep.kind, "neurons": list(sweep.neurons),
                "axes": [n for n, _ in sweep.axes], "reference": sweep.reference, "meta": sweep.meta}
        if sweep.kind == "light":
            meta["groups"] = {str(n): {k: v for k, v in response_groups(sweep, n).items() if k.endswith("example")}
                              for n in sweep.neurons}
        with open(tmp / "sweep.json", "w") as fh:
            json.dump(meta, fh, indent=1, default=_plain)

    return atomic_directory(directory, write, overwrite=overwrite, error=TuningError, kinds=SWEEP_KINDS)


def _plain(value):
    """JSON for NumPy's numbers and arrays in a sweep's meta (np.float32 was the JSON encoder's TypeError)."""
    if isinstance(value, (np.generic, np.ndarray)):
        return value.tolist()
    raise TypeError(f"a sweep's meta holds a {type(value).__name__}, which JSON cannot write")


def load_sweep(directory) -> Sweep:
    """Read a directory written by :func:`save_sweep`; raises TuningError if it is missing or incomplete."""
    if not isinstance(directory, (str, os.PathLike)):  # None was Path()'s TypeError
        raise TuningError(f"a sweep directory is a path, got {type(directory).__name__}")
    directory = Path(directory)
    if not directory.is_dir():
        raise TuningError(f"no sweep directory at {directory}")
    try:
        with open(directory / "sweep.json") as fh:
            meta = json.load(fh)
        data = np.load(directory / "sweep.npz")
        if not isinstance(meta, dict) or meta.get("format") != SWEEP_FORMAT or meta.get("complete") is not True:
            raise TuningError(f"{directory} holds no complete sweep of format {SWEEP_FORMAT}")
        axes = tuple((str(n), np.asarray(data[f"axis_{n}"], dtype=np.float64)) for n in meta["axes"])
        raw = np.asarray(data["responses"])
        if np.iscomplexobj(raw):  # np.asarray(float64) dropped the imaginary part with a warning
            raise TuningError(f"{directory} is not a readable sweep: its responses must be finite real numbers")
        responses = np.asarray(raw, dtype=np.float64)
        neurons = tuple(int(n) for n in meta["neurons"])
        kind, reference, extra = str(meta["kind"]), meta.get("reference", {}), meta.get("meta", {})
        if not isinstance(reference, dict) or not isinstance(extra, dict):
            raise TypeError("reference and meta must be objects")
    except TuningError:
        raise
    except (OSError, KeyError, ValueError, TypeError, AttributeError, EOFError, zipfile.BadZipFile) as err:  # damaged, hand-edited
        raise TuningError(f"{directory} is not a readable sweep: {type(err).__name__}: {err}") from None
    _check_loaded(directory, meta, kind, neurons, axes, responses)
    return Sweep(kind, responses, axes, neurons, reference, extra)


def _check_loaded(directory: Path, meta: dict, kind: str, neurons: tuple, axes: tuple, responses) -> None:
    """TuningError unless what was read is a sweep save_sweep could have written: found by fuzzing, NaN
    responses loaded (and argmax named the NaN cell), "neurons": "34" was read as (3, 4) and [3.7] as (3,), a
    kind of "bogus" loaded and failed in matplotlib when saved again, complex responses lost their imaginary
    part with a warning, and a 0-d axis ended in "len() of unsized object"."""
    def bad(why: str):
        return TuningError(f"{directory} is not a readable sweep: {why}")

    listed = meta["neurons"]
    if (not isinstance(listed, list) or not listed
            or not all(is_int(n) and n >= 0 for n in listed)
            or len(set(listed)) != len(listed)):
        raise bad(f"neurons must be a list of distinct neuron indices, got {listed!r:.80}")
    if kind not in SWEEP_AXES:
        raise bad(f"kind must be one of {sorted(SWEEP_AXES)}, got {kind!r}")
    names = tuple(n for n, _ in axes)
    if names not in SWEEP_AXES[kind]:
        raise bad(f"a {kind} sweep has the axes {' or '.join(map(str, SWEEP_AXES[kind]))}, got {names}")
    for name, values in axes:
        if values.ndim != 1 or not len(values) or not np.isfinite(values).all():
            raise bad(f"axis {name} must be a non-empty list of finite angles, got {values!r:.80}")
    if not np.isfinite(responses).all():
        raise bad("its responses must be finite real numbers")
    if responses.shape != (len(neurons), *[len(v) for _, v in axes]):
        raise TuningError(f"{directory}: responses of shape {responses.shape} do not match the axes")
