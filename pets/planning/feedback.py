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

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from pets.planning.planners import PLANNER_CLASSES


@dataclass
class FeedbackConfig:
    """``planner.feedback.*``: linear state-feedback candidates (``planner.candidates=feedback``)."""

    features: list[int] | None = None  # observation indices fed back; null: all
    scale: list[float] | None = None  # their fixed scales; null: the replay buffer's std, refitted every training
    bias: bool = False  # a constant term per action besides the gains
    gain_bound: float = 10.0  # |gain| bound, in action half-ranges per feature scale
    gain_std: float = 1.0  # the gains' sampling std at every plan (CEM's initial std; MPPI's sigma)


def check_feedback(p: Any) -> None:
    """The settings of ``planner.candidates=feedback`` in the config's ``planner`` section ``p``: a ValueError in
    one line naming the key. (The observation indices are checked against the env's observation size when the law
    is built, :class:`LinearFeedback`.)"""
    f = p.feedback
    for key in ("gain_bound", "gain_std"):
        if not math.isfinite(f[key]) or f[key] <= 0:
            raise ValueError(f"planner.feedback.{key} must be a finite number > 0, got {f[key]}")
    can = [  # the planners that search gains (pets.planning.planners.BoxPlanner.gain_options)
        name for name, cls in PLANNER_CLASSES.items() if cls.gain_options(f.gain_bound, f.gain_std) is not None
    ]
    if p.name not in can:
        raise ValueError(
            f"planner.candidates=feedback needs planner.name {' or '.join(can)}, got {p.name!r} "
            f"({PLANNER_CLASSES[p.name].gains_note})"
        )
    if p.replan_every != 1:
        raise ValueError(
            f"planner.candidates=feedback replans every step: planner.replan_every must be 1, got {p.replan_every}"
        )
    if f.features is not None and len(f.features) == 0:
        raise ValueError("planner.feedback.features must be null (all observations) or a non-empty list of indices")
    if f.scale is not None:
        n = len(f.features) if f.features is not None else None
        if (n is not None and len(f.scale) != n) or not all(math.isfinite(v) and v > 0 for v in f.scale):
            raise ValueError(
                f"planner.feedback.scale must be null or one finite value > 0 per feature, got {list(f.scale)}"
            )


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
