"""A user's own planner and model for the tests and docs/api.md, registered when the module is imported: name it in
the config key ``imports`` (``imports=[tests.own_planner]``; from your folder, ``imports=[own_planner]``).

- planner ``random_shooting``: uniform samples around the warm start, the best of all iterations; its own section
  ``planner.random_shooting.spread`` (how far it samples, in half-ranges of the action box);
- model ``delta-mine``: PETS' delta model under another name.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from pets.models import MODELS, ModelEntry, gaussian_ensemble, register_model
from pets.planning.planners import BoxPlanner, register_planner


@dataclass
class RandomShootingOptions:
    """The planner's own argument and config section ``planner.random_shooting.*``."""

    spread: float = 1.0

    def checked(self) -> RandomShootingOptions:
        if not 0 < self.spread <= 1:
            raise ValueError(f"spread must be in (0, 1], got {self.spread}")
        return self


@register_planner
class RandomShooting(BoxPlanner):
    """Uniform samples within ``spread`` half-ranges around the warm start; the best one of all iterations."""

    name = "random_shooting"
    Options = RandomShootingOptions
    section = RandomShootingOptions

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


register_model("delta-mine", ModelEntry("PETS' delta model under my name", False, MODELS["delta"].make_head,
                                        gaussian_ensemble))  # fmt: skip
