"""The training data's random holdout split and per-member bootstrap resamples (:mod:`pets.learning.trainer`)."""

from __future__ import annotations

import torch
from torch import Tensor


def bootstrap_indices(n: int, ensemble_size: int, generator: torch.Generator) -> Tensor:
    """Per-member bootstrap resamples: (ensemble_size, n) indices drawn uniformly with replacement from [0, n)."""
    if n < 1 or ensemble_size < 1:
        raise ValueError(f"bootstrap needs n >= 1 and ensemble_size >= 1, got n={n}, ensemble_size={ensemble_size}")
    return torch.randint(n, (ensemble_size, n), generator=generator, device=generator.device)


def split_holdout(n: int, holdout_ratio: float, max_holdout: int, generator: torch.Generator) -> tuple[Tensor, Tensor]:
    """Random (train, holdout) index split: holdout size min(int(n * ratio), max_holdout), empty if that is 0
    or would leave no training sample."""
    n_hold = min(int(n * holdout_ratio), max_holdout)
    if n_hold < 1 or n - n_hold < 1:
        n_hold = 0
    perm = torch.randperm(n, generator=generator, device=generator.device)
    return perm[n_hold:], perm[:n_hold]
