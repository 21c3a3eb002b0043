"""Per-member training losses of the dynamics models: (E, B, D) batches in, (E,) out."""

from __future__ import annotations

import torch
from torch import Tensor


def gaussian_nll(mean: Tensor, logvar: Tensor, target: Tensor) -> Tensor:
    """Gaussian negative log-likelihood without the constant, averaged over all but the first dim.

    nll = 0.5 * mean((target - mean)^2 * exp(-logvar) + logvar); shape (E,) for (E, B, D) inputs.
    """
    per = (target - mean).pow(2) * torch.exp(-logvar) + logvar
    return 0.5 * per.flatten(1).mean(dim=1)


def mse_loss(mean: Tensor, target: Tensor, scale: Tensor | None = None) -> Tensor:
    """Mean squared error, averaged over all but the first dim: mean(((target - mean) / scale)^2); (E,) for
    (E, B, D); ``scale`` (D,) per-dimension, None for 1."""
    err = target - mean if scale is None else (target - mean) / scale
    return err.pow(2).flatten(1).mean(dim=1)
