"""The group-feature ablation ``delta-groupfeat``: GEM's input features, the delta head's targets."""

from __future__ import annotations

from torch import Tensor

from dynamics.heads import DeltaHead
from envs.layout import ObsLayout
from gem_head.head import GemHead

__all__ = ["GroupFeatureDeltaHead"]


class GroupFeatureDeltaHead(DeltaHead):
    """``delta-groupfeat``: GemHead's inputs (group features), DeltaHead's targets ``next_obs - obs``, Gaussian NLL.

    Inputs are exactly ``GemHead(layout, act_dim).inputs`` (``input_names`` lists them): non-invariant Rn
    coordinates, velocities and other entries, cos/sin of hinge angles, the (cos, sin) pairs, the 9 rotation
    matrix entries of each quaternion, then the action.
    """

    name = "delta-groupfeat"

    def __init__(self, layout: ObsLayout, act_dim: int) -> None:
        super().__init__(layout, act_dim)
        self._features = GemHead(layout, act_dim)
        self.input_dim = self._features.input_dim
        self.input_names: tuple[str, ...] = self._features.input_names

    def inputs(self, obs: Tensor, act: Tensor) -> Tensor:
        """GemHead's network inputs (..., input_dim)."""
        return self._features.inputs(obs, act)
