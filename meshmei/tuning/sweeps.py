"""Pose and light sweeps: render an optimised mesh over a grid of poses or lights and record the responses.

The conventions of the grids are those of :mod:`meshmei.tuning.grids`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from .._checks import is_integral
from ..encoders import Encoder, frozen_encoder
from ..errors import MeshError, TuningError
from ..mesh import check_mesh
from ..render import DEFAULT_DISTANCE, Camera, render
from .grids import check_angles, light_positions, pose_rotations

__all__ = ["Sweep", "pose_sweep", "light_sweep", "response_groups", "camera_distance"]


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


def _scene(result):
    """(V, F, scene kwargs) of an MEI result, or of a plain ``(V, F)`` / ``(V, F, scene)`` tuple."""
    if isinstance(result, tuple):
        if len(result) not in (2, 3):
            raise TuningError(f"a bare mesh is (V, F) or (V, F, scene), got a tuple of {len(result)}")
        V, F, scene = result if len(result) == 3 else (*result, {})
        if not isinstance(scene, dict):  # None failed in dict()
            raise TuningError(f"a bare mesh's scene must be a dict of render() arguments, got {type(scene).__name__}")
        try:  # a NumPy V ended in an AttributeError, a key's typo in render()'s TypeError
            V, F = check_mesh(V, F)
        except MeshError as err:
            raise TuningError(f"a bare mesh: {err}") from None
        return V, F, _bare_scene(scene)
    if not all(hasattr(result, k) for k in ("V", "F", "scene")):  # None failed with an AttributeError
        raise TuningError(f"result must be an MEIResult, or a (V, F) or (V, F, scene) tuple, got "
                          f"{type(result).__name__}")
    return result.V, result.F, result.scene()


SCENE_KEYS = ("camera", "light", "rotation", "translation", "settings", "albedo", "uv")  # render()'s scene


def _bare_scene(scene: dict) -> dict:
    """A bare mesh's scene, checked: render()'s keyword arguments only, arrays as tensors, a rotation (3, 3)
    and a translation (3,) (a rotation of (2, 3, 3) ended in torch's size mismatch, a camera of text in an
    AttributeError)."""
    unknown = sorted(set(scene) - set(SCENE_KEYS))
    if unknown:
        raise TuningError(f"a bare mesh's scene takes {', '.join(SCENE_KEYS)}; got {unknown}")
    scene = {k: torch.from_numpy(np.asarray(v, dtype=np.float64)) if isinstance(v, (np.ndarray, list)) else v
             for k, v in scene.items()}
    for key, shape in (("rotation", (3, 3)), ("translation", (3,))):
        value = scene.get(key)
        if value is not None and not (isinstance(value, torch.Tensor) and tuple(value.shape) == shape):
            got = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
            raise TuningError(f"a bare mesh's scene {key} must be a {shape} tensor, got {got}")
    if scene.get("camera") is not None and not isinstance(scene["camera"], Camera):
        raise TuningError(f"a bare mesh's scene camera must be a Camera, got {type(scene['camera']).__name__}")
    return scene


def camera_distance(scene: dict) -> float:
    """Distance of the scene's camera from the origin (the default camera's without one)."""
    cam = scene.get("camera")
    if cam is None:
        return DEFAULT_DISTANCE
    return float(torch.as_tensor(cam.eye, device="cpu").reshape(-1, 3)[0].norm())


def _on_encoder(encoder, V, F, scene):
    """The mesh and the scene's tensors on the encoder's device, where the sweep renders (a result is on the
    CPU; its model may be on a GPU)."""
    dev = encoder.device
    return V.to(dev), F.to(dev), {k: v.to(dev) if isinstance(v, torch.Tensor) else v for k, v in scene.items()}


def _check_call(encoder, batch_size) -> None:
    """The sweep's encoder and batch size, refused in one line (an encoder of None, a batch size of 0 or 2.5
    failed inside the sweep with an AttributeError, a TypeError or range()'s error); the result is
    :func:`_scene`'s to check."""
    if not isinstance(encoder, Encoder):
        raise TuningError(f"encoder must be a meshmei Encoder (make_encoder, encoder_from_model), got "
                          f"{type(encoder).__name__}")
    if not (is_integral(batch_size) and batch_size >= 1):
        raise TuningError(f"batch_size must be a positive integer, got {batch_size!r}")


def _neurons(encoder, neurons, result):
    if neurons is None:
        neurons = [result.neuron] if hasattr(result, "neuron") else list(range(encoder.n_neurons))
    if isinstance(neurons, torch.Tensor):  # a 0-d tensor failed in iteration, a 1-d one was refused
        neurons = neurons.tolist()
    if is_integral(neurons):
        neurons = [int(neurons)]
    if isinstance(neurons, (dict, set, frozenset)):  # a dict's keys, a set in no order
        raise TuningError(f"neurons must be None, a neuron index or a sequence of them, got a {type(neurons).__name__}")
    if not isinstance(neurons, (str, bytes)) and hasattr(neurons, "__iter__"):
        neurons = list(neurons)  # a generator was consumed by the check below, then called empty
    # '12' was read digit by digit as neurons (1, 2), [0.7, 1.9] as (0, 1)
    if (isinstance(neurons, (str, bytes)) or not hasattr(neurons, "__iter__")
            or not all(is_integral(n) for n in neurons)):
        raise TuningError(f"neurons must be None, a neuron index or a sequence of them, got {neurons!r}")
    neurons = [int(n) for n in neurons]
    if not neurons:
        raise TuningError("neurons is empty; ask for at least one neuron")
    bad = [n for n in neurons if not 0 <= n < encoder.n_neurons]
    if bad:
        raise TuningError(f"neuron index out of range for an encoder of {encoder.n_neurons} neurons: {bad}")
    return neurons


@torch.no_grad()
def _respond(encoder, V, F, neurons, scene, batch_size, **batched):
    """Render the batched scene parameters in chunks and return responses ``(N, k)``; the encoder runs in
    eval mode, as in the optimisation (its mode is restored after)."""
    n = next(iter(batched.values())).shape[0]
    out = []
    with frozen_encoder(encoder):
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
    _check_call(encoder, batch_size)
    V, F, scene = _on_encoder(encoder, *_scene(result))
    neurons = _neurons(encoder, neurons, result)
    base = scene.pop("rotation", None)
    R = pose_rotations(elevation, azimuth, roll, dtype=V.dtype, device=V.device)
    grid = R.shape[:-2]
    Rf = R.reshape(-1, 3, 3)
    if base is not None:
        Rf = Rf @ base.to(V.dtype)
    t = time.perf_counter()
    resp = _respond(encoder, V, F, neurons, scene, batch_size, rotation=Rf)
    seconds = time.perf_counter() - t
    own = base if base is not None else torch.eye(3, dtype=V.dtype, device=V.device)  # the run's own pose
    ref = _respond(encoder, V, F, neurons, scene, 1, rotation=own[None])
    axes = [("elevation", check_angles("elevation", elevation)), ("azimuth", check_angles("azimuth", azimuth))]
    if roll is not None:
        axes.append(("roll", check_angles("roll", roll)))
    return Sweep("pose", resp.T.reshape(len(neurons), *grid), tuple(axes), tuple(neurons),
                 {"responses": ref[0].tolist()}, {"seconds": seconds, "renders": int(Rf.shape[0])})


def light_sweep(result, encoder, *, neurons=None, elevation=np.linspace(0, 90, 10),
                azimuth=np.arange(0, 360, 10.0), distance: float | None = None, batch_size: int = 64) -> Sweep:
    """Responses while a point light moves over the camera-facing hemisphere.

    ``distance`` defaults to the camera's distance from the origin. Returns a Sweep with ``responses``
    of shape ``(k, E, A)``; see :func:`response_groups` for the high / mid / low split.
    """
    _check_call(encoder, batch_size)
    V, F, scene = _on_encoder(encoder, *_scene(result))
    neurons = _neurons(encoder, neurons, result)
    if distance is None:
        distance = camera_distance(scene)
    P = light_positions(elevation, azimuth, distance, dtype=V.dtype, device=V.device)
    orig = scene.pop("light", None)  # the reference keeps the scene's own light: a run's, or a bare scene's
    if orig is None and hasattr(result, "light"):
        orig = result.light
    t = time.perf_counter()
    resp = _respond(encoder, V, F, neurons, scene, batch_size, light=P.reshape(-1, 3))
    seconds = time.perf_counter() - t
    ref_scene = dict(scene)
    if orig is not None:
        ref_scene["light"] = orig
    with torch.no_grad(), frozen_encoder(encoder):
        ref = encoder(render(V, F, **ref_scene), neurons).double().reshape(-1).tolist()
    axes = (("elevation", check_angles("elevation", elevation)), ("azimuth", check_angles("azimuth", azimuth)))
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
