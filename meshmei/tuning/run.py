"""Sweep a saved MEI run from its directory and write the sweep beside it: the body of ``meshmei tune``."""

from __future__ import annotations

from pathlib import Path

from .._files import check_apart, check_output
from ..errors import MEIError, TuningError
from ..mei import load_run
from .files import SWEEP_KINDS, save_sweep
from .sweeps import Sweep, light_sweep, pose_sweep
from .views import example_renders

__all__ = ["run_tuning"]


def run_tuning(what: str, mei_dir, out=None, *, neurons=None, elevation=None, azimuth=None, roll=None,
               distance=None, overwrite=False, log=print, how: str = "overwrite=True") -> tuple[Sweep, Path]:
    """Load a run, sweep its pose or light, and save arrays and plots; the body of ``meshmei tune``.

    Parameters
    ----------
    what : {"pose", "light"}
    mei_dir : str or Path
        A run directory written by :func:`meshmei.mei.save_run`.
    out : str or Path, optional
        Output directory (default ``mei_dir/tuning_<what>``).
    neurons, elevation, azimuth, roll, distance
        As in :func:`pose_sweep` / :func:`light_sweep`; None keeps their defaults (``roll`` and ``distance``
        belong to one sweep each).
    overwrite : bool
        Replace an existing ``out`` (checked before the sweep; never ``mei_dir`` or a folder holding it).
    log : callable
        Receives one line per neuron and the output directory.
    how : str
        How the caller passes ``overwrite``, for the message when ``out`` exists (the CLI: ``--overwrite``).

    Returns
    -------
    (Sweep, Path)
    """
    if what not in ("pose", "light"):
        raise TuningError(f"what must be 'pose' or 'light', got {what!r}")
    if what == "light" and roll is not None:  # each sweep's own options: none is silently dropped
        raise TuningError("roll is a pose sweep's axis; a light sweep takes elevation, azimuth and distance")
    if what == "pose" and distance is not None:
        raise TuningError("distance places the light of a light sweep; a pose sweep takes elevation, azimuth and roll")
    out = Path(out) if out is not None else Path(mei_dir) / f"tuning_{what}"
    check_apart(out, mei_dir, TuningError, "the run being swept")
    # before the sweep's work, not after it
    check_output(out, overwrite=overwrite, error=TuningError, how=how, kinds=SWEEP_KINDS)
    try:
        run = load_run(mei_dir, rebuild_encoder=True)
    except MEIError as err:
        raise TuningError(str(err)) from None
    encoder = run.encoder_module
    grid = {k: v for k, v in (("elevation", elevation), ("azimuth", azimuth)) if v is not None}
    if what == "pose":
        sweep = pose_sweep(run, encoder, neurons=neurons, roll=roll, **grid)
        images = None
    else:
        sweep = light_sweep(run, encoder, neurons=neurons, distance=distance, **grid)
        images = {nrn: example_renders(run, sweep, nrn) for nrn in sweep.neurons}  # each neuron's own examples
    sweep.meta["run"] = str(Path(mei_dir))
    save_sweep(sweep, out, overwrite=overwrite, images=images)
    for nrn in sweep.neurons:
        best = sweep.argmax(nrn)
        log(f"{what} sweep, neuron {nrn}: {sweep.responses.size // len(sweep.neurons)} conditions in "
            f"{sweep.meta['seconds']:.1f} s; original {sweep.reference['responses'][sweep.neurons.index(nrn)]:.4f}, "
            f"best {sweep.of(nrn).max():.4f} at " + ", ".join(f"{k} {v:.0f}" for k, v in best.items()))
    log(f"wrote {out}")
    return sweep, out
