"""Environment catalogue: the eight gymnasium MuJoCo v5 tasks with layouts, rewards and terminations.

>>> import envs
>>> spec = envs.get("HalfCheetah-v5")          # also "halfcheetah", "half_cheetah", "half-cheetah"
>>> env = spec.make()                           # gymnasium env whose obs matches spec.layout
>>> r = spec.reward(obs, act, next_obs)         # batched torch, any leading dims / dtype / device

Measured agreement with the simulator: docs/envs.md.
"""

from __future__ import annotations

from functools import cache
from typing import Any

from envs.catalogue import GYM_IDS, build, catalogue_key
from envs.custom import custom_spec, file_name, register, registered
from envs.layout import Group, ObsLayout
from envs.render import select_gl_backend
from envs.spec import AppendObservation, EnvSpec

select_gl_backend()  # headless MUJOCO_GL before anything imports mujoco (none of the imports above does)

__all__ = [
    "names",
    "get",
    "canonical_name",
    "register",
    "custom_spec",
    "file_name",
    "EnvSpec",
    "ObsLayout",
    "Group",
    "AppendObservation",
]


def names() -> list[str]:
    """The canonical env names, in catalogue order."""
    return list(GYM_IDS)


def canonical_name(name: str) -> str:
    """Canonical name of ``name``: case, ``_``, ``-``, spaces and a ``-v5`` suffix are ignored.

    Raises ValueError (listing the valid names) for anything else.
    """
    if not isinstance(name, str):
        raise ValueError(f"env name must be a string, got {type(name).__name__}; valid: {', '.join(names())}")
    if registered(name) is not None:  # your own env: registered, or an import path module:ATTR
        return name
    key = catalogue_key(name)
    if key is None:
        valid = ", ".join(f"{n} ({g})" for n, g in GYM_IDS.items())
        raise ValueError(
            f"unknown env {name!r}; valid names (or gymnasium ids): {valid}; or your own as package.module:ATTR"
        )
    return key


@cache
def _default(name: str) -> EnvSpec:
    return build(name, {})


def get(name: str, **env_kwargs: Any) -> EnvSpec:
    """The spec of env ``name``; ``env_kwargs`` override gymnasium constructor defaults (e.g. ``ctrl_cost_weight``).

    The spec's reward and termination read their constants from the env built with those kwargs.
    """
    own = registered(name) if isinstance(name, str) else None
    if own is not None:
        if env_kwargs:
            raise ValueError(f"{name}: env kwargs are fixed when your spec is built (envs.custom_spec(env_kwargs=...))")
        return own
    key = canonical_name(name)
    return build(key, env_kwargs) if env_kwargs else _default(key)
