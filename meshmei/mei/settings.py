"""3D-MEI settings and results: everything that defines a run besides the encoder, the neuron and the
initial mesh, and everything a run returns (enough to rebuild its mesh and scene exactly)."""

from __future__ import annotations

import math
import numbers
from dataclasses import asdict, dataclass, field, fields, replace

import numpy as np
import torch

from .._checks import check_distinct_seeds, is_int, is_integral, seed_twin
from ..contact import MAX_CONTACT_DISTANCE
from ..deform import MAX_LR_SCALE, NarrowKernelError, RBFDeformer
from ..encoders import Encoder
from ..errors import MEIError, RenderError
from ..optim import MAX_STEPS
from ..quality import health_report
from ..regularizers import REGULARIZERS
from ..render import Camera, RenderSettings, axis_angle_to_matrix, render
from ..render.camera import DEFAULT_DISTANCE, DEFAULT_FOV_DEGREES
from ..render.settings import MAX_IMAGE_SIZE
from ..shapes.primitives import MAX_VERTICES
from ..validity import ValidityRules

__all__ = ["MEISettings", "MEIResult", "DEFAULT_STEPS", "ALBEDO_MIN_STEPS", "DEFAULT_CONTACT_WEIGHT",
           "DEFAULT_SIGMA_FACTOR", "make_deformer", "rebuild_deformer"]

# Steps per seed when ``MEISettings.steps`` is None, by start. A closed start has farther to travel to a
# relief than the sheet: from the sphere and the torus, 300 steps left Gabor cells at 0.88-0.95 of their
# bound and 800 reach 0.95 (docs/mei.md, *How many steps*). A mesh of your own gets the sheet's count.
# From the torus 1,600 (with narrower kernels, DEFAULT_SIGMA_FACTOR below): at 800 it reached 0.95 of the bound
# in 9 of 18 Gabor cells, at 1,600 with the default kernels in 4 of 6 (docs/mei.md, *The torus's kernels and
# steps*).
DEFAULT_STEPS = {"sheet": 300, "sphere": 800, "torus": 1600, "custom": 300}

# With an albedo (and ``steps`` None) a run takes at least this many steps: its texture's 4,096 values are
# still climbing at 300. Demo neuron 9 at 300 steps ended at 0.921-0.970 of its pixel MEI depending on
# rounding-level changes to the renderer (three versions of the code), at 500 at 0.957-0.977; neurons 2, 4,
# 5, 7 and 8 (none of the albedo benchmark's) ended 0.1-0.5 % higher at 500 (docs/mei.md, *Shape and albedo*).
ALBEDO_MIN_STEPS = 500

# A robust 3D-MEI renders robust_points^2 views per robust axis (pose, light; both: every pair) at every step,
# in one batch: 4,096 is robust_points 8 with both axes (64 px: about 65 MB of float32 images per step)
MAX_ROBUST_VIEWS = 4096

# Contact-barrier weight when ``MEISettings.contact_weight`` is None, by start. The sheet starts as a graph
# over the image plane and the guard's turn barrier keeps its faces facing the camera, so no two distant
# parts of it can come close: over six Gabor cells its response was the same without the contact barrier
# (0.964-0.992 against 0.971-0.991) and its step 14 % cheaper. From the sphere two of six cells lost 0.02-0.04
# without it, and the torus stalls (docs/mei.md, *Valid objects*). A mesh of your own keeps the barrier.
DEFAULT_CONTACT_WEIGHT = {"sheet": 0.0, "sphere": 100.0, "torus": 100.0, "custom": 100.0}

# RBF kernel width in mean centre spacings when ``MEISettings.sigma_factor`` is None, by start. From the torus
# 1.5 with its 1,600 steps: over 18 Gabor cells (three sets of six, two of them used for no choice) 18 reached
# 0.95 of the bound, against 9 at 2.0 and 800 steps; at 2.0 and 1,600 steps 4 of 6, at 1.5 and 800 steps 4
# of 6 and 5 of 6; wider kernels (3, 4) lost on every cell (docs/mei.md, *The torus's kernels and steps*).
DEFAULT_SIGMA_FACTOR = {"sheet": 2.0, "sphere": 2.0, "torus": 1.5, "custom": 2.0}


def _is_number(v) -> bool:
    """A real number, not a bool (nor a string that spells one)."""
    return isinstance(v, numbers.Real) and not isinstance(v, bool)


def _default_weights():
    return {"laplacian": 30.0, "edge": 30.0, "area": 1000.0, "arap": 0.0}


_RETIRED = {"margin_weight"}  # fields of older runs that no longer apply (a quadratic margin, now a barrier)


@dataclass(frozen=True)
class MEISettings:
    """Everything that defines a 3D-MEI run besides the encoder, the neuron and the initial mesh.

    Attributes
    ----------
    image_size : int
        Rendered image size in pixels (square).
    n_vertices : int
        Approximate vertex count of a built-in initial mesh (ignored for a given mesh).
    steps : int or None
        Adam steps per seed; None (default): by start, :data:`DEFAULT_STEPS` (300 from the sheet or a mesh
        of your own, 800 from the sphere or the torus), and at least :data:`ALBEDO_MIN_STEPS` (500) with
        ``albedo``. A run records the count it used.
    lr : float
        Learning rate of the RBF offsets (world units; the initial meshes span 1).
    lr_scales : float
        Learning rate of the RBF log-scales (0 freezes the scales), at most ``meshmei.deform.MAX_LR_SCALE`` (10).
    lr_decay : float
        The learning rates follow a cosine from ``lr`` down to ``lr * lr_decay``.
    seeds : tuple of int
        One run per seed; the seed draws the initial offsets (normal, std ``init_noise``). Distinct integers
        from 0 to ``2**32 - 1`` (``meshmei._checks.SEED_RANGE``: torch's CPU generator keeps a seed's low 32
        bits, so 2**32 or -3 would repeat one of these runs; a run saved with such a seed loads with the seed in
        the range whose run it is, ``seed % 2**32``).
    init_noise : float
        Standard deviation of the random initial offsets (breaks symmetries; 0 for none).
    sigma_factor : float or None
        Initial RBF scale as a multiple of the mean spacing of the kernel centres. None (default): by start,
        :data:`DEFAULT_SIGMA_FACTOR` (2, but 1.5 from the torus).
    centers : int or None
        Number of RBF centres (farthest-point sampled); None puts one on every vertex (the paper).
    r_cut : float
        RBF truncation radius in scales (see :class:`~meshmei.deform.RBFDeformer`).
    weights : dict
        Regularizer weights by name (see :data:`REGULARIZERS`); zero weights are not evaluated. The dict
        replaces the defaults as a whole: a regularizer it leaves out has weight 0
        (``weights={"laplacian": 100}`` drops the default edge and area terms; to change one weight, start
        from ``MEISettings().weights``). The command line's ``--weight NAME=W`` changes one and keeps the
        others.
    reg_ref_vertices : int or None
        (Default 400, the default mesh, for which the default weights were chosen.) ``weights`` are stated
        for a mesh of this many vertices and scaled to the run's (its ``n_vertices`` for a built-in start,
        its vertex count for a given mesh) by :func:`meshmei.regularizers.scale_weights`: the Laplacian and
        area weights by ``(n / ref)^2``, edge and direction ARAP by ``n / ref``; and above it the offsets'
        learning rate is ``lr * sqrt(ref / n)`` (see ``lr_by_edge``), so that the same settings behave alike
        at 400 and 2,500 vertices (docs/mei.md, *Resolution*). None: the weights and ``lr`` as given.
    lr_by_edge : bool
        (Default on.) With ``reg_ref_vertices``, a mesh finer than it takes the learning rate of its offsets
        shrunk as its edge length, ``lr * sqrt(reg_ref_vertices / n)``: a step stays the same share of an
        edge, where the guard and the barriers work. Off: only the weights are scaled.
    valid_steps : bool
        (Default on.) Accept only steps whose mesh is valid (:class:`~meshmei.validity.ValidityRules`: no
        new self-intersections, no face flipped against the rest mesh, no triangle below ``min_quality``);
        a refused step is halved until it passes (:func:`meshmei.optim.minimize`). Every accepted iterate,
        and so the result, is intersection-free and unflipped (docs/mei.md, *Valid objects*).
    min_quality : float
        The triangle-quality bound of ``valid_steps``.
    barrier_weight : float
        Weight of the guard's own barrier (:meth:`~meshmei.validity.StepGuard.barrier`, summed over faces)
        with ``valid_steps``: it turns the run away from the turn and quality bounds before a step reaches
        them, so that few steps are refused.
    contact_weight : float or None
        With ``valid_steps``, weight of the contact barrier (:class:`~meshmei.contact.ContactBarrier`, over
        vertex-face and edge-edge pairs), which keeps the surface from touching itself (0: no barrier; the
        guard alone then stalls a run whose optimum presses parts together). None (default): by start,
        :data:`DEFAULT_CONTACT_WEIGHT` (100, but 0 from the sheet, which stays a graph over the image plane).
        A run records the weight it used.
    contact_distance : float
        The contact barrier's reach, as a share of the start's mean edge length.
    keep : str
        ``"best"``: return the iterate with the lowest loss seen; ``"last"``: the final iterate.
    optimize_light, optimize_pose : bool
        Also optimise the point light position / the object's rotation (axis-angle) and translation.
    lr_light, lr_pose : float
        Their learning rates.
    albedo : bool
        Also optimise a per-vertex gray surface albedo, ``sigmoid(theta)`` (so in [0, 1]), starting at
        ``albedo_init`` everywhere, with learning rate ``lr_albedo`` and the smoothness penalty
        ``albedo_smoothness * mean_i (a_i - mean of a over i's 1-ring)^2``; the RBF offsets then move at
        ``albedo_shape_lr * lr`` (1 by default; 0.1 lets the albedo lead, which unguarded runs needed to keep
        the shape from folding, docs/mei.md). From the sheet the albedo is an
        ``albedo_resolution`` x ``albedo_resolution`` texture over the sheet's own grid instead (texel
        neighbours in the penalty; at most 8192, the largest image side); 0: per vertex there too. False
        (default): shape only, the paper's setting.
    robust_pose, robust_light : float
        Degrees (0: off). Maximise the expected response over object turns (azimuth about y, elevation
        about x) uniform within +-``robust_pose``, and over light positions turned the same way about the
        object within +-``robust_light`` (both: every pair), instead of the response in the one scene; the
        expectation by Gauss-Legendre quadrature, ``robust_points`` nodes per angle. The reported response
        is the one in the plain scene.
    robust_points : int
        Quadrature nodes per angle (3: 0 and +-0.775 d, weights 8/18 and 5/18 each).
    robust_widen : float
        Share of the run over which the robust ranges widen linearly from 0 to full (in ``[0, 1)``; 0: full
        from the start): the run finds the plain optimum first, then holds it over more views (docs/mei.md).
        Keep-best considers only the iterates after the ranges are full.
    light : tuple of 3 floats or None
        Point light position; None puts it at the camera.
    camera_distance, fov_degrees : float
        The overhead camera at ``(0, 0, camera_distance)`` looking at the origin.
    render : RenderSettings, dict or None
        How the image is formed (background, ambient, sigma, ...): a
        :class:`~meshmei.render.RenderSettings`, or a dict of its fields (as a run's ``summary.json``
        stores it). Its ``image_size`` is replaced by ``image_size`` above, the one place the run's
        image size is set. None: the defaults.
    dtype : str
        ``"float32"`` or ``"float64"``.
    """

    image_size: int = 64
    n_vertices: int = 400
    steps: int | None = None
    lr: float = 3e-3
    lr_scales: float = 1e-2
    lr_decay: float = 0.05
    seeds: tuple = (0, 1, 2)
    init_noise: float = 1e-3
    sigma_factor: float | None = None
    centers: int | None = None
    r_cut: float = 4.0
    weights: dict = field(default_factory=_default_weights)
    reg_ref_vertices: int | None = 400
    lr_by_edge: bool = True
    valid_steps: bool = True
    min_quality: float = 0.01
    barrier_weight: float = 0.1
    contact_weight: float | None = None
    contact_distance: float = 0.25
    keep: str = "best"
    optimize_light: bool = False
    optimize_pose: bool = False
    lr_light: float = 2e-2
    lr_pose: float = 1e-2
    albedo: bool = False
    lr_albedo: float = 0.2
    albedo_smoothness: float = 1.0
    albedo_init: float = 0.5
    albedo_resolution: int = 64
    albedo_shape_lr: float = 1.0
    robust_pose: float = 0.0
    robust_light: float = 0.0
    robust_points: int = 3
    robust_widen: float = 0.5
    light: tuple | None = None
    camera_distance: float = DEFAULT_DISTANCE
    fov_degrees: float = DEFAULT_FOV_DEGREES
    render: RenderSettings | dict | None = None
    dtype: str = "float32"

    def __post_init__(self):
        self._check_numbers()
        self._check_seeds()
        self._check_weights()
        self._check_validity()
        self._check_albedo_and_robustness()
        self._check_optimiser()
        self._check_scene()
        object.__setattr__(self, "render", _render_settings(self.render, self.image_size))

    def _check_numbers(self):
        """Flags, counts, rates and the camera: of the types and ranges they take."""
        for f in fields(self):  # numpy scalars as Python numbers: compared as such, and JSON-able in a run folder
            v = getattr(self, f.name)
            if isinstance(v, np.generic):
                object.__setattr__(self, f.name, v.item())
        for name in ("valid_steps", "lr_by_edge", "optimize_light", "optimize_pose", "albedo"):
            if not isinstance(getattr(self, name), bool):  # "false" is a true string
                raise MEIError(f"{name} must be True or False, got {getattr(self, name)!r}")
        for name in ("image_size", "n_vertices", "steps", "robust_points"):
            v = getattr(self, name)
            if name == "steps" and v is None:
                continue
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise MEIError(f"{name} must be a positive integer, got {v!r}")
            if name == "steps" and v > MAX_STEPS:
                raise MEIError(f"steps must be at most {MAX_STEPS:.0e}, got {v!r}")
        for name in ("lr", "lr_scales", "lr_decay", "init_noise", "sigma_factor", "r_cut", "lr_light", "lr_pose",
                     "camera_distance", "fov_degrees", "lr_albedo", "albedo_smoothness", "albedo_shape_lr",
                     "robust_pose", "robust_light"):
            v = getattr(self, name)
            if name == "sigma_factor" and v is None:  # by start (for_start)
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise MEIError(f"{name} must be a finite non-negative number, got {v!r}")
        if self.lr <= 0 or (self.sigma_factor is not None and self.sigma_factor <= 0) or self.r_cut <= 0:
            raise MEIError(f"lr, sigma_factor and r_cut must be positive, got {self.lr}, {self.sigma_factor}, {self.r_cut}")
        if self.lr_decay > 1:
            raise MEIError(f"lr_decay must lie in [0, 1] (the learning rates' final share), got {self.lr_decay!r}")
        if self.camera_distance <= 0:
            raise MEIError(f"camera_distance must be positive, got {self.camera_distance!r}")
        if not 0 < self.fov_degrees < 180:
            raise MEIError(f"fov_degrees must lie in (0, 180), got {self.fov_degrees!r}")

    def _check_seeds(self):
        """``seeds``: a non-empty sequence of distinct integers in range (one int: a sequence of one)."""
        try:
            seeds = tuple(self.seeds) if not isinstance(self.seeds, numbers.Integral) else (self.seeds,)
        except TypeError:  # None, a float
            seeds = ()
        if not seeds or not all(isinstance(s, numbers.Integral) and not isinstance(s, bool) for s in seeds):
            raise MEIError(f"seeds must be a non-empty sequence of integers, got {self.seeds!r}")
        seeds = tuple(int(s) for s in seeds)
        check_distinct_seeds(seeds, error=MEIError)
        object.__setattr__(self, "seeds", seeds)

    def _check_weights(self):
        """``weights`` by registered regularizer name, and the vertex count they are stated for."""
        if not isinstance(self.weights, dict):
            raise MEIError(f"weights must be a dict of regularizer name -> weight, got {type(self.weights).__name__}")
        for k, w in self.weights.items():
            if k not in REGULARIZERS:
                raise MEIError(f"unknown regularizer {k!r}; expected one of {sorted(REGULARIZERS)}")
            if isinstance(w, bool) or not isinstance(w, (int, float)) or not math.isfinite(w) or w < 0:
                raise MEIError(f"weight of {k!r} must be a finite non-negative number, got {w!r}")
        ref = self.reg_ref_vertices
        if ref is not None and (not is_integral(ref) or ref < 1):
            raise MEIError(f"reg_ref_vertices must be a positive integer or None, got {ref!r}")
        if ref is not None and ref > MAX_VERTICES:  # the weights it scales would underflow to 0
            raise MEIError(f"reg_ref_vertices must be a vertex count of at most {MAX_VERTICES:,}, got {ref!r}")

    def _check_validity(self):
        """The step guard's quality floor and the two barriers' weights and reach."""
        if not _is_number(self.min_quality) or not 0 <= self.min_quality < 1:
            raise MEIError(f"min_quality must lie in [0, 1), got {self.min_quality!r}")
        for name in ("barrier_weight", "contact_weight", "contact_distance"):
            v = getattr(self, name)
            if v is None and name == "contact_weight":
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise MEIError(f"{name} must be a finite non-negative number, got {v!r}")
        if not 0 < self.contact_distance <= MAX_CONTACT_DISTANCE:
            raise MEIError(f"contact_distance must lie in (0, {MAX_CONTACT_DISTANCE:g}] mean edge lengths, got "
                           f"{self.contact_distance!r}")

    def _check_albedo_and_robustness(self):
        """The albedo's texture and start, and the robust quadrature's spread and size."""
        r = self.albedo_resolution
        if isinstance(r, bool) or not isinstance(r, int) or r < 0 or r == 1:
            raise MEIError(f"albedo_resolution must be 0 (per vertex) or an integer >= 2, got {r!r}")
        if r > MAX_IMAGE_SIZE:  # a texture finer than the largest image; 10**9 reached the allocator
            raise MEIError(f"albedo_resolution must be at most {MAX_IMAGE_SIZE} (the largest image side), got {r!r}")
        if not _is_number(self.albedo_init) or not 0 < self.albedo_init < 1:
            raise MEIError(f"albedo_init must lie in (0, 1), got {self.albedo_init!r}")
        w = self.robust_widen
        if isinstance(w, bool) or not isinstance(w, (int, float)) or not 0 <= w < 1:
            raise MEIError(f"robust_widen must lie in [0, 1), got {w!r}")
        for name in ("robust_pose", "robust_light"):
            if getattr(self, name) > 180:  # +-180 degrees already turns the object (or the light) all the way round
                raise MEIError(f"{name} must be at most 180 degrees, got {getattr(self, name)!r}")
        axes = (self.robust_pose > 0) + (self.robust_light > 0)
        views = self.robust_points ** (2 * axes)
        if views > MAX_ROBUST_VIEWS:  # every view is rendered at every step, in one batch
            raise MEIError(f"robust_points={self.robust_points} gives {views:,} views per step "
                           f"({'pose and light' if axes == 2 else 'two angles'}); at most {MAX_ROBUST_VIEWS:,}")

    def _check_optimiser(self):
        """``keep``, ``dtype``, and learning rates whose first Adam step fits the dtype and the RBF scales."""
        if self.keep not in ("best", "last"):
            raise MEIError(f"keep must be 'best' or 'last', got {self.keep!r}")
        if self.dtype not in ("float32", "float64"):
            raise MEIError(f"dtype must be 'float32' or 'float64', got {self.dtype!r}")
        # Adam's first step is lr / (1 - beta1) = 10 lr, which must be a number of the run's dtype
        top = torch.finfo(self.torch_dtype).max * (1 - 0.9)
        shape_lr = self.lr * (self.albedo_shape_lr if self.albedo else 1.0)
        for name, v in (("lr", self.lr), ("lr_scales", self.lr_scales), ("lr_light", self.lr_light),
                        ("lr_pose", self.lr_pose), ("lr_albedo", self.lr_albedo), ("lr * albedo_shape_lr", shape_lr)):
            if not v <= top:
                raise MEIError(f"{name} must be at most {top:.3g} (a tenth of {self.dtype}'s largest number: Adam's "
                               f"first step is 10 lr), got {v!r}")
        if self.lr_scales > MAX_LR_SCALE:  # 100 overflowed every kernel scale at the first step: a translation
            raise MEIError(f"lr_scales must be at most {MAX_LR_SCALE:g} (a step may widen an RBF kernel e^lr_scales "
                           f"times; at 100 the first step overflowed every scale), got {self.lr_scales!r}")

    def _check_scene(self):
        """A fixed light of three finite numbers (made a tuple) and the RBF centre count."""
        if self.light is not None:
            try:  # a string is a sequence too: "123" must not pass as (1, 2, 3)
                lt = () if isinstance(self.light, (str, bytes)) else tuple(float(x) for x in self.light)
            except (TypeError, ValueError):
                lt = ()
            if len(lt) != 3 or not all(math.isfinite(x) for x in lt):
                raise MEIError(f"light must be three finite numbers or None, got {self.light!r}")
            object.__setattr__(self, "light", lt)
        c = self.centers
        if c is not None and (isinstance(c, bool) or not isinstance(c, numbers.Integral) or c < 1):
            raise MEIError(f"centers must be None or an int (a positive number of RBF centres), got {c!r}")

    def offset_lr(self, n_vertices: int) -> float:
        """The learning rate of the RBF offsets for a mesh of ``n_vertices`` (the count the weights scale
        to): ``lr``, times ``albedo_shape_lr`` with an albedo, times ``sqrt(reg_ref_vertices / n)`` above
        the reference with ``lr_by_edge``."""
        lr = self.lr * (self.albedo_shape_lr if self.albedo else 1.0)  # with an albedo the shape follows
        ref = self.reg_ref_vertices
        if self.lr_by_edge and ref is not None and n_vertices > ref:
            lr = lr * (ref / n_vertices) ** 0.5
        return lr

    def for_start(self, init_name: str) -> "MEISettings":
        """These settings with ``steps``, ``contact_weight`` and ``sigma_factor`` set for the start
        ``init_name`` (a key of :data:`DEFAULT_STEPS`, :data:`DEFAULT_CONTACT_WEIGHT` and
        :data:`DEFAULT_SIGMA_FACTOR`, else ``"custom"``; with ``albedo``, at least :data:`ALBEDO_MIN_STEPS`
        steps) where they are None."""
        known = init_name if init_name in DEFAULT_STEPS else "custom"
        if self.steps is not None:
            steps = self.steps
        else:
            steps = max(DEFAULT_STEPS[known], ALBEDO_MIN_STEPS) if self.albedo else DEFAULT_STEPS[known]
        contact = DEFAULT_CONTACT_WEIGHT[known] if self.contact_weight is None else self.contact_weight
        sigma = DEFAULT_SIGMA_FACTOR[known] if self.sigma_factor is None else self.sigma_factor
        if steps == self.steps and contact == self.contact_weight and sigma == self.sigma_factor:
            return self
        return replace(self, steps=steps, contact_weight=contact, sigma_factor=sigma)

    def render_settings(self) -> RenderSettings:
        """The :class:`~meshmei.render.RenderSettings` of the run (``render``, at ``image_size``)."""
        return self.render

    def validity_rules(self) -> ValidityRules:
        """The rules of ``valid_steps``: no new self-intersections, no face flipped against the rest mesh."""
        return ValidityRules(turn_from="rest", min_quality=self.min_quality)

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
    def with_overrides(cls, settings: "MEISettings | None", overrides: dict) -> "MEISettings":
        """``settings`` (default: the defaults) with the fields in ``overrides`` replaced, all checked."""
        settings = settings if settings is not None else cls()
        if not isinstance(settings, cls):
            raise MEIError(f"settings must be an MEISettings, got {type(settings).__name__}")
        unknown = set(overrides) - {f.name for f in fields(cls)}
        if unknown:
            raise MEIError(f"unknown MEISettings fields {sorted(unknown)}")
        return replace(settings, **overrides) if overrides else settings

    @classmethod
    def from_dict(cls, d: dict) -> "MEISettings":
        known = {f.name for f in fields(cls)}
        d = {k: v for k, v in d.items() if k not in _RETIRED}
        unknown = set(d) - known
        if unknown:
            raise MEIError(f"unknown MEISettings fields {sorted(unknown)}")
        d = dict(d)
        if "seeds" in d:  # a run saved with a seed beyond SEED_RANGE (-3 was taken) was the run of its twin in it
            d["seeds"] = tuple(seed_twin(s) if is_int(s) else s for s in d["seeds"])
        if d.get("light") is not None:
            d["light"] = tuple(d["light"])
        return cls(**d)


@dataclass(frozen=True)
class MEIResult:
    """Outcome of :func:`optimize_mei` (or of :func:`load_run`). Its tensors are on the CPU, whatever device
    the run used (the model's).

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
        Unweighted value of each active regularizer at every step of the winning seed, and of the albedo's
        smoothness term (``albedo_roughness``) in a run that learns an albedo.
    seed : int
        The winning seed.
    seed_activations : dict of int -> float
        Final response per seed.
    settings : MEISettings
    neuron : int
    encoder : dict
        :func:`~meshmei.encoders.encoder_spec` of the encoder (enough to rebuild the built-in ones).
    deformer_state : dict
        ``state_dict`` of the winning :class:`~meshmei.deform.RBFDeformer`.
    light : (3,) tensor or None
        Light position used (None: at the camera).
    albedo : (n,) or (R, R) tensor or None
        The optimised albedo in [0, 1] (``settings.albedo``): per vertex, or a texture over ``albedo_uv``;
        None for shape only.
    albedo_uv : (n, 2) tensor or None
        The vertices' texture coordinates for a texture albedo.
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
        JSON-able additions written to the summary (e.g. ``pixel_mei_activation``); add them with
        ``dataclasses.replace(result, extra={**result.extra, ...})``.
    encoder_module : Encoder or None
        The encoder itself, where :func:`~meshmei.mei.load_run` was asked to rebuild or given it.
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
    encoder_module: Encoder | None = field(default=None, compare=False, repr=False)
    albedo: torch.Tensor | None = None
    albedo_uv: torch.Tensor | None = None

    @property
    def fraction_of_bound(self) -> float | None:
        ub = self.encoder.get("upper_bound")
        return None if ub is None else self.activation / ub

    def scene(self) -> dict:
        """Keyword arguments for :func:`meshmei.render.render` that reproduce :attr:`image` from ``V, F``."""
        return dict(camera=self.settings.camera(), light=self.light,
                    rotation=axis_angle_to_matrix(self.rotation), translation=self.translation,
                    settings=self.settings.render_settings(), albedo=self.albedo, uv=self.albedo_uv)

    def render(self, **overrides) -> torch.Tensor:
        """Re-render the result (``overrides`` replace entries of :meth:`scene`)."""
        kw = self.scene()
        kw.update(overrides)
        return render(self.V, self.F, **kw)

    def health(self) -> dict:
        """The mesh's health (:func:`meshmei.quality.health_report`: self-intersections, faces flipped
        against :attr:`V0`, triangle quality, watertightness)."""
        return health_report(self.V, self.F, self.V0)

    def deformer(self) -> RBFDeformer:
        """Rebuild the winning RBF deformer from :attr:`V0` and :attr:`deformer_state`.

        ``deformer()()`` reproduces :attr:`V` up to float round-off when the deformer's (vertex, kernel) pair
        list was never rebuilt during the run (``lr_scales=0``, or scales that stayed within the list's
        headroom). When learnable scales grew past it, the run's list and the rebuilt one keep different pairs
        beyond ``r_cut`` scales, and the two meshes differ by at most ``exp(-r_cut^2 / 2)`` times the summed
        offset norms, ``sum_k |offsets_k|`` (each (vertex, kernel) pair is dropped by at most one of the two
        lists, and every dropped weight is below ``exp(-r_cut^2 / 2)``): no difference seen at the default
        ``r_cut=4``, 0.037 in world units after five steps from the sphere at ``r_cut=1``, ``lr_scales=0.5``.
        :attr:`V` is the mesh the run rendered and scored, and :func:`~meshmei.mei.load_run` keeps the saved
        :attr:`V`.
        """
        return rebuild_deformer(self.V0, self.deformer_state, self.settings)



def _render_settings(render, image_size: int) -> RenderSettings:
    if render is None:
        return RenderSettings(image_size=image_size)
    if isinstance(render, dict):
        try:
            return RenderSettings(**{"image_size": image_size, **render})
        except TypeError as err:
            raise MEIError(f"render holds an unknown RenderSettings field: {err}") from None
        except RenderError as err:
            raise MEIError(f"render: {err}") from None
    if not isinstance(render, RenderSettings):
        raise MEIError(f"render must be a RenderSettings, a dict of its fields or None, got {type(render).__name__}")
    return replace(render, image_size=image_size)


def make_deformer(V0, settings: MEISettings, centers=None):
    """The RBF deformer of ``settings`` over ``V0``; settings not resolved for a start
    (:meth:`MEISettings.for_start`) take a mesh of your own's kernel width."""
    sigma_factor = DEFAULT_SIGMA_FACTOR["custom"] if settings.sigma_factor is None else settings.sigma_factor
    if centers is None:
        centers = settings.centers
    try:  # a kernel too narrow for the dtype: NaN vertices at the first render, were it built
        return RBFDeformer(V0, centers, sigma_factor=sigma_factor, r_cut=settings.r_cut,
                           learn_scales=settings.lr_scales > 0)
    except NarrowKernelError as err:
        raise MEIError(f"sigma_factor={sigma_factor!r}: {err}; raise sigma_factor") from None


def rebuild_deformer(V0, state, settings):
    rbf = make_deformer(V0, settings, centers=state["center_index"])
    rbf.load_state_dict(state)
    return rbf
