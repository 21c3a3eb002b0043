"""One episode in a real env: the policy protocol, the random and MPC policies, and :func:`run_episode`.

Every loop that steps an env (the PETS loop's seed steps and trials, ``pets.collect``, open-loop
replay, the benchmarks' random data: :func:`collect_random`) is "make a policy, run episodes" with these.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from envs import EnvSpec


class EnvFailed(RuntimeError):
    """The env's ``reset`` or ``step`` raised, or returned an observation of another shape or a non-finite observation
    or reward (a user's own env, ``--env module:SPEC``): the env's fault, not the model's or the planner's. One line,
    naming the step."""


def _checked(where: str, shape: tuple[int, ...] | None, call: Callable[..., Any], *args: Any, **kwargs: Any) -> tuple:
    """What ``call(*args, **kwargs)`` (the env's ``reset`` or ``step``) returned, checked: :class:`EnvFailed` for an
    exception, a result that is not ``(obs, info)`` or ``(obs, reward, terminated, truncated, info)``, an observation
    that is not of ``shape`` (None: any) or not finite, or a reward that is not a finite number. ``where``: the
    step it was, for the message."""
    try:
        out = call(*args, **kwargs)
    except Exception as err:  # the user's code: any error; a Ctrl-C is no Exception
        text = str(err).strip().splitlines()
        raise EnvFailed(f"the env's {where} raised {type(err).__name__}: {text[0] if text else 'no message'}") from None
    size = 2 if where == "reset" else 5
    if not isinstance(out, tuple) or len(out) != size:
        kind = "(obs, info)" if size == 2 else "(obs, reward, terminated, truncated, info)"
        raise EnvFailed(f"the env's {where} returned {type(out).__name__} {_short(out)}, not gymnasium's {kind}")
    try:
        obs, reward = np.asarray(out[0], np.float64), float(out[1]) if size == 5 else 0.0
    except (TypeError, ValueError) as err:
        raise EnvFailed(f"the env's {where} returned an observation or reward that is not numbers ({err})") from None
    if shape is not None and obs.shape != shape:
        raise EnvFailed(f"the env's {where} returned an observation of shape {obs.shape}, its reset one of {shape}")
    if not np.isfinite(obs).all() or not np.isfinite(reward):
        what = "observation (nan or inf)" if not np.isfinite(obs).all() else f"reward ({reward})"
        raise EnvFailed(f"the env's {where} returned a non-finite {what}")
    return out


def _short(value: Any) -> str:
    text = " ".join(repr(value).split())
    return text if len(text) <= 80 else text[:77] + "..."


class Policy(Protocol):
    """What :func:`run_episode` drives: ``reset`` at the start of every episode, then ``act`` once per step."""

    name: str

    def reset(self, rng: np.random.Generator) -> None: ...

    def act(self, obs: np.ndarray) -> np.ndarray: ...


class RandomPolicy:
    """Uniform i.i.d. actions in ``[low, high]``, drawn from the generator of the last ``reset``."""

    def __init__(self, low: Any, high: Any) -> None:
        self.low, self.high = np.asarray(low, np.float64), np.asarray(high, np.float64)
        self.name = "random"
        self._rng = np.random.default_rng(0)

    def reset(self, rng: np.random.Generator) -> None:
        self._rng = rng

    def act(self, obs: np.ndarray) -> np.ndarray:
        return self._rng.uniform(self.low, self.high)


class MPCPolicy:
    """An MPC agent (``reset()``, ``act(obs)``) as a policy; ``seconds`` and ``cpu_seconds``: its planning time
    in this episode, wall-clock and the process's CPU (all its threads)."""

    def __init__(self, agent: Any, name: str = "mpc") -> None:
        self.agent = agent
        self.name = name
        self.seconds = self.cpu_seconds = 0.0

    def reset(self, rng: np.random.Generator) -> None:
        self.agent.reset()
        self.seconds = self.cpu_seconds = 0.0

    def act(self, obs: np.ndarray) -> np.ndarray:
        t0, c0 = time.perf_counter(), time.process_time()
        action = self.agent.act(obs)
        self.seconds += time.perf_counter() - t0
        self.cpu_seconds += time.process_time() - c0
        return action


@dataclass
class Episode:
    """The steps of one episode (float64 arrays, one row per step, at least one) and its summed reward.

    ``truncated`` is the env's truncation, and also true on the last step when ``max_steps`` ended the episode.
    """

    obs: np.ndarray
    act: np.ndarray
    next_obs: np.ndarray
    rewards: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    total_reward: float

    def __len__(self) -> int:
        return len(self.rewards)

    @property
    def done(self) -> bool:
        """Whether the last step ended the episode (termination, truncation or ``max_steps``)."""
        return bool(self.terminated[-1] or self.truncated[-1])

    @property
    def states(self) -> np.ndarray:
        """The ``len + 1`` observations: the reset's, then one after every step."""
        return np.concatenate([self.obs[:1], self.next_obs])


def run_episode(
    env: Any,
    policy: Policy,
    *,
    max_steps: int,
    reset_seed: int | None = None,
    rng: np.random.Generator | None = None,
    on_step: Callable[[Episode], None] | None = None,
) -> Episode:
    """Reset ``env`` (``seed=reset_seed``), reset ``policy`` (with ``rng``; None: a fresh unseeded generator) and
    step it until termination, truncation or ``max_steps`` steps.

    Actions are ``policy.act(obs)`` as float64 arrays of the action space's shape. ``on_step(so_far)`` runs after
    every step with the episode so far (views, valid during the call). The reward sum is taken step by step.
    :class:`EnvFailed` where the env raises or returns an observation of another shape, or a non-finite one or reward.
    """
    if isinstance(max_steps, bool) or not isinstance(max_steps, int) or max_steps < 1:
        raise ValueError(f"max_steps must be a positive int, got {max_steps!r}")
    obs, _ = _checked("reset", None, env.reset, seed=reset_seed)
    policy.reset(np.random.default_rng() if rng is None else rng)
    act_shape, obs_shape = env.action_space.shape, np.shape(obs)
    obs_arr = np.empty((max_steps, *obs_shape))
    next_arr = np.empty((max_steps, *obs_shape))
    act_arr = np.empty((max_steps, *act_shape))
    rewards = np.empty(max_steps)
    terminated = np.zeros(max_steps, bool)
    truncated = np.zeros(max_steps, bool)
    total = 0.0

    def upto(n: int, copy: bool = False) -> Episode:
        arrays = (a[:n].copy() if copy else a[:n] for a in (obs_arr, act_arr, next_arr, rewards, terminated, truncated))
        return Episode(*arrays, total_reward=total)

    for t in range(max_steps):
        action = np.asarray(policy.act(obs), np.float64).reshape(act_shape)
        next_obs, reward, term, trunc, _ = _checked(f"step {t + 1} of the episode", obs_shape, env.step, action)
        obs_arr[t], act_arr[t], next_arr[t] = obs, action, next_obs
        rewards[t] = float(reward)
        total += float(reward)
        terminated[t], truncated[t] = bool(term), bool(trunc) or t + 1 == max_steps
        obs = next_obs
        if on_step is not None:
            on_step(upto(t + 1))
        if term or trunc:
            break
    return upto(t + 1, copy=True)  # not views of the max_steps-long buffers


def run_steps(
    env: Any,
    policy: Policy,
    steps: int,
    *,
    max_steps: int,
    reset_seeds: Iterable[int | None],
    rng: np.random.Generator | None = None,
) -> list[Episode]:
    """Episodes of at most ``max_steps`` steps, reset with the successive ``reset_seeds``, until ``steps`` steps
    in all (the last episode is cut short there); ``rng`` is passed to every ``policy.reset``."""
    episodes: list[Episode] = []
    done, seeds = 0, iter(reset_seeds)
    while done < steps:
        episode = run_episode(env, policy, max_steps=min(max_steps, steps - done), reset_seed=next(seeds), rng=rng)
        episodes.append(episode)
        done += len(episode)
    return episodes


def collect_random(spec: EnvSpec, steps: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``steps`` uniformly random transitions (float32 obs, act, next obs) over as many episodes as needed;
    the first reset is seeded with ``seed``, the actions come from ``default_rng(seed)``."""
    env, policy = spec.make(), RandomPolicy(spec.action_low, spec.action_high)
    seeds = itertools.chain([seed], itertools.repeat(None))
    episodes = run_steps(env, policy, steps, max_steps=steps, reset_seeds=seeds, rng=np.random.default_rng(seed))
    env.close()
    return tuple(
        np.concatenate([getattr(ep, k) for ep in episodes]).astype(np.float32) for k in ("obs", "act", "next_obs")
    )
