"""Dynamics heads: the swappable part between observations and the network (the delta heads live here).

Data flow:  (obs, act) --inputs--> ensemble --target sample--> next_obs(obs, sample)

A head turns (obs, act) into network inputs, (obs, next_obs) into training targets,
and (obs, predicted target) back into a next observation. A ``dynamics.model.DynamicsModel`` joins
a head and a network; everything else talks to the model.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import torch
from torch import Tensor

from dynamics.losses import gaussian_nll, mse_loss
from envs.layout import ObsLayout


class DynamicsHead(ABC):
    """Base class. Subclasses set ``name``, ``input_dim``, ``target_dim`` and implement the three maps.

    ``deterministic`` heads (``DeterministicDeltaHead``, ``gem_head.two_stage``) go with a model that has no
    predictive variance: their ``loss`` ignores ``logvar`` (it is a constant that makes sampling noise zero).
    """

    name: str = "base"
    deterministic: bool = False
    input_dim: int
    target_dim: int

    def __init__(self, layout: ObsLayout, act_dim: int) -> None:
        self.layout = layout
        self.obs_dim = layout.obs_dim
        self.act_dim = act_dim

    @abstractmethod
    def inputs(self, obs: Tensor, act: Tensor) -> Tensor:
        """Network inputs, shape (..., input_dim)."""

    @abstractmethod
    def targets(self, obs: Tensor, next_obs: Tensor) -> Tensor:
        """Training targets, shape (..., target_dim)."""

    @abstractmethod
    def next_obs(self, obs: Tensor, target: Tensor) -> Tensor:
        """Next observation from a (predicted or sampled) target, shape (..., obs_dim)."""

    def loss(
        self, mean: Tensor, logvar: Tensor, target: Tensor, obs: Tensor, next_obs: Tensor, scale: Tensor | None = None
    ) -> Tensor:
        """Per-member training loss, shape (E,), for (E, B, .) batches. Default: Gaussian NLL.

        ``scale`` (target_dim,): the model's target std (the trainer passes it). Squared-error losses divide
        each slot's error by it, so that every slot weighs the same; the NLL does not need it (its gradients
        are the same in standardised and in target units).
        """
        return gaussian_nll(mean, logvar, target)


class DeltaHead(DynamicsHead):
    """The PETS baseline: predict next_obs - obs; position-invariant coordinates are not inputs.

    Derived entries of the layout (``ObsLayout.derived``) are neither inputs nor targets: ``next_obs``
    carries them over from ``obs``.
    """

    name = "delta"

    def __init__(self, layout: ObsLayout, act_dim: int) -> None:
        super().__init__(layout, act_dim)
        self._keep = torch.tensor(layout.model_indices, dtype=torch.long)
        self._predicted = None if not layout.derived else torch.tensor(layout.predicted_indices, dtype=torch.long)
        self.input_dim = len(layout.model_indices) + act_dim
        self.target_dim = len(layout.predicted_indices)

    def inputs(self, obs: Tensor, act: Tensor) -> Tensor:
        keep = self._keep.to(obs.device)
        return torch.cat([obs.index_select(-1, keep), act], dim=-1)

    def targets(self, obs: Tensor, next_obs: Tensor) -> Tensor:
        if self._predicted is None:
            return next_obs - obs
        idx = self._predicted.to(obs.device)
        return next_obs.index_select(-1, idx) - obs.index_select(-1, idx)

    def next_obs(self, obs: Tensor, target: Tensor) -> Tensor:
        if self._predicted is None:
            return obs + target
        idx = self._predicted.to(obs.device)
        batch = torch.broadcast_shapes(obs.shape[:-1], target.shape[:-1])
        out = obs.expand(*batch, self.obs_dim).to(torch.promote_types(obs.dtype, target.dtype), copy=True)
        return out.index_add_(-1, idx, target.expand(*batch, self.target_dim).to(out.dtype))


class DeterministicDeltaHead(DeltaHead):
    """``delta-det``: DeltaHead's inputs, targets (``next_obs - obs``) and decoding; MSE loss, no variance."""

    name = "delta-det"
    deterministic = True

    def loss(
        self, mean: Tensor, logvar: Tensor, target: Tensor, obs: Tensor, next_obs: Tensor, scale: Tensor | None = None
    ) -> Tensor:
        """Per-member mean squared error (E,) of the predicted deltas, each divided by ``scale``; ``logvar`` is
        ignored."""
        return mse_loss(mean, target, scale)
