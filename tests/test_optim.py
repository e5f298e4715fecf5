"""The one optimisation loop: schedules, budgets, the NaN guard, keep-best, stages sharing a trace."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from meshmei.deform import RBFParameterisation, VertexParameterisation
from meshmei.optim import Budget, Lookahead, Schedule, StepPoint, Trace, make_optimizer, minimize


def quadratic(x, target):
    def objective(point: StepPoint):
        loss = ((x - target) ** 2).sum()
        return loss, {"x0": float(x[0].detach())}

    return objective


@pytest.mark.parametrize("shape, floor, mid", [("cosine", 0.05, 0.525), ("geometric", 0.01, 0.1), ("constant", 1.0, 1.0)])
def test_schedule_runs_from_one_to_its_floor(shape, floor, mid):
    s = Schedule(shape, floor)
    assert s.factor(0.0) == pytest.approx(1.0)
    assert s.factor(1.0) == pytest.approx(floor)
    assert s.factor(0.5) == pytest.approx(mid)


def test_schedule_endpoint_reaches_the_floor_on_the_last_step():
    b = Budget(steps=5)
    assert b.schedule_fraction(4, 0.0, endpoint=True) == 1.0
    assert b.schedule_fraction(4, 0.0, endpoint=False) == pytest.approx(0.8)
    assert Budget(steps=1).schedule_fraction(0, 0.0, endpoint=True) == 0.0


def test_bad_schedules_and_budgets_are_rejected():
    with pytest.raises(ValueError, match="shape must be one of"):
        Schedule("linear")
    with pytest.raises(ValueError, match="floor must lie in"):
        Schedule("geometric", 0.0)
    with pytest.raises(ValueError, match="needs steps, seconds or both"):
        Budget()
    with pytest.raises(ValueError, match="steps must be a positive integer, got 2.5"):
        Budget(steps=2.5)
    with pytest.raises(ValueError, match="seconds must be positive and finite"):
        Budget(seconds=math.inf)
    with pytest.raises(ValueError, match="optimizer must be one of"):
        make_optimizer("sgd", [{"params": [torch.zeros(1, requires_grad=True)], "lr": 1.0}])


def test_minimize_follows_the_schedule_and_records_every_step():
    x = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.SGD([x], lr=0.1)
    trace = Trace()
    out = minimize(quadratic(x, torch.ones(3, dtype=torch.float64)), opt, Budget(steps=10),
                   schedule=Schedule("geometric", 0.1), trace=trace)
    assert trace.step == 10 and len(trace.history) == 10 and out.budget_spent
    lrs = [r["lr"] for r in trace.history]
    assert lrs == pytest.approx([0.1 * 0.1 ** (t / 10) for t in range(10)])
    assert [r["step"] for r in trace.history] == list(range(1, 11))
    times = [r["time"] for r in trace.history]
    assert times == sorted(times) and times[0] > 0
    # plain gradient descent on |x - 1|^2 with these rates, step by step
    y = 0.0
    for lr in lrs:
        y = y - lr * 2 * (y - 1.0)
    assert float(x[0].detach()) == pytest.approx(y, rel=1e-12)


def test_keep_best_restores_the_lowest_loss_iterate_including_the_final_one():
    x = torch.zeros(1, dtype=torch.float64, requires_grad=True)
    # lr 1.5 overshoots |x - 1|^2 more each step: iterates 0, 3, -3, 9, ...; the start is best
    out = minimize(quadratic(x, torch.ones(1, dtype=torch.float64)), torch.optim.SGD([x], lr=1.5), Budget(steps=4),
                   keep="best")
    assert out.step == 0 and out.loss == pytest.approx(1.0) and float(x.detach()) == 0.0
    x2 = torch.zeros(1, dtype=torch.float64, requires_grad=True)
    out = minimize(quadratic(x2, torch.ones(1, dtype=torch.float64)), torch.optim.SGD([x2], lr=0.25), Budget(steps=4),
                   keep="best")
    assert out.step == 4 and out.loss == pytest.approx(0.5**8) and float(x2.detach()) == pytest.approx(1 - 0.5**4)


def test_keep_best_from_a_fraction_ignores_the_iterates_before_it():
    """A continuation's early losses are of another objective: with ``keep_from`` they are not offered."""
    x = torch.zeros(1, dtype=torch.float64, requires_grad=True)
    one = torch.ones(1, dtype=torch.float64)

    def objective(point):  # the first half's loss is lowered by 10: keep-best from 0 would take the start
        loss = ((x - one) ** 2).sum() - (10.0 if point.fraction < 0.5 else 0.0)
        return loss, {}

    # lr 1.5 overshoots: iterates 0, 3, -3, 9, -15, 33 (loss from step 3 on: 64, 256, 1024; final 4096)
    out = minimize(objective, torch.optim.SGD([x], lr=1.5), Budget(steps=6), keep="best")
    assert out.step == 0 and float(x.detach()) == 0.0
    x.data.zero_()
    out = minimize(objective, torch.optim.SGD([x], lr=1.5), Budget(steps=6), keep="best", keep_from=0.5)
    assert out.step == 3 and out.loss == pytest.approx(64.0) and float(x.detach()) == pytest.approx(9.0)


def test_non_finite_loss_raises_the_clients_error_before_the_step():
    x = torch.ones(2, requires_grad=True)
    calls = []

    def objective(point):
        calls.append(point.step)
        loss = (x * x).sum() if point.step < 2 else (x * math.nan).sum()
        return loss, {}

    with pytest.raises(KeyError, match=r"the loss became nan at step 2 of seed 7; lower the learning rate \(lr=0.01\)"):
        minimize(objective, torch.optim.SGD([x], lr=0.01), Budget(steps=5), error=KeyError, where=" of seed 7")
    assert calls == [0, 1, 2] and bool(torch.isfinite(x).all())


def test_a_non_finite_gradient_of_a_finite_loss_raises_before_the_step_carries_it():
    x = torch.zeros(2, requires_grad=True)

    def objective(point):  # finite (zero) loss; sqrt's slope at 0 times 0 is NaN
        return (x.sqrt() * 0.0).sum() + (x - 1.0).square().sum() * (point.step == 0), {}

    with pytest.raises(FloatingPointError, match=r"^the gradient became non-finite at step 0 of seed 7 although the "
                                                 r"loss was finite: .*shape \(2,\)\)$"):
        minimize(objective, torch.optim.Adam([x], lr=0.01), Budget(steps=5), where=" of seed 7")
    assert torch.equal(x.detach(), torch.zeros(2))  # the step was not taken


def test_a_step_that_overflows_the_dtype_raises_the_clients_error_not_torchs():
    """Adam at lr=1e39 on float32 parameters failed inside torch ("value cannot be converted to type float
    without overflow"), a traceback from the CLI."""
    x = torch.ones(2, requires_grad=True)
    with pytest.raises(KeyError, match=r"the optimiser's step 0 of seed 7 overflowed the parameters' dtype "
                                       r"\(lr=1e\+39\); lower the learning rate"):
        minimize(quadratic(x, torch.zeros(2)), torch.optim.Adam([x], lr=1e39), Budget(steps=3), error=KeyError,
                 where=" of seed 7")


def test_stages_share_a_trace_and_stop_at_their_share():
    x = torch.zeros(2, dtype=torch.float64, requires_grad=True)
    trace = Trace()
    budget = Budget(steps=10)
    first = minimize(quadratic(x, torch.ones(2, dtype=torch.float64)), torch.optim.Adam([x], lr=0.1), budget,
                     trace=trace, stop_at=0.3)
    assert trace.step == 3 and not first.budget_spent
    seen = []
    second = minimize(quadratic(x, torch.ones(2, dtype=torch.float64)), torch.optim.Adam([x], lr=0.1), budget,
                      trace=trace, callbacks=[seen.append])
    assert trace.step == 10 and second.budget_spent and [r["step"] for r in seen] == list(range(4, 11))


def test_a_stage_stops_at_its_own_step_limit_before_its_share():
    x = torch.zeros(2, dtype=torch.float64, requires_grad=True)
    trace = Trace(step=2)
    out = minimize(quadratic(x, torch.ones(2, dtype=torch.float64)), torch.optim.Adam([x], lr=0.1), Budget(steps=10),
                   trace=trace, stop_at=0.8, stop_step=5)
    assert trace.step == 5 and len(trace.history) == 3 and not out.budget_spent
    # the share comes first when it is reached first
    out = minimize(quadratic(x, torch.ones(2, dtype=torch.float64)), torch.optim.Adam([x], lr=0.1), Budget(steps=10),
                   trace=trace, stop_at=0.7, stop_step=9)
    assert trace.step == 7 and not out.budget_spent
    for bad in (2.5, True, "3"):
        with pytest.raises(ValueError, match="stop_step must be an integer or None"):
            minimize(quadratic(x, torch.ones(2, dtype=torch.float64)), torch.optim.Adam([x], lr=0.1),
                     Budget(steps=10), stop_step=bad)


def test_parameterisations_start_at_the_rest_shape_and_list_their_groups():
    from meshmei.shapes import initial_mesh

    V0, F = initial_mesh("sphere", n_vertices=100)
    for p in (VertexParameterisation(V0, lr=0.1), RBFParameterisation(V0, lr=0.1, lr_scales=0.01)):
        torch.testing.assert_close(p.vertices(), V0.to(p.vertices().dtype), rtol=0, atol=0)
        n = sum(t.numel() for g in p.groups for t in g["params"])
        assert n >= V0.numel() and all(g["lr"] > 0 for g in p.groups)
    assert set(RBFParameterisation(V0, lr=0.1).info()) >= {"n_kernels", "truncation_error", "n_pairs_final"}


def test_a_batched_objective_steps_each_item_as_if_alone():
    """A (B,) loss over parameters with the items on their leading axis: per-item keep-best, outcome and
    history, and the same iterates as B separate scalar runs (Adam is element-wise)."""
    targets = torch.tensor([[1.0, -2.0], [0.5, 3.0], [-1.0, 0.0]], dtype=torch.float64)
    noise = torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)

    def bumpy(x, t):  # a loss that rises late in the run for some items: keep-best must act per item
        return ((x - t) ** 2).sum(-1) + noise * torch.cos(7 * x.sum(-1))

    X = torch.zeros(3, 2, dtype=torch.float64, requires_grad=True)
    out = minimize(lambda p: (bumpy(X, targets), {}), make_optimizer("adam", [{"params": [X], "lr": 0.3}]),
                   Budget(steps=25), keep="best")
    assert isinstance(out.loss, list) and len(out.loss) == 3 and len(out.step) == 3
    for b in range(3):
        x = torch.zeros(2, dtype=torch.float64, requires_grad=True)
        solo = minimize(lambda p: (((x - targets[b]) ** 2).sum() + noise[b] * torch.cos(7 * x.sum()), {}),
                        make_optimizer("adam", [{"params": [x], "lr": 0.3}]), Budget(steps=25), keep="best")
        torch.testing.assert_close(X.detach()[b], x.detach(), rtol=1e-12, atol=1e-12)
        assert out.loss[b] == pytest.approx(solo.loss, rel=1e-12) and out.step[b] == solo.step
    assert len(set(out.step)) > 1  # the items kept iterates of different steps: keep-best acted per item


def test_a_batched_objective_names_the_items_whose_loss_is_not_finite():
    X = torch.zeros(4, 2, requires_grad=True)

    def objective(point):
        loss = (X ** 2).sum(-1)
        return loss / torch.tensor([1.0, 0.0, 1.0, 0.0]), {}

    with pytest.raises(FloatingPointError, match=r"item\(s\) \[1, 3\]"):
        minimize(objective, make_optimizer("adam", [{"params": [X], "lr": 0.1}]), Budget(steps=3))


def test_a_non_finite_final_iterate_is_refused_when_it_is_the_one_kept():
    # the step overflows x; the final evaluation used to return its NaN loss as the outcome of keep="last"
    x = torch.ones(2, dtype=torch.float64, requires_grad=True)

    def objective(point):
        return (x * x).sum() * torch.exp(x.sum()), {}

    with pytest.raises(KeyError, match=r"the loss became (nan|inf) at step 1 of seed 3; lower the learning rate"):
        minimize(objective, torch.optim.SGD([x], lr=1e306), Budget(steps=1), keep="last", evaluate_last=True,
                 error=KeyError, where=" of seed 3")
    # keep="best" falls back on the best iterate seen instead
    x.data.fill_(1.0)
    out = minimize(objective, torch.optim.SGD([x], lr=1e306), Budget(steps=1), keep="best")
    assert out.step == 0 and math.isfinite(out.loss) and torch.equal(x.detach(), torch.ones(2, dtype=torch.float64))
    # ... but with nothing offered before (keep_from past every step) the final iterate is the one kept, and
    # its non-finite loss is refused as under keep="last" (review: returning it passed every test)
    x.data.fill_(1.0)
    with pytest.raises(KeyError, match=r"the loss became (nan|inf) at step 1"):
        minimize(objective, torch.optim.SGD([x], lr=1e306), Budget(steps=1), keep="best", keep_from=1.0,
                 error=KeyError)


def test_a_non_finite_starting_loss_points_at_the_inputs_not_the_learning_rate():
    x = torch.ones(2, requires_grad=True)
    with pytest.raises(KeyError, match=r"the starting loss is inf \(before any step of seed 7\): check the "
                                       r"objective's weights and inputs") as err:
        minimize(lambda p: (1e300 * torch.tensor(1e300) * (x * x).sum(), {}), torch.optim.SGD([x], lr=0.01),
                 Budget(steps=3), error=KeyError, where=" of seed 7")
    assert "learning rate is not the cause" in str(err.value) and "lower the learning rate" not in str(err.value)
    X = torch.ones(3, 2, requires_grad=True)
    with pytest.raises(FloatingPointError, match=r"the starting loss is nan for item\(s\) \[1\] of the batch"):
        minimize(lambda p: ((X * X).sum(-1) * torch.tensor([1.0, math.nan, 1.0]), {}),
                 make_optimizer("adam", [{"params": [X], "lr": 0.1}]), Budget(steps=3))


def _quadratic():
    x = torch.zeros(3, requires_grad=True)
    return x, (lambda pt: (((x - 1) ** 2).sum(), {})), make_optimizer("adam", [{"params": [x], "lr": 0.1}])


def test_a_stage_stopped_early_scores_its_final_iterate_where_it_stopped():
    """With stop_at < 1 the final iterate was scored at fraction 1.0: under an objective that changes with
    the fraction, keep-best kept an older iterate (loss 1.666 at step 4 against 1.419 at step 5)."""
    x = torch.zeros(3, requires_grad=True)
    seen = []

    def objective(pt):
        seen.append((pt.fraction, pt.factor))
        return ((x - 1) ** 2).sum() * (1 + pt.fraction), {}

    schedule = Schedule("cosine", 0.1)
    out = minimize(objective, make_optimizer("adam", [{"params": [x], "lr": 0.1}]), Budget(steps=10), stop_at=0.5,
                   keep="best", schedule=schedule)
    # scored at the fraction and the schedule's factor where it stopped (the factor was not checked: scoring
    # at the end's factor passed; review)
    assert seen[-1] == (0.5, schedule.factor(0.5)) and schedule.factor(0.5) != schedule.factor(1.0) and out.step == 5
    assert out.loss == pytest.approx(float(((x.detach() - 1) ** 2).sum()) * 1.5, rel=1e-6)


@pytest.mark.parametrize("kw, match", [
    (dict(stop_at=2.0), r"stop_at must lie in \(0, 1\]"),  # ran past the budget, the cosine lr climbing back
    (dict(stop_at=0), r"stop_at must lie in \(0, 1\]"),  # a NaN loss and no error
    (dict(keep_from=5.0), r"keep_from must lie in \[0, 1\]"),
    (dict(max_halvings=-1, accept=lambda: True), "max_halvings must be a non-negative integer"),  # undid every step
])
def test_minimize_refuses_settings_that_misbehaved_silently(kw, match):
    x, objective, opt = _quadratic()
    with pytest.raises(ValueError, match=match):
        minimize(objective, opt, Budget(steps=3), **kw)


def test_minimize_checks_what_the_objective_returns_and_the_optimiser_of_a_batch():
    x, _, opt = _quadratic()
    with pytest.raises(TypeError, match=r"must return \(loss tensor, record dict\), got a Tensor"):
        minimize(lambda pt: ((x - 1) ** 2).sum(), opt, Budget(steps=1))
    z = torch.zeros(2, 3, requires_grad=True)
    batch = lambda pt: (((z - 1) ** 2).sum(1), {})  # noqa: E731
    with pytest.raises(ValueError, match="AdamUniform couples every entry"):  # items stepped together before
        minimize(batch, make_optimizer("uniform", [{"params": [z], "lr": 0.1}]), Budget(steps=2))
    out = minimize(batch, make_optimizer("adam", [{"params": [z], "lr": 0.1}]), Budget(steps=3))
    assert out.step == [3, 3] and len(out.loss) == 2  # one step per item, as with evaluate_last (an int before)
    with pytest.raises(ValueError, match="steps must be a positive integer, got inf"):  # an OverflowError before
        Budget(steps=float("inf"))


def test_an_endpoint_schedule_reaches_its_floor_with_a_time_limit_too():
    x, objective, opt = _quadratic()
    trace = Trace()
    minimize(objective, opt, Budget(steps=5, seconds=1e3), schedule=Schedule("geometric", 0.01, endpoint=True),
             trace=trace)
    assert trace.history[-1]["lr"] == pytest.approx(0.1 * 0.01)  # 0.0025 before: the endpoint was ignored


# ------------------------------------------------------------------ what the parameters depend on besides
def _widening_deformer(seed: int = 0):
    """An RBF deformer with a narrow cut (r_cut 1), learnable scales and random offsets: a step that widens
    its scales rebuilds its pair list, and a wider list keeps pairs a narrower one drops."""
    from meshmei.deform import RBFDeformer
    from meshmei.shapes import initial_mesh

    V0, _ = initial_mesh("sphere", n_vertices=200, dtype=torch.float64)
    rbf = RBFDeformer(V0, r_cut=1.0)
    with torch.no_grad():
        rbf.offsets.copy_(0.02 * torch.randn(rbf.offsets.shape, generator=torch.Generator().manual_seed(seed),
                                             dtype=torch.float64))
    return rbf


def test_an_undone_step_puts_the_deformers_pair_list_back_with_its_parameters():
    """The guard's check of a refused step evaluated the deformer at wider scales, which rebuilt its pair
    list; undoing the step put the parameters back but not the list, so the run went on from (and could
    return) a mesh 0.05 away from the one the guard had accepted (review)."""
    rbf = _widening_deformer()
    with torch.no_grad():
        start = rbf().clone()
    checked = []

    def refuse_all():
        with torch.no_grad():
            checked.append(rbf().clone())  # the guard's evaluation of the trial step
        return False

    minimize(lambda p: (-rbf.log_sigma.sum(), {}), make_optimizer("adam", [{"params": [rbf.log_sigma], "lr": 0.5}]),
             Budget(steps=3), accept=refuse_all, max_halvings=1, states=(rbf,))
    assert rbf.n_rebuilds > 0 and len(checked) == 6  # the trial steps did rebuild the list
    with torch.no_grad():
        assert torch.equal(rbf(), start)  # every step undone: exactly the start, list and all


def test_keep_best_puts_the_deformers_pair_list_back_with_the_best_parameters():
    """The loss rises every step (a constant added), so the best iterate is the first; the steps widen the
    scales and rebuild the list on the way. The returned mesh is the one evaluated at the best step."""
    rbf = _widening_deformer(1)
    seen = {}

    def objective(p):
        V = rbf()
        seen[p.step] = V.detach().clone()
        return -rbf.log_sigma.sum() + 100.0 * p.step, {}

    out = minimize(objective, make_optimizer("adam", [{"params": [rbf.log_sigma], "lr": 0.5}]), Budget(steps=4),
                   keep="best", states=(rbf,))
    assert out.step == 0 and rbf.n_rebuilds > 0
    with torch.no_grad():
        assert torch.equal(rbf(), seen[0])


def test_a_batch_puts_back_the_pair_list_of_the_items_whose_step_is_undone_alone():
    rbfs = [_widening_deformer(0), _widening_deformer(1)]
    with torch.no_grad():
        starts = [r().clone() for r in rbfs]
    log_sigma = torch.nn.Parameter(torch.stack([r.log_sigma.detach() for r in rbfs]))

    def vertices():
        for r, ls in zip(rbfs, log_sigma):
            r.cover(ls)
        return [r.displacement_with(r.offsets, ls) + r.V0 for r, ls in zip(rbfs, log_sigma)]

    def accept(pending):
        vertices()  # the check evaluates both items at their trial scales
        return torch.tensor([False, True])  # item 0 refused every time, item 1 accepted

    minimize(lambda p: (-log_sigma.sum(1), {}), make_optimizer("adam", [{"params": [log_sigma], "lr": 0.5}]),
             Budget(steps=3), accept=accept, max_halvings=1, states=rbfs)
    with torch.no_grad():
        V = vertices()
    assert torch.equal(V[0], starts[0])  # undone, list and all
    assert not torch.allclose(V[1], starts[1])  # moved
    with pytest.raises(ValueError, match="one state per item"):
        minimize(lambda p: (-log_sigma.sum(1), {}), make_optimizer("adam", [{"params": [log_sigma], "lr": 0.5}]),
                 Budget(steps=1), states=rbfs[:1])


def test_a_lookahead_hands_its_kept_evaluation_out_once_and_only_at_the_same_parameters():
    x = torch.tensor([1.0, 2.0], requires_grad=True)
    calls = []

    def fn():
        calls.append(1)
        return 3.0 * x

    look = Lookahead(fn, [x])
    with torch.no_grad():  # where the guard calls it: inside the backtracking's no_grad
        checked = look.candidate()
    assert not checked.requires_grad and len(calls) == 1
    kept = look()
    assert len(calls) == 1 and torch.equal(kept, 3.0 * x.detach()) and kept.grad_fn is not None  # the kept graph
    kept.sum().backward()
    assert torch.equal(x.grad, torch.tensor([3.0, 3.0]))
    look()  # handed out once: a second call evaluates again (the kept graph was used)
    assert len(calls) == 2
    look.candidate()
    with torch.no_grad():
        x.add_(1.0)  # the parameters moved (an optimiser's step, a halving): the kept result is stale
    assert torch.equal(look().detach(), 3.0 * x.detach()) and len(calls) == 4
    look.candidate()
    with torch.no_grad():  # a final result taken without a gradient: the kept result, without its graph
        final = look()
    assert len(calls) == 5 and torch.equal(final, 3.0 * x.detach()) and not final.requires_grad


def test_a_guarded_run_with_a_lookahead_is_the_run_without_it_with_one_evaluation_less_per_accepted_step():
    """The guard's check of the candidate and the next objective share one evaluation of the deformer (the
    scales widen, so its pair list is rebuilt on the way; three checks in five refuse, so steps are halved
    and undone): parameters, losses and step scales are bit for bit those of evaluating it at each call."""

    def run(lookahead: bool):
        torch.manual_seed(0)
        rbf = _widening_deformer(2)
        calls = [0]

        def deformed():
            calls[0] += 1
            return rbf()

        vertices = Lookahead(deformed, (rbf.offsets, rbf.log_sigma)) if lookahead else deformed
        target = torch.randn(rbf.V0.shape, generator=torch.Generator().manual_seed(1), dtype=rbf.V0.dtype)
        checks = [0]

        def accept():
            checks[0] += 1
            with torch.no_grad():
                V = vertices.candidate() if lookahead else vertices()
            return bool(torch.isfinite(V).all()) and checks[0] % 5 not in (2, 3, 4)

        def objective(p):
            V = vertices()
            return ((V - target) ** 2).sum() - rbf.log_sigma.sum(), {}

        trace = Trace()
        minimize(objective, make_optimizer("adam", [{"params": [rbf.offsets], "lr": 0.05},
                                                    {"params": [rbf.log_sigma], "lr": 0.2}]),
                 Budget(steps=12), trace=trace, accept=accept, max_halvings=1, states=(rbf,))
        return rbf, trace.history, calls[0]

    plain, h_plain, n_plain = run(False)
    look, h_look, n_look = run(True)
    assert look.n_rebuilds > 0 and any(r["step_scale"] == 0 for r in h_look) and any(
        r["step_scale"] == 0.5 for r in h_look)
    assert torch.equal(look.offsets, plain.offsets) and torch.equal(look.log_sigma, plain.log_sigma)
    assert [r["loss"] for r in h_look] == [r["loss"] for r in h_plain]
    assert [r["step_scale"] for r in h_look] == [r["step_scale"] for r in h_plain]
    # the objective after an accepted step (not the undone ones, nor after the last step) took the kept one
    assert n_plain - n_look == sum(1 for r in h_look[:-1] if r["step_scale"] > 0)


def test_a_step_count_beyond_a_floats_range_is_refused_in_one_line():
    """Found by fuzzing: --steps 10**400 passed the checks (math.isfinite raised OverflowError on it)."""
    from meshmei.optim import MAX_STEPS

    with pytest.raises(ValueError, match=r"^steps must be at most 1e\+12, got 1000"):
        Budget(10**400)
    assert Budget(MAX_STEPS).steps == MAX_STEPS


def test_an_adam_group_with_a_negative_or_non_finite_lr_is_refused():
    """torch checks Adam's default lr only: a group's lr of -1 climbed the loss from 3 to 26 without a word."""
    p = torch.ones(3, requires_grad=True)
    assert isinstance(make_optimizer("adam", [{"params": [p], "lr": 0.0}]), torch.optim.Adam)  # 0: held still
    for lr in (-1.0, math.nan, math.inf, "0.1"):
        with pytest.raises(ValueError, match="parameter group 0: lr must be a finite non-negative number"):
            make_optimizer("adam", [{"params": [p], "lr": lr}])


def test_budget_and_schedule_numbers_and_a_run_without_a_step():
    """Budget(seconds="5") and Schedule(floor=None) failed in a comparison; a keep="last" run that took no
    step reported its loss as NaN."""
    for bad in ("5", True):
        with pytest.raises(ValueError, match="seconds must be positive and finite"):
            Budget(seconds=bad)
    for bad in (None, "0.1"):
        with pytest.raises(ValueError, match="floor must lie in"):
            Schedule("cosine", bad)
    p = torch.ones(3, requires_grad=True)
    out = minimize(lambda point: ((p ** 2).sum(), {}), make_optimizer("adam", [{"params": [p], "lr": 0.1}]),
                   Budget(steps=3), keep="last", stop_step=0)
    assert out.loss == 3.0 and out.step == 0 and torch.equal(p.detach(), torch.ones(3))


def test_a_loss_without_a_gradient_is_named():
    """Parameters that do not require grad, or a detached loss, ended in torch's "element 0 of tensors does
    not require grad"."""
    free = torch.ones(3)
    held = torch.ones(3, requires_grad=True)
    for p, loss in ((free, lambda: (free ** 2).sum()), (held, lambda: (held ** 2).sum().detach())):
        with pytest.raises(ValueError, match="the objective's loss carries no gradient"):
            minimize(lambda point: (loss(), {}), make_optimizer("adam", [{"params": [p], "lr": 0.1}]), Budget(steps=2))



@pytest.mark.parametrize("answer", [None, 1, "yes", torch.tensor([True, True])])
def test_accept_must_answer_with_a_bool(answer):
    # accept=lambda: None read as a refusal: every step was undone and the run ended where it began, silently
    x = torch.nn.Parameter(torch.tensor([1.0, -2.0]))
    with pytest.raises(TypeError, match=r"accept\(\) must return a bool"):
        minimize(lambda p: ((x ** 2).sum(), {}), make_optimizer("adam", [{"params": [x], "lr": 0.1}]),
                 Budget(steps=2), accept=lambda: answer)


@pytest.mark.parametrize("answer", [True, np.bool_(True), torch.tensor(True)])
def test_accept_answers_of_any_bool_type_are_taken(answer):
    x = torch.nn.Parameter(torch.tensor([1.0, -2.0]))
    minimize(lambda p: ((x ** 2).sum(), {}), make_optimizer("adam", [{"params": [x], "lr": 0.1}]),
             Budget(steps=2), accept=lambda: answer)
    assert float((x ** 2).sum()) < 5.0


@pytest.mark.parametrize("answer", [None, [1, 0], torch.tensor([True]), torch.tensor([[True, True]])])
def test_a_batched_accept_must_answer_with_one_bool_per_item(answer):
    x = torch.nn.Parameter(torch.tensor([[1.0], [-2.0]]))
    with pytest.raises(TypeError, match=r"accept\(pending\) must return 2 bools"):
        minimize(lambda p: ((x ** 2).sum(1), {}), make_optimizer("adam", [{"params": [x], "lr": 0.1}]),
                 Budget(steps=2), accept=lambda pending: answer)
