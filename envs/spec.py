"""`EnvSpec`: one environment of the catalogue (how to build it, its layout, reward and termination).

The reward and termination functions are batched torch functions of ``(obs, act, next_obs)``
over any leading dims, float dtype and device. Their constants are read from the
gymnasium env that ``make()`` builds (its defaults plus the overrides given to ``envs.get``),
so they cannot drift from the simulator.
"""

from __future__ import annotations

import contextlib
import importlib
import inspect
import warnings
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import gymnasium
import numpy as np
from torch import Tensor

from envs.layout import ObsLayout

RewardFn = Callable[[Tensor, Tensor, Tensor], Tensor]

#: Env constructor kwargs that never change observations, rewards or terminations.
HARMLESS_KWARGS = frozenset({"default_camera_config", "reset_noise_scale"})


class ReadOnlyDict(dict):
    """A dict that refuses mutation (and still pickles, unlike ``types.MappingProxyType``)."""

    def _refuse(self, *args: Any, **kwargs: Any) -> None:
        raise TypeError("EnvSpec constants are read-only; build a new spec with envs.get(name, **kwargs)")

    __setitem__ = __delitem__ = clear = pop = popitem = setdefault = update = __ior__ = _refuse  # type: ignore[assignment]

    def __reduce__(self) -> tuple:
        return (ReadOnlyDict, (dict(self),))


class AppendObservation(gymnasium.ObservationWrapper):
    """Appends ``extra(env.unwrapped)`` (a 1-D float array) to every observation.

    Used where the env's reward reads a quantity the observation lacks (Ant's main-body x
    as MuJoCo's ``xpos`` holds it at the end of a step, Humanoid's mass-centre x).
    """

    def __init__(self, env: gymnasium.Env, extra: Callable[[Any], np.ndarray], names: tuple[str, ...]) -> None:
        super().__init__(env)
        self._extra = extra
        self.appended_names = names
        low, high = env.observation_space.low, env.observation_space.high
        k = len(names)
        self.observation_space = gymnasium.spaces.Box(
            low=np.concatenate([low, np.full(k, -np.inf)]),
            high=np.concatenate([high, np.full(k, np.inf)]),
            dtype=env.observation_space.dtype,
        )

    def observation(self, observation: np.ndarray) -> np.ndarray:
        extra = np.asarray(self._extra(self.env.unwrapped), dtype=observation.dtype).reshape(-1)
        return np.concatenate([observation, extra])


@dataclass(frozen=True, eq=False)
class EnvSpec:
    """A catalogue entry.

    Fields: ``name`` (canonical), ``gym_id`` (``"HalfCheetah-v5"``), ``layout`` (index-by-index
    observation groups), ``act_dim``, ``action_low``/``action_high`` (tuples), ``dt`` (seconds per
    env step), ``episode_length`` (max steps), ``params`` (the env constants the reward and
    termination use, read from the built env), ``env_kwargs`` (what ``make`` passes to
    ``gymnasium.make``), ``reward_error`` (documented bound of ``reward`` vs the simulator;
    "exact" means equal up to float rounding).
    """

    name: str
    gym_id: str
    layout: ObsLayout
    act_dim: int
    action_low: tuple[float, ...]
    action_high: tuple[float, ...]
    dt: float
    episode_length: int
    params: Mapping[str, Any]
    env_kwargs: Mapping[str, Any]
    reward_error: str
    reward_fn: RewardFn = field(repr=False, compare=False)
    terminated_fn: RewardFn = field(repr=False, compare=False)
    wrap: Callable[[gymnasium.Env], gymnasium.Env] | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "params", ReadOnlyDict(self.params))
        object.__setattr__(self, "env_kwargs", ReadOnlyDict(self.env_kwargs))

    @property
    def obs_dim(self) -> int:
        return self.layout.obs_dim

    def make(self, **kwargs: Any) -> gymnasium.Env:
        """Build the gymnasium v5 env (with this spec's kwargs and observation wrapper).

        Extra kwargs pass through to ``gymnasium.make`` (``render_mode``, ``width``,
        ``max_episode_steps``, ...). Env constructor kwargs that change rewards, terminations or
        the observation are refused here: give them to ``envs.get(name, **kwargs)`` instead,
        so that the spec's ``reward``/``terminated`` match the env.
        """
        ctor = env_constructor_params(self.gym_id)
        fixed = sorted(k for k in kwargs if k in ctor and k not in HARMLESS_KWARGS)
        if fixed:
            raise ValueError(
                f"{self.name}: make() does not accept {fixed}: they change the reward, termination or "
                f"observation; use envs.get({self.name!r}, {fixed[0]}=...) so the spec matches the env"
            )
        env = gymnasium_make(self.gym_id, **{**self.env_kwargs, **kwargs})
        return self.wrap(env) if self.wrap is not None else env

    def reward(self, obs: Tensor, act: Tensor, next_obs: Tensor) -> Tensor:
        """Reward of the transitions, shape ``(...)`` for ``(..., obs_dim)``, ``(..., act_dim)`` inputs."""
        self._check(obs, act, next_obs)
        return self.reward_fn(obs, act, next_obs)

    def terminated(self, obs: Tensor, act: Tensor, next_obs: Tensor) -> Tensor:
        """Boolean termination flag of the transitions, shape ``(...)``."""
        self._check(obs, act, next_obs)
        return self.terminated_fn(obs, act, next_obs)

    def _check(self, obs: Tensor, act: Tensor, next_obs: Tensor) -> None:
        if obs.shape[-1:] != (self.obs_dim,) or next_obs.shape[-1:] != (self.obs_dim,):
            raise ValueError(
                f"{self.name}: obs and next_obs must end in obs_dim={self.obs_dim}, "
                f"got {tuple(obs.shape)} and {tuple(next_obs.shape)}"
            )
        if act.shape[-1:] != (self.act_dim,):
            raise ValueError(f"{self.name}: act must end in act_dim={self.act_dim}, got {tuple(act.shape)}")


#: MuJoCo's compiler warning for gymnasium's own half_cheetah.xml (``<compiler settotalmass="14">``). It is harmless
#: and not ours to fix: MuJoCo still applies the attribute (HalfCheetah's total mass stays 14, as tested), and
#: editing the asset could change the physics. MuJoCo's C library prints it (to stderr and MUJOCO_LOG.TXT, twice per
#: model load), so ``warnings.filterwarnings`` cannot reach it: :func:`gymnasium_make` drops this message only.
SETTOTALMASS_WARNING = "compiler attribute 'settotalmass' is deprecated"


@contextlib.contextmanager
def _without_settotalmass_warning() -> Iterator[None]:
    """While the block runs, MuJoCo warnings go through a handler that drops :data:`SETTOTALMASS_WARNING` and
    passes any other message to the previous handler (or, with MuJoCo's default one, to ``warnings.warn``)."""
    try:
        import mujoco
    except ImportError:  # not a MuJoCo env
        yield
        return
    previous = mujoco.get_mju_user_warning()

    def handler(message: str) -> None:
        if SETTOTALMASS_WARNING in message:
            return
        if previous is not None:
            previous(message)
        else:
            warnings.warn(f"MuJoCo: {message.strip()}", RuntimeWarning, stacklevel=2)

    mujoco.set_mju_user_warning(handler)
    try:
        yield
    finally:
        mujoco.set_mju_user_warning(previous)


def gymnasium_make(gym_id: str, **kwargs: Any) -> gymnasium.Env:
    """``gymnasium.make`` without MuJoCo's harmless settotalmass deprecation (see :data:`SETTOTALMASS_WARNING`)."""
    with _without_settotalmass_warning():
        return gymnasium.make(gym_id, **kwargs)


def env_constructor_params(gym_id: str) -> dict[str, Any]:
    """The keyword parameters (name -> default) of the registered env class's ``__init__``."""
    entry = gymnasium.spec(gym_id).entry_point
    if isinstance(entry, str):
        module, _, attr = entry.partition(":")
        entry = getattr(importlib.import_module(module), attr)
    sig = inspect.signature(entry.__init__)
    return {
        k: p.default
        for k, p in sig.parameters.items()
        if k != "self" and p.kind not in (p.VAR_KEYWORD, p.VAR_POSITIONAL)
    }
