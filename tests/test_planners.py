"""CEM planner, truncated-normal sampling and the MPC warm start (pets/planners.py)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.stats import truncnorm
from torch import Tensor

from pets.planners import CEMPlanner, shift_plan, truncated_normal

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
LOW = np.array([-1.0, -2.0])
HIGH = np.array([1.0, 0.5])


def quadratic(target: Tensor):
    """Objective -sum((a - a*)^2) over the sequence, recording every population it sees."""
    seen: list[Tensor] = []

    def f(a: Tensor) -> Tensor:
        seen.append(a.clone())
        return -((a - target) ** 2).sum(dim=(1, 2))

    return f, seen


@pytest.mark.parametrize("device", DEVICES)
def test_cem_finds_the_optimum_inside_the_bounds(device: str) -> None:
    h = 5
    target = torch.tensor([[0.3, -1.2], [-0.4, -0.2], [0.0, -0.5], [0.5, -1.4], [-0.5, -0.5]], device=device)
    planner = CEMPlanner(LOW, HIGH, horizon=h, population=400, elites=40, iterations=15, device=device)
    f, seen = quadratic(target)
    plan = planner.plan(f, generator=torch.Generator(device=device).manual_seed(0))
    assert plan.shape == (h, 2) and plan.device.type == device
    torch.testing.assert_close(plan, target, rtol=0, atol=1e-3)
    assert len(seen) == 15 and all(s.shape == (400, h, 2) for s in seen)
    # PETS defaults (5 iterations, alpha 0.1) already get close.
    plan5 = CEMPlanner(LOW, HIGH, horizon=h, population=400, elites=40, device=device).plan(
        quadratic(target)[0], generator=torch.Generator(device=device).manual_seed(0))
    torch.testing.assert_close(plan5, target, rtol=0, atol=0.1)


@pytest.mark.parametrize("seed", [0, 1])
def test_cem_respects_the_bounds_and_ends_on_the_bound(seed: int) -> None:
    lb, ub = torch.tensor(LOW, dtype=torch.float32), torch.tensor(HIGH, dtype=torch.float32)
    # Optimum far outside the box in every coordinate: the answer is its projection, a corner.
    # (CEM closes in on a bound geometrically; in 4 dimensions 15 iterations reach ~3e-3.)
    target = torch.tensor([[3.0, -4.0], [-3.0, 3.0]])
    f, seen = quadratic(target)
    plan = CEMPlanner(LOW, HIGH, horizon=2, population=400, elites=0.1, iterations=15).plan(
        f, generator=torch.Generator().manual_seed(seed))
    allseen = torch.cat(seen)
    assert (allseen >= lb).all() and (allseen <= ub).all()
    assert (plan >= lb).all() and (plan <= ub).all()
    torch.testing.assert_close(plan, torch.minimum(torch.maximum(target, lb), ub), rtol=0, atol=1e-2)
    # Mixed inside / outside optimum over a longer horizon: samples and plan never leave the box.
    target = torch.tensor([[3.0, 0.0], [-5.0, 2.0], [0.2, -4.0], [1.5, -1.0], [0.0, 9.0]])
    f, seen = quadratic(target)
    plan = CEMPlanner(LOW, HIGH, horizon=5, population=300, elites=0.1, iterations=8).plan(
        f, generator=torch.Generator().manual_seed(seed))
    allseen = torch.cat(seen)
    assert (allseen >= lb).all() and (allseen <= ub).all()
    assert (plan >= lb).all() and (plan <= ub).all()


def test_cem_is_deterministic_given_the_generator() -> None:
    target = torch.full((6, 2), 0.2)
    planner = CEMPlanner(LOW, HIGH, horizon=6, population=50, elites=5, iterations=3)
    p1 = planner.plan(quadratic(target)[0], generator=torch.Generator().manual_seed(7))
    p2 = planner.plan(quadratic(target)[0], generator=torch.Generator().manual_seed(7))
    p3 = planner.plan(quadratic(target)[0], generator=torch.Generator().manual_seed(8))
    assert torch.equal(p1, p2)
    assert not torch.equal(p1, p3)


def test_elites_as_count_and_as_ratio() -> None:
    kw = dict(horizon=3, population=100, iterations=3)
    assert CEMPlanner(LOW, HIGH, elites=10, **kw).num_elites == 10
    assert CEMPlanner(LOW, HIGH, elites=0.1, **kw).num_elites == 10
    assert CEMPlanner(LOW, HIGH, elites=0.078, **kw).num_elites == 8  # ceil(7.8)
    assert CEMPlanner(LOW, HIGH, elites=1.0, **kw).num_elites == 100
    target = torch.full((3, 2), -0.3)
    pa = CEMPlanner(LOW, HIGH, elites=10, **kw).plan(quadratic(target)[0], generator=torch.Generator().manual_seed(0))
    pb = CEMPlanner(LOW, HIGH, elites=0.1, **kw).plan(quadratic(target)[0], generator=torch.Generator().manual_seed(0))
    assert torch.equal(pa, pb)


def test_update_rule_alpha_zero_returns_last_elite_mean() -> None:
    """alpha = 0: the result is exactly the mean of the last iteration's top-k samples."""
    target = torch.tensor([[0.5, -0.5], [0.1, 0.2]])
    f, seen = quadratic(target)
    k = 7
    plan = CEMPlanner(LOW, HIGH, horizon=2, population=60, elites=k, iterations=2, alpha=0.0).plan(
        f, generator=torch.Generator().manual_seed(0))
    last = seen[-1]
    values = -((last - target) ** 2).sum(dim=(1, 2))
    elite = last[values.argsort(descending=True)[:k]]
    torch.testing.assert_close(plan, elite.mean(0))


def test_update_rule_smoothing_and_first_iteration_statistics() -> None:
    """One iteration: mu = alpha * mu0 + (1 - alpha) * elite mean, from the warm start mu0."""
    alpha = 0.3
    target = torch.tensor([[0.5, -0.5]])
    mu0 = torch.tensor([[-0.2, 0.1]])
    f, seen = quadratic(target)
    plan = CEMPlanner(LOW, HIGH, horizon=1, population=80, elites=8, iterations=1, alpha=alpha).plan(
        f, init_mean=mu0, generator=torch.Generator().manual_seed(0))
    pop = seen[0]
    values = -((pop - target) ** 2).sum(dim=(1, 2))
    elite = pop[values.argsort(descending=True)[:8]]
    torch.testing.assert_close(plan, alpha * mu0 + (1 - alpha) * elite.mean(0))
    # Samples of the first iteration: centred on mu0, spread from the initial variance (ub-lb)^2/16
    # constrained to (dist_to_bound / 2)^2, never beyond 2 std.
    lb, ub = torch.tensor(LOW, dtype=torch.float32), torch.tensor(HIGH, dtype=torch.float32)
    std = torch.minimum((ub - lb) / 4, torch.minimum(mu0 - lb, ub - mu0) / 2)
    assert ((pop - mu0).abs() <= 2 * std + 1e-6).all()


def test_alpha_one_keeps_the_warm_start_and_flat_objective() -> None:
    mu0 = torch.tensor([[0.5, -1.0], [-0.9, 0.4], [0.0, 0.0]])
    planner = CEMPlanner(LOW, HIGH, horizon=3, population=20, elites=4, alpha=1.0)
    plan = planner.plan(lambda a: torch.zeros(a.shape[0]), init_mean=mu0, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(plan, mu0)


def test_warm_start_is_clipped_and_mean_on_a_bound_does_not_move() -> None:
    """A mean on a bound has zero allowed variance there: every sample sits on that bound."""
    mu0 = torch.tensor([[1.0, 3.0], [1.0, -2.0]])  # 3.0 is clipped to the upper bound 0.5
    planner = CEMPlanner(LOW, HIGH, horizon=2, population=30, elites=3, iterations=1)
    seen: list[Tensor] = []

    def flat(a: Tensor) -> Tensor:
        seen.append(a)
        return torch.zeros(a.shape[0])

    planner.plan(flat, init_mean=mu0, generator=torch.Generator().manual_seed(0))
    pop = seen[0]
    assert (pop[:, 0, 0] == 1.0).all() and (pop[:, 0, 1] == 0.5).all()
    assert (pop[:, 1, 0] == 1.0).all() and (pop[:, 1, 1] == -2.0).all()


def test_return_best_sample_and_nan_objective_values() -> None:
    target = torch.tensor([[0.25, -0.75], [0.1, 0.3]])
    f, seen = quadratic(target)
    plan = CEMPlanner(LOW, HIGH, horizon=2, population=50, elites=5, iterations=3, return_mean_elites=False).plan(
        f, generator=torch.Generator().manual_seed(0))
    allseen = torch.cat(seen)
    values = -((allseen - target) ** 2).sum(dim=(1, 2))
    torch.testing.assert_close(plan, allseen[values.argmax()])

    # NaN returns are never elites: half the population returns NaN, the rest a plain quadratic.
    def nan_half(a: Tensor) -> Tensor:
        v = -((a - target) ** 2).sum(dim=(1, 2))
        return torch.where(a[:, 0, 0] > 0.3, torch.nan, v)

    plan = CEMPlanner(LOW, HIGH, horizon=2, population=200, elites=10, iterations=6).plan(
        nan_half, generator=torch.Generator().manual_seed(0))
    assert torch.isfinite(plan).all()
    torch.testing.assert_close(plan, target, rtol=0, atol=0.05)


@pytest.mark.parametrize("device", DEVICES)
def test_truncated_normal_matches_scipy_moments(device: str) -> None:
    mean = torch.tensor([0.0, 1.5, -3.0], device=device)
    std = torch.tensor([1.0, 0.2, 2.5], device=device)
    n = 200_000
    x = truncated_normal((n,), mean, std, generator=torch.Generator(device=device).manual_seed(0))
    assert x.shape == (n, 3) and x.device.type == device
    assert ((x - mean).abs() <= 2 * std * (1 + 1e-6)).all()
    x = x.double().cpu()
    ref_mean = np.array([truncnorm.mean(-2, 2, loc=m, scale=s) for m, s in zip(mean.tolist(), std.tolist())])
    ref_std = np.array([truncnorm.std(-2, 2, loc=m, scale=s) for m, s in zip(mean.tolist(), std.tolist())])
    se = ref_std / math.sqrt(n)
    assert np.all(np.abs(x.mean(0).numpy() - ref_mean) < 5 * se)
    np.testing.assert_allclose(x.std(0).numpy(), ref_std, rtol=5e-3)
    # The standardised truncated normal has std ~0.880 (not 1): check the shape too, via the 4th moment.
    z = ((x - mean.cpu().double()) / std.cpu().double()).numpy()
    np.testing.assert_allclose((z ** 4).mean(0), truncnorm.moment(4, -2, 2), rtol=2e-2)
    # Other truncations.
    y = truncated_normal((n,), torch.zeros(()), torch.ones(()), bound=1.0, generator=torch.Generator().manual_seed(1))
    assert y.abs().max() <= 1.0
    assert abs(float(y.double().std()) - truncnorm.std(-1, 1)) < 5e-3


def test_shift_plan() -> None:
    plan = torch.arange(10, dtype=torch.float32).reshape(5, 2)
    out = shift_plan(plan, LOW, HIGH)
    assert out.shape == (5, 2)
    torch.testing.assert_close(out[:4], plan[1:])
    torch.testing.assert_close(out[4], torch.tensor([0.0, -0.75]))
    torch.testing.assert_close(plan, torch.arange(10, dtype=torch.float32).reshape(5, 2))  # input untouched
    assert shift_plan(plan[:1], LOW, HIGH).tolist() == [[0.0, -0.75]]
    with pytest.raises(ValueError, match="act_dim"):
        shift_plan(torch.zeros(5, 3), LOW, HIGH)


def test_bad_arguments() -> None:
    with pytest.raises(ValueError, match="population"):
        CEMPlanner(LOW, HIGH, horizon=3, population=0)
    with pytest.raises(ValueError, match="elites"):
        CEMPlanner(LOW, HIGH, horizon=3, population=10, elites=11)
    with pytest.raises(ValueError, match="elites"):
        CEMPlanner(LOW, HIGH, horizon=3, population=10, elites=1.5)
    with pytest.raises(ValueError, match="alpha"):
        CEMPlanner(LOW, HIGH, horizon=3, population=10, alpha=1.5)
    with pytest.raises(ValueError, match="action_low"):
        CEMPlanner(HIGH, LOW, horizon=3, population=10)
    with pytest.raises(ValueError, match="same length"):
        CEMPlanner(LOW, HIGH[:1], horizon=3, population=10)
    planner = CEMPlanner(LOW, HIGH, horizon=3, population=10)
    with pytest.raises(ValueError, match="init_mean"):
        planner.plan(lambda a: torch.zeros(a.shape[0]), init_mean=torch.zeros(4, 2))
    with pytest.raises(ValueError, match="objective"):
        planner.plan(lambda a: torch.zeros(a.shape[0], 1))
