"""Tuning in 3D: sweep an optimised mesh's pose and its light over physical axes and record responses.

The scene is the paper's: the camera on +z looking at the origin with +y up, so image right is +x and
image up is +y. Angles are in degrees.

- Pose: the object turns about its own centre. Azimuth turns its front (the face seen by the camera)
  towards image right (a rotation about +y), elevation tilts the front up (about -x), and roll
  (optional) turns the image plane counter-clockwise as seen by the camera (about +z, the view axis).
  They apply in that order, on top of the run's own pose. (0, 0, 0) is the original view.
- Light: a point light at ``distance`` from the origin on the hemisphere facing the camera, at
  ``d * (cos(el) cos(az), cos(el) sin(az), sin(el))``: elevation 90 is at the camera's axis, elevation 0
  grazes in the image plane, azimuth 0 lights from image right, 90 from above, 180 from the left.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ._files import atomic_directory
from .errors import TuningError
from .render import axis_angle_to_matrix, render

__all__ = [
    "TuningError",
    "Sweep",
    "pose_rotations",
    "light_positions",
    "pose_sweep",
    "light_sweep",
    "response_groups",
    "save_sweep",
    "load_sweep",
    "add_parser",
]

SWEEP_FORMAT = "meshmei-sweep-1"


@dataclass(frozen=True)
class Sweep:
    """Responses over a grid of scene parameters.

    Attributes
    ----------
    kind : str
        ``"pose"`` or ``"light"``.
    responses : (k, *grid) float64 array
        Response of each of the ``k`` neurons at every grid point.
    axes : tuple of (name, (g,) float64 array)
        The grid axes in order, in degrees: ``elevation, azimuth[, roll]`` for a pose sweep,
        ``elevation, azimuth`` for a light sweep.
    neurons : tuple of int
    reference : dict
        The original scene's responses (``"responses"``, one per neuron) for comparison.
    meta : dict
        JSON-able details (light distance, image size, timing, source run).
    """

    kind: str
    responses: np.ndarray
    axes: tuple
    neurons: tuple
    reference: dict = field(default_factory=dict)
    meta: dict = field(default_factory=dict)

    @property
    def shape(self) -> tuple:
        return tuple(len(v) for _, v in self.axes)

    def axis(self, name: str) -> np.ndarray:
        for n, v in self.axes:
            if n == name:
                return v
        raise TuningError(f"this {self.kind} sweep has no axis {name!r}; it has {[n for n, _ in self.axes]}")

    def of(self, neuron: int) -> np.ndarray:
        """The response grid of one neuron (by its index in the encoder)."""
        if neuron not in self.neurons:
            raise TuningError(f"neuron {neuron} was not swept; swept: {list(self.neurons)}")
        return self.responses[self.neurons.index(neuron)]

    def argmax(self, neuron: int) -> dict:
        """Grid coordinates (degrees) of the strongest response of ``neuron``."""
        r = self.of(neuron)
        idx = np.unravel_index(int(np.argmax(r)), r.shape)
        return {name: float(v[i]) for (name, v), i in zip(self.axes, idx)}


# ------------------------------------------------------------------------------------------- grids


def _angles(name, values, lo=None, hi=None):
    a = np.asarray(values, dtype=np.float64).reshape(-1)
    if a.size == 0:
        raise TuningError(f"{name} range is empty; give at least one angle")
    if not np.isfinite(a).all():
        raise TuningError(f"{name} holds NaN or Inf: {a.tolist()[:8]}")
    if lo is not None and (a.min() < lo or a.max() > hi):
        raise TuningError(f"{name} must lie in [{lo}, {hi}] degrees, got [{a.min()}, {a.max()}]")
    return a


def _rot(axis, deg, dtype):
    aa = torch.zeros(len(deg), 3, dtype=dtype)
    aa[:, axis] = torch.as_tensor(np.radians(deg), dtype=dtype)
    return axis_angle_to_matrix(aa)


def pose_rotations(elevation, azimuth, roll=None, *, dtype=torch.float32) -> torch.Tensor:
    """Rotation matrices ``(E, A[, R], 3, 3)`` for a grid of elevation x azimuth (x roll), degrees.

    ``R = R_roll(z) @ R_elevation(-x) @ R_azimuth(y)``: azimuth first, then elevation, then roll.
    """
    el, az = _angles("elevation", elevation), _angles("azimuth", azimuth)
    rl = np.zeros(1) if roll is None else _angles("roll", roll)
    Ry = _rot(1, az, dtype)  # (A, 3, 3)
    Rx = _rot(0, -el, dtype)  # (E, 3, 3)
    Rz = _rot(2, rl, dtype)  # (R, 3, 3)
    R = Rz[None, None] @ Rx[:, None, None] @ Ry[None, :, None]  # (E, A, R, 3, 3)
    return R if roll is not None else R[:, :, 0]


def light_positions(elevation, azimuth, distance: float, *, dtype=torch.float32) -> torch.Tensor:
    """Light positions ``(E, A, 3)`` on the camera-facing hemisphere (see the module docstring)."""
    el = np.radians(_angles("elevation", elevation, 0.0, 90.0))
    az = np.radians(_angles("azimuth", azimuth))
    if not (isinstance(distance, (int, float)) and math.isfinite(distance) and distance > 0):
        raise TuningError(f"light distance must be a positive number, got {distance!r}")
    E, A = np.meshgrid(el, az, indexing="ij")
    P = distance * np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1)
    return torch.as_tensor(P, dtype=dtype)


# ------------------------------------------------------------------------------------------ sweeps


def _scene(result):
    """(V, F, scene kwargs) of an MEI result, or of a plain ``(V, F)`` / ``(V, F, scene)`` tuple."""
    if isinstance(result, tuple):
        if len(result) not in (2, 3):
            raise TuningError(f"a bare mesh is (V, F) or (V, F, scene), got a tuple of {len(result)}")
        V, F, scene = result if len(result) == 3 else (*result, {})
        return V, F, dict(scene)
    return result.V, result.F, result.scene()


def _neurons(encoder, neurons, result):
    if neurons is None:
        neurons = [result.neuron] if hasattr(result, "neuron") else list(range(encoder.n_neurons))
    if isinstance(neurons, (int, np.integer)) and not isinstance(neurons, bool):
        neurons = [int(neurons)]
    neurons = [int(n) for n in neurons]
    if not neurons:
        raise TuningError("neurons is empty; ask for at least one neuron")
    bad = [n for n in neurons if not 0 <= n < encoder.n_neurons]
    if bad:
        raise TuningError(f"neuron index out of range for an encoder of {encoder.n_neurons} neurons: {bad}")
    return neurons


@torch.no_grad()
def _respond(encoder, V, F, neurons, scene, batch_size, **batched):
    """Render the batched scene parameters in chunks and return responses ``(N, k)``."""
    n = next(iter(batched.values())).shape[0]
    out = []
    for s in range(0, n, batch_size):
        kw = dict(scene)
        kw.update({k: v[s:s + batch_size] for k, v in batched.items()})
        img = render(V, F, **kw)
        out.append(encoder(img, neurons).double().cpu())
    return torch.cat(out).numpy()


def pose_sweep(result, encoder, *, neurons=None, elevation=np.linspace(-90, 90, 37),
               azimuth=np.linspace(-90, 90, 37), roll=None, batch_size: int = 64) -> Sweep:
    """Responses while the object turns over a grid of elevation x azimuth (x roll) relative to its view.

    Parameters
    ----------
    result : MEIResult, (V, F) or (V, F, scene)
        An optimised mesh in its scene (:func:`meshmei.mei.optimize_mei` or :func:`meshmei.mei.load_run`),
        or a bare mesh in the default scene or in ``scene`` (keyword arguments of
        :func:`meshmei.render.render`: camera, light, rotation, translation, settings).
    encoder : Encoder
    neurons : int or sequence of int, optional
        Default: the run's neuron (all neurons for a bare mesh).
    elevation, azimuth, roll : sequences of degrees
        Grid axes; ``roll=None`` leaves the roll axis out.
    batch_size : int
        Poses rendered per call.

    Returns
    -------
    Sweep with ``responses`` of shape ``(k, E, A)`` or ``(k, E, A, R)``.
    """
    import time

    V, F, scene = _scene(result)
    neurons = _neurons(encoder, neurons, result)
    base = scene.pop("rotation", None)
    R = pose_rotations(elevation, azimuth, roll, dtype=V.dtype)
    grid = R.shape[:-2]
    Rf = R.reshape(-1, 3, 3)
    if base is not None:
        Rf = Rf @ base.to(V.dtype)
    t = time.perf_counter()
    resp = _respond(encoder, V, F, neurons, scene, batch_size, rotation=Rf)
    seconds = time.perf_counter() - t
    ref = _respond(encoder, V, F, neurons, scene, 1, rotation=(base if base is not None else torch.eye(3, dtype=V.dtype))[None])
    axes = [("elevation", _angles("elevation", elevation)), ("azimuth", _angles("azimuth", azimuth))]
    if roll is not None:
        axes.append(("roll", _angles("roll", roll)))
    return Sweep("pose", resp.T.reshape(len(neurons), *grid), tuple(axes), tuple(neurons),
                 {"responses": ref[0].tolist()}, {"seconds": seconds, "renders": int(Rf.shape[0])})


def light_sweep(result, encoder, *, neurons=None, elevation=np.linspace(0, 90, 10),
                azimuth=np.arange(0, 360, 10.0), distance: float | None = None, batch_size: int = 64) -> Sweep:
    """Responses while a point light moves over the camera-facing hemisphere.

    ``distance`` defaults to the camera's distance from the origin. Returns a Sweep with ``responses``
    of shape ``(k, E, A)``; see :func:`response_groups` for the high / mid / low split.
    """
    import time

    V, F, scene = _scene(result)
    neurons = _neurons(encoder, neurons, result)
    cam = scene.get("camera")
    if distance is None:
        distance = float(torch.as_tensor(cam.eye).reshape(-1, 3)[0].norm()) if cam is not None else 2.5
    P = light_positions(elevation, azimuth, distance, dtype=V.dtype)
    scene.pop("light", None)
    t = time.perf_counter()
    resp = _respond(encoder, V, F, neurons, scene, batch_size, light=P.reshape(-1, 3))
    seconds = time.perf_counter() - t
    orig = result.light if hasattr(result, "light") else None
    ref_scene = dict(scene)
    if orig is not None:
        ref_scene["light"] = orig
    with torch.no_grad():
        ref = encoder(render(V, F, **ref_scene), neurons).double().reshape(-1).tolist()
    axes = (("elevation", _angles("elevation", elevation)), ("azimuth", _angles("azimuth", azimuth)))
    return Sweep("light", resp.T.reshape(len(neurons), *P.shape[:2]), axes, tuple(neurons), {"responses": ref},
                 {"seconds": seconds, "renders": int(P.shape[0] * P.shape[1]), "distance": float(distance)})


def response_groups(sweep: Sweep, neuron: int | None = None) -> dict:
    """Split a sweep's conditions into thirds by response: ``{"high"|"mid"|"low": [coords, ...]}``.

    Each entry also names its example condition (the maximum, the median and the minimum response) under
    ``"<group>_example"``, with its coordinates and response.
    """
    neuron = sweep.neurons[0] if neuron is None else neuron
    r = sweep.of(neuron).reshape(-1)
    order = np.argsort(r, kind="stable")[::-1]  # descending
    coords = np.stack(np.meshgrid(*[v for _, v in sweep.axes], indexing="ij"), -1).reshape(-1, len(sweep.axes))
    names = [n for n, _ in sweep.axes]
    thirds = np.array_split(order, 3)
    out = {}
    for label, idx in zip(("high", "mid", "low"), thirds):
        out[label] = [dict(zip(names, coords[i].tolist()), response=float(r[i])) for i in idx]
    for label, i in (("high", order[0]), ("mid", order[len(order) // 2]), ("low", order[-1])):
        out[f"{label}_example"] = dict(zip(names, coords[i].tolist()), response=float(r[i]))
    return out


# ------------------------------------------------------------------------------------------- files


def save_sweep(sweep: Sweep, directory, *, overwrite: bool = False, figures: bool = True, images=None) -> Path:
    """Write ``sweep.npz`` (responses and axes), ``sweep.json`` (metadata) and plots, atomically.

    ``images`` (optional) maps group labels to example renders for the light plot.
    """

    def write(tmp: Path):
        np.savez(tmp / "sweep.npz", responses=sweep.responses, **{f"axis_{n}": v for n, v in sweep.axes})
        if figures:
            from .plots import plot_light_polar, plot_pose_heatmap

            for nrn in sweep.neurons:
                stem = tmp / f"{sweep.kind}_neuron{nrn}"
                if sweep.kind == "pose":
                    plot_pose_heatmap(sweep, nrn, stem)
                else:
                    plot_light_polar(sweep, nrn, stem, images=images)
        meta = {"format": SWEEP_FORMAT, "complete": True, "kind": sweep.kind, "neurons": list(sweep.neurons),
                "axes": [n for n, _ in sweep.axes], "reference": sweep.reference, "meta": sweep.meta}
        if sweep.kind == "light":
            meta["groups"] = {str(n): {k: v for k, v in response_groups(sweep, n).items() if k.endswith("example")}
                              for n in sweep.neurons}
        with open(tmp / "sweep.json", "w") as fh:
            json.dump(meta, fh, indent=1)

    return atomic_directory(directory, write, overwrite=overwrite, error=TuningError)


def load_sweep(directory) -> Sweep:
    """Read a directory written by :func:`save_sweep`; raises TuningError if it is missing or incomplete."""
    directory = Path(directory)
    if not directory.is_dir():
        raise TuningError(f"no sweep directory at {directory}")
    try:
        with open(directory / "sweep.json") as fh:
            meta = json.load(fh)
        data = np.load(directory / "sweep.npz")
        if meta.get("format") != SWEEP_FORMAT or meta.get("complete") is not True:
            raise TuningError(f"{directory} holds no complete sweep of format {SWEEP_FORMAT}")
        axes = tuple((n, data[f"axis_{n}"]) for n in meta["axes"])
        responses = data["responses"]
    except TuningError:
        raise
    except (OSError, KeyError, ValueError, json.JSONDecodeError) as err:
        raise TuningError(f"{directory} is not a readable sweep: {type(err).__name__}: {err}") from None
    if responses.shape != (len(meta["neurons"]), *[len(v) for _, v in axes]):
        raise TuningError(f"{directory}: responses of shape {responses.shape} do not match the axes")
    return Sweep(meta["kind"], responses, axes, tuple(meta["neurons"]), meta.get("reference", {}), meta.get("meta", {}))


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


def run_tuning(what: str, mei_dir, out=None, *, neurons=None, elevation=None, azimuth=None, roll=None,
               distance=None, overwrite=False, log=print) -> tuple[Sweep, Path]:
    """Load a run, sweep its pose or light, and save arrays and plots; the CLI's body."""
    from .errors import MEIError
    from .mei import load_run

    try:
        run = load_run(mei_dir, rebuild_encoder=True)
    except MEIError as err:
        raise TuningError(str(err)) from None
    encoder = run.encoder_module
    out = Path(out) if out is not None else Path(mei_dir) / f"tuning_{what}"
    if what == "pose":
        sweep = pose_sweep(run, encoder, neurons=neurons,
                           elevation=np.linspace(-90, 90, 37) if elevation is None else elevation,
                           azimuth=np.linspace(-90, 90, 37) if azimuth is None else azimuth, roll=roll)
        images = None
    else:
        sweep = light_sweep(run, encoder, neurons=neurons,
                            elevation=np.linspace(0, 90, 10) if elevation is None else elevation,
                            azimuth=np.arange(0, 360, 10.0) if azimuth is None else azimuth, distance=distance)
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


def example_renders(run, sweep: Sweep, neuron: int | None = None) -> dict:
    """Renders of the light sweep's high / mid / low example conditions: ``{label: (H, W) array}``."""
    groups = response_groups(sweep, neuron)
    d = sweep.meta["distance"]
    out = {}
    for label in ("high", "mid", "low"):
        ex = groups[f"{label}_example"]
        P = light_positions([ex["elevation"]], [ex["azimuth"]], d, dtype=run.V.dtype).reshape(1, 3)
        with torch.no_grad():
            out[label] = (run.render(light=P)[0, 0].cpu().numpy(), ex)
    return out


def _run_cli(args) -> int:
    run_tuning(args.what, args.mei, args.out, neurons=args.neurons,
               elevation=None if args.elevation is None else _range(args.elevation),
               azimuth=None if args.azimuth is None else _range(args.azimuth),
               roll=None if args.roll is None else _range(args.roll), distance=args.distance,
               overwrite=args.overwrite)
    return 0
