"""A user's own env for the tests and docs/api.md: gymnasium's Pendulum-v1, with GEM composing its pole on SO(2).

Observation (cos theta, sin theta, theta_dot); reward -(theta^2 + 0.1 theta_dot^2 + 0.001 u^2) of the state
before the step (theta in (-pi, pi]) and the action clipped to +-2, as Pendulum-v1 computes it; it never terminates.
"""

from __future__ import annotations

import torch
from torch import Tensor

import envs
from envs import Group, ObsLayout


def pendulum_reward(obs: Tensor, act: Tensor, next_obs: Tensor) -> Tensor:
    theta = torch.atan2(obs[..., 1], obs[..., 0])
    u = act[..., 0].clamp(-2.0, 2.0)
    return -(theta**2 + 0.1 * obs[..., 2] ** 2 + 0.001 * u**2)


def pendulum() -> envs.EnvSpec:
    layout = ObsLayout(obs_dim=3, groups=(Group("pole", "SO2_cossin", (0, 1)),), velocities=(2,))
    return envs.custom_spec("pendulum", "Pendulum-v1", layout, pendulum_reward)


#: ``--env tests.custom_envs:PENDULUM`` (a function returning the spec works as well: ``tests.custom_envs:pendulum``).
PENDULUM = pendulum()


def wrapped_pendulum() -> envs.EnvSpec:
    """InvertedPendulum with its hinge of the kind ``SO2_wrapped``, a codec of one's own (tests/own_codec.py), which
    this module does not import: ``--env tests.custom_envs:wrapped_pendulum imports=[tests.own_codec]``."""
    ip = envs.get("invertedpendulum")
    layout = ObsLayout(4, (Group("cart", "Rn", (0,)), Group("hinge", "SO2_wrapped", (1,))), velocities=(2, 3))
    return envs.custom_spec("ip-wrapped", "InvertedPendulum-v5", layout, ip.reward, ip.terminated)
