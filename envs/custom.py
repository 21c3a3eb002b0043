"""Your own env: an ``EnvSpec`` built from a gymnasium id, a layout and batched torch reward / termination functions,
found by name everywhere an env name is accepted (docs/api.md, "Your own env").

Two ways to name it:

- ``envs.register(spec)``: under ``spec.name``, in this process (the Python API);
- an import path ``"package.module:ATTR"`` (an ``EnvSpec``, or a function returning one), as gymnasium's entry
  points: ``run_pets.py --env package.module:ATTR`` and every other command. The run directory records the path,
  so ``--resume``, ``pets.load_model`` and ``pets.evaluate`` import it again in a new process.
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import torch
from torch import Tensor

from envs.layout import ObsLayout
from envs.spec import EnvSpec, RewardFn, gymnasium_make

_REGISTRY: dict[str, EnvSpec] = {}


def _never(obs: Tensor, act: Tensor, next_obs: Tensor) -> Tensor:
    return torch.zeros(obs.shape[:-1], dtype=torch.bool, device=obs.device)


def custom_spec(
    name: str,
    gym_id: str,
    layout: ObsLayout,
    reward_fn: RewardFn,
    terminated_fn: RewardFn | None = None,
    *,
    env_kwargs: Mapping[str, Any] | None = None,
    params: Mapping[str, Any] | None = None,
    episode_length: int | None = None,
) -> EnvSpec:
    """An :class:`envs.EnvSpec` for the gymnasium env ``gym_id`` (built once here, to read its action bounds, time
    step and episode length, and to check the layout and the functions on a real transition).

    reward_fn, terminated_fn: batched ``(obs, act, next_obs) -> (...)`` torch functions (float reward, bool
    termination; ``None``: never terminates), for any leading dims. ValueError (one line) for a layout that does not
    cover the observation or functions of the wrong shape.
    """
    env = gymnasium_make(gym_id, **dict(env_kwargs or {}))
    obs_space, act_space = env.observation_space, env.action_space
    if len(obs_space.shape) != 1 or len(act_space.shape) != 1:
        raise ValueError(f"{name}: only flat Box observations and actions are supported, got {obs_space}, {act_space}")
    if obs_space.shape[0] != layout.obs_dim:
        raise ValueError(
            f"{name}: the layout covers {layout.obs_dim} observation entries, {gym_id} has {obs_space.shape[0]}"
        )
    dt = float(getattr(env.unwrapped, "dt", 0.0) or 0.0)
    length = episode_length or (env.spec.max_episode_steps if env.spec and env.spec.max_episode_steps else 1000)
    obs, _ = env.reset(seed=0)
    act = act_space.sample()
    nxt, *_ = env.step(act)
    env.close()
    terminated_fn = terminated_fn or _never
    o, a, n = (torch.as_tensor(np.stack([x, x]), dtype=torch.float32) for x in (obs, act, nxt))
    for what, fn, kind in (("reward_fn", reward_fn, "float"), ("terminated_fn", terminated_fn, "bool")):
        out = fn(o, a, n)
        if not isinstance(out, Tensor) or out.shape != (2,):
            shape = tuple(out.shape) if isinstance(out, Tensor) else type(out).__name__
            raise ValueError(
                f"{name}: {what} must return a tensor of shape (batch,) for (batch, dim) inputs, got {shape}"
            )
        if kind == "bool" and out.dtype != torch.bool:
            raise ValueError(f"{name}: terminated_fn must return a bool tensor, got {out.dtype}")
    return EnvSpec(
        name=name,
        gym_id=gym_id,
        layout=layout,
        act_dim=int(act_space.shape[0]),
        action_low=tuple(float(x) for x in act_space.low),
        action_high=tuple(float(x) for x in act_space.high),
        dt=dt,
        episode_length=int(length),
        params=dict(params or {}),
        env_kwargs=dict(env_kwargs or {}),
        reward_error="user-defined",
        reward_fn=reward_fn,
        terminated_fn=terminated_fn,
    )


def register(spec: EnvSpec) -> EnvSpec:
    """Make ``spec`` an env name (``spec.name``) in this process; returns it. A catalogue name cannot be taken."""
    from envs.catalogue import GYM_IDS

    if not isinstance(spec, EnvSpec):
        raise ValueError(f"register takes an envs.EnvSpec, got {type(spec).__name__}")
    if spec.name in GYM_IDS:
        raise ValueError(f"{spec.name!r} is a catalogue env; register yours under another name")
    _REGISTRY[spec.name] = spec
    return spec


def registered(name: str) -> EnvSpec | None:
    """The spec registered or importable as ``name`` (an import path ``module:ATTR`` is imported and registered
    under that path), else None."""
    if name in _REGISTRY:
        return _REGISTRY[name]
    if ":" not in name:
        return None
    module, _, attr = name.partition(":")
    try:
        found: Any = getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as err:
        raise ValueError(f"--env {name}: cannot import {attr!r} from {module!r} ({err})") from None
    spec = found() if isinstance(found, Callable) and not isinstance(found, EnvSpec) else found
    if not isinstance(spec, EnvSpec):
        raise ValueError(
            f"--env {name}: {attr} is a {type(spec).__name__}, not an envs.EnvSpec (or a function of none)"
        )
    spec = dataclasses.replace(spec, name=name)  # the path is the name a run directory records
    _REGISTRY[name] = spec
    return spec
