"""Linear state-feedback candidates: the planner searches gains of a policy instead of an action sequence.

With ``planner.candidates=feedback`` a candidate is a gain matrix ``K`` (F, A) (plus a bias row with
``planner.feedback.bias``), and the rollout computes each particle's action from its own predicted state:

    a_t = clip(mid + half * (z(s_t) @ K)),   z(s) = s[features] / scale   (then a 1 appended for the bias row)

``mid`` and ``half`` are the centre and half-range of the action box, so gains are in units of the action range
per feature scale. The law acts around ``s = 0`` (upright and centred for the pendulums); ``scale`` is fixed by
``planner.feedback.scale`` or, if unset, the standard deviation of the replay buffer's observations, refitted after
every training (:meth:`LinearFeedback.fit_scale`). Why: open-loop sequences of an unstable system that survive
the horizon are too rare to sample, closed-loop ones are not (InvertedDoublePendulum, docs/planning.md).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor


class LinearFeedback:
    """The feedback law of the candidates and the scale of its features.

    obs_dim: observation size; features: observation indices fed back (None: all); scale: their fixed scales
    (None: fitted from data with :meth:`fit_scale`, 1 until then); bias: one more row of K acting on a constant 1;
    horizon: steps each candidate policy is rolled out for; action_low, action_high: the action box.
    """

    def __init__(
        self,
        obs_dim: int,
        action_low: object,
        action_high: object,
        *,
        horizon: int,
        features: Sequence[int] | None = None,
        scale: Sequence[float] | None = None,
        bias: bool = False,
        device: torch.device | str | None = None,
    ) -> None:
        idx = list(range(obs_dim)) if features is None else [int(i) for i in features]
        if not idx or any(not 0 <= i < obs_dim for i in idx) or len(set(idx)) != len(idx):
            raise ValueError(f"features must be distinct observation indices in [0, {obs_dim}), got {features!r}")
        if scale is not None and (len(scale) != len(idx) or not all(float(s) > 0 for s in scale)):
            raise ValueError(f"scale must have one positive value per feature ({len(idx)}), got {scale!r}")
        if isinstance(horizon, bool) or not isinstance(horizon, int) or horizon < 1:
            raise ValueError(f"horizon must be a positive int, got {horizon!r}")
        low = torch.as_tensor(action_low, dtype=torch.float32, device=device).reshape(-1)
        high = torch.as_tensor(action_high, dtype=torch.float32, device=device).reshape(-1)
        self.horizon = horizon
        self.bias = bias
        self.features = torch.tensor(idx, dtype=torch.long, device=low.device)
        self.fixed_scale = scale is not None
        self.scale = torch.tensor(scale if scale is not None else [1.0] * len(idx), device=low.device)
        self.low, self.high = low, high
        self.mid, self.half = 0.5 * (low + high), 0.5 * (high - low)

    @property
    def shape(self) -> tuple[int, int]:
        """Shape (rows, act_dim) of one candidate's gains: the planner's (horizon, act_dim) box."""
        return self.features.numel() + int(self.bias), self.low.numel()

    def fit_scale(self, obs: Tensor) -> None:
        """Scales = the features' standard deviations in ``obs`` (N, obs_dim), floored at 1e-3 (no-op if fixed)."""
        if self.fixed_scale or obs.shape[0] < 2:
            return
        std = obs.index_select(-1, self.features.to(obs.device)).std(dim=0)
        self.scale = std.clamp(min=1e-3).to(self.scale)

    def actions(self, gains: Tensor, obs: Tensor) -> Tensor:
        """Actions (B, A) of gains (B, rows, A) at observations (B, obs_dim), clipped to the action box."""
        z = obs.index_select(-1, self.features) / self.scale
        if self.bias:
            z = torch.cat([z, torch.ones_like(z[..., :1])], dim=-1)
        a = self.mid + self.half * torch.bmm(z.unsqueeze(1).to(gains.dtype), gains).squeeze(1)
        return torch.minimum(torch.maximum(a, self.low), self.high)

    def state_dict(self) -> dict[str, Tensor]:
        return {"scale": self.scale.cpu()}

    def load_state_dict(self, state: dict[str, Tensor]) -> None:
        self.scale = state["scale"].to(self.scale)
