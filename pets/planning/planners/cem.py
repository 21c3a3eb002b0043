"""CEM over action sequences, as PETS uses it (the algorithm: the ``pets.planning.planners`` docstring)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from pets.planning.planners.base import BoxPlanner, Objective, check_real, truncated_normal


@dataclass
class CEMOptions:
    """CEM's own arguments (no config section: PETS' settings; feedback candidates set ``init_std``)."""

    epsilon: float = 0.0
    return_mean_elites: bool = True
    init_std: float | None = None

    def checked(self) -> CEMOptions:
        """The arguments validated (a ValueError naming the first out of range)."""
        init_std = self.init_std
        return CEMOptions(
            check_real("epsilon", self.epsilon, 0.0, math.inf),
            bool(self.return_mean_elites),
            None if init_std is None else check_real("init_std", init_std, 0.0, math.inf, low_open=True),
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

    name = "cem"
    Options = CEMOptions
    uses_elites = True
    faster = "planner.name=icem (about 30% fewer)"

    @classmethod
    def gain_options(cls, gain_bound: float, gain_std: float) -> dict[str, float] | None:
        """Gains are sampled with ``gain_std`` at the start of every call."""
        return {"init_std": gain_std}

    def search(
        self, objective: Objective, mu: Tensor, init_mean: Tensor | None, generator: torch.Generator | None
    ) -> Tensor:
        """CEM's iterations (the ``pets.planning.planners`` docstring): the final mean, or the best sample seen."""
        h, a = self.horizon, self.act_dim
        lb, ub = self.low, self.high
        if self.init_std is None:
            var = ((ub - lb) ** 2 / 16.0).expand(h, a).clone()
        else:
            var = torch.full((h, a), self.init_std**2, device=self.device, dtype=self.dtype)
        best_value = torch.full((), -math.inf, device=self.device, dtype=self.dtype)
        best = mu.clone()
        for _ in range(self.iterations):
            dist = torch.minimum(mu - lb, ub - mu)
            var_c = torch.minimum(var, (0.5 * dist) ** 2)
            samples = self.clip(truncated_normal((self.population,), mu, var_c.sqrt(), generator=generator))
            values = torch.nan_to_num(objective(samples), nan=-math.inf)
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
        return mu if self.return_mean_elites else best
