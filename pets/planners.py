"""The cross-entropy method (CEM) over action sequences, as PETS uses it, and the MPC warm start.

CEM keeps a diagonal Gaussian over the (H, act_dim) action sequence. Each iteration it

1. constrains the variance so that 2 standard deviations stay inside the bounds:
   ``var_c = min(var, (min(mu - lb, ub - mu) / 2)^2)``;
2. samples ``population`` sequences ``mu + sqrt(var_c) * z`` with ``z`` a standard normal
   truncated to [-2, 2] (inverse-CDF sampling, see :func:`truncated_normal`), clipped to the
   bounds against rounding;
3. scores them with the objective (higher is better; NaN counts as -inf) and takes the
   ``elites`` best;
4. smooths: ``mu = alpha * mu + (1 - alpha) * mean(elites)``, ``var = alpha * var + (1 - alpha) * var(elites)``
   (population variance, as ``np.var``).

The initial mean is the middle of the bounds (or the warm start), the initial variance
``(ub - lb)^2 / 16``. The result is the final CEM mean ``mu`` (the smoothed elite mean of the
last iteration, what PETS returns), or with ``return_mean_elites=False`` the best sample seen.
The planner keeps no state between calls other than its configuration.
"""
from __future__ import annotations

import math
import numbers
from typing import Callable

import torch
from torch import Tensor

def truncated_normal(shape: tuple[int, ...], mean: Tensor, std: Tensor, *, bound: float = 2.0,
                     generator: torch.Generator | None = None) -> Tensor:
    """Samples of N(mean, std^2) truncated to ``mean +- bound * std``, shape ``shape + mean.shape``.

    Inverse-CDF method: ``u ~ U(Phi(-bound), Phi(bound))``, ``z = sqrt(2) erfinv(2 u - 1)``
    (so ``z = Phi^-1(u)`` is a standard normal truncated to [-bound, bound]), clamped to
    [-bound, bound] against rounding; result ``mean + std * z``. ``mean`` and ``std`` broadcast.
    Rejection-free, so the cost is fixed and all randomness comes from ``generator``.
    """
    if not bound > 0:
        raise ValueError(f"bound must be > 0 standard deviations, got {bound}")
    mean, std = torch.broadcast_tensors(mean, std)
    lo = 0.5 * math.erfc(bound / math.sqrt(2.0))
    u = torch.rand(tuple(shape) + tuple(mean.shape), generator=generator, device=mean.device, dtype=mean.dtype)
    u = lo + (1.0 - 2.0 * lo) * u
    z = math.sqrt(2.0) * torch.erfinv(2.0 * u - 1.0)
    z = z.clamp(-bound, bound)
    return mean + std * z


def _as_bounds(low: object, high: object, device: torch.device | str | None,
               dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """Validated (act_dim,) bound tensors on ``device`` (checked on the host, before the move)."""
    lb = torch.as_tensor(low).detach().to("cpu", torch.float64).reshape(-1)
    ub = torch.as_tensor(high).detach().to("cpu", torch.float64).reshape(-1)
    if lb.shape != ub.shape or lb.numel() == 0:
        raise ValueError(f"action_low and action_high must be non-empty and of the same length, "
                         f"got {tuple(lb.shape)} and {tuple(ub.shape)}")
    if not (torch.isfinite(lb).all() and torch.isfinite(ub).all()):
        raise ValueError("action bounds must be finite")
    if not (lb < ub).all():
        raise ValueError(f"every action_low must be < action_high, got low={lb.tolist()} high={ub.tolist()}")
    return lb.to(device=device, dtype=dtype), ub.to(device=device, dtype=dtype)


def shift_plan(plan: Tensor, action_low: object, action_high: object) -> Tensor:
    """Warm start for the next MPC step: drop the first action, append the middle of the bounds.

    plan (H, act_dim) -> (H, act_dim): ``[plan[1], ..., plan[H-1], (low + high) / 2]``.
    """
    if plan.dim() != 2:
        raise ValueError(f"plan must have shape (H, act_dim), got {tuple(plan.shape)}")
    # No value checks here (they would synchronise with the device every MPC step): the planner validates bounds.
    lb = torch.as_tensor(action_low, device=plan.device, dtype=plan.dtype).reshape(-1)
    ub = torch.as_tensor(action_high, device=plan.device, dtype=plan.dtype).reshape(-1)
    if lb.numel() != plan.shape[1] or ub.numel() != plan.shape[1]:
        raise ValueError(f"plan has act_dim {plan.shape[1]} but the bounds have {lb.numel()} and {ub.numel()} entries")
    mid = 0.5 * (lb + ub)
    return torch.cat([plan[1:], mid.unsqueeze(0)], dim=0)


class CEMPlanner:
    """Cross-entropy method over (horizon, act_dim) action sequences within box bounds.

    action_low, action_high: (act_dim,) finite bounds, low < high.
    horizon, population, iterations: positive ints.
    elites: a count (int, 1..population) or a ratio (float in (0, 1]; count = ceil(ratio * population)).
    alpha: smoothing in [0, 1]: ``mu = alpha * mu + (1 - alpha) * elite_mean`` (same for var).
    epsilon: PETS's early stop: stop iterating once every variance is below it (0 disables it;
      when enabled it costs one host synchronisation per iteration).
    return_mean_elites: return the final CEM mean (PETS), else the best sample seen.
    device, dtype: where the samples live (the objective gets tensors there).
    """

    def __init__(self, action_low: object, action_high: object, *, horizon: int, population: int,
                 elites: int | float = 0.1, iterations: int = 5, alpha: float = 0.1, epsilon: float = 0.0,
                 return_mean_elites: bool = True, device: torch.device | str | None = None,
                 dtype: torch.dtype = torch.float32) -> None:
        for name, val in (("horizon", horizon), ("population", population), ("iterations", iterations)):
            if isinstance(val, bool) or not isinstance(val, int) or val < 1:
                raise ValueError(f"{name} must be a positive int, got {val!r}")
        if isinstance(elites, bool) or not isinstance(elites, numbers.Real):
            raise ValueError(f"elites must be an int count or a float ratio, got {elites!r}")
        if isinstance(elites, numbers.Integral):
            if not 1 <= elites <= population:
                raise ValueError(f"elites as a count must be in [1, population={population}], got {elites}")
            num_elites = int(elites)
        else:
            if not 0.0 < elites <= 1.0:
                raise ValueError(f"elites as a ratio must be in (0, 1], got {elites}")
            num_elites = min(population, max(1, math.ceil(round(float(elites) * population, 4))))
        if not 0.0 <= alpha <= 1.0:
            raise ValueError(f"alpha must be in [0, 1], got {alpha}")
        if not epsilon >= 0.0:
            raise ValueError(f"epsilon must be >= 0, got {epsilon}")
        self.low, self.high = _as_bounds(action_low, action_high, device, dtype)
        self.act_dim = self.low.numel()
        self.horizon = horizon
        self.population = population
        self.num_elites = num_elites
        self.iterations = iterations
        self.alpha = float(alpha)
        self.epsilon = float(epsilon)
        self.return_mean_elites = return_mean_elites
        self.device = self.low.device
        self.dtype = dtype

    def plan(self, objective: Callable[[Tensor], Tensor], init_mean: Tensor | None = None,
             generator: torch.Generator | None = None) -> Tensor:
        """Optimise ``objective`` ((N, H, act_dim) -> (N,), higher is better); returns (H, act_dim) in bounds.

        init_mean: warm start (H, act_dim), clipped to the bounds; default the middle of the bounds.
        generator: source of all the randomness (on the planner's device).
        """
        h, a = self.horizon, self.act_dim
        lb, ub = self.low, self.high
        if generator is not None and generator.device.type != self.device.type:
            raise ValueError(f"generator is on {generator.device}, the planner on {self.device}")
        if init_mean is None:
            mu = (0.5 * (lb + ub)).expand(h, a).clone()
        else:
            mu = torch.as_tensor(init_mean, device=self.device, dtype=self.dtype)
            if mu.shape != (h, a):
                raise ValueError(f"init_mean must have shape ({h}, {a}), got {tuple(mu.shape)}")
            mu = torch.minimum(torch.maximum(mu, lb), ub)
        var = ((ub - lb) ** 2 / 16.0).expand(h, a).clone()
        best_value = torch.full((), -math.inf, device=self.device, dtype=self.dtype)
        best = mu.clone()

        for _ in range(self.iterations):
            dist = torch.minimum(mu - lb, ub - mu)
            var_c = torch.minimum(var, (0.5 * dist) ** 2)
            samples = truncated_normal((self.population,), mu, var_c.sqrt(), generator=generator)
            samples = torch.minimum(torch.maximum(samples, lb), ub)
            values = objective(samples)
            if values.shape != (self.population,):
                raise ValueError(f"objective must return shape ({self.population},), got {tuple(values.shape)}")
            values = torch.nan_to_num(values.to(self.dtype), nan=-math.inf)
            top, idx = torch.topk(values, self.num_elites)
            elite = samples.index_select(0, idx)
            if not self.return_mean_elites:
                better = top[0] > best_value
                best = torch.where(better, elite[0], best)
                best_value = torch.where(better, top[0], best_value)
            mu = self.alpha * mu + (1.0 - self.alpha) * elite.mean(dim=0)
            var = self.alpha * var + (1.0 - self.alpha) * elite.var(dim=0, unbiased=False)
            if self.epsilon > 0.0 and bool(var.max() < self.epsilon):
                break

        out = mu if self.return_mean_elites else best
        return torch.minimum(torch.maximum(out, lb), ub)
