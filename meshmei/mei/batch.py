"""Batched 3D-MEIs: many (neuron, seed) items optimised together, one render and one model call per step.

The items share the start mesh, its faces and the settings. Each has its own RBF offsets and scales (and
light and pose when those are optimised), stacked on a leading batch axis. A step renders the B meshes in
one call, runs the model once on the B images and reads each item's own neuron, evaluates the regularizers
on the batch, and takes one backward of the summed losses: items share no parameter, so each gets the
gradient it would get alone, and Adam, which acts element by element, steps each as if alone
(:func:`meshmei.optim.minimize`, batched objectives). Results equal those of :func:`optimize_mei` run item
by item up to float rounding (tested).
"""

from __future__ import annotations

import time
from typing import Iterator

import torch

from ..deform.rbf import dense_map, dense_negatives
from ..encoders import Encoder, frozen_encoder
from ..errors import MEIError
from ..optim import (Budget, Lookahead, Progress, Schedule, Trace, checked_callbacks, make_optimizer, minimize,
                     tagged_callbacks)
from ..regularizers import regularizer_values
from ..render import axis_angle_to_matrix, render
from ..validity import StepGuard, face_frame
from .optimize import (check_neuron, contact_barriers, guard_report, initial, objective_weights, optimize_mei,
                       reg_terms, result_from_seeds, settings_for_encoder, start_name, valid_start, validity_barriers)
from .scene import SeedScene, albedo_penalty, sheet_uv
from .settings import MEIResult, MEISettings

__all__ = ["BatchScene", "optimize_mei_batch", "mei_batches"]


class BatchScene:
    """The learnable scenes of B items, stacked: offsets ``(B, K, 3)``, log-scales ``(B, K)``, lights and poses.

    Each item keeps its own :class:`~meshmei.deform.RBFDeformer` for its pair list (rebuilt when its own
    scales outgrow it, as alone); when every item's map is dense the B maps run as one batched product.
    Given the faces ``F`` and ``settings.valid_steps``, each item has its own
    :class:`~meshmei.validity.StepGuard` and contact barrier, as alone (:meth:`acceptor`, :meth:`penalties`).
    """

    def __init__(self, V0, settings: MEISettings, seeds, uv=None, F=None, n_weights: int | None = None):
        self.seeds = [SeedScene(V0, settings, s, uv, n_weights) for s in seeds]  # the same initial draws as alone
        self.guards = self.contacts = None
        if settings.valid_steps and F is not None:  # each item's own guard, and the same valid first iterates
            self.guards = [StepGuard(V0, F, settings.validity_rules()) for _ in self.seeds]
            for scene, guard in zip(self.seeds, self.guards):
                valid_start(scene.rbf, guard)
        self.rbfs = [s.rbf for s in self.seeds]
        self.V0 = V0
        self.offsets = torch.nn.Parameter(torch.stack([r.offsets.detach() for r in self.rbfs]))
        log_sigma = torch.stack([r.log_sigma.detach() for r in self.rbfs])
        learn = settings.lr_scales > 0
        self.log_sigma = torch.nn.Parameter(log_sigma) if learn else log_sigma
        self.groups = [{"params": [self.offsets], "lr": self.seeds[0].groups[0]["lr"]}]  # as alone
        if learn:
            self.groups.append({"params": [self.log_sigma], "lr": settings.lr_scales})
        first = self.seeds[0]
        self.light = None
        if first.light is not None:
            self.light = torch.stack([s.light.detach() for s in self.seeds])
            if settings.optimize_light:
                self.light = torch.nn.Parameter(self.light)
                self.groups.append({"params": [self.light], "lr": settings.lr_light})
        self.albedo_logit = None
        if settings.albedo:
            self.albedo_logit = torch.nn.Parameter(torch.stack([s.albedo_logit.detach() for s in self.seeds]))
            self.groups.append({"params": [self.albedo_logit], "lr": settings.lr_albedo})
        B = len(self.seeds)
        self.rotation = V0.new_zeros(B, 3)
        self.translation = V0.new_zeros(B, 3)
        self.pose = settings.optimize_pose
        if self.pose:
            self.rotation, self.translation = torch.nn.Parameter(self.rotation), torch.nn.Parameter(self.translation)
            self.groups.append({"params": [self.rotation, self.translation], "lr": settings.lr_pose})
        self.camera, self.render_settings = first.camera, first.render_settings
        self._dense_key, self._dense = None, None
        # every item's deformed vertices, (B, n, 3): the guards' check of a candidate and the next objective
        # share one map (meshmei.optim.Lookahead)
        self.vertices = Lookahead(self._deformed, (self.offsets, self.log_sigma))
        if self.guards is not None:
            self.contacts = contact_barriers(V0, F, settings, len(self.seeds))

    def _deformed(self) -> torch.Tensor:
        """Deformed vertices of every item, ``(B, n, 3)``."""
        for r, ls in zip(self.rbfs, self.log_sigma):
            r.cover(ls)
        pairs = [r.dense_pairs() for r in self.rbfs]
        if any(p is None for p in pairs):  # a sparse map somewhere: item by item
            disp = torch.stack([r.displacement_with(o, ls) for r, o, ls in zip(self.rbfs, self.offsets, self.log_sigma)])
            return self.V0 + disp
        key = tuple(r.n_rebuilds for r in self.rbfs)
        if key != self._dense_key:
            D2, mask = torch.stack([p[0] for p in pairs]), torch.stack([p[1] for p in pairs])
            self._dense = (D2, mask, dense_negatives(D2, mask))
            self._dense_key = key
        inv = 0.5 * torch.exp(-2.0 * self.log_sigma)  # (B, K)
        return self.V0 + dense_map(inv, self.offsets, *self._dense).to(self.V0.dtype)  # (B, n, K) weights

    def image(self, V, F, *, pose: bool | None = None) -> torch.Tensor:
        kw = {}
        if self.pose if pose is None else pose:
            kw = dict(rotation=axis_angle_to_matrix(self.rotation), translation=self.translation)
        return render(V, F, camera=self.camera, light=self.light, settings=self.render_settings,
                      albedo=self.albedo(), uv=self.seeds[0].uv, **kw)

    def albedo(self) -> torch.Tensor | None:
        """Every item's per-vertex albedo ``(B, n)`` in [0, 1], or None (shape only)."""
        return None if self.albedo_logit is None else torch.sigmoid(self.albedo_logit)

    def penalties(self, V, F, active: dict, settings: MEISettings, record: dict) -> torch.Tensor:
        """The items' regularizer terms ``(B,)``, weighted, with the albedo's smoothness; each term's values
        go into ``record`` as lists."""
        total = torch.zeros(V.shape[0], dtype=V.dtype, device=V.device)
        for k, r in regularizer_values(V, self.V0, F, active).items():  # each (B,)
            record[k] = r.detach().tolist()
            total = total + active[k] * r
        if settings.albedo:
            r = albedo_penalty(self.albedo(), self.seeds[0].uv, F)
            record["albedo_roughness"] = r.detach().tolist()
            total = total + settings.albedo_smoothness * r
        if self.guards is not None:  # the items share the start: one guard's barrier serves all
            total = total + validity_barriers(self.guards[0], self.contacts, V, settings, record)
        return total

    def acceptor(self):
        """``accept(pending)`` for :func:`meshmei.optim.minimize`: each pending item's mesh checked by its own
        guard, a ``(B,)`` bool verdict; None without guards."""
        if self.guards is None:
            return None

        def accept(pending: torch.Tensor) -> torch.Tensor:
            with torch.no_grad():
                V = self.vertices.candidate().to("cpu", torch.float64)  # the guards check on the CPU
                n, q = face_frame(V, self.guards[0].F)  # every item's frame in one pass
            return torch.tensor([not p or g.accept(V[b], (n[b], q[b]))
                                 for b, (g, p) in enumerate(zip(self.guards, pending.tolist()))], device="cpu")

        return accept

    @property
    def max_halvings(self) -> int:
        return 0 if self.guards is None else self.guards[0].rules.max_halvings

    def item_runs(self, V, images, acts, history: list, losses, steps, settings: MEISettings) -> list[dict]:
        """One run dict per item, as ``optimize_mei`` makes per seed, from the batch's final state and its
        history (records holding one list entry per item)."""
        h = history
        return [dict(
            V=V[b], image=images[b:b + 1], activation=acts[b], loss=losses[b], best_step=steps[b],
            history=[r["response"][b] for r in h], loss_history=[r["loss"][b] for r in h],
            reg_history={k: [r[k][b] for r in h] for k in reg_terms(settings, h)},
            time_history=[r["time"] for r in h], deformer_state=self.item_state(b),
            light=None if self.light is None else self.light[b].detach().clone(),
            albedo=None if self.albedo_logit is None else self.albedo()[b].detach().clone(),
            albedo_uv=self.seeds[0].uv,
            guard=None if self.guards is None else guard_report(self.guards[b], [r["step_scale"][b] for r in h]),
            rotation=self.rotation[b].detach().clone(), translation=self.translation[b].detach().clone())
            for b in range(V.shape[0])]

    def item_state(self, b: int) -> dict:
        """Item ``b``'s deformer ``state_dict``, as :func:`optimize_mei` stores it."""
        rbf = self.rbfs[b]
        with torch.no_grad():
            rbf.offsets.copy_(self.offsets[b])
            rbf.log_sigma.copy_(self.log_sigma[b])
        return {k: v.detach().clone() for k, v in rbf.state_dict().items()}


def _responses(encoder, images, neurons) -> torch.Tensor:
    """Each item's own neuron's response, ``(B,)``, from one model call over the distinct neurons."""
    unique, cols = torch.unique(torch.as_tensor(neurons, device="cpu"), return_inverse=True)
    return encoder(images, unique.tolist()).gather(1, cols.view(-1, 1).to(images.device)).squeeze(1)


def _objective(encoder, neurons, F, scene: BatchScene, active: dict, settings: MEISettings):
    def objective(point):
        V = scene.vertices()
        f = _responses(encoder, scene.image(V, F), neurons)
        record = {"response": f.detach().tolist()}
        return -f + scene.penalties(V, F, active, settings, record), record

    return objective


def check_batch_size(batch_size) -> None:
    if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
        raise MEIError(f"batch_size must be a positive integer, got {batch_size!r}")


def _run_batch(encoder, items, V0, F, settings: MEISettings, n_weights: int, bar: Progress, uv,
               callbacks=()) -> list[dict]:
    """Optimise the ``(neuron, seed)`` items together; one run dict per item, as ``optimize_mei`` makes per seed.
    ``callbacks`` get each step's record with ``items``."""
    neurons = [n for n, _ in items]
    scene = BatchScene(V0, settings, [s for _, s in items], uv, F, n_weights)
    trace = Trace()
    out = minimize(_objective(encoder, neurons, F, scene, objective_weights(settings, n_weights), settings),
                   make_optimizer("adam", scene.groups), Budget(steps=settings.steps),
                   schedule=Schedule("cosine", settings.lr_decay, endpoint=True), keep=settings.keep,
                   evaluate_last=True, trace=trace, progress=bar, accept=scene.acceptor(),
                   callbacks=tagged_callbacks(callbacks, items=[tuple(item) for item in items]),
                   max_halvings=scene.max_halvings, states=scene.rbfs, error=MEIError, where=f" (items {items})")
    with torch.no_grad():
        V = scene.vertices().detach()
        images = scene.image(V, F, pose=True).detach()
        acts = _responses(encoder, images, neurons).tolist()
    return scene.item_runs(V, images, acts, trace.history, out.loss, out.step, settings)


def mei_batches(encoder: Encoder, neurons, init="sheet", settings: MEISettings | None = None, *,
                batch_size: int = 8, progress: Progress | None = None, callbacks=(),
                **overrides) -> Iterator[tuple[int, MEIResult]]:
    """3D-MEIs of several neurons, their (neuron, seed) items run ``batch_size`` at a time; yields
    ``(neuron, MEIResult)`` as soon as all of a neuron's seeds are done, in the order of ``neurons``.

    Each result is the one :func:`optimize_mei` gives for that neuron (the lowest-loss seed), up to float
    rounding; its ``wall_time`` is the neuron's share of its batches' time. With ``valid_steps`` each item
    has its own guard and contact barrier; a refused item's step is halved on its own. With a robust
    objective (K views per item) every neuron runs alone through :func:`optimize_mei`.
    ``progress`` (a :class:`~meshmei.optim.Progress` over steps of batches) is updated, not closed.

    ``callbacks`` (one callable or several) are called after every step of every batch with the step's
    history record and ``items``, the batch's ``(neuron, seed)`` pairs: each item's values (``response``,
    ``loss``, the regularizers', ``step_scale``) are lists in that order. With a robust objective a neuron's
    records are :func:`optimize_mei`'s (one value each, its ``seed``), with ``items`` ``[(neuron, seed)]``.
    Their time is not counted in the run's times.
    """
    settings = settings_for_encoder(MEISettings.with_overrides(settings, overrides), encoder)
    callbacks = checked_callbacks(callbacks, MEIError)
    neurons = [check_neuron(encoder, n) for n in neurons]
    if len(set(neurons)) != len(neurons):
        twice = sorted({n for n in neurons if neurons.count(n) > 1})
        raise MEIError(f"neurons {twice} are listed twice; each neuron's seeds are its items")
    check_batch_size(batch_size)
    if settings.robust_pose > 0 or settings.robust_light > 0:
        for n in neurons:  # K views per item: each neuron alone
            alone = [(lambda rec, n=n, cb=cb: cb({**rec, "items": [(n, rec["seed"])]})) for cb in callbacks]
            yield n, optimize_mei(encoder, n, init, settings, callbacks=alone)
        return
    V0, F, init_name = initial(init, settings, encoder.device)
    settings = settings.for_start(init_name)
    n_weights = settings.n_vertices if init_name != "custom" else V0.shape[0]
    items = [(n, s) for n in neurons for s in settings.seeds]
    done: dict[int, dict] = {}
    seconds: dict[int, float] = {}
    bar = progress if progress is not None else Progress(1, "", enabled=False)
    with frozen_encoder(encoder):
        for start in range(0, len(items), batch_size):
            chunk = items[start:start + batch_size]
            t0 = time.perf_counter()
            runs = _run_batch(encoder, chunk, V0, F, settings, n_weights, bar,
                              sheet_uv(V0) if init_name == "sheet" else None, callbacks)
            share = (time.perf_counter() - t0) / len(chunk)
            for (n, s), run in zip(chunk, runs):
                done.setdefault(n, {})[s] = run
                seconds[n] = seconds.get(n, 0.0) + share
            finished = [n for n in dict.fromkeys(n for n, _ in chunk) if len(done[n]) == len(settings.seeds)]
            for n in finished:
                yield n, result_from_seeds(done.pop(n), V0, F, settings, n, encoder, init_name, seconds.pop(n))


def optimize_mei_batch(encoder: Encoder, neurons, init="sheet", settings: MEISettings | None = None, *,
                       batch_size: int = 8, progress: bool = False, callbacks=(), **overrides) -> dict[int, MEIResult]:
    """3D-MEIs of several neurons, batched (see :func:`mei_batches`, also for ``callbacks``): ``{neuron: MEIResult}``.

    Examples
    --------
    >>> from meshmei.encoders import GaborSimpleCell
    >>> res = optimize_mei_batch(GaborSimpleCell(), [0], "sheet", steps=3, seeds=(0, 1), image_size=16, n_vertices=64)
    >>> sorted(res[0].seed_activations)
    [0, 1]
    """
    s = MEISettings.with_overrides(settings, overrides).for_start(start_name(init))
    check_batch_size(batch_size)
    try:
        neurons = list(neurons)
    except TypeError:  # a single index: list(1) raised a bare TypeError
        raise MEIError(f"neurons must be a sequence of neuron indices (e.g. [{neurons!r}]), got {neurons!r}") from None
    bar = Progress(s.steps * -(-len(neurons) * len(s.seeds) // batch_size), "3D-MEI batches", enabled=progress)
    try:
        return dict(mei_batches(encoder, neurons, init, s, batch_size=batch_size, progress=bar, callbacks=callbacks))
    finally:
        bar.close()
