"""The one optimisation loop: 3D-MEIs, pixel MEIs and reconstructions are its clients.

A client supplies an objective (a closure computing the loss of the current parameters) and a torch
optimizer over its parameters; :func:`minimize` runs the steps with one learning-rate schedule, one
NaN/Inf guard, keep-best, one progress bar, a timed history and callbacks. A run may be cut into pieces
(the coarse-to-fine stages of a reconstruction, the seeds of an MEI) that share one :class:`Trace` and one
:class:`Progress`.
"""

from __future__ import annotations

import math
import numbers
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch

from ._checks import all_finite, is_integral
from .deform.largesteps import AdamUniform

MAX_STEPS = 10**12  # a budget's most steps: 30 years at a millisecond a step (more made tqdm's total overflow)

__all__ = ["Schedule", "Budget", "StepPoint", "Trace", "Progress", "Outcome", "Lookahead", "make_optimizer",
           "minimize", "checked_callbacks", "tagged_callbacks"]

SCHEDULE_SHAPES = ("cosine", "geometric", "constant")
OPTIMIZERS = ("adam", "uniform")


@dataclass(frozen=True)
class Schedule:
    """The learning-rate factor over a run: 1 at the start, ``floor`` at the end.

    Attributes
    ----------
    shape : {"cosine", "geometric", "constant"}
        ``floor + (1 - floor) (1 + cos(pi f)) / 2``, ``floor ** f``, or 1, at progress fraction ``f``.
    floor : float
        The factor at ``f = 1`` (in ``(0, 1]`` for ``"geometric"``; ``[0, 1]`` for ``"cosine"``).
    endpoint : bool
        With a budget in steps, reach ``f = 1`` at the last step (``f = t / (steps - 1)``) instead of one
        step after it (``f = t / steps``).
    """

    shape: str = "cosine"
    floor: float = 1.0
    endpoint: bool = False

    def __post_init__(self):
        if self.shape not in SCHEDULE_SHAPES:
            raise ValueError(f"schedule shape must be one of {SCHEDULE_SHAPES}, got {self.shape!r}")
        lo = 0.0 if self.shape == "cosine" else math.ulp(0.0)
        if isinstance(self.floor, bool) or not isinstance(self.floor, numbers.Real) or not lo <= self.floor <= 1.0:
            raise ValueError(f"a {self.shape} schedule's floor must lie in [{lo:g}, 1], got {self.floor!r}")

    def factor(self, f: float) -> float:
        """The learning-rate factor at progress fraction ``f`` in ``[0, 1]``."""
        if self.shape == "cosine":
            return self.floor + (1 - self.floor) * 0.5 * (1 + math.cos(math.pi * f))
        if self.shape == "geometric":
            return self.floor**f
        return 1.0


@dataclass(frozen=True)
class Budget:
    """When a run ends: after ``steps`` steps, after ``seconds`` of optimisation time, whichever comes first."""

    steps: int | None = None
    seconds: float | None = None

    def __post_init__(self):
        if self.steps is None and self.seconds is None:
            raise ValueError("a budget needs steps, seconds or both")
        if self.steps is not None and (not is_integral(self.steps) or self.steps < 1):
            raise ValueError(f"steps must be a positive integer, got {self.steps!r}")
        if self.steps is not None and self.steps > MAX_STEPS:
            raise ValueError(f"steps must be at most {MAX_STEPS:.0e}, got {self.steps!r}")
        if self.seconds is not None and (isinstance(self.seconds, bool) or not isinstance(self.seconds, numbers.Real)
                                         or not (self.seconds > 0 and math.isfinite(self.seconds))):
            raise ValueError(f"seconds must be positive and finite, got {self.seconds!r}")  # "5" failed in '>'

    def fraction(self, step: int, seconds: float) -> float:
        """The share of the budget used after ``step`` steps and ``seconds`` of optimisation."""
        f = 0.0
        if self.steps is not None:
            f = max(f, step / self.steps)
        if self.seconds is not None:
            f = max(f, seconds / self.seconds)
        return f

    def schedule_fraction(self, step: int, seconds: float, endpoint: bool) -> float:
        """The fraction a schedule reads: as :meth:`fraction`, or ``step / (steps - 1)`` with ``endpoint``."""
        if endpoint and self.steps is not None:  # with a time limit too: whichever is further along
            f = step / max(self.steps - 1, 1)
            return f if self.seconds is None else max(f, seconds / self.seconds)
        return self.fraction(step, seconds)


@dataclass(frozen=True)
class StepPoint:
    """Where a step stands, as the objective sees it: steps done before it, budget fraction, lr factor."""

    step: int
    fraction: float
    factor: float


@dataclass
class Trace:
    """What a run has done so far, shared by its pieces (stages, seeds).

    Attributes
    ----------
    step : int
        Steps taken.
    seconds : float
        Optimisation seconds (set-up a client adds, the steps; callbacks and evaluation excluded).
    history : list of dict
        One record per step: ``step`` (steps done after it), ``time`` (``seconds`` after it), ``loss``,
        ``lr`` (of the first parameter group) and the objective's own record.
    """

    step: int = 0
    seconds: float = 0.0
    history: list = field(default_factory=list)


class Progress:
    """One tqdm bar over a whole run (all seeds, all stages), in steps or in seconds of a time budget.

    Parameters
    ----------
    total : float
        Steps, or seconds with ``unit="s"``.
    desc : str
    unit : {"step", "s"}
    postfix : callable, optional
        ``postfix(record) -> dict`` of values to show, from a step's history record.
    every : int
        Refresh the postfix every this many steps.
    enabled : bool
        False: do nothing (callers need not branch).
    """

    def __init__(self, total: float, desc: str, *, unit: str = "step", postfix: Callable | None = None,
                 every: int = 1, enabled: bool = True):
        self.unit, self.postfix, self.every, self.bar = unit, postfix, max(1, int(every)), None
        if enabled:
            from tqdm.auto import tqdm  # deferred: only runs that show a bar pay for the import

            fmt = None if unit != "s" else "{l_bar}{bar}| {n:.1f}/{total:.0f} s {postfix}"
            self.bar = tqdm(total=total, unit=unit, desc=desc, bar_format=fmt)

    def update(self, seconds: float, record: dict) -> None:
        if self.bar is None:
            return
        self.bar.update(seconds if self.unit == "s" else 1)
        if self.postfix is not None and record["step"] % self.every == 0:
            self.bar.set_postfix(**self.postfix(record))

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


@dataclass(frozen=True)
class Outcome:
    """How one call of :func:`minimize` ended.

    Attributes
    ----------
    loss : float, or list of floats for a batched objective
        The kept iterate's loss (the lowest seen with ``keep="best"``; the last step's otherwise).
    step : int, or list of ints for a batched objective
        Steps done before the kept iterate (``trace.step`` when it is the final one).
    budget_spent : bool
        The whole budget is used (False when the call stopped at ``stop_at < 1`` or at ``stop_step``).
    """

    loss: float | list
    step: int | list
    budget_spent: bool


class Lookahead:
    """``fn()`` (the vertices a parameterisation gives) evaluated once per step where a step guard checks it.

    A guarded step evaluates the parameters' vertices twice at the same point: the guard checks the candidate
    after ``optimizer.step()``, and the next objective maps the same parameters again, with a graph.
    :meth:`candidate` (the guard's call) evaluates ``fn`` with a graph, keeps it and hands out a detached
    copy; the next call of the lookahead itself (the objective's) takes the kept result, once, if none of
    ``tensors`` changed in between (their version counters, which every in-place update moves: the
    optimiser's step, a halving, an undone step, a restored best iterate), and evaluates ``fn`` otherwise.
    The values and the gradients are those of evaluating ``fn`` at the call: the same operations on the
    same inputs (under ``torch.no_grad`` the kept result comes back detached, as ``fn`` would give it there).
    ``fn`` must depend on nothing that changes without one of ``tensors`` changing (an RBF deformer's pair
    list is rebuilt inside its own call and restored only with the parameters).
    """

    def __init__(self, fn: Callable[[], torch.Tensor], tensors):
        self.fn, self.tensors = fn, tuple(tensors)
        self._kept = None

    def _key(self) -> tuple:
        return tuple((t._version, t.data_ptr()) for t in self.tensors)

    def __call__(self) -> torch.Tensor:
        kept, self._kept = self._kept, None  # handed out once: a second backward through it would fail
        if kept is not None and kept[0] == self._key():  # detached where no graph is wanted: a result made
            return kept[1] if torch.is_grad_enabled() else kept[1].detach()  # under no_grad carried one
        return self.fn()

    def candidate(self) -> torch.Tensor:
        """``fn()`` now, detached; its graph is kept for the next call."""
        with torch.enable_grad():
            out = self.fn()
        self._kept = (self._key(), out)
        return out.detach()


def make_optimizer(name: str, groups: list) -> torch.optim.Optimizer:
    """``"adam"``: :class:`torch.optim.Adam`; ``"uniform"``: :class:`~meshmei.deform.largesteps.AdamUniform`
    (one step normalisation per tensor, which keeps the smoothness of a preconditioned gradient).

    Adam runs its per-tensor loop (``foreach=False``): the same arithmetic, bit for bit, as the default
    multi-tensor path, and 0.1-0.2 ms a step cheaper with the one to four tensors of these problems.
    """
    if name == "adam":  # torch checks its default lr only: a group's negative lr climbed the loss without a word
        for k, group in enumerate(groups):
            lr = group.get("lr", 1e-3) if isinstance(group, dict) else 1e-3
            if isinstance(lr, bool) or not isinstance(lr, (int, float)) or not 0 <= lr < math.inf:
                raise ValueError(f"parameter group {k}: lr must be a finite non-negative number, got {lr!r}")
        return torch.optim.Adam(groups, foreach=False)
    if name == "uniform":
        return AdamUniform(groups)
    raise ValueError(f"optimizer must be one of {OPTIMIZERS}, got {name!r}")


def _parameters(optimizer):
    return [p for g in optimizer.param_groups for p in g["params"]]


def _returned(out) -> tuple:
    """An objective's ``(loss, record)``, or a TypeError saying what it returned instead."""
    if not (isinstance(out, tuple) and len(out) == 2 and isinstance(out[0], torch.Tensor)
            and isinstance(out[1], dict)):
        got = type(out).__name__ + (f" of {len(out)}" if isinstance(out, tuple) else "")
        raise TypeError(f"the objective must return (loss tensor, record dict), got a {got}")
    return out


def _guard(values: torch.Tensor, step: int, optimizer, error: type[Exception], where: str) -> None:
    """Raise ``error`` where the loss ``values`` (a scalar or ``(B,)``) is NaN or Inf. Before any step
    (``step`` 0) the learning rate cannot be the cause: the message points at the objective's inputs."""
    if all_finite(values):
        return
    lr = optimizer.param_groups[0]["lr0"]
    bad = [] if values.ndim == 0 else (~torch.isfinite(values)).nonzero().squeeze(1).tolist()
    value = float(values) if values.ndim == 0 else float(values[bad[0]])
    items = "" if values.ndim == 0 else f" for item(s) {bad} of the batch"
    if step == 0:
        raise error(f"the starting loss is {value}{items} (before any step{where}): check the objective's weights "
                    f"and inputs (the start, the model, the scene); the learning rate is not the cause")
    if values.ndim == 0:
        raise error(f"the loss became {value} at step {step}{where}; lower the learning rate (lr={lr:g})")
    raise error(f"the loss became {value} at step {step}{items}{where}; "
                f"lower the learning rate (lr={lr:g}) or run those items alone")


def _guard_gradients(params, step: int, error: type[Exception], where: str) -> None:
    """Raise ``error`` where a gradient is NaN or Inf although the loss was finite: the step would carry
    it into the parameters, and a step guard would then refuse every later step, a run that stalls
    without a word."""
    for p in params:
        if p.grad is not None and not all_finite(p.grad):
            raise error(f"the gradient became non-finite at step {step}{where} although the loss was finite: "
                        f"a term of the objective has no finite slope there (a parameter of shape "
                        f"{tuple(p.shape)})")


class _Best:
    """Keep-best: the lowest loss seen and a copy of the parameters then. For a batched objective (a loss
    vector), per item: every parameter's leading axis indexes the items."""

    def __init__(self, params, step: int, states=()):
        self.params, self.value, self.step, self.saved = params, math.inf, step, None
        self.states, self.saved_states = list(states), None

    @torch.no_grad()
    def offer(self, values: torch.Tensor, step: int) -> None:
        if values.ndim == 0:
            if float(values) < self.value:
                self.value, self.step, self.saved = float(values), step, [p.detach().clone() for p in self.params]
                self.saved_states = [s.snapshot() for s in self.states]
            return
        if self.saved is None:
            self.value = torch.full_like(values, math.inf)
            self.step = torch.full(values.shape, step, dtype=torch.int64, device="cpu")
            self.saved = [p.detach().clone() for p in self.params]
            self.saved_states = [s.snapshot() for s in self.states]
        better = values < self.value
        if bool(better.any()):
            self.value = torch.where(better, values, self.value)
            self.step = torch.where(better.cpu(), step, self.step)
            for kept, p in zip(self.saved, self.params):
                kept.copy_(torch.where(better.view(-1, *[1] * (p.ndim - 1)), p.detach(), kept))
            for i in better.nonzero().flatten().tolist() if self.states else ():  # one state per item
                self.saved_states[i] = self.states[i].snapshot()

    @torch.no_grad()
    def finish(self, last: torch.Tensor, step: int) -> tuple:
        """Keep the final iterate where it is no worse than the best seen, else restore the best."""
        if last.ndim == 0:
            if self.saved is None or float(last) <= self.value:
                return float(last), step
            for p, kept in zip(self.params, self.saved):
                p.copy_(kept)
            for s, kept in zip(self.states, self.saved_states):
                s.restore(kept)
            return self.value, self.step
        if self.saved is None:
            return last.tolist(), [step] * last.shape[0]
        take = last <= self.value
        for p, kept in zip(self.params, self.saved):
            p.copy_(torch.where(take.view(-1, *[1] * (p.ndim - 1)), p, kept))
        for i in (~take).nonzero().flatten().tolist() if self.states else ():
            self.states[i].restore(self.saved_states[i])
        return torch.where(take, last, self.value).tolist(), torch.where(take.cpu(), step, self.step).tolist()


def _as_record(values: torch.Tensor):
    return float(values) if values.ndim == 0 else values.tolist()


def _verdict(value) -> bool:
    """``accept()``'s answer as a bool; anything else (None from a check that forgot to return) is refused,
    since it would read as a refusal and undo every step without a word."""
    if isinstance(value, torch.Tensor) and value.numel() == 1 and value.dtype == torch.bool:
        return bool(value)
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    raise TypeError(f"accept() must return a bool, got {type(value).__name__}")


def _verdicts(value, items: int) -> torch.Tensor:
    """A batched ``accept(pending)``'s answer as a ``(items,)`` bool tensor on the CPU."""
    if isinstance(value, (list, tuple, np.ndarray, torch.Tensor)):
        verdicts = torch.as_tensor(value, device="cpu") if not isinstance(value, torch.Tensor) else value.cpu()
        if verdicts.dtype == torch.bool and verdicts.shape == (items,):
            return verdicts
        raise TypeError(f"accept(pending) must return {items} bools, got {tuple(verdicts.shape)} of "
                        f"{verdicts.dtype}")
    raise TypeError(f"accept(pending) must return {items} bools, got {type(value).__name__}")


@torch.no_grad()
def _backtrack(params, before, accept, max_halvings: int, items: int | None = None, states=(), before_states=()):
    """Shrink the step just taken until ``accept()`` holds; the scale kept (0: the step is undone, and
    ``states`` are put back to ``before_states`` with the parameters).

    With ``items`` (a batched objective), ``accept(pending)`` gets a ``(B,)`` bool mask of the items still
    to check and returns a ``(B,)`` bool verdict; each item's slice (leading axis) is halved on its own,
    and the scales come back as a list; ``states`` then hold one object per item.
    """
    after = [p.detach().clone() for p in params]
    if items is None:
        scale = 1.0
        for _ in range(max_halvings + 1):
            if _verdict(accept()):
                return scale
            scale *= 0.5
            for p, b, a in zip(params, before, after):
                p.copy_(b + scale * (a - b))
        for p, b in zip(params, before):
            p.copy_(b)
        for s, b in zip(states, before_states):
            s.restore(b)
        return 0.0
    scale = torch.ones(items, dtype=torch.float64, device="cpu")  # the bookkeeping stays on the CPU
    done = torch.zeros(items, dtype=torch.bool, device="cpu")
    for _ in range(max_halvings + 1):
        done |= _verdicts(accept(~done), items)
        if bool(done.all()):
            return scale.tolist()
        scale = torch.where(done, scale, 0.5 * scale)
        for p, b, a in zip(params, before, after):
            s = scale.to(device=p.device, dtype=p.dtype).view(-1, *[1] * (p.ndim - 1))
            p.copy_(torch.where(done.to(p.device).view_as(s), p, b + s * (a - b)))
    for p, b in zip(params, before):
        p.copy_(torch.where(done.to(p.device).view(-1, *[1] * (p.ndim - 1)), p, b))
    for i in (~done).nonzero().flatten().tolist() if states else ():
        states[i].restore(before_states[i])
    return torch.where(done, scale, torch.zeros_like(scale)).tolist()


def checked_callbacks(callbacks, error: type[Exception] = ValueError) -> tuple:
    """``callbacks`` (one callable, or a sequence of them, each called with every step's record) as a tuple, or
    ``error`` where one is not callable, raised by the entry point (``optimize_mei``, ``reconstruct``) before
    anything is built: a step's record handed to it failed deep inside the run."""
    callbacks = (callbacks,) if callable(callbacks) else callbacks
    try:
        callbacks = tuple(callbacks)
    except TypeError:
        raise error(f"callbacks must be a callable or a sequence of callables, got {callbacks!r}") from None
    for k, cb in enumerate(callbacks):
        if not callable(cb):
            raise error(f"callbacks[{k}] is not callable: {cb!r}")
    return callbacks


def tagged_callbacks(callbacks, **tags) -> tuple:
    """``callbacks`` each of which gets every record with ``tags`` added (a copy: the history keeps its own):
    which seed, or which items of a batch, a step belongs to."""
    return tuple((lambda rec, cb=cb: cb({**rec, **tags})) for cb in callbacks)


def minimize(objective: Callable, optimizer: torch.optim.Optimizer, budget: Budget, *,
             schedule: Schedule = Schedule(), keep: str = "last", keep_from: float = 0.0,
             trace: Trace | None = None, stop_at: float = 1.0, stop_step: int | None = None,
             progress: Progress | None = None, callbacks=(),
             evaluate_last: bool = False, accept: Callable[[], bool] | None = None, max_halvings: int = 6,
             states=(), error: type[Exception] = FloatingPointError, where: str = "") -> Outcome:
    """Minimise ``objective`` with ``optimizer`` until ``budget`` (or ``stop_at`` of it) is used.

    Each step: set every group's ``lr`` to its ``lr0`` (its ``lr`` at the first call) times the schedule's
    factor (also stored as the group's ``factor``, for step rules that scale more than the step, as the
    pixel MEI's blur); ``loss, record = objective(point)``; check the loss is finite; keep a copy of the
    parameters if it is the lowest loss so far (``keep="best"``); backward; ``optimizer.step()``; with
    ``accept``, halve the step until ``accept()`` holds, or undo it; append a history record; update
    ``progress``; call each ``callback(record)`` (their time is not counted).

    **Batched objectives.** The loss may be a ``(B,)`` vector of B independent items (a batch of 3D-MEIs):
    every parameter then has the items on its leading axis and no parameter is shared between items. One
    backward of the sum gives each item its own gradient; element-wise optimisers (Adam) then step each
    item as if alone. Keep-best, the final comparison and the outcome are per item; the history records
    the loss as a list. A non-finite loss of any item raises ``error`` naming the items. With a batched
    objective ``accept(pending)`` takes a ``(B,)`` bool mask of the items to check and returns a ``(B,)``
    bool verdict (True for the items not checked); each refused item's step is halved on its own.

    Parameters
    ----------
    objective : callable
        ``objective(point: StepPoint) -> (loss, record)``: a scalar tensor with a graph to the optimizer's
        parameters, and a dict of floats to keep in the history.
    optimizer : torch.optim.Optimizer
    budget : Budget
    schedule : Schedule
    keep : {"last", "best"}
        ``"best"``: end on the lowest-loss iterate seen, the final one included (evaluated once more
        after the last step, without a gradient).
    keep_from : float
        With ``keep="best"``, offer only the iterates from this budget fraction on (and the final one): an
        objective that changes during the run (a continuation, as the widening robust ranges of a 3D-MEI)
        has comparable losses only from there.
    evaluate_last : bool
        With ``keep="last"``, also evaluate the final iterate's loss (the outcome's ``loss``); without it
        the outcome reports the loss before the last step, and the objective is not called again (a
        sampled objective would draw from its generator), unless the run holds no step to report.
    trace : Trace, optional
        Continue a run (steps, time and history go on from it).
    stop_at : float
        Stop when this share of the budget is used (a stage of a longer run).
    stop_step : int, optional
        Also stop once ``trace.step`` reaches this many steps (a stage's own limit), whichever comes first.
    progress : Progress, optional
    callbacks : sequence of callables
    accept : callable, optional
        ``accept() -> bool`` on the parameters after a step (e.g. :meth:`meshmei.validity.StepGuard.accept`
        on the vertices they give). A refused step is halved, ``p = p_before + s (p_after - p_before)`` with
        ``s = 1/2, 1/4, ...``, up to ``max_halvings`` times, and undone (``s = 0``) if none is accepted; the
        record's ``step_scale`` says which ``s`` was taken. The optimiser's own state (Adam's moments) keeps
        the full step's update. An answer that is not a bool (a Python, NumPy or one-element torch bool; a
        batched objective's ``(B,)`` bool tensor, array or list) is a TypeError.
    max_halvings : int
    states : sequence
        What the objective depends on besides the parameters, as objects with ``snapshot()`` and
        ``restore(saved)`` (an RBF deformer's pair list, :meth:`meshmei.deform.RBFDeformer.snapshot`): an
        undone step and a restored best iterate put them back with the parameters, so that the iterate the
        run goes on from (or returns) is the one it evaluated and ``accept`` checked. With a batched
        objective, one object per item, in item order.
    error : exception class
        Raised when the loss is NaN or Inf: at any step, and at the final evaluation when the final iterate
        is what is kept (``keep="last"``, or ``"best"`` with nothing offered before; a non-finite final
        iterate under keep-best yields to the best one seen).
    where : str
        Said after the step in that error (e.g. ``" of seed 2"``).

    Returns
    -------
    Outcome
    """
    if keep not in ("last", "best"):
        raise ValueError(f"keep must be 'last' or 'best', got {keep!r}")
    for name, value, lo_open in (("stop_at", stop_at, True), ("keep_from", keep_from, False)):
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not (
                (0 < value <= 1) if lo_open else (0 <= value <= 1)):
            raise ValueError(f"{name} must lie in {'(0, 1]' if lo_open else '[0, 1]'} (a share of the budget), "
                             f"got {value!r}")
    if isinstance(max_halvings, bool) or not isinstance(max_halvings, numbers.Integral) or max_halvings < 0:
        raise ValueError(f"max_halvings must be a non-negative integer, got {max_halvings!r}")
    if stop_step is not None and (isinstance(stop_step, bool) or not isinstance(stop_step, numbers.Integral)):
        raise ValueError(f"stop_step must be an integer or None, got {stop_step!r}")
    trace = trace if trace is not None else Trace()
    params = _parameters(optimizer)
    for g in optimizer.param_groups:
        g.setdefault("lr0", g["lr"])
    states = list(states)
    best = _Best(params, trace.step, states)
    while ((f := budget.fraction(trace.step, trace.seconds)) < stop_at
           and (stop_step is None or trace.step < stop_step)):
        t0 = time.perf_counter()
        c = schedule.factor(budget.schedule_fraction(trace.step, trace.seconds, schedule.endpoint))
        for g in optimizer.param_groups:
            g["lr"], g["factor"] = g["lr0"] * c, c
        optimizer.zero_grad(set_to_none=True)
        loss, record = _returned(objective(StepPoint(trace.step, f, c)))
        values = loss.detach()
        if values.ndim == 1 and not getattr(optimizer, "elementwise", True):
            raise ValueError(f"{type(optimizer).__name__} couples every entry of a parameter (one step size "
                             "for all), so the items of a batched (B,) loss would not step as if alone; use "
                             "an element-wise optimiser (adam) for batches")
        if values.ndim > 1:
            raise ValueError(f"the objective must return a scalar or a (B,) loss; got shape {tuple(values.shape)}")
        if values.ndim == 1 and states and len(states) != values.shape[0]:
            raise ValueError(f"a batched objective takes one state per item: {len(states)} states for "
                             f"{values.shape[0]} items")
        _guard(values, trace.step, optimizer, error, where)
        if keep == "best" and f >= keep_from:
            best.offer(values, trace.step)
        if not loss.requires_grad:  # torch's "element 0 of tensors does not require grad" said neither which nor why
            raise ValueError("the objective's loss carries no gradient: the optimiser's parameters must require "
                             "grad and the loss must be computed from them (not detached, not under no_grad)")
        (loss if loss.ndim == 0 else loss.sum()).backward()  # items share no parameter: one backward for all
        _guard_gradients(params, trace.step, error, where)
        before = None if accept is None else [p.detach().clone() for p in params]
        before_states = [] if accept is None else [st.snapshot() for st in states]
        try:
            optimizer.step()
        except RuntimeError as err:  # a learning rate beyond the parameters' dtype (lr=1e39 in float32)
            if "overflow" not in str(err):
                raise
            raise error(f"the optimiser's step {trace.step}{where} overflowed the parameters' dtype "
                        f"(lr={optimizer.param_groups[0]['lr']:g}); lower the learning rate") from None
        if accept is not None:
            items = None if values.ndim == 0 else values.shape[0]
            record = dict(record, step_scale=_backtrack(params, before, accept, max_halvings, items, states,
                                                        before_states))
        trace.step += 1
        trace.seconds += time.perf_counter() - t0
        rec = {"step": trace.step, "time": trace.seconds, "loss": _as_record(values),
               "lr": optimizer.param_groups[0]["lr"], **record}
        trace.history.append(rec)
        if progress is not None:
            progress.update(time.perf_counter() - t0, rec)
        for cb in callbacks:
            cb(rec)
    spent = budget.fraction(trace.step, trace.seconds) >= 1.0
    if keep == "last" and not evaluate_last and trace.history:  # without a step there is no loss but the final
        loss = trace.history[-1]["loss"]  # iterate's (it was reported as NaN): it is evaluated below
        return Outcome(loss, [trace.step] * len(loss) if isinstance(loss, list) else trace.step, spent)
    # the final iterate, where the run stopped: the budget's end, or stop_at's fraction of it (an objective
    # that changes with the fraction, a continuation, scores it there, as the steps before it)
    point = StepPoint(trace.step, 1.0, schedule.factor(1.0))
    if not spent:
        point = StepPoint(trace.step, budget.fraction(trace.step, trace.seconds),
                          schedule.factor(budget.schedule_fraction(trace.step, trace.seconds, schedule.endpoint)))
    with torch.no_grad():
        last = _returned(objective(point))[0].detach()
    if keep == "last" or best.saved is None:  # the final iterate is what is kept: it must be finite too
        _guard(last, trace.step, optimizer, error, where)
    if keep == "last":
        return Outcome(_as_record(last), trace.step if last.ndim == 0 else [trace.step] * last.shape[0], spent)
    loss, step = best.finish(last, trace.step)
    return Outcome(loss, step, spent)
