"""Replay buffer of real transitions (float32), growing as trials are collected."""

from __future__ import annotations

import numpy as np
import torch


class ReplayBuffer:
    def __init__(self, obs_dim: int, act_dim: int) -> None:
        self.obs = np.zeros((0, obs_dim), np.float32)
        self.act = np.zeros((0, act_dim), np.float32)
        self.next_obs = np.zeros((0, obs_dim), np.float32)

    def __len__(self) -> int:
        return len(self.obs)

    def add_episode(self, obs: np.ndarray, act: np.ndarray, next_obs: np.ndarray) -> None:
        """Append a batch of transitions (n, .)."""
        self.obs = np.concatenate([self.obs, np.asarray(obs, np.float32)])
        self.act = np.concatenate([self.act, np.asarray(act, np.float32)])
        self.next_obs = np.concatenate([self.next_obs, np.asarray(next_obs, np.float32)])

    def tensors(self, device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return tuple(torch.as_tensor(a, device=device) for a in (self.obs, self.act, self.next_obs))

    def state_dict(self) -> dict[str, np.ndarray]:
        return {"obs": self.obs, "act": self.act, "next_obs": self.next_obs}

    def load_state_dict(self, d: dict[str, np.ndarray]) -> None:
        self.obs, self.act, self.next_obs = d["obs"], d["act"], d["next_obs"]
