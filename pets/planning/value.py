"""A learned terminal value for MPC: ``V(obs)``, fitted to the discounted real returns that followed each state.

PETS scores a candidate by its rewards over the planning horizon only. Where the reward is flat while the
system survives (InvertedPendulum's alive bonus), every candidate that survives the horizon ties, and what
happens after it (the cart reaching the end of its rail) is invisible; docs/planning.md has the evidence.
With ``value.enabled`` the planner scores ``sum of horizon rewards + V(final state)`` for every
particle that did not terminate (an estimate of the whole episode's return, not a shaped objective).

Targets: Monte-Carlo returns-to-go ``G_t = r_t + discount * G_{t+1}`` of the real episodes in the replay
buffer (rewards recomputed with the env's exact reward function); an episode that ended by termination ends
with ``G = 0`` after its last reward, one cut short (time limit, or the data so far) is bootstrapped with
the value before this fit.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from dynamics.networks import column_mean_std


@dataclass
class ValueConfig:
    """``value.*``: a learned terminal value for the planner (:class:`ValueFunction`; docs/planning.md)."""

    # true: a candidate's return is its horizon rewards plus V(final state) for particles that did not terminate,
    # V fitted whenever the model trains to the discounted real returns-to-go. false: the horizon rewards only (PETS).
    enabled: bool = False
    discount: float = 0.99  # of the returns V estimates: they look about 1 / (1 - discount) steps ahead
    hidden_size: int = 64
    steps: int = 1000  # Adam steps (batch 256) per fit, continuing from the last fit


def episode_ends(obs: Tensor, next_obs: Tensor) -> Tensor:
    """Bool (N,): transition ``i`` is the last of its episode (the buffer's next row does not continue it).

    The replay buffer stores episodes back to back; within an episode ``obs[i + 1]`` is ``next_obs[i]`` exactly
    (the same float32 copy of the env's observation), so any other row after ``i`` starts a new episode.
    """
    ends = torch.ones(len(obs), dtype=torch.bool, device=obs.device)
    if len(obs) > 1:
        ends[:-1] = (obs[1:] != next_obs[:-1]).any(dim=-1)
    return ends


def returns_to_go(rewards: Tensor, ends: Tensor, bootstrap: Tensor, discount: float) -> Tensor:
    """Discounted returns-to-go (N,) of back-to-back episodes.

    ``G_i = rewards_i + discount * (G_{i+1} if not ends_i else bootstrap_i)``; ``bootstrap`` (N,) is the
    value after an episode's last transition (0 for a termination), read only where ``ends``.
    """
    r, e, b = rewards.tolist(), ends.tolist(), bootstrap.tolist()
    values, acc = [0.0] * len(r), 0.0
    for i in range(len(r) - 1, -1, -1):  # one pass from the end (a Python loop: ~0.1 s per 10^5 transitions)
        acc = r[i] + discount * (b[i] if e[i] else acc)
        values[i] = acc
    return torch.tensor(values, dtype=rewards.dtype, device=rewards.device)


class ValueFunction(nn.Module):
    """``V(obs)`` in reward units: an MLP (SiLU) on standardised observations, standardised output."""

    def __init__(self, obs_dim: int, *, hidden_size: int = 64, num_layers: int = 2, discount: float = 0.99) -> None:
        super().__init__()
        if not 0.0 < discount < 1.0:
            raise ValueError(f"discount must be in (0, 1), got {discount!r}")
        self.discount = discount
        layers: list[nn.Module] = []
        width = obs_dim
        for _ in range(num_layers):
            layers += [nn.Linear(width, hidden_size), nn.SiLU()]
            width = hidden_size
        layers.append(nn.Linear(width, 1))
        self.net = nn.Sequential(*layers)
        self.register_buffer("obs_mean", torch.zeros(obs_dim))
        self.register_buffer("obs_std", torch.ones(obs_dim))
        self.register_buffer("value_mean", torch.zeros(()))
        self.register_buffer("value_std", torch.ones(()))
        self.register_buffer("fitted", torch.zeros((), dtype=torch.bool))

    def forward(self, obs: Tensor) -> Tensor:
        """V of observations ``(..., obs_dim)``, shape ``(...)``; 0 before the first :meth:`fit`."""
        x = (obs.to(self.obs_mean.dtype) - self.obs_mean) / self.obs_std
        v = self.net(x).squeeze(-1) * self.value_std + self.value_mean
        return torch.where(self.fitted, v, torch.zeros_like(v)).to(obs.dtype)

    def fit(
        self,
        obs: Tensor,
        targets: Tensor,
        generator: torch.Generator,
        *,
        steps: int = 1000,
        batch_size: int = 256,
        lr: float = 1e-3,
    ) -> float:
        """Regress ``V(obs)`` on ``targets`` (N,) with Adam for ``steps`` minibatch steps (continuing from the
        current weights); returns the final mean squared error in reward units over all the data."""
        mean, std = column_mean_std(obs)
        self.obs_mean.copy_(mean)
        self.obs_std.copy_(std)
        self.value_mean.copy_(targets.mean())
        self.value_std.copy_(targets.std().clamp(min=1e-6) if len(targets) > 1 else torch.ones(()))
        self.fitted.fill_(True)
        x = (obs - self.obs_mean) / self.obs_std
        y = (targets - self.value_mean) / self.value_std
        opt = torch.optim.Adam(self.net.parameters(), lr=lr)
        with torch.enable_grad():
            for _ in range(steps):
                idx = torch.randint(len(x), (min(batch_size, len(x)),), generator=generator, device=generator.device)
                loss = (self.net(x[idx]).squeeze(-1) - y[idx]).square().mean()
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
        with torch.no_grad():
            return float((self(obs) - targets).square().mean())
