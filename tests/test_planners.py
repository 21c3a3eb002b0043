"""CEM planner, truncated-normal sampling and the MPC warm start (pets/planning/planners)."""

from __future__ import annotations

import math
from dataclasses import dataclass, make_dataclass

import numpy as np
import pytest
import torch
from scipy.stats import truncnorm
from torch import Tensor

from pets.planning.planners import BoxPlanner, CEMPlanner, shift_plan, truncated_normal

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
        quadratic(target)[0], generator=torch.Generator(device=device).manual_seed(0)
    )
    torch.testing.assert_close(plan5, target, rtol=0, atol=0.1)


@pytest.mark.parametrize("seed", [0, 1])
def test_cem_respects_the_bounds_and_ends_on_the_bound(seed: int) -> None:
    lb, ub = torch.tensor(LOW, dtype=torch.float32), torch.tensor(HIGH, dtype=torch.float32)
    # Optimum far outside the box in every coordinate: the answer is its projection, a corner.
    # (CEM closes in on a bound geometrically; in 4 dimensions 15 iterations reach ~3e-3.)
    target = torch.tensor([[3.0, -4.0], [-3.0, 3.0]])
    f, seen = quadratic(target)
    plan = CEMPlanner(LOW, HIGH, horizon=2, population=400, elites=0.1, iterations=15).plan(
        f, generator=torch.Generator().manual_seed(seed)
    )
    allseen = torch.cat(seen)
    assert (allseen >= lb).all() and (allseen <= ub).all()
    assert (plan >= lb).all() and (plan <= ub).all()
    torch.testing.assert_close(plan, torch.minimum(torch.maximum(target, lb), ub), rtol=0, atol=1e-2)
    # Mixed inside / outside optimum over a longer horizon: samples and plan never leave the box.
    target = torch.tensor([[3.0, 0.0], [-5.0, 2.0], [0.2, -4.0], [1.5, -1.0], [0.0, 9.0]])
    f, seen = quadratic(target)
    plan = CEMPlanner(LOW, HIGH, horizon=5, population=300, elites=0.1, iterations=8).plan(
        f, generator=torch.Generator().manual_seed(seed)
    )
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
        f, generator=torch.Generator().manual_seed(0)
    )
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
        f, init_mean=mu0, generator=torch.Generator().manual_seed(0)
    )
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
        f, generator=torch.Generator().manual_seed(0)
    )
    allseen = torch.cat(seen)
    values = -((allseen - target) ** 2).sum(dim=(1, 2))
    torch.testing.assert_close(plan, allseen[values.argmax()])

    # NaN returns are never elites: half the population returns NaN, the rest a plain quadratic.
    def nan_half(a: Tensor) -> Tensor:
        v = -((a - target) ** 2).sum(dim=(1, 2))
        return torch.where(a[:, 0, 0] > 0.3, torch.nan, v)

    plan = CEMPlanner(LOW, HIGH, horizon=2, population=200, elites=10, iterations=6).plan(
        nan_half, generator=torch.Generator().manual_seed(0)
    )
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
    np.testing.assert_allclose((z**4).mean(0), truncnorm.moment(4, -2, 2), rtol=2e-2)
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


# ---------------------------------------------------------------------------------------------- iCEM / MPPI
from pets.planning.planners import ICEMPlanner, MPPIPlanner, colored_noise, smoothing_matrix  # noqa: E402

TARGET = torch.tensor([[0.3, -1.2], [-0.4, -0.2], [0.0, -0.5], [0.5, -1.4], [-0.5, -0.5]])


@pytest.mark.parametrize("t", [32, 15])
@pytest.mark.parametrize("beta", [0.0, 1.0, 2.0, 2.5])
def test_colored_noise_unit_variance_and_spectrum_slope(t: int, beta: float) -> None:
    n = 40_000
    y = colored_noise((n, t), beta, generator=torch.Generator().manual_seed(0))
    assert y.shape == (n, t) and y.dtype == torch.float32
    yd = y.double().numpy()
    # Unit variance and zero mean at every step (stationary), Gaussian marginals (kurtosis 3).
    np.testing.assert_allclose(yd.var(0), 1.0, atol=0.04)
    assert np.abs(yd.mean(0)).max() < 0.04
    np.testing.assert_allclose((yd**4).mean(0) / yd.var(0) ** 2, 3.0, atol=0.15)
    # Periodogram (numpy's FFT, independent of torch's): log power vs log frequency has slope -beta.
    power = (np.abs(np.fft.rfft(yd, axis=1)) ** 2).mean(0)
    k = np.arange(1, (t - 1) // 2 + 1)  # interior frequencies (no DC, no Nyquist)
    slope = np.polyfit(np.log(k / t), np.log(power[k]), 1)[0]
    assert abs(slope + beta) < 0.05, slope
    if beta == 0.0:  # white: no correlation between steps
        assert abs(np.corrcoef(yd[:, 3], yd[:, 4])[0, 1]) < 0.02
    else:  # red/pink: neighbouring steps are positively correlated
        assert np.corrcoef(yd[:, 3], yd[:, 4])[0, 1] > 0.2


def test_colored_noise_small_lengths_batches_and_generator() -> None:
    for t in (1, 2, 3):
        y = colored_noise((30_000, t), 2.0, generator=torch.Generator().manual_seed(1)).double()
        torch.testing.assert_close(y.var(0), torch.ones(t, dtype=torch.double), rtol=0, atol=0.04)
    a = colored_noise((4, 3, 10), 2.0, generator=torch.Generator().manual_seed(5))
    b = colored_noise((4, 3, 10), 2.0, generator=torch.Generator().manual_seed(5))
    c = colored_noise((4, 3, 10), 2.0, generator=torch.Generator().manual_seed(6))
    assert a.shape == (4, 3, 10) and torch.equal(a, b) and not torch.equal(a, c)
    assert colored_noise((2, 5), 1.0, dtype=torch.float64).dtype == torch.float64
    with pytest.raises(ValueError, match="beta"):
        colored_noise((3, 5), -1.0)
    with pytest.raises(ValueError, match="shape"):
        colored_noise((3, 0), 1.0)


def test_smoothing_matrix_matches_the_recursion() -> None:
    """u_0 = n_0, u_t = b n_t + (1 - b) u_{t-1}, each step scaled to unit variance (Python-loop ground truth)."""
    h, b = 7, 0.4
    n = torch.randn(h, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    u = [n[0]]
    var = [1.0]
    for t in range(1, h):
        u.append(b * n[t] + (1 - b) * u[-1])
        # Var(u_t) = b^2 + (1 - b)^2 Var(u_{t-1}) for independent unit n.
        var.append(b**2 + (1 - b) ** 2 * var[-1])
    expected = torch.stack(u) / torch.tensor(var, dtype=torch.float64).sqrt()[:, None]
    torch.testing.assert_close(smoothing_matrix(h, b, dtype=torch.float64) @ n, expected)
    torch.testing.assert_close(smoothing_matrix(4, 1.0), torch.eye(4))
    with pytest.raises(ValueError, match="smoothing"):
        smoothing_matrix(4, 0.0)


@pytest.mark.parametrize("device", DEVICES)
def test_icem_finds_the_optimum_inside_the_bounds(device: str) -> None:
    target = TARGET.to(device)
    # White noise (beta = 0) for a target that jumps between steps; the mean as result is the most precise.
    f, seen = quadratic(target)
    planner = ICEMPlanner(LOW, HIGH, horizon=5, population=400, elites=40, iterations=12, noise_beta=0.0, device=device)
    plan = planner.plan(f, generator=torch.Generator(device=device).manual_seed(0))
    assert plan.shape == (5, 2) and plan.device.type == device
    torch.testing.assert_close(plan, target, rtol=0, atol=0.03)
    # A target that is smooth in time (and periodic over the horizon, like the FFT noise): the paper's red
    # noise (beta = 2, default best-sample result) gets closer than white noise on the same budget.
    t = torch.arange(10.0)
    smooth = torch.stack(
        [0.4 + 0.2 * torch.cos(2 * math.pi * t / 10), -1.0 + 0.3 * torch.sin(2 * math.pi * t / 10)], dim=1
    ).to(device)
    err = {}
    for beta in (0.0, 2.0):
        planner = ICEMPlanner(
            LOW, HIGH, horizon=10, population=300, elites=30, iterations=10, noise_beta=beta, device=device
        )
        plan = planner.plan(quadratic(smooth)[0], generator=torch.Generator(device=device).manual_seed(0))
        err[beta] = float((plan - smooth).abs().max())
    assert err[2.0] < 0.08 and err[2.0] < err[0.0], err


@pytest.mark.parametrize("seed", [0, 1])
def test_icem_respects_the_bounds_and_ends_on_the_bound(seed: int) -> None:
    lb, ub = torch.tensor(LOW, dtype=torch.float32), torch.tensor(HIGH, dtype=torch.float32)
    target = torch.tensor([[3.0, -4.0], [-3.0, 3.0], [0.2, 9.0]])
    f, seen = quadratic(target)
    plan = ICEMPlanner(LOW, HIGH, horizon=3, population=400, elites=20, iterations=15, population_decay=1.1).plan(
        f, generator=torch.Generator().manual_seed(seed)
    )
    allseen = torch.cat(seen)
    assert (allseen >= lb).all() and (allseen <= ub).all()
    assert (plan >= lb).all() and (plan <= ub).all()
    torch.testing.assert_close(plan, torch.minimum(torch.maximum(target, lb), ub), rtol=0, atol=0.03)
    # Red noise over a longer horizon with a target far outside: every sample stays in the box.
    f, seen = quadratic(10 * TARGET)
    plan = ICEMPlanner(LOW, HIGH, horizon=5, population=100, elites=10, iterations=4).plan(
        f, generator=torch.Generator().manual_seed(seed)
    )
    allseen = torch.cat(seen)
    assert (allseen >= lb).all() and (allseen <= ub).all()
    assert (plan >= lb).all() and (plan <= ub).all()


def test_icem_population_schedule_carried_elites_and_mean() -> None:
    f, seen = quadratic(TARGET)
    planner = ICEMPlanner(
        LOW,
        HIGH,
        horizon=5,
        population=100,
        elites=10,
        iterations=4,
        population_decay=2.0,
        keep_elites=0.3,
        alpha=0.0,
        return_mean_elites=True,
    )
    assert planner.populations == [100, 50, 25, 20]  # max(floor(100 / 2^i), 2 * elites)
    assert planner.num_keep == 3
    plan = planner.plan(f, generator=torch.Generator().manual_seed(0))
    assert [s.shape[0] for s in seen] == [100, 53, 28, 24]  # + 3 carried elites (+ the mean at the last)
    for i in range(1, 4):
        prev = seen[i - 1]
        top = prev[(-((prev - TARGET) ** 2).sum(dim=(1, 2))).argsort(descending=True)[:3]]
        torch.testing.assert_close(seen[i][planner.populations[i] : planner.populations[i] + 3], top)
    # alpha = 0: the mean added to the last population is the elite mean of iteration 2, and the
    # result (return_mean_elites) is the elite mean of the last population.
    third = seen[2]
    elite2 = third[(-((third - TARGET) ** 2).sum(dim=(1, 2))).argsort(descending=True)[:10]]
    torch.testing.assert_close(seen[3][-1], elite2.mean(0))
    last = seen[3]
    elite3 = last[(-((last - TARGET) ** 2).sum(dim=(1, 2))).argsort(descending=True)[:10]]
    torch.testing.assert_close(plan, elite3.mean(0))
    # Default result: the best sample of the last population.
    f2, seen2 = quadratic(TARGET)
    best = ICEMPlanner(LOW, HIGH, horizon=5, population=100, elites=10, iterations=2).plan(
        f2, generator=torch.Generator().manual_seed(0)
    )
    last = seen2[-1]
    torch.testing.assert_close(best, last[(-((last - TARGET) ** 2).sum(dim=(1, 2))).argmax()])


def test_icem_keeps_shifted_elites_between_mpc_steps() -> None:
    planner = ICEMPlanner(LOW, HIGH, horizon=5, population=60, elites=10, iterations=2, keep_elites=0.5)
    f, seen = quadratic(TARGET)
    plan = planner.plan(f, generator=torch.Generator().manual_seed(0))
    last = seen[-1]
    elites = last[(-((last - TARGET) ** 2).sum(dim=(1, 2))).argsort(descending=True)[:5]]
    # The agent's warm start after executing 2 steps: the plan shifted twice.
    init = shift_plan(shift_plan(plan, LOW, HIGH), LOW, HIGH)
    f, seen = quadratic(TARGET)
    planner.plan(f, init_mean=init, generator=torch.Generator().manual_seed(1))
    mid = torch.tensor((LOW + HIGH) / 2, dtype=torch.float32)
    expected = torch.cat([elites[:, 2:], mid.expand(5, 2, 2)], dim=1)
    torch.testing.assert_close(seen[0][60:], expected)
    # No warm start (a new episode) or a warm start that is not a shifted plan: nothing is carried.
    for init in (None, torch.zeros(5, 2)):
        f, seen = quadratic(TARGET)
        planner.plan(f, init_mean=init, generator=torch.Generator().manual_seed(1))
        assert seen[0].shape[0] == 60


@pytest.mark.parametrize("cls", [ICEMPlanner, MPPIPlanner])
def test_icem_and_mppi_are_deterministic_given_the_generator(cls) -> None:
    target = torch.full((6, 2), 0.2)
    kw = dict(horizon=6, population=50, iterations=3)
    p1 = cls(LOW, HIGH, **kw).plan(quadratic(target)[0], generator=torch.Generator().manual_seed(7))
    p2 = cls(LOW, HIGH, **kw).plan(quadratic(target)[0], generator=torch.Generator().manual_seed(7))
    p3 = cls(LOW, HIGH, **kw).plan(quadratic(target)[0], generator=torch.Generator().manual_seed(8))
    assert torch.equal(p1, p2)
    assert not torch.equal(p1, p3)


@pytest.mark.parametrize("device", DEVICES)
def test_mppi_finds_the_optimum_inside_the_bounds(device: str) -> None:
    target = TARGET.to(device)
    planner = MPPIPlanner(LOW, HIGH, horizon=5, population=500, iterations=15, sigma=0.15, device=device)
    f, seen = quadratic(target)
    plan = planner.plan(f, generator=torch.Generator(device=device).manual_seed(0))
    assert plan.shape == (5, 2) and plan.device.type == device
    assert len(seen) == 15 and all(s.shape == (500, 5, 2) for s in seen)
    torch.testing.assert_close(plan, target, rtol=0, atol=0.03)


@pytest.mark.parametrize("smoothing", [1.0, 0.5])
def test_mppi_respects_the_bounds(smoothing: float) -> None:
    lb, ub = torch.tensor(LOW, dtype=torch.float32), torch.tensor(HIGH, dtype=torch.float32)
    target = torch.tensor([[3.0, -4.0], [-3.0, 3.0], [0.2, 9.0]])
    corner = torch.minimum(torch.maximum(target, lb), ub)
    mid_error = float((0.5 * (lb + ub) - corner).abs().max())
    for sigma in (1.0, 0.3):  # wide perturbations: many samples clipped
        f, seen = quadratic(target)
        plan = MPPIPlanner(LOW, HIGH, horizon=3, population=300, iterations=20, sigma=sigma, smoothing=smoothing).plan(
            f, generator=torch.Generator().manual_seed(0)
        )
        allseen = torch.cat(seen)
        assert (allseen >= lb).all() and (allseen <= ub).all()
        assert (plan >= lb).all() and (plan <= ub).all()
        # A weighted mean of samples never sits exactly on a bound: it approaches the corner.
        assert float((plan - corner).abs().max()) < 0.6 * mid_error
    if smoothing == 1.0:
        torch.testing.assert_close(plan, corner, rtol=0, atol=0.15)


def test_mppi_perturbations_std_and_smoothing() -> None:
    """Wide bounds (no clipping): per-step std sigma * half-range; lag-1 correlation 1 - smoothing."""
    lo, hi = np.array([-100.0]), np.array([100.0])
    for smoothing in (1.0, 0.3):
        f, seen = quadratic(torch.zeros(20, 1))
        MPPIPlanner(lo, hi, horizon=20, population=20_000, iterations=1, sigma=0.02, smoothing=smoothing).plan(
            f, init_mean=torch.full((20, 1), 5.0), generator=torch.Generator().manual_seed(0)
        )
        eps = (seen[0][..., 0] - 5.0).double()  # (N, H)
        torch.testing.assert_close(eps.std(0), torch.full((20,), 2.0, dtype=torch.double), rtol=0.03, atol=0)
        corr = np.corrcoef(eps[:, 15].numpy(), eps[:, 16].numpy())[0, 1]
        assert abs(corr - (1.0 - smoothing)) < 0.03


def test_mppi_weights() -> None:
    planner = MPPIPlanner(LOW, HIGH, horizon=2, population=5, temperature=0.5)
    v = torch.tensor([1.0, 3.0, 2.0, 0.0, 3.0])
    # (v - max) / (max - median) / T with median 2 -> softmax of (v - 3) / 0.5
    torch.testing.assert_close(planner.weights(v), torch.softmax((v - 3.0) / 0.5, dim=0))
    torch.testing.assert_close(planner.weights(torch.full((5,), 7.0)), torch.full((5,), 0.2))
    # Non-finite returns count as the worst finite one; all non-finite: uniform.
    w = planner.weights(torch.tensor([1.0, torch.nan, 2.0, -torch.inf, 3.0]))
    assert torch.isfinite(w).all() and w[1] == w[3] == w[0]
    torch.testing.assert_close(planner.weights(torch.full((5,), torch.nan)), torch.full((5,), 0.2))
    # A huge outlier (a diverged rollout scored -1e6) does not flatten the weights of the others.
    w = planner.weights(torch.tensor([1.0, 3.0, 2.0, -1e6, 3.0]))
    torch.testing.assert_close(w[:3], torch.softmax(torch.tensor([1.0, 3.0, 2.0, -1e6, 3.0]) * 2 - 6, 0)[:3])
    # Temperature -> 0: the plan is the best sample of the single iteration (random shooting).
    f, seen = quadratic(TARGET)
    plan = MPPIPlanner(LOW, HIGH, horizon=5, population=100, iterations=1, alpha=0.0, temperature=1e-6).plan(
        f, generator=torch.Generator().manual_seed(0)
    )
    values = -((seen[0] - TARGET) ** 2).sum(dim=(1, 2))
    torch.testing.assert_close(plan, seen[0][values.argmax()])


def test_icem_and_mppi_bad_arguments() -> None:
    with pytest.raises(ValueError, match="population_decay"):
        ICEMPlanner(LOW, HIGH, horizon=3, population=10, population_decay=0.5)
    with pytest.raises(ValueError, match="keep_elites"):
        ICEMPlanner(LOW, HIGH, horizon=3, population=10, keep_elites=1.5)
    with pytest.raises(ValueError, match="noise_beta"):
        ICEMPlanner(LOW, HIGH, horizon=3, population=10, noise_beta=-1.0)
    with pytest.raises(ValueError, match="elites"):
        ICEMPlanner(LOW, HIGH, horizon=3, population=10, elites=11)
    with pytest.raises(ValueError, match="sigma"):
        MPPIPlanner(LOW, HIGH, horizon=3, population=10, sigma=0.0)
    with pytest.raises(ValueError, match="temperature"):
        MPPIPlanner(LOW, HIGH, horizon=3, population=10, temperature=-1.0)
    with pytest.raises(ValueError, match="smoothing"):
        MPPIPlanner(LOW, HIGH, horizon=3, population=10, smoothing=1.5)
    with pytest.raises(ValueError, match="horizon"):
        MPPIPlanner(LOW, HIGH, horizon=0, population=10)
    for planner in (ICEMPlanner(LOW, HIGH, horizon=3, population=10), MPPIPlanner(LOW, HIGH, horizon=3, population=10)):
        with pytest.raises(ValueError, match="init_mean"):
            planner.plan(lambda a: torch.zeros(a.shape[0]), init_mean=torch.zeros(4, 2))
        with pytest.raises(ValueError, match="objective"):
            planner.plan(lambda a: torch.zeros(a.shape[0], 1))


@pytest.mark.parametrize("name, cls", [("cem", CEMPlanner), ("icem", ICEMPlanner), ("mppi", MPPIPlanner)])
def test_config_builds_the_named_planner(name: str, cls) -> None:
    import envs
    from pets.builder import make_planner
    from pets.config import ConfigError, make_config

    cfg = make_config(
        "hopper",
        preset="fast",
        overrides={"planner.name": name, "planner.icem.noise_beta": "2.5", "planner.mppi.temperature": "0.2"},
    )
    planner = make_planner(cfg, envs.get("hopper"), torch.device("cpu"))
    assert isinstance(planner, cls) and planner.horizon == cfg.planner.horizon
    if name == "icem":
        assert planner.noise_beta == 2.5 and planner.num_elites == 10
    if name == "mppi":
        assert planner.temperature == 0.2
    for item in (
        "planner.name=random",
        "planner.mppi.sigma=0",
        "planner.icem.population_decay=0.9",
        "planner.icem.keep_elites=2",
        "planner.precision=fp16",
        "planner.mppi.smoothing=0",
    ):
        key, value = item.split("=")
        with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
            make_config("hopper", overrides={key: value})


def test_the_planner_table_is_the_config_choice_list() -> None:
    from pets.config import PLANNERS
    from pets.planning.planners import PLANNER_CLASSES

    assert tuple(PLANNERS) == tuple(PLANNER_CLASSES) == ("cem", "icem", "mppi")
    assert [cls.uses_elites for cls in PLANNER_CLASSES.values()] == [True, True, False]
    assert all(name == cls.name for name, cls in PLANNER_CLASSES.items())


def test_a_planner_section_is_the_config_section_and_its_checks() -> None:
    from pets.config import ConfigError, make_config
    from pets.planning.planners import PLANNER_CLASSES

    cfg = make_config("hopper", preset="fast")
    sections = {name for name, cls in PLANNER_CLASSES.items() if cls.section is not None}
    assert sections == {"icem", "mppi"} and all(name in cfg.planner for name in sections) and "cem" not in cfg.planner
    assert cfg.planner.icem.noise_beta == ICEMPlanner(LOW, HIGH, horizon=2, population=4).noise_beta == 2.0
    with pytest.raises(ValueError, match="MPPIPlanner has no argument 'noise_beta'; its own arguments: sigma"):
        MPPIPlanner(LOW, HIGH, horizon=2, population=4, noise_beta=1.0)
    with pytest.raises(ValueError, match="MPPIPlanner takes no elites"):
        MPPIPlanner(LOW, HIGH, horizon=2, population=4, elites=2)
    with pytest.raises(ConfigError, match=r"planner\.icem\.noise_beta must be a finite number"):
        make_config("hopper", overrides={"planner.icem.noise_beta": "nan"})


@dataclass
class ShootingOptions:
    """The toy planner's own argument (and config section ``planner.shooting.*``): how far it samples around the
    warm start, in half-ranges of the box."""

    spread: float = 1.0

    def checked(self) -> ShootingOptions:
        if not 0 < self.spread <= 1:
            raise ValueError(f"spread must be in (0, 1], got {self.spread}")
        return self


class RandomShooting(BoxPlanner):
    """A toy planner outside pets/: uniform samples around the warm start, the best one of all iterations."""

    name = "shooting"
    Options = ShootingOptions
    section = ShootingOptions

    def search(self, objective, mu, init_mean, generator):
        best, best_value = mu, torch.tensor(-math.inf, device=mu.device)
        half = self.spread * 0.5 * (self.high - self.low)
        for _ in range(self.iterations):
            shape = (self.population, self.horizon, self.act_dim)
            u = torch.rand(shape, generator=generator, device=mu.device, dtype=mu.dtype) * 2 - 1
            samples = self.clip(mu + half * u)
            values = torch.nan_to_num(objective(samples), nan=-math.inf)
            top = int(values.argmax())
            if values[top] > best_value:
                best, best_value = samples[top], values[top]
        return best


def test_a_planner_registered_from_outside_the_package_plans_a_run(tmp_path, monkeypatch, capsys) -> None:
    import run_pets
    from pets.config import ConfigError, all_keys, make_config
    from pets.planning.planners import PLANNER_CLASSES, register_planner
    from tests.test_cli import TINY

    assert "planner.shooting.spread" not in all_keys()  # the schema's keys are worked out (and kept) before it
    monkeypatch.setitem(PLANNER_CLASSES, "shooting", RandomShooting)  # removed again after the test
    assert register_planner(RandomShooting) is RandomShooting
    assert "planner.shooting.spread" in all_keys() and "planner.mppi.sigma" in all_keys()
    f, _ = quadratic(torch.zeros(3, 2))
    plan = RandomShooting(LOW, HIGH, horizon=3, population=200).plan(f, generator=torch.Generator().manual_seed(0))
    assert plan.shape == (3, 2) and float(f(plan[None])[0]) > -0.5
    cfg = make_config("invertedpendulum", overrides={"planner.name": "shooting", "planner.shooting.spread": "0.5"})
    assert cfg.planner.shooting.spread == 0.5 and cfg.planner.mppi.sigma == 0.5
    with pytest.raises(ConfigError, match=r"planner\.shooting\.spread must be in \(0, 1\], got 2\.0"):
        make_config("invertedpendulum", overrides={"planner.shooting.spread": "2"})
    with pytest.raises(ConfigError, match="planner.candidates=feedback needs planner.name cem or mppi, got 'shooting'"):
        make_config("invertedpendulum", overrides={"planner.name": "shooting", "planner.candidates": "feedback"})
    out = tmp_path / "run"
    args = ["--env", "invertedpendulum", "--trials", "1", "--out", str(out), *TINY, "planner.name=shooting"]
    assert run_pets.main([*args, "value.enabled=false"]) == 0
    assert (out / "metrics.csv").read_text().count("\n") == 2  # the header and the one trial
    assert "name: shooting" in (out / "config.yaml").read_text()
    monkeypatch.delitem(PLANNER_CLASSES, "shooting")  # as in a new process that has not registered it
    from pets.config import load_config

    with pytest.raises(ConfigError, match="its planner 'shooting' is not a planner here .* register_planner") as err:
        load_config(str(out / "config.yaml"))  # was: "does not match this version's config schema ... restore it"
    assert "\n" not in str(err.value)
    with pytest.raises(ConfigError, match=r"got 'shooting' .* register_planner is imported: .* imports=\[my_planner\]"):
        make_config("invertedpendulum", overrides={"planner.name": "shooting"})
    from omegaconf import OmegaConf

    stored = OmegaConf.load(out / "config.yaml")
    stored.planner.name = "cem"  # a run of cem made where shooting was registered: its section is in config.yaml
    OmegaConf.save(stored, out / "config.yaml")
    with pytest.raises(ConfigError, match="its planner 'shooting' is not a planner here .* imports=") as err:
        load_config(str(out / "config.yaml"))  # was: "does not match this version's config schema ... restore it"
    del stored.planner["name"], stored.planner["shooting"]  # no name: the schema's default, as before
    OmegaConf.save(stored, out / "config.yaml")
    assert load_config(str(out / "config.yaml")).planner.name == "cem"


def test_flat_planner_keys_of_version_0_1_still_work_with_a_warning(tmp_path) -> None:
    from omegaconf import OmegaConf

    from pets.config import DEPRECATED_KEYS, load_config, make_config

    for old, new in DEPRECATED_KEYS.items():
        value = 1.5 if new.endswith("population_decay") else 0.7  # a value in the key's range
        with pytest.warns(FutureWarning, match=new.replace(".", r"\.")):
            cfg = make_config("hopper", overrides={old: str(value)})
        assert OmegaConf.select(cfg, new) == value
    # a run directory's config.yaml written with the flat keys loads into the nested ones
    stored = OmegaConf.to_container(make_config("hopper"))
    stored["planner"].pop("icem")
    stored["planner"]["icem_keep_elites"] = 0.25
    stored["planner"]["noise_beta"] = 1.5
    path = tmp_path / "config.yaml"
    path.write_text(OmegaConf.to_yaml(stored))
    cfg = load_config(str(path))
    assert cfg.planner.icem.keep_elites == 0.25 and cfg.planner.icem.noise_beta == 1.5
    assert cfg.planner.icem.population_decay == 1.25  # the default where the old file had nothing


@pytest.mark.parametrize("replan_every", [1, 3])
def test_icem_carries_elites_through_the_mpc_agent(replan_every: int) -> None:
    """With pets.agent.MPCAgent's warm start (the plan shifted by the executed steps) iCEM recognises the shift."""
    from pets.agent import MPCAgent

    sizes: list[int] = []

    def evaluator(obs: Tensor, actions: Tensor, generator: torch.Generator | None = None) -> Tensor:
        sizes.append(actions.shape[0])
        return -((actions - 0.3) ** 2).sum(dim=(1, 2))

    planner = ICEMPlanner(LOW, HIGH, horizon=5, population=40, elites=10, iterations=2, keep_elites=0.3)
    agent = MPCAgent(
        planner,
        evaluator,
        replan_every=replan_every,
        action_low=LOW,
        action_high=HIGH,
        device=torch.device("cpu"),
        generator=torch.Generator().manual_seed(0),
    )
    for _ in range(2 * replan_every):
        agent.act(np.zeros(3))
    # First plan: 40, then 32 + 3 carried + mean; second plan: 40 + 3 shifted elites, then 32 + 3 + 1.
    assert sizes == [40, 36, 43, 36]
    agent.reset()  # a new episode: nothing carried
    agent.act(np.zeros(3))
    assert sizes[4] == 40


# ------------------------------------------------------------------------------------- non-finite returns
from pets.planning.planners import PlanningFailed  # noqa: E402


@pytest.mark.parametrize("cls", [CEMPlanner, ICEMPlanner, MPPIPlanner])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_a_plan_whose_returns_are_all_non_finite_raises(cls, bad: float) -> None:
    """Issue 17: every candidate non-finite (a broken model) is an error, not a random action."""
    planner = cls(LOW, HIGH, horizon=3, population=20, iterations=2)
    with pytest.raises(PlanningFailed, match="every candidate action sequence got a non-finite return"):
        planner.plan(lambda a: torch.full((a.shape[0],), bad), generator=torch.Generator().manual_seed(0))
    assert issubclass(PlanningFailed, RuntimeError)


@pytest.mark.parametrize("cls", [CEMPlanner, ICEMPlanner, MPPIPlanner])
def test_a_plan_with_some_finite_returns_in_every_iteration_still_plans(cls) -> None:
    """Only the all-non-finite case fails: candidates with some non-finite returns are ranked at the bottom."""
    target = torch.tensor([[0.25, -0.75], [0.1, 0.3], [0.0, 0.0]])

    def mostly_nan(a: Tensor) -> Tensor:
        v = -((a - target) ** 2).sum(dim=(1, 2))
        keep = torch.zeros_like(v, dtype=torch.bool)
        keep[:3] = True  # three finite candidates per iteration
        return torch.where(keep, v, torch.nan)

    plan = cls(LOW, HIGH, horizon=3, population=40, iterations=3).plan(
        mostly_nan, generator=torch.Generator().manual_seed(0)
    )
    assert plan.shape == (3, 2) and torch.isfinite(plan).all()


def test_a_planner_that_returns_a_bad_plan_or_takes_a_name_is_refused_naming_it() -> None:
    """A registered planner whose search returns nan (was: nan actions sent to MuJoCo, the run failing later at
    training without naming the planner) or another shape (was: accepted, broadcast) is refused at the call; a
    class under a name another holds (``cem``) is refused, the built-in CEM kept."""
    from pets.planning.planners import PLANNER_CLASSES, CEMPlanner, PlanningFailed, register_planner

    class NanPlanner(RandomShooting):
        name = "nan-plan"

        def search(self, objective, mu, init_mean, generator):
            return mu * math.nan

    class FlatPlanner(RandomShooting):
        name = "flat"

        def search(self, objective, mu, init_mean, generator):
            return mu[:1, :1]

    f, _ = quadratic(torch.zeros(3, 2))
    with pytest.raises(PlanningFailed, match="planner 'nan-plan': search returned a plan with nan or inf"):
        NanPlanner(LOW, HIGH, horizon=3, population=20).plan(f, generator=torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match=r"planner 'flat': search returned \(1, 1\), not a plan of shape \(3, 2\)"):
        FlatPlanner(LOW, HIGH, horizon=3, population=20).plan(f, generator=torch.Generator().manual_seed(0))

    class MyCEM(RandomShooting):
        name = "cem"

    with pytest.raises(ValueError, match="planner name 'cem' is taken by CEMPlanner; give MyCEM another name"):
        register_planner(MyCEM)
    assert PLANNER_CLASSES["cem"] is CEMPlanner and register_planner(CEMPlanner) is CEMPlanner


def _two_argument_search(self, objective, mu):
    return mu


@pytest.mark.parametrize(
    ("attrs", "message"),
    [
        ({}, r"does not implement search\(objective, mu, init_mean, generator\)"),
        ({"search": _two_argument_search}, r"search must take \(self, objective, mu, init_mean, generator\)"),
        ({"search": RandomShooting.search, "Options": dict}, "Options must be a dataclass"),
        ({"search": RandomShooting.search, "Options": make_dataclass("O", [])}, "needs a checked"),
        ({"search": RandomShooting.search, "section": int}, "section must be a dataclass or None"),
        (  # was: a TypeError traceback from the config's schema (its section is the dataclass field planner.<name>)
            {"search": RandomShooting.search, "section": ShootingOptions, "name": "my-planner"},
            "planner 'my-planner': a planner with a section needs a name that is a Python identifier",
        ),
    ],
)
def test_an_incomplete_planner_is_refused_at_registration_in_one_line(attrs, message) -> None:
    """A planner without its search, with a search of another signature, or without dataclass Options: refused when
    registered (was: accepted, then a traceback at its first plan, after the seed episodes and the first training)."""
    from pets.planning.planners import PLANNER_CLASSES, register_planner

    cls = type("Incomplete", (BoxPlanner,), {"name": "incomplete", **attrs})
    with pytest.raises(ValueError, match=message) as info:
        register_planner(cls)
    assert "\n" not in str(info.value) and "incomplete" not in PLANNER_CLASSES
