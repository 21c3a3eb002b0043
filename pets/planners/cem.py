"""CEM over action sequences, as PETS uses it (the algorithm: the ``pets.planners`` docstring)."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from pets.planners.base import (
    BoxPlanner,
    check_generator,
    check_planned,
    check_real,
    elite_count,
    initial_mean,
    no_finite,
    truncated_normal,
)


class CEMPlanner(BoxPlanner):
    """Cross-entropy method over (horizon, act_dim) action sequences within box bounds.

    action_low, action_high: (act_dim,) finite bounds, low < high.
    horizon, population, iterations: positive ints.
    elites: a count (int, 1..population) or a ratio (float in (0, 1]; count = ceil(ratio * population)).
    alpha: smoothing in [0, 1]: ``mu = alpha * mu + (1 - alpha) * elite_mean`` (same for var).
    epsilon: PETS's early stop: stop iterating once every variance is below it (0 disables it;
      when enabled it costs one host synchronisation per iteration).
    return_mean_elites: return the final CEM mean (PETS), else the best sample seen.
    init_std: the samples' std at the start of every call (a number, in the bounds' units); None: a quarter of the
      box width, ``(high - low) / 4`` (PETS).
    device, dtype: where the samples live (the objective gets tensors there).
    """

    uses_elites = True

    def __init__(
        self,
        action_low: object,
        action_high: object,
        *,
        horizon: int,
        population: int,
        elites: int | float = 0.1,
        iterations: int = 5,
        alpha: float = 0.1,
        epsilon: float = 0.0,
        return_mean_elites: bool = True,
        init_std: float | None = None,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        common = dict(horizon=horizon, population=population, iterations=iterations, alpha=alpha)
        super().__init__(action_low, action_high, **common, device=device, dtype=dtype)
        self.num_elites = elite_count(elites, population)
        if not epsilon >= 0.0:
            raise ValueError(f"epsilon must be >= 0, got {epsilon}")
        self.epsilon = float(epsilon)
        self.return_mean_elites = return_mean_elites
        self.init_std = None if init_std is None else check_real("init_std", init_std, 0.0, math.inf, low_open=True)

    def plan(
        self,
        objective: Callable[[Tensor], Tensor],
        init_mean: Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> Tensor:
        """Optimise ``objective`` ((N, H, act_dim) -> (N,), higher is better); returns (H, act_dim) in bounds.

        init_mean: warm start (H, act_dim), clipped to the bounds; default the middle of the bounds.
        generator: source of all the randomness (on the planner's device).
        """
        h, a = self.horizon, self.act_dim
        lb, ub = self.low, self.high
        check_generator(generator, self.device)
        mu = initial_mean(init_mean, lb, ub, h, a)
        if self.init_std is None:
            var = ((ub - lb) ** 2 / 16.0).expand(h, a).clone()
        else:
            var = torch.full((h, a), self.init_std**2, device=self.device, dtype=self.dtype)
        best_value = torch.full((), -math.inf, device=self.device, dtype=self.dtype)
        best = mu.clone()
        failed = torch.zeros((), dtype=torch.bool, device=self.device)

        for _ in range(self.iterations):
            dist = torch.minimum(mu - lb, ub - mu)
            var_c = torch.minimum(var, (0.5 * dist) ** 2)
            samples = truncated_normal((self.population,), mu, var_c.sqrt(), generator=generator)
            samples = torch.minimum(torch.maximum(samples, lb), ub)
            values = objective(samples)
            if values.shape != (self.population,):
                raise ValueError(f"objective must return shape ({self.population},), got {tuple(values.shape)}")
            values = values.to(self.dtype)
            failed = failed | no_finite(values)
            values = torch.nan_to_num(values, nan=-math.inf)
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

        check_planned(failed)
        out = mu if self.return_mean_elites else best
        return torch.minimum(torch.maximum(out, lb), ub)
