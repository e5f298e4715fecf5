"""3D maximally exciting inputs: deform a mesh so that a model neuron's response to its rendering is maximal.

The pipeline of the paper: a starting mesh (sheet, sphere, torus or your own) is deformed by Gaussian RBF
offsets and scales (:class:`meshmei.deform.RBFDeformer`), rendered in a fixed scene (overhead camera, point
light at the camera, Lambertian gray, uniform background), preprocessed by the encoder, and the loss
``-f(I) + sum_r w_r L_r(V)`` is minimised with Adam. Light position and object pose can optionally join
the optimisation. Several seeds are run (the seed draws a small random initial offset, so runs differ) and
the best kept. Runs are saved to a directory from which the exact mesh and scene can be rebuilt.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import torch

from .._files import atomic_directory
from ..deform import RBFDeformer
from ..encoders import Encoder, EncoderError, GaborComplexCell, GaborSimpleCell
from ..errors import MEIError
from .pixel import eval_mode
from ..operators import doublearea
from ..regularizers import arap_direction_loss, arap_loss, area_loss, edge_loss, laplacian_loss
from ..render import Camera, RenderSettings, axis_angle_to_matrix, render
from ..shapes import INITIAL_KINDS, initial_mesh

__all__ = [
    "MEIError",
    "MEISettings",
    "MEIResult",
    "REGULARIZERS",
    "optimize_mei",
    "triangle_quality",
    "mesh_quality",
    "grid_search",
    "random_deformations",
    "random_mesh_responses",
    "save_run",
    "load_run",
    "make_encoder",
    "encoder_spec",
    "add_parser",
]

RUN_FORMAT = 1


# name -> loss(V, V0, F); the paper's four first, then the two variants beyond it
REGULARIZERS = {
    "laplacian": lambda V, V0, F: laplacian_loss(V, F),
    "edge": lambda V, V0, F: edge_loss(V, F),
    "area": lambda V, V0, F: area_loss(V, F),
    "arap": lambda V, V0, F: arap_direction_loss(V, V0, F),
    "laplacian_cot": lambda V, V0, F: laplacian_loss(V, F, method="cotangent"),
    "arap_sorkine": lambda V, V0, F: arap_loss(V, V0, F),
}


def _default_weights():
    return {"laplacian": 30.0, "edge": 30.0, "area": 1000.0, "arap": 0.0}


@dataclass(frozen=True)
class MEISettings:
    """Everything that defines a 3D-MEI run besides the encoder, the neuron and the initial mesh.

    Attributes
    ----------
    image_size : int
        Rendered image size in pixels (square).
    n_vertices : int
        Approximate vertex count of a built-in initial mesh (ignored for a given mesh).
    steps : int
        Adam steps per seed.
    lr : float
        Learning rate of the RBF offsets (world units; the initial meshes span 1).
    lr_scales : float
        Learning rate of the RBF log-scales (0 freezes the scales).
    lr_decay : float
        The learning rates follow a cosine from ``lr`` down to ``lr * lr_decay``.
    seeds : tuple of int
        One run per seed; the seed draws the initial offsets (normal, std ``init_noise``).
    init_noise : float
        Standard deviation of the random initial offsets (breaks symmetries; 0 for none).
    sigma_factor : float
        Initial RBF scale as a multiple of the mean spacing of the kernel centres.
    centers : int or None
        Number of RBF centres (farthest-point sampled); None puts one on every vertex (the paper).
    r_cut : float
        RBF truncation radius in scales (see :class:`~meshmei.deform.RBFDeformer`).
    weights : dict
        Regularizer weights by name (see :data:`REGULARIZERS`); zero weights are not evaluated.
    keep : str
        ``"best"``: return the iterate with the lowest loss seen; ``"last"``: the final iterate.
    optimize_light, optimize_pose : bool
        Also optimise the point light position / the object's rotation (axis-angle) and translation.
    lr_light, lr_pose : float
        Their learning rates.
    light : tuple of 3 floats or None
        Point light position; None puts it at the camera.
    camera_distance, fov_degrees : float
        The overhead camera at ``(0, 0, camera_distance)`` looking at the origin.
    render : dict
        Other :class:`~meshmei.render.RenderSettings` fields (background, ambient, sigma, ...).
    dtype : str
        ``"float32"`` or ``"float64"``.
    """

    image_size: int = 64
    n_vertices: int = 400
    steps: int = 300
    lr: float = 3e-3
    lr_scales: float = 1e-2
    lr_decay: float = 0.05
    seeds: tuple = (0, 1, 2)
    init_noise: float = 1e-3
    sigma_factor: float = 2.0
    centers: int | None = None
    r_cut: float = 4.0
    weights: dict = field(default_factory=_default_weights)
    keep: str = "best"
    optimize_light: bool = False
    optimize_pose: bool = False
    lr_light: float = 2e-2
    lr_pose: float = 1e-2
    light: tuple | None = None
    camera_distance: float = 2.5
    fov_degrees: float = 30.0
    render: dict = field(default_factory=dict)
    dtype: str = "float32"

    def __post_init__(self):
        for name in ("image_size", "n_vertices", "steps"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise MEIError(f"{name} must be a positive integer, got {v!r}")
        for name in ("lr", "lr_scales", "lr_decay", "init_noise", "sigma_factor", "r_cut", "lr_light", "lr_pose",
                     "camera_distance", "fov_degrees"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise MEIError(f"{name} must be a finite non-negative number, got {v!r}")
        if self.lr <= 0 or self.sigma_factor <= 0 or self.r_cut <= 0:
            raise MEIError(f"lr, sigma_factor and r_cut must be positive, got {self.lr}, {self.sigma_factor}, {self.r_cut}")
        seeds = tuple(self.seeds) if not isinstance(self.seeds, int) else (self.seeds,)
        if not seeds or any(isinstance(s, bool) or int(s) != s for s in seeds):
            raise MEIError(f"seeds must be a non-empty sequence of integers, got {self.seeds!r}")
        object.__setattr__(self, "seeds", tuple(int(s) for s in seeds))
        if not isinstance(self.weights, dict):
            raise MEIError(f"weights must be a dict of regularizer name -> weight, got {type(self.weights).__name__}")
        for k, w in self.weights.items():
            if k not in REGULARIZERS:
                raise MEIError(f"unknown regularizer {k!r}; expected one of {sorted(REGULARIZERS)}")
            if isinstance(w, bool) or not isinstance(w, (int, float)) or not math.isfinite(w) or w < 0:
                raise MEIError(f"weight of {k!r} must be a finite non-negative number, got {w!r}")
        if self.keep not in ("best", "last"):
            raise MEIError(f"keep must be 'best' or 'last', got {self.keep!r}")
        if self.dtype not in ("float32", "float64"):
            raise MEIError(f"dtype must be 'float32' or 'float64', got {self.dtype!r}")
        if self.light is not None:
            lt = tuple(float(x) for x in self.light)
            if len(lt) != 3 or not all(math.isfinite(x) for x in lt):
                raise MEIError(f"light must be three finite numbers or None, got {self.light!r}")
            object.__setattr__(self, "light", lt)
        if self.centers is not None and (isinstance(self.centers, bool) or int(self.centers) != self.centers
                                         or self.centers < 1):
            raise MEIError(f"centers must be None or a positive integer, got {self.centers!r}")
        if not isinstance(self.render, dict):
            raise MEIError(f"render must be a dict of RenderSettings fields, got {type(self.render).__name__}")
        self.render_settings()  # validates the render fields

    def render_settings(self) -> RenderSettings:
        try:
            return RenderSettings(image_size=self.image_size, **self.render)
        except TypeError as err:
            raise MEIError(f"render holds an unknown RenderSettings field: {err}") from None

    def camera(self) -> Camera:
        return Camera(eye=(0.0, 0.0, float(self.camera_distance)), fov_degrees=float(self.fov_degrees))

    @property
    def torch_dtype(self) -> torch.dtype:
        return getattr(torch, self.dtype)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["seeds"] = list(self.seeds)
        d["light"] = list(self.light) if self.light is not None else None
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "MEISettings":
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise MEIError(f"unknown MEISettings fields {sorted(unknown)}")
        d = dict(d)
        if "seeds" in d:
            d["seeds"] = tuple(d["seeds"])
        if d.get("light") is not None:
            d["light"] = tuple(d["light"])
        return cls(**d)


@dataclass
class MEIResult:
    """Outcome of :func:`optimize_mei` (or of :func:`load_run`).

    Attributes
    ----------
    V : (n, 3) tensor
        The optimised mesh's vertices in object coordinates (before the pose).
    F : (m, 3) int64 tensor
    V0 : (n, 3) tensor
        The initial (rest) mesh.
    image : (1, 1, S, S) tensor
        The rendering of the result in its scene (raw pixel values).
    activation : float
        The neuron's response to ``image``.
    history : list of float
        Response at every step of the winning seed.
    loss_history : list of float
        Total loss at every step of the winning seed.
    reg_history : dict of str -> list of float
        Unweighted value of each active regularizer at every step of the winning seed.
    seed : int
        The winning seed.
    seed_activations : dict of int -> float
        Final response per seed.
    settings : MEISettings
    neuron : int
    encoder : dict
        :func:`encoder_spec` of the encoder (enough to rebuild the built-in ones).
    deformer_state : dict
        ``state_dict`` of the winning :class:`~meshmei.deform.RBFDeformer`.
    light : (3,) tensor or None
        Light position used (None: at the camera).
    rotation : (3,) tensor
        Object pose as an axis-angle vector (zeros unless the pose was optimised).
    translation : (3,) tensor
    init : str
        ``"sheet"``, ``"sphere"``, ``"torus"`` or ``"custom"``.
    wall_time : float
        Seconds for all seeds.
    seconds_per_step : float
    time_history : list of float
        Seconds since the start of the winning seed at the end of every step.
    extra : dict
        JSON-able additions written to the summary (e.g. ``pixel_mei_activation``).
    """

    V: torch.Tensor
    F: torch.Tensor
    V0: torch.Tensor
    image: torch.Tensor
    activation: float
    history: list
    loss_history: list
    reg_history: dict
    seed: int
    seed_activations: dict
    settings: MEISettings
    neuron: int
    encoder: dict
    deformer_state: dict
    light: torch.Tensor | None
    rotation: torch.Tensor
    translation: torch.Tensor
    init: str = "custom"
    wall_time: float = 0.0
    seconds_per_step: float = 0.0
    time_history: list = field(default_factory=list)
    extra: dict = field(default_factory=dict)

    @property
    def fraction_of_bound(self) -> float | None:
        ub = self.encoder.get("upper_bound")
        return None if ub is None else self.activation / ub

    def scene(self) -> dict:
        """Keyword arguments for :func:`meshmei.render.render` that reproduce :attr:`image` from ``V, F``."""
        return dict(camera=self.settings.camera(), light=self.light,
                    rotation=axis_angle_to_matrix(self.rotation), translation=self.translation,
                    settings=self.settings.render_settings())

    def render(self, **overrides) -> torch.Tensor:
        """Re-render the result (``overrides`` replace entries of :meth:`scene`)."""
        kw = self.scene()
        kw.update(overrides)
        return render(self.V, self.F, **kw)

    def deformer(self) -> RBFDeformer:
        """Rebuild the winning RBF deformer; ``deformer()()`` equals :attr:`V`."""
        return _rebuild_deformer(self.V0, self.deformer_state, self.settings)


# ---------------------------------------------------------------------------------------------- encoders

def encoder_spec(encoder: Encoder) -> dict:
    """A JSON-able description of an encoder; :func:`make_encoder` rebuilds the built-in kinds from it."""
    pre = encoder.preprocess
    spec = {"class": type(encoder).__name__, "upper_bound": encoder.upper_bound, "n_neurons": encoder.n_neurons,
            "mean": float(pre.mean), "std": float(pre.std), "norm": pre.norm, "eps": pre.eps}
    if isinstance(encoder, (GaborSimpleCell, GaborComplexCell)):
        spec["kind"] = "gabor-simple" if isinstance(encoder, GaborSimpleCell) else "gabor-complex"
        spec["params"] = {k: v.tolist() for k, v in encoder.params.items()}
    elif getattr(encoder, "_meshmei_demo", False):
        spec["kind"] = "demo"
    else:
        spec["kind"] = "custom"
    return spec


def make_encoder(kind: str, **params) -> Encoder:
    """A built-in encoder by name: ``"gabor-simple"``, ``"gabor-complex"`` (Gabor parameters as keywords),
    or ``"demo"`` (the shipped demo model, :func:`meshmei.encoders.load_demo_model`)."""
    if kind == "gabor-simple":
        return GaborSimpleCell(**params)
    if kind == "gabor-complex":
        return GaborComplexCell(**params)
    if kind == "demo":
        from ..encoders import load_demo_model

        return load_demo_model()
    raise MEIError(f"unknown encoder {kind!r}; expected 'gabor-simple', 'gabor-complex' or 'demo'")


def _encoder_from_spec(spec: dict) -> Encoder:
    kind = spec.get("kind")
    if kind in ("gabor-simple", "gabor-complex"):
        return make_encoder(kind, **spec["params"], mean=spec["mean"], std=spec["std"], norm=spec["norm"],
                            eps=spec["eps"])
    if kind == "demo":
        return make_encoder("demo")
    raise MEIError(f"cannot rebuild a {spec.get('class')} encoder from a run directory; pass encoder=... to load_run")


# ---------------------------------------------------------------------------------------------- quality

def triangle_quality(V: torch.Tensor, F: torch.Tensor) -> torch.Tensor:
    """Per-face quality ``4 sqrt(3) A / (l1^2 + l2^2 + l3^2)``: 1 for equilateral, 0 for degenerate, ``(m,)``."""
    T = V[F]  # (m, 3, 3)
    e = T.roll(-1, dims=1) - T  # edge vectors
    l2 = (e * e).sum((1, 2))
    return 2.0 * math.sqrt(3.0) * doublearea(V, F) / l2.clamp_min(torch.finfo(V.dtype).tiny)


def mesh_quality(V: torch.Tensor, F: torch.Tensor, *, self_intersections: bool = True) -> dict:
    """Minimum and mean triangle quality, and self-intersecting face pairs (libigl, exact predicates)."""
    q = triangle_quality(V.detach().double(), F)
    out = {"min_quality": float(q.min()), "mean_quality": float(q.mean()), "self_intersections": None}
    if self_intersections:
        import igl.predicates
        import numpy as np

        _, pairs, _ = igl.predicates.find_self_intersections(
            np.ascontiguousarray(V.detach().double().cpu().numpy()),
            np.ascontiguousarray(F.cpu().numpy().astype(np.int64)), False)
        out["self_intersections"] = int(len(pairs))
    return out


# ---------------------------------------------------------------------------------------------- optimisation

def _initial(init, settings: MEISettings, dtype):
    if isinstance(init, str):
        if init not in INITIAL_KINDS:
            raise MEIError(f"init must be one of {INITIAL_KINDS} or a (V, F) pair, got {init!r}")
        V0, F = initial_mesh(init, n_vertices=settings.n_vertices, dtype=dtype)
        return V0, F, init
    try:
        V0, F = init
    except (TypeError, ValueError):
        raise MEIError(f"init must be one of {INITIAL_KINDS} or a (V, F) pair, got {type(init).__name__}") from None
    from ..mesh import check_mesh

    V0, F = torch.as_tensor(V0), torch.as_tensor(F)
    check_mesh(V0, F)
    return V0.detach().to(dtype), F.long(), "custom"


def _make_deformer(V0, settings: MEISettings, centers=None):
    if centers is None:
        centers = settings.centers
    return RBFDeformer(V0, centers, sigma_factor=settings.sigma_factor, r_cut=settings.r_cut,
                       learn_scales=settings.lr_scales > 0)


def _rebuild_deformer(V0, state, settings):
    rbf = _make_deformer(V0, settings, centers=state["center_index"])
    rbf.load_state_dict(state)
    return rbf


def _cosine(t, T, decay):
    return decay + (1 - decay) * 0.5 * (1 + math.cos(math.pi * t / max(T - 1, 1)))


def _run_seed(encoder, neuron, V0, F, settings: MEISettings, seed: int, bar=None):
    dtype = V0.dtype
    g = torch.Generator().manual_seed(int(seed))
    rbf = _make_deformer(V0, settings)
    with torch.no_grad():
        rbf.offsets.copy_(settings.init_noise * torch.randn(rbf.offsets.shape, generator=g, dtype=torch.float64))
    groups = [{"params": [rbf.offsets], "lr": settings.lr, "base": settings.lr}]
    if settings.lr_scales > 0:
        groups.append({"params": [rbf.log_sigma], "lr": settings.lr_scales, "base": settings.lr_scales})
    camera = settings.camera()
    light0 = settings.light if settings.light is not None else (0.0, 0.0, float(settings.camera_distance))
    light = torch.tensor(light0, dtype=dtype) if (settings.optimize_light or settings.light is not None) else None
    rot = torch.zeros(3, dtype=dtype)
    trans = torch.zeros(3, dtype=dtype)
    if settings.optimize_light:
        light.requires_grad_(True)
        groups.append({"params": [light], "lr": settings.lr_light, "base": settings.lr_light})
    if settings.optimize_pose:
        rot.requires_grad_(True)
        trans.requires_grad_(True)
        groups.append({"params": [rot, trans], "lr": settings.lr_pose, "base": settings.lr_pose})
    opt = torch.optim.Adam(groups)
    st = settings.render_settings()
    active = {k: w for k, w in settings.weights.items() if w > 0}
    hist, loss_hist, reg_hist, times = [], [], {k: [] for k in active}, []
    best = None
    t_start = time.perf_counter()

    def snapshot():
        return ({k: v.detach().clone() for k, v in rbf.state_dict().items()},
                None if light is None else light.detach().clone(), rot.detach().clone(), trans.detach().clone())

    for t in range(settings.steps):
        c = _cosine(t, settings.steps, settings.lr_decay)
        for grp in opt.param_groups:
            grp["lr"] = grp["base"] * c
        V = rbf()
        pose = {}
        if settings.optimize_pose:
            pose = dict(rotation=axis_angle_to_matrix(rot), translation=trans)
        I = render(V, F, camera=camera, light=light, settings=st, **pose)
        f = encoder(I, neuron)[0, 0]
        loss = -f
        for k, w in active.items():
            r = REGULARIZERS[k](V, rbf.V0, F)
            reg_hist[k].append(float(r.detach()))
            loss = loss + w * r
        hist.append(float(f.detach()))
        loss_hist.append(float(loss.detach()))
        if not math.isfinite(loss_hist[-1]):
            raise MEIError(f"the loss became {loss_hist[-1]} at step {t} of seed {seed}; lower lr")
        if settings.keep == "best" and (best is None or loss_hist[-1] < best[0]):
            best = (loss_hist[-1], t, snapshot())
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        times.append(time.perf_counter() - t_start)
        if bar is not None:
            bar.update(1)
            bar.set_postfix(seed=seed, act=f"{hist[-1]:.4f}")
    # evaluate the final iterate too (the loop records the state before each step)
    with torch.no_grad():
        V = rbf()
        pose = dict(rotation=axis_angle_to_matrix(rot), translation=trans) if settings.optimize_pose else {}
        I = render(V, F, camera=camera, light=light, settings=st, **pose)
        f = float(encoder(I, neuron)[0, 0])
        loss_last = -f + sum(w * float(REGULARIZERS[k](V, rbf.V0, F)) for k, w in active.items())
    if settings.keep == "last" or loss_last <= best[0]:
        best = (loss_last, settings.steps, snapshot())
    state, lt, rt, tr = best[2]
    rbf.load_state_dict(state)
    with torch.no_grad():
        V = rbf().detach()
        pose = dict(rotation=axis_angle_to_matrix(rt), translation=tr)
        I = render(V, F, camera=camera, light=lt, settings=st, **pose).detach()
        act = float(encoder(I, neuron)[0, 0])
    return dict(V=V, image=I, activation=act, loss=best[0], history=hist, loss_history=loss_hist,
                reg_history=reg_hist, time_history=times, deformer_state=state, light=lt, rotation=rt, translation=tr, best_step=best[1])


def optimize_mei(encoder: Encoder, neuron: int, init="sphere", settings: MEISettings | None = None, *,
                 progress: bool = False, **overrides) -> MEIResult:
    """Optimise a mesh so that ``encoder``'s neuron ``neuron`` responds maximally to its rendering.

    Parameters
    ----------
    encoder : Encoder
        Any :class:`meshmei.encoders.Encoder`; it runs in eval mode (its mode is restored afterwards) and
        its parameters receive no gradient.
    neuron : int
    init : str or (V, F)
        ``"sphere"``, ``"sheet"``, ``"torus"`` (built with ``settings.n_vertices`` vertices), or a mesh
        ``V : (n, 3) float tensor``, ``F : (m, 3) int64 tensor``.
    settings : MEISettings, optional
    progress : bool
        Show a tqdm progress bar over all steps of all seeds.
    **overrides
        Fields of :class:`MEISettings` replacing those of ``settings``.

    Returns
    -------
    MEIResult
        The seed with the lowest final loss; within a seed the lowest-loss iterate (``keep="best"``).

    Examples
    --------
    >>> from meshmei.encoders import GaborSimpleCell
    >>> res = optimize_mei(GaborSimpleCell(), 0, "sheet", steps=3, seeds=(0,), image_size=16, n_vertices=64)
    >>> res.image.shape, len(res.history)
    (torch.Size([1, 1, 16, 16]), 3)
    """
    if not isinstance(encoder, Encoder):
        raise MEIError(f"encoder must be a meshmei Encoder, got {type(encoder).__name__}")
    settings = settings if settings is not None else MEISettings()
    if not isinstance(settings, MEISettings):
        raise MEIError(f"settings must be an MEISettings, got {type(settings).__name__}")
    if overrides:
        unknown = set(overrides) - {f.name for f in fields(MEISettings)}
        if unknown:
            raise MEIError(f"unknown MEISettings fields {sorted(unknown)}")
        settings = replace(settings, **overrides)
    try:
        idx = encoder.neuron_index(neuron)
    except EncoderError as err:
        raise MEIError(str(err)) from None
    if idx.numel() != 1 or neuron is None:
        raise MEIError(f"neuron must be a single index, got {neuron!r}")
    neuron = int(idx[0])
    V0, F, init_name = _initial(init, settings, settings.torch_dtype)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=settings.steps * len(settings.seeds), desc=f"3D-MEI neuron {neuron}")
    runs = {}
    t0 = time.perf_counter()
    try:
        with eval_mode(encoder):
            params = list(encoder.parameters())
            flags = [p.requires_grad for p in params]
            for p in params:
                p.requires_grad_(False)
            try:
                for seed in settings.seeds:
                    runs[seed] = _run_seed(encoder, neuron, V0, F, settings, seed, bar)
            finally:
                for p, fl in zip(params, flags):
                    p.requires_grad_(fl)
    finally:
        if bar is not None:
            bar.close()
    wall = time.perf_counter() - t0
    seed = min(runs, key=lambda s: runs[s]["loss"])
    r = runs[seed]
    return MEIResult(
        V=r["V"], F=F, V0=V0, image=r["image"], activation=r["activation"], history=r["history"],
        loss_history=r["loss_history"], reg_history=r["reg_history"], seed=seed, time_history=r["time_history"],
        seed_activations={s: runs[s]["activation"] for s in runs}, settings=settings, neuron=neuron,
        encoder=encoder_spec(encoder), deformer_state=r["deformer_state"], light=r["light"], rotation=r["rotation"],
        translation=r["translation"], init=init_name, wall_time=wall,
        seconds_per_step=wall / (settings.steps * len(settings.seeds)))


def grid_search(encoder: Encoder, neuron: int, init="sphere", grid: dict | None = None,
                settings: MEISettings | None = None, *, self_intersections: bool = True, progress: bool = False,
                **overrides) -> list[dict]:
    """Run :func:`optimize_mei` for every combination of regularizer weights in ``grid``.

    Parameters
    ----------
    grid : dict of str -> sequence of float
        Weights to try per regularizer (names of :data:`REGULARIZERS`); regularizers not named keep the
        weight of ``settings``. Default: Laplacian and edge weights in ``{0, 1, 10}``.

    Returns
    -------
    list of dict, one per setting: ``weights``, ``activation``, ``fraction_of_bound``, ``min_quality``,
    ``mean_quality``, ``self_intersections``, ``seconds``.
    """
    import itertools

    settings = settings if settings is not None else MEISettings()
    if overrides:
        settings = replace(settings, **overrides)
    grid = grid if grid is not None else {"laplacian": [0.0, 1.0, 10.0], "edge": [0.0, 1.0, 10.0]}
    if not isinstance(grid, dict) or not grid:
        raise MEIError(f"grid must be a non-empty dict of regularizer name -> weights, got {grid!r}")
    for k, ws in grid.items():
        if k not in REGULARIZERS:
            raise MEIError(f"unknown regularizer {k!r} in grid; expected one of {sorted(REGULARIZERS)}")
        if len(list(ws)) == 0:
            raise MEIError(f"grid entry {k!r} is empty")
    names = list(grid)
    rows = []
    for combo in itertools.product(*(list(grid[k]) for k in names)):
        w = dict(settings.weights)
        w.update(dict(zip(names, (float(x) for x in combo))))
        res = optimize_mei(encoder, neuron, init, replace(settings, weights=w), progress=progress)
        q = mesh_quality(res.V, res.F, self_intersections=self_intersections)
        rows.append({"weights": w, "activation": res.activation, "fraction_of_bound": res.fraction_of_bound,
                     **q, "seconds": res.wall_time})
    return rows


def random_deformations(V0: torch.Tensor, n: int, *, generator: torch.Generator | None = None, n_bumps: int = 4,
                        amplitude: float = 0.15, width=(0.1, 0.3)) -> torch.Tensor:
    """``n`` random smooth deformations of a mesh: sums of ``n_bumps`` Gaussian bumps of random displacement.

    Each bump sits on a random vertex, has a width drawn uniformly from ``width`` and a displacement drawn
    from ``N(0, amplitude^2 I)`` (world units; the initial meshes span 1).

    Returns
    -------
    (n, V0.shape[0], 3) tensor of deformed vertex positions (dtype and device of ``V0``).
    """
    g = generator if generator is not None else torch.Generator().manual_seed(0)
    dt = V0.dtype
    c = V0[torch.randint(V0.shape[0], (n, n_bumps), generator=g)]  # (n, k, 3)
    w = width[0] + (width[1] - width[0]) * torch.rand(n, 1, n_bumps, generator=g, dtype=dt)
    d = amplitude * torch.randn(n, n_bumps, 3, generator=g, dtype=dt)
    K = torch.exp(-torch.cdist(V0.unsqueeze(0).expand(n, -1, -1), c) ** 2 / (2 * w * w))  # (n, nv, k)
    return V0 + K @ d


@torch.no_grad()
def random_mesh_responses(encoder: Encoder, neuron: int, init="sphere", n: int = 1000,
                          settings: MEISettings | None = None, *, seed: int = 0, batch: int = 50,
                          **deform_kw) -> torch.Tensor:
    """Responses ``(n,)`` of a neuron to ``n`` random deformations of the initial mesh, in the MEI's scene.

    The baseline a 3D-MEI has to beat: the same starting mesh, scene and preprocessing, with random smooth
    deformations (:func:`random_deformations`) instead of optimised ones.
    """
    settings = settings if settings is not None else MEISettings()
    V0, F, _ = _initial(init, settings, settings.torch_dtype)
    g = torch.Generator().manual_seed(int(seed))
    out = []
    with eval_mode(encoder):
        for start in range(0, n, batch):
            Vb = random_deformations(V0, min(batch, n - start), generator=g, **deform_kw)
            I = render(Vb, F, camera=settings.camera(),
                       light=None if settings.light is None else torch.tensor(settings.light, dtype=V0.dtype),
                       settings=settings.render_settings())
            out.append(encoder(I, neuron)[:, 0])
    return torch.cat(out)


# ---------------------------------------------------------------------------------------------- run directories

_REQUIRED = ("summary.json", "state.pt", "mesh.obj")
_SUMMARY_KEYS = {"format", "complete", "neuron", "init", "activation", "fraction_of_bound", "seed", "seed_activations",
                 "encoder", "settings", "light", "rotation_axis_angle", "translation", "n_vertices", "n_faces",
                 "wall_time_s", "seconds_per_step", "quality", "history", "loss_history", "reg_history",
                 "time_history"}


def _write_obj(path, V, F):
    with open(path, "w") as fh:
        fh.write("# meshmei 3D-MEI mesh\n")
        for v in V.detach().double().cpu().tolist():
            fh.write(f"v {v[0]:.9g} {v[1]:.9g} {v[2]:.9g}\n")
        for f in (F.cpu() + 1).tolist():
            fh.write(f"f {f[0]} {f[1]} {f[2]}\n")


def _summary(result: MEIResult) -> dict:
    return {
        "format": RUN_FORMAT,
        "complete": True,
        "neuron": result.neuron,
        "init": result.init,
        "activation": result.activation,
        "fraction_of_bound": result.fraction_of_bound,
        "seed": result.seed,
        "seed_activations": {str(k): v for k, v in result.seed_activations.items()},
        "encoder": result.encoder,
        "settings": result.settings.to_dict(),
        "light": None if result.light is None else result.light.tolist(),
        "rotation_axis_angle": result.rotation.tolist(),
        "translation": result.translation.tolist(),
        "n_vertices": int(result.V.shape[0]),
        "n_faces": int(result.F.shape[0]),
        "wall_time_s": result.wall_time,
        "seconds_per_step": result.seconds_per_step,
        "quality": mesh_quality(result.V, result.F, self_intersections=result.V.shape[0] <= 20000),
        "history": result.history,
        "loss_history": result.loss_history,
        "reg_history": result.reg_history,
        "time_history": result.time_history,
        **result.extra,
    }


def save_run(result: MEIResult, directory, *, overwrite: bool = False, figures: bool = True) -> Path:
    """Write a run directory: ``mesh.obj``, ``rest.obj``, ``state.pt``, ``summary.json`` and PNG figures.

    ``state.pt`` holds the exact tensors (rest mesh, faces, deformer ``state_dict``, light, pose, image), so
    :func:`load_run` rebuilds the mesh and the scene bit for bit; ``summary.json`` holds the settings,
    encoder description, histories and mesh quality. Everything is written to a temporary sibling
    directory that is renamed into place only when complete, so an interrupted save never leaves a
    directory that :func:`load_run` would take for a finished run.
    """
    def write(tmp: Path):
        _write_obj(tmp / "mesh.obj", result.V, result.F)
        _write_obj(tmp / "rest.obj", result.V0, result.F)
        torch.save({"format": RUN_FORMAT, "V": result.V, "F": result.F, "V0": result.V0,
                    "deformer": result.deformer_state, "light": result.light, "rotation": result.rotation,
                    "translation": result.translation, "image": result.image}, tmp / "state.pt")
        if figures:
            _figures(result, tmp)
        with open(tmp / "summary.json", "w") as fh:
            json.dump(_summary(result), fh, indent=1)

    return atomic_directory(directory, write, overwrite=overwrite, error=MEIError)


def _figures(result: MEIResult, out: Path):
    # the object-oriented API: no pyplot state, no backend switch in the caller's session
    import matplotlib.image
    from matplotlib.figure import Figure

    from ..render import camera_from_angles

    matplotlib.image.imsave(out / "render.png", result.image[0, 0].detach().cpu().numpy(), cmap="gray", vmin=0, vmax=1)
    views = []
    for az in (0.0, 45.0, 90.0):  # three more views of the mesh, turned about the vertical axis
        cam = camera_from_angles(az, 30.0, result.settings.camera_distance, fov_degrees=result.settings.fov_degrees)
        with torch.no_grad():
            img = render(result.V, result.F, camera=cam, settings=result.settings.render_settings())
        views.append(img[0, 0].cpu().numpy())
    fig = Figure(figsize=(12, 3.2))
    axes = fig.subplots(1, 4)
    axes[0].imshow(result.image[0, 0].detach().cpu().numpy(), cmap="gray", vmin=0, vmax=1)
    axes[0].set_title(f"MEI render, response {result.activation:.3f}")
    for ax, img, az in zip(axes[1:], views, (0, 45, 90)):
        ax.imshow(img, cmap="gray", vmin=0, vmax=1)
        ax.set_title(f"azimuth {az}, elevation 30")
    for ax in axes:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(out / "views.png", dpi=100)
    fig = Figure(figsize=(5, 3.2))
    ax = fig.subplots()
    ub = result.encoder.get("upper_bound")
    y = [h / ub for h in result.history] if ub else result.history
    ax.plot(range(1, len(y) + 1), y)
    ax.set_xlabel("step")
    ax.set_ylabel("fraction of upper bound" if ub else "response")
    ax.set_title(f"neuron {result.neuron}, seed {result.seed}")
    fig.tight_layout()
    fig.savefig(out / "activation.png", dpi=100)


def load_run(directory, *, encoder: Encoder | None = None, rebuild_encoder: bool = False) -> MEIResult:
    """Read a run directory written by :func:`save_run` back into an :class:`MEIResult`.

    The vertices are recomputed from the saved rest mesh and deformer state and checked against the saved
    ones. With ``rebuild_encoder=True`` (or ``encoder`` given), the returned result also carries the encoder
    as attribute ``encoder_module``.

    Raises
    ------
    MEIError
        The directory is missing, incomplete (an interrupted save leaves only a hidden ``.partial``
        sibling, never the directory itself), or its files are corrupt.
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise MEIError(f"no MEI run directory at {directory}")
    missing = [n for n in _REQUIRED if not (directory / n).is_file()]
    if missing:
        raise MEIError(f"{directory} is not a complete MEI run: missing {missing}")
    try:
        with open(directory / "summary.json") as fh:
            summary = json.load(fh)
    except (OSError, json.JSONDecodeError) as err:
        raise MEIError(f"{directory / 'summary.json'} is unreadable: {err}") from None
    if not isinstance(summary, dict) or summary.get("complete") is not True or summary.get("format") != RUN_FORMAT:
        raise MEIError(f"{directory} holds no complete run of format {RUN_FORMAT}")
    try:
        state = torch.load(directory / "state.pt", map_location="cpu", weights_only=True)
        settings = MEISettings.from_dict(summary["settings"])
        rbf = _rebuild_deformer(state["V0"], state["deformer"], settings)
        with torch.no_grad():
            V = rbf()
    except MEIError:
        raise
    except Exception as err:  # torch.load / load_state_dict errors on a damaged file
        raise MEIError(f"{directory} is corrupt: {type(err).__name__}: {err}") from None
    # The rebuilt deformer truncates its kernels for the final scales, the optimised one for the scales at
    # its last pair-list rebuild: each may drop weights up to exp(-r_cut^2 / 2), so the two meshes agree to
    # twice that times the summed offset lengths (plus float round-off). The saved vertices are kept.
    offsets = state["deformer"]["offsets"].double()
    bound = 2 * math.exp(-rbf.r_cut**2 / 2) * float(offsets.norm(dim=-1).sum())
    bound += 1e-5 * (1 + float(state["V"].abs().max()))
    if V.shape != state["V"].shape or float((V.double() - state["V"].double()).abs().max()) > bound:
        raise MEIError(f"{directory}: the deformer state does not reproduce the saved vertices")
    res = MEIResult(
        V=state["V"], F=state["F"], V0=state["V0"], image=state["image"], activation=float(summary["activation"]),
        history=summary["history"], loss_history=summary["loss_history"], reg_history=summary["reg_history"],
        seed=int(summary["seed"]), seed_activations={int(k): v for k, v in summary["seed_activations"].items()},
        settings=settings, neuron=int(summary["neuron"]), encoder=summary["encoder"],
        deformer_state=state["deformer"], light=state["light"], rotation=state["rotation"],
        translation=state["translation"], init=summary["init"], wall_time=float(summary["wall_time_s"]),
        seconds_per_step=float(summary["seconds_per_step"]), time_history=summary.get("time_history", []),
        extra={k: summary[k] for k in summary if k not in _SUMMARY_KEYS})
    if encoder is not None or rebuild_encoder:
        res.encoder_module = encoder if encoder is not None else _encoder_from_spec(summary["encoder"])
        if res.encoder_module.n_neurons <= res.neuron:
            raise MEIError(f"the encoder has {res.encoder_module.n_neurons} neurons; the run used neuron {res.neuron}")
    return res


# ---------------------------------------------------------------------------------------------- CLI

def add_parser(subparsers) -> None:
    p = subparsers.add_parser("mei", help="optimise a 3D-MEI for one neuron and write mesh, renders and summary")
    p.add_argument("--encoder", default="gabor-simple", choices=("gabor-simple", "gabor-complex", "demo"))
    p.add_argument("--neuron", type=int, default=0)
    p.add_argument("--init", default="sheet", choices=INITIAL_KINDS)
    p.add_argument("--out", required=True, help="run directory to write (must not exist unless --overwrite)")
    p.add_argument("--steps", type=int, default=MEISettings.steps)
    p.add_argument("--seeds", type=int, nargs="+", default=list(MEISettings.seeds))
    p.add_argument("--image-size", type=int, default=MEISettings.image_size)
    p.add_argument("--n-vertices", type=int, default=MEISettings.n_vertices)
    p.add_argument("--lr", type=float, default=MEISettings.lr)
    p.add_argument("--weight", action="append", default=[], metavar="NAME=W",
                   help="regularizer weight, e.g. --weight laplacian=1 (repeatable)")
    p.add_argument("--optimize-light", action="store_true")
    p.add_argument("--optimize-pose", action="store_true")
    p.add_argument("--pixel-mei", action="store_true", help="also run the pixel-MEI baseline and compare")
    p.add_argument("--overwrite", action="store_true")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_run_cli)


def _run_cli(args) -> int:
    weights = _default_weights()
    for item in args.weight:
        name, _, w = item.partition("=")
        try:
            weights[name] = float(w)
        except ValueError:
            raise MEIError(f"--weight expects NAME=NUMBER, got {item!r}") from None
    out = Path(args.out)
    if out.exists() and not args.overwrite:
        raise MEIError(f"{out} exists; pass --overwrite to replace it")
    encoder = make_encoder(args.encoder)
    settings = MEISettings(steps=args.steps, seeds=tuple(args.seeds), image_size=args.image_size,
                           n_vertices=args.n_vertices, lr=args.lr, weights=weights,
                           optimize_light=args.optimize_light, optimize_pose=args.optimize_pose)
    res = optimize_mei(encoder, args.neuron, args.init, settings, progress=not args.quiet)
    frac = res.fraction_of_bound
    line = f"3D-MEI neuron {res.neuron} ({args.encoder}, {args.init}): response {res.activation:.4f}"
    if frac is not None:
        line += f" = {frac:.3f} of the upper bound"
    if args.pixel_mei:
        from .pixel import pixel_mei

        pm = pixel_mei(encoder, args.neuron, image_size=args.image_size)
        line += f"; pixel MEI {pm.activation:.4f}"
        res.extra["pixel_mei_activation"] = pm.activation
    save_run(res, out, overwrite=args.overwrite)
    print(line)
    print(f"wrote {out}/: mesh.obj, rest.obj, state.pt, summary.json, render.png, views.png, activation.png "
          f"({res.wall_time:.1f} s, {1000 * res.seconds_per_step:.0f} ms per step)")
    return 0
