"""Collect trajectories from a catalogue env into an ``.npz`` data set (format: :mod:`pets.data.datasets`).

The command ``python -m pets.collect`` is :mod:`pets.tools.collect`.

Policies:

- ``random``: i.i.d. uniform actions in the action bounds.
- ``smooth-random[:BETA]`` (BETA in [0, 1), default 0.9): a discretised Ornstein-Uhlenbeck process
  mapped into the bounds. Per action dimension ``z_0 ~ N(0, 1)``,
  ``z_{t+1} = BETA z_t + sqrt(1 - BETA^2) eps_t`` (``eps_t ~ N(0, 1)``), a stationary AR(1) with unit
  variance and lag-k correlation ``BETA^k`` (time constant ``-1 / ln BETA`` ~ 9.5 steps at 0.9);
  the action is ``a_t = low + (high - low) Phi(z_t)`` with ``Phi`` the standard normal CDF, so every
  single action is exactly uniform in the bounds (as ``random``), but consecutive actions are
  strongly correlated. BETA = 0 is ``random`` again.
- ``run:RUN_DIR``: the MPC agent of a trained run (online ``run_pets.py`` or offline
  ``pets.train``), with the run's own planner config; its randomness comes from ``--seed``.
- ``sb3:AGENT.zip``: a saved Stable-Baselines3 agent of any algorithm (``pets.data.sb3``), its stochastic
  policy seeded per episode, or its mean action with ``--deterministic``.
- ``sac:STEPS``: trains SB3's SAC (default hyperparameters) for STEPS env steps and writes every transition it
  experienced, episode by episode as it happened (the GEM paper's data); ``--save-agent`` keeps the agent for
  ``sb3:`` test data. The env's first reset is seeded with ``--seed``, later ones continue its generator, so
  ``reset_seeds`` is not stored.

Seeding: episode ``i`` uses ``np.random.SeedSequence([seed, i])``: its first 32-bit word is the
``env.reset`` seed (stored as ``reset_seeds``), the sequence itself seeds the policy's numpy
generator. So a file is a pure function of its arguments (byte-identical for the same seed on the
same machine) and the first k episodes do not depend on ``--episodes``.

Episodes end at termination, at the env's time limit, or after ``--max-steps`` steps (which
replaces the env's own time limit, so it can also lengthen episodes).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pets.data.rollout import Episode, MPCPolicy, Policy, RandomPolicy, run_episode

if TYPE_CHECKING:
    from envs import EnvSpec

POLICIES = ("random", "smooth-random[:BETA]", "run:RUN_DIR", "sb3:AGENT.zip", "sac:STEPS")
DEFAULT_BETA = 0.9


class SmoothRandomPolicy:
    """Ornstein-Uhlenbeck (AR(1)) noise mapped through the normal CDF into the bounds (module docstring).

    z_{t+1} = beta z_t + sqrt(1 - beta^2) eps_t, a_t = low + (high - low) Phi(z_t); z_0 ~ N(0, 1).
    """

    def __init__(self, low: Any, high: Any, beta: float = DEFAULT_BETA) -> None:
        if not (isinstance(beta, (int, float)) and 0.0 <= beta < 1.0):
            raise ValueError(f"smooth-random: BETA must be a number in [0, 1), got {beta!r}")
        self.low, self.high = np.asarray(low, np.float64), np.asarray(high, np.float64)
        from scipy.special import ndtr

        self._ndtr = ndtr
        self.beta = float(beta)
        self.name = f"smooth-random:{self.beta:g}"
        self._rng = np.random.default_rng(0)
        self._z = np.zeros_like(self.low)

    def reset(self, rng: np.random.Generator) -> None:
        self._rng = rng
        self._z = rng.standard_normal(self.low.shape)

    def act(self, obs: np.ndarray) -> np.ndarray:
        action = self.low + (self.high - self.low) * self._ndtr(self._z)
        eps = self._rng.standard_normal(self.low.shape)
        self._z = self.beta * self._z + math.sqrt(1.0 - self.beta**2) * eps
        return np.clip(action, self.low, self.high)


class AgentPolicy(MPCPolicy):
    """The MPC agent of a trained run directory (its model, its config's planner and its terminal value if any)."""

    def __init__(self, run_dir: str | Path, seed: int = 0, device: str = "auto") -> None:
        import torch

        from pets import builder

        self.run_dir = Path(run_dir)
        dev = builder.resolve_device(device)
        self.cfg, self.spec, self.model = builder.load_model(self.run_dir, dev)
        self.generator = torch.Generator(device=dev).manual_seed(int(seed))
        super().__init__(
            builder.make_agent(
                self.cfg,
                self.spec,
                self.model,
                dev,
                self.generator,
                builder.load_value(self.run_dir, self.cfg, self.spec, dev),
            ),
            f"run:{self.run_dir}",
        )


def parse_policy(text: str) -> tuple[str, Any]:
    """Split a ``--policy`` string into (kind, argument): ``("random", None)``, ``("smooth-random", beta)``,
    ``("run", Path)``, ``("sb3", Path)``, ``("sac", steps)``. ValueError for anything else (no file access, no
    heavy imports)."""
    if text == "random":
        return "random", None
    if text == "smooth-random" or text.startswith("smooth-random:"):
        _, _, arg = text.partition(":")
        try:
            beta = float(arg) if arg else DEFAULT_BETA
        except ValueError:
            raise ValueError(f"smooth-random:BETA needs a number in [0, 1), got {arg!r}") from None
        if not 0.0 <= beta < 1.0:
            raise ValueError(f"smooth-random:BETA needs a number in [0, 1), got {beta}")
        return "smooth-random", beta
    if text.startswith("run:"):
        path = Path(text[4:])
        if not text[4:]:
            raise ValueError("run:RUN_DIR needs a run directory after 'run:'")
        return "run", path
    if text.startswith("sb3:"):
        if not text[4:]:
            raise ValueError("sb3:AGENT.zip needs the path of a saved Stable-Baselines3 agent after 'sb3:'")
        return "sb3", Path(text[4:])
    if text.startswith("sac:"):
        try:
            steps = int(text[4:])
        except ValueError:
            steps = 0
        if steps < 1:
            raise ValueError(f"sac:STEPS needs a positive number of env steps such as sac:100000, got {text!r}")
        return "sac", steps
    raise ValueError(f"unknown policy {text!r}; accepted: {', '.join(POLICIES)}")


def make_policy(text: str, spec: EnvSpec, seed: int = 0, device: str = "auto", deterministic: bool = False) -> Policy:
    """Build the policy named by ``text`` (see :func:`parse_policy`) for env ``spec``.

    A ``run:`` or ``sb3:`` policy must come from the same env (ValueError otherwise); ``sac:`` is trained, not
    rolled (:func:`collect_sac`). ``deterministic``: an ``sb3:`` agent's mean action.
    """
    kind, arg = parse_policy(text)
    if kind == "random":
        return RandomPolicy(spec.action_low, spec.action_high)
    if kind == "smooth-random":
        return SmoothRandomPolicy(spec.action_low, spec.action_high, arg)
    if kind == "sb3":
        from pets.data.sb3 import SB3Policy

        return SB3Policy(arg, spec, deterministic=deterministic, device=device)
    if kind == "sac":
        raise ValueError("sac:STEPS trains an agent instead of rolling one; use collect_sac")
    run_env = run_env_name(arg)
    if run_env != spec.name:
        raise ValueError(
            f"run {arg} was trained on {run_env}, not on {spec.name}; collect on its env or pick another run"
        )
    return AgentPolicy(arg, seed=seed, device=device)


def run_env_name(run_dir: Path) -> str:
    """The env of a run directory (ValueError if it is not one or has no trained model yet)."""
    from pets.config import load_run_config
    from pets.runs import rundir

    run_dir = Path(run_dir)
    cfg = load_run_config(run_dir)
    if not (run_dir / rundir.CHECKPOINT_FILE).is_file():
        raise ValueError(f"{run_dir} has no {rundir.CHECKPOINT_FILE} yet (no trained model)")
    return str(cfg.env)


def episode_seeds(seed: int, episode: int) -> tuple[int, np.random.SeedSequence]:
    """(env reset seed, policy seed sequence) of episode ``episode`` of a collection with ``seed``."""
    ss = np.random.SeedSequence([int(seed), int(episode)])
    return int(ss.generate_state(1)[0]), ss


def collect(
    spec: EnvSpec,
    policy: Policy | str,
    episodes: int,
    seed: int = 0,
    max_steps: int | None = None,
    *,
    device: str = "auto",
    progress: bool = False,
) -> dict[str, np.ndarray]:
    """Roll ``policy`` (a :class:`Policy` or a ``--policy`` string) in ``spec.make()`` for ``episodes`` episodes.

    Returns the data set arrays of :mod:`pets.data.datasets` (NaN-padded to the longest episode) plus
    ``policy``, ``seed`` and ``reset_seeds``.
    """
    from tqdm.auto import tqdm

    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"episodes must be a positive int, got {episodes!r}")
    if max_steps is not None and (isinstance(max_steps, bool) or not isinstance(max_steps, int) or max_steps < 1):
        raise ValueError(f"max_steps must be a positive int or None, got {max_steps!r}")
    if isinstance(policy, str):
        policy = make_policy(policy, spec, seed=seed, device=device)
    limit = max_steps or spec.episode_length
    env = spec.make(max_episode_steps=limit)
    episodes_run, reset_seeds = [], []
    try:
        for i in tqdm(range(episodes), desc=f"collect {spec.name}", unit="episode", disable=not progress):
            reset_seed, ss = episode_seeds(seed, i)
            episodes_run.append(
                run_episode(env, policy, max_steps=limit, reset_seed=reset_seed, rng=np.random.default_rng(ss))
            )
            reset_seeds.append(reset_seed)
    finally:
        env.close()

    return pack_episodes(spec, episodes_run, policy.name, seed, reset_seeds)


def pack_episodes(
    spec: EnvSpec, episodes: list[Episode], policy_name: str, seed: int, reset_seeds: list[int] | None = None
) -> dict[str, np.ndarray]:
    """The data set arrays of :mod:`pets.data.datasets` for ``episodes`` (NaN-padded to the longest), with metadata."""
    if not episodes:
        raise ValueError("no episodes to write: a data set needs at least one step")
    lengths = np.array([len(ep) for ep in episodes], np.int64)
    n, t = len(episodes), int(lengths.max())
    obs_arr = np.full((n, t + 1, spec.obs_dim), np.nan)
    act_arr = np.full((n, t, spec.act_dim), np.nan)
    rew_arr = np.full((n, t), np.nan)
    term_arr = np.zeros((n, t), bool)
    for i, (ep, k) in enumerate(zip(episodes, lengths)):
        obs_arr[i, : k + 1] = ep.states
        act_arr[i, :k] = ep.act
        rew_arr[i, :k] = ep.rewards
        term_arr[i, :k] = ep.terminated
    data = {
        "obs": obs_arr,
        "act": act_arr,
        "rew": rew_arr,
        "terminated": term_arr,
        "lengths": lengths,
        "env": np.array(spec.name),
        "policy": np.array(policy_name),
        "seed": np.array(int(seed), np.int64),
    }
    if reset_seeds is not None:
        data["reset_seeds"] = np.array(reset_seeds, np.int64)
    return data


def collect_sac(
    spec: EnvSpec,
    steps: int,
    seed: int = 0,
    max_steps: int | None = None,
    *,
    device: str = "auto",
    progress: bool = False,
    sac_kwargs: dict[str, Any] | None = None,
    checkpoint: Path | None = None,
) -> tuple[dict[str, np.ndarray], Any]:
    """Train SAC for ``steps`` env steps (:func:`pets.data.sb3.train_sac`, resumable from ``checkpoint``);
    ``(data set arrays, agent)``. A collection that went on from a checkpoint records where in ``sac_resumed_at``."""
    from pets.data.sb3 import train_sac

    episodes, agent, resumed_at = train_sac(
        spec,
        steps,
        seed=seed,
        max_steps=max_steps,
        device=device,
        progress=progress,
        sac_kwargs=sac_kwargs,
        checkpoint=checkpoint,
    )
    data = pack_episodes(spec, episodes, f"sac:{steps}", seed)
    if resumed_at:
        data["sac_resumed_at"] = np.array(resumed_at, np.int64)
    return data, agent
