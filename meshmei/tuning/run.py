"""Sweep a saved MEI run from its directory and write the sweep beside it: the body of ``meshmei tune``."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import MEIError, TuningError
from ..mei import load_run
from .files import save_sweep
from .sweeps import Sweep, light_sweep, pose_sweep
from .views import example_renders

__all__ = ["run_tuning", "add_parser"]


def run_tuning(what: str, mei_dir, out=None, *, neurons=None, elevation=None, azimuth=None, roll=None,
               distance=None, overwrite=False, log=print) -> tuple[Sweep, Path]:
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
    log : callable
        Receives one line per neuron and the output directory.

    Returns
    -------
    (Sweep, Path)
    """
    if what not in ("pose", "light"):
        raise TuningError(f"what must be 'pose' or 'light', got {what!r}")
    try:
        run = load_run(mei_dir, rebuild_encoder=True)
    except MEIError as err:
        raise TuningError(str(err)) from None
    encoder = run.encoder_module
    out = Path(out) if out is not None else Path(mei_dir) / f"tuning_{what}"
    grid = {k: v for k, v in (("elevation", elevation), ("azimuth", azimuth)) if v is not None}
    if what == "pose":
        sweep = pose_sweep(run, encoder, neurons=neurons, roll=roll, **grid)
        images = None
    else:
        sweep = light_sweep(run, encoder, neurons=neurons, distance=distance, **grid)
        images = example_renders(run, sweep)
    sweep.meta["run"] = str(Path(mei_dir))
    save_sweep(sweep, out, overwrite=overwrite, images=images)
    for nrn in sweep.neurons:
        best = sweep.argmax(nrn)
        log(f"{what} sweep, neuron {nrn}: {sweep.responses.size // len(sweep.neurons)} conditions in "
            f"{sweep.meta['seconds']:.1f} s; original {sweep.reference['responses'][sweep.neurons.index(nrn)]:.4f}, "
            f"best {sweep.of(nrn).max():.4f} at " + ", ".join(f"{k} {v:.0f}" for k, v in best.items()))
    log(f"wrote {out}")
    return sweep, out


# --------------------------------------------------------------------------------------------- CLI


def _range(text: str):
    """``"lo:hi:n"`` -> n angles from lo to hi inclusive."""
    try:
        lo, hi, n = text.split(":")
        n = int(n)
        lo, hi = float(lo), float(hi)
    except ValueError:
        raise TuningError(f"a range is 'lo:hi:n' (degrees, count), got {text!r}") from None
    if n < 1:
        raise TuningError(f"a range needs at least one angle, got n={n} in {text!r}")
    return np.linspace(lo, hi, n)


def add_parser(sub) -> None:
    """Add ``meshmei tune`` to an argparse subparsers object."""
    p = sub.add_parser("tune", help="sweep the pose or the light of a saved MEI run and plot the tuning")
    p.add_argument("what", choices=["pose", "light"])
    p.add_argument("--mei", required=True, help="a run directory written by 'meshmei mei'")
    p.add_argument("--out", default=None, help="output directory (default: MEI_DIR/tuning_<what>)")
    p.add_argument("--neurons", type=int, nargs="+", default=None, help="default: the run's neuron")
    p.add_argument("--elevation", default=None, help="lo:hi:n degrees (pose default -90:90:37, light 0:90:10)")
    p.add_argument("--azimuth", default=None, help="lo:hi:n degrees (pose default -90:90:37, light 0:350:36)")
    p.add_argument("--roll", default=None, help="lo:hi:n degrees: add an in-plane roll axis to a pose sweep")
    p.add_argument("--distance", type=float, default=None, help="light distance (default: the camera's)")
    p.add_argument("--overwrite", action="store_true")
    p.set_defaults(func=_run_cli)


def _run_cli(args) -> int:
    # the command line gives ranges as text; everything else is run_tuning's
    run_tuning(args.what, args.mei, args.out, neurons=args.neurons,
               elevation=None if args.elevation is None else _range(args.elevation),
               azimuth=None if args.azimuth is None else _range(args.azimuth),
               roll=None if args.roll is None else _range(args.roll), distance=args.distance,
               overwrite=args.overwrite)
    return 0
