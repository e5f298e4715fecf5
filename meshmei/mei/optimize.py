"""3D-MEI optimisation: a mesh deformed by Gaussian RBFs, rendered in the paper's scene, climbs a model
neuron's response; the objective is ``-f(I) + sum_r w_r L_r(V)`` and :mod:`meshmei.optim` runs it.

Light position and object pose can join the optimisation. Several seeds are run (the seed draws a small
random initial offset, so runs differ) and the one with the lowest final loss is kept.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import replace

import torch

from ..contact import ContactBarrier, contact_energies
from ..encoders import Encoder, encoder_spec, frozen_encoder
from ..errors import EncoderError, MEIError
from ..mesh import load_mesh, remove_unreferenced
from ..optim import Budget, Progress, Schedule, Trace, checked_callbacks, make_optimizer, minimize, tagged_callbacks
from ..regularizers import regularizer_values, scale_weights
from ..shapes import INITIAL_KINDS, initial_mesh
from ..validity import StepGuard
from .scene import SeedScene, sheet_uv
from .settings import MEIResult, MEISettings

__all__ = ["optimize_mei", "initial", "start_from_file", "check_neuron", "settings_for_encoder", "result_from_seeds", "objective_weights",
           "validity_barriers", "contact_barriers", "guard_report"]


def check_neuron(encoder, neuron, error: type[ValueError] = MEIError) -> int:
    """The neuron's index in ``encoder`` as an int; ``error`` for anything but one valid index."""
    if not isinstance(encoder, Encoder):
        raise error(f"encoder must be a meshmei Encoder, got {type(encoder).__name__}")
    try:
        idx = encoder.neuron_index(neuron)
    except EncoderError as err:
        raise error(str(err)) from None
    if idx.numel() != 1 or neuron is None:
        raise error(f"neuron must be a single index, got {neuron!r}")
    return int(idx[0])


def settings_for_encoder(settings: MEISettings, encoder) -> MEISettings:
    """The settings a run uses with ``encoder``: a lab's model (:class:`~meshmei.encoders.ModelEncoder`) is
    rendered at the longer side of its input (its own size when square; a 36 x 64 model gets a 64 x 64
    render whose middle 36 rows it sees, :func:`~meshmei.encoders.fit_to_size`)."""
    size = getattr(encoder, "image_size", None)
    if size is not None and settings.image_size != max(size):
        settings = replace(settings, image_size=int(max(size)))
    return settings


def start_name(init) -> str:
    """The start's name for :data:`~meshmei.mei.settings.DEFAULT_STEPS`: a built-in start's own, else
    ``"custom"`` (checked by :func:`initial`)."""
    return init if isinstance(init, str) else "custom"


def initial(init, settings: MEISettings, device="cpu"):
    """``(V0, F, name)`` on ``device``: a built-in starting mesh by name (``settings.n_vertices``) or a given
    ``(V, F)`` (vertices no face uses are dropped: they would only widen the RBF kernels' spacing). A run
    passes its model's device (:attr:`meshmei.encoders.Encoder.device`): the mesh, its deformation and its
    render live where the model computes."""
    if isinstance(init, str):
        if init not in INITIAL_KINDS:
            raise MEIError(f"init must be one of {INITIAL_KINDS} or a (V, F) pair, got {init!r}")
        try:
            V0, F = initial_mesh(init, n_vertices=settings.n_vertices, dtype=settings.torch_dtype, device="cpu")
        except ValueError as err:  # a vertex count the start cannot have
            raise MEIError(f"{init} start: {err}") from None
        return V0.to(device), F.to(device), init
    try:
        V0, F = init
    except (TypeError, ValueError):
        raise MEIError(f"init must be one of {INITIAL_KINDS} or a (V, F) pair, got {type(init).__name__}") from None
    V0, F = remove_unreferenced(torch.as_tensor(V0, device="cpu").detach(), torch.as_tensor(F, device="cpu"))
    side = float((V0.amax(0) - V0.amin(0)).max())
    if not 0.25 <= side <= 4.0:
        # lr and the initial noise are lengths sized for the built-in starts (largest side 1): a start 50
        # times smaller kept its shape but had most steps refused, one 50 times larger barely moved
        warnings.warn(f"the start's largest side is {side:.3g}; lr ({settings.lr}) and the initial noise are "
                      "world lengths sized for starts of about 1 (the built-in ones, and files given to "
                      "meshmei mei --init, are scaled to 1): scale the start, or lr with it", stacklevel=3)
    return V0.to(device=device, dtype=settings.torch_dtype), F.to(device), "custom"


def start_from_file(path, dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """A 3D-MEI start ``(V, F)`` from a mesh file (:func:`meshmei.mesh.load_mesh`), placed as the built-in
    starts are: its bounding box centred at the origin and its largest side scaled to 1 (the sphere's
    diameter, the sheet's side), so that it fills the camera's view as they do. Faces keep their
    orientation; an open mesh is allowed (as the sheet); vertices no face uses are dropped."""
    V, F = remove_unreferenced(*load_mesh(path, dtype=torch.float64))
    lo, hi = V.min(0).values, V.max(0).values
    side = float((hi - lo).max())
    if not side > 0:
        raise MEIError(f"{path}: the mesh has no extent (all its vertices coincide)")
    return ((V - 0.5 * (lo + hi)) / side).to(dtype), F


def objective_weights(settings: MEISettings, n_weights: int) -> dict:
    """The regularizer weights a run uses (scaled to ``n_weights`` vertices), the zero ones left out."""
    weights = scale_weights(settings.weights, n_weights, settings.reg_ref_vertices)
    return {k: w for k, w in weights.items() if w > 0}


def validity_barriers(guard, contacts, V, settings: MEISettings, record: dict) -> torch.Tensor:
    """The guard's barrier and the contact barriers, weighted: of one mesh ``V (n, 3)`` (a scalar) or of a
    batch ``(B, n, 3)`` of meshes of the guard's start (``(B,)``; one guard serves all). ``contacts``: one
    :class:`~meshmei.contact.ContactBarrier` per mesh, or None. Their values go into ``record``
    (``"barrier"``, ``"contact"``: a float, or a list per item) when they are evaluated."""
    total = V.new_zeros(V.shape[:-2])
    if guard is not None and settings.barrier_weight > 0:
        b = guard.barrier(V)
        record["barrier"] = b.detach().tolist()
        total = total + settings.barrier_weight * b
    if contacts is not None:
        c = contact_energies(contacts, V) if V.ndim == 3 else contacts[0](V)
        record["contact"] = c.detach().tolist()
        total = total + settings.contact_weight * c
    return total


def contact_barriers(V0, F, settings: MEISettings, items: int = 1):
    """One contact barrier per item of a guarded run (None without ``valid_steps`` or with
    ``contact_weight`` 0)."""
    if not settings.valid_steps or settings.contact_weight <= 0:
        return None
    # at most one candidate search every fourth step: the guard, not the barrier, holds the guarantee. Edges
    # are paired with edges too: two edges crossing like an X come close with every vertex far from the other's
    # faces, and a run pushed into such a contact had every step refused by the intersection test from there
    # on (a torus start stalled at step 58 of 800: 0.746 of the bound against 0.955 with edge pairs;
    # docs/mei.md, *Edge contacts*)
    barriers = [ContactBarrier.for_mesh(V0, F, settings.contact_distance, min_interval=4, edges=True)
                for _ in range(items)]
    for cb in barriers:  # a user's start with a T-junction or touching parts: those pairs would lock the run
        cb.leave_out(V0)
    return barriers


def _objective(encoder, neuron, F, scene: SeedScene, settings: MEISettings, n_weights: int, guard):
    active = objective_weights(settings, n_weights)
    contacts = contact_barriers(scene.rbf.V0, F, settings)
    if guard is not None and contacts is not None:
        guard.use_contact(contacts[0])  # its distances at each accepted mesh clear most steps of libigl's test

    def objective(point):
        V = scene.vertices()
        # the candidate search (C and NumPy, without the GIL) runs beside the render where the render leaves the
        # CPU free (a GPU's). On the CPU torch's threads take every core in the render, and the search in a
        # thread beside them cost as much or more than in line (whole default runs in one lockstep, guarded over
        # unguarded: from the torus 1.64-1.78 against 1.55-1.66, from the sphere 1.26-1.28 both ways, and
        # 1.44-1.59 against 1.15-1.40 once the caller had set torch's thread count, to its default 2); the same
        # results (docs/mei.md, *The search in line*)
        if contacts is not None and V.device.type != "cpu":
            contacts[0].prefetch(V)
        scene.widen(point.fraction)
        f = scene.expected(encoder(scene.views(V, F), neuron)[:, 0])  # one view, or the robust quadrature
        loss, record = -f, {"response": float(f.detach())}
        for k, r in regularizer_values(V, scene.rbf.V0, F, active).items():
            record[k] = float(r.detach())
            loss = loss + active[k] * r
        if settings.albedo:
            r = scene.albedo_roughness(F)
            record["albedo_roughness"] = float(r.detach())
            loss = loss + settings.albedo_smoothness * r
        return loss + validity_barriers(guard, contacts, V, settings, record), record

    return objective


def valid_start(rbf, guard, halvings: int = 30) -> int:
    """Halve the seed's initial offsets of ``rbf`` until the deformed start meets ``guard``'s rules (the rest
    mesh meets them by construction); returns how often they were halved. A start the noise would fold (a
    fine or thin mesh of your own) then runs from a valid first iterate instead of one every step is refused
    from; the built-in starts' noise is far inside the rules and is left as it is."""
    for k in range(halvings + 1):
        with torch.no_grad():
            if guard.why_not(rbf()) is None:
                return k
            rbf.offsets.mul_(0.5)
    with torch.no_grad():
        rbf.offsets.zero_()
    return halvings + 1


def _run_seed(encoder, neuron, V0, F, settings: MEISettings, seed: int, bar: Progress, guard, n_weights,
              uv=None, callbacks=()) -> dict:
    scene = SeedScene(V0, settings, seed, uv, n_weights)
    if guard is not None:
        valid_start(scene.rbf, guard)
    trace = Trace()
    accept = None if guard is None else guard.acceptor(scene.vertices.candidate)
    out = minimize(_objective(encoder, neuron, F, scene, settings, n_weights, guard), make_optimizer("adam", scene.groups),
                   Budget(steps=settings.steps), schedule=Schedule("cosine", settings.lr_decay, endpoint=True),
                   keep=settings.keep, keep_from=settings.robust_widen if scene.robust is not None else 0.0,
                   evaluate_last=True, trace=trace, progress=bar, callbacks=tagged_callbacks(callbacks, seed=seed),
                   accept=accept, max_halvings=0 if guard is None else guard.rules.max_halvings, states=(scene.rbf,),
                   error=MEIError, where=f" of seed {seed}")
    with torch.no_grad():
        V = scene.rbf().detach()
        image = scene.image(V, F, pose=True).detach()
        act = float(encoder(image, neuron)[0, 0])
    h = trace.history
    state = {k: v.detach().clone() for k, v in scene.rbf.state_dict().items()}
    light = None if scene.light is None else scene.light.detach().clone()
    albedo = None if scene.albedo_logit is None else scene.albedo().detach().clone()
    return dict(V=V, image=image, activation=act, loss=out.loss, best_step=out.step, albedo=albedo, albedo_uv=scene.uv,
                guard=None if guard is None else guard_report(guard, [r["step_scale"] for r in h]),
                history=[r["response"] for r in h], loss_history=[r["loss"] for r in h],
                reg_history={k: [r[k] for r in h] for k in reg_terms(settings, h)},
                time_history=[r["time"] for r in h], deformer_state=state, light=light,
                rotation=scene.rotation.detach().clone(), translation=scene.translation.detach().clone())


def guard_report(guard, scales) -> dict:
    """``guard``'s :meth:`~meshmei.validity.StepGuard.report` of one seed's run, with ``"undone"``: its steps
    of which no halving was accepted (``scales``: each step's ``step_scale``), where the mesh stayed put. A
    run that undoes most of its steps has stalled at a contact or a bound, whatever its response."""
    return {**guard.report(), "undone": sum(1 for s in scales if s == 0)}


def reg_terms(settings: MEISettings, history) -> list:
    """The terms a run's ``reg_history`` holds: each regularizer with a positive weight, and the albedo's
    smoothness term when the run learned an albedo (it weighs in the loss too)."""
    terms = [k for k, w in settings.weights.items() if w > 0]
    return terms + (["albedo_roughness"] if history and "albedo_roughness" in history[0] else [])


def optimize_mei(encoder: Encoder, neuron: int, init="sphere", settings: MEISettings | None = None, *,
                 progress: bool = False, callbacks=(), **overrides) -> MEIResult:
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
    callbacks : callable or sequence of callables
        Each called after every step of every seed with the step's history record and its ``seed`` (a dict:
        ``step``, ``time``, ``loss``, ``response``, the regularizers' values, ``step_scale`` with the guard,
        ``seed``), in seed order; their time is not counted in the run's times (:func:`meshmei.optim.minimize`).
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
    settings = MEISettings.with_overrides(settings, overrides)
    neuron = check_neuron(encoder, neuron)
    callbacks = checked_callbacks(callbacks, MEIError)
    settings = settings_for_encoder(settings, encoder)
    V0, F, init_name = initial(init, settings, encoder.device)
    settings = settings.for_start(init_name)
    n_weights = settings.n_vertices if init_name != "custom" else V0.shape[0]  # the count weights scale to
    bar = Progress(settings.steps * len(settings.seeds), f"3D-MEI neuron {neuron}", enabled=progress,
                   postfix=lambda rec: {"act": f"{rec['response']:.4f}"})
    runs = {}
    t0 = time.perf_counter()
    try:
        with frozen_encoder(encoder):
            for seed in settings.seeds:
                guard = StepGuard(V0, F, settings.validity_rules()) if settings.valid_steps else None
                runs[seed] = _run_seed(encoder, neuron, V0, F, settings, seed, bar, guard, n_weights,
                                       uv=sheet_uv(V0) if init_name == "sheet" else None, callbacks=callbacks)
    finally:
        bar.close()
    wall = time.perf_counter() - t0
    return result_from_seeds(runs, V0, F, settings, neuron, encoder, init_name, wall)


def _on_cpu(x):
    """``x`` with every tensor in it (in dicts, lists and tuples too) moved to the CPU."""
    if isinstance(x, torch.Tensor):
        return x.cpu()
    if isinstance(x, dict):
        return {k: _on_cpu(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return type(x)(_on_cpu(v) for v in x)
    return x


def result_from_seeds(runs: dict, V0, F, settings: MEISettings, neuron: int, encoder, init_name: str,
                      wall: float) -> MEIResult:
    """The :class:`MEIResult` of one neuron from its seeds' runs (``seed -> run dict``): the lowest loss wins,
    among the seeds whose loss and response are finite (``MEIError`` if none is). Its tensors are on the CPU,
    whatever device the run used: a result is a record to save, plot and compare (a few hundred vertices and
    one image), not a state to keep on a GPU."""
    finite = [s for s in runs if math.isfinite(runs[s]["loss"]) and math.isfinite(runs[s]["activation"])]
    if not finite:
        ends = {s: (runs[s]["loss"], runs[s]["activation"]) for s in runs}
        raise MEIError(f"no seed of neuron {neuron} ended with a finite loss and response ((loss, response) by "
                       f"seed: {ends})")
    seed = min(finite, key=lambda s: runs[s]["loss"])
    r, V0, F = _on_cpu(runs[seed]), V0.cpu(), F.cpu()
    return MEIResult(
        V=r["V"], F=F, V0=V0, image=r["image"], activation=r["activation"], history=r["history"],
        loss_history=r["loss_history"], reg_history=r["reg_history"], seed=seed, time_history=r["time_history"],
        seed_activations={s: runs[s]["activation"] for s in runs}, settings=settings, neuron=neuron,
        encoder=encoder_spec(encoder), deformer_state=r["deformer_state"], light=r["light"], rotation=r["rotation"],
        translation=r["translation"], init=init_name, wall_time=wall,
        seconds_per_step=wall / (settings.steps * len(runs)), albedo=r.get("albedo"), albedo_uv=r.get("albedo_uv"),
        extra={} if r.get("guard") is None else {"guard": r["guard"]})
