"""Stable-Baselines3 agents as data sources: SAC trained while every transition it experiences is recorded,
and a saved SB3 agent (any algorithm) rolled as a :class:`pets.data.rollout.Policy`.

Needs the ``sac`` extra (``pip install -e ".[sac]"``); every import of stable-baselines3 happens inside a
function, so the rest of the package works without it. docs/data.md lists SAC's wall time per env.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import TYPE_CHECKING, Any

import gymnasium
import numpy as np

from pets.data.rollout import Episode

if TYPE_CHECKING:
    from envs import EnvSpec

INSTALL_HINT = 'stable-baselines3 is not installed; install the extra: pip install -e ".[sac]"'


def require_sb3() -> None:
    """ImportError with the install command unless stable-baselines3 can be imported."""
    try:
        import stable_baselines3  # noqa: F401
    except ImportError:
        raise ImportError(INSTALL_HINT) from None


class TransitionRecorder(gymnasium.Wrapper):
    """Records every episode exactly as it happens in the wrapped env (whoever drives it, e.g. SB3's learner).

    ``episodes()``: the finished episodes and the running one (if it has a step), as :class:`Episode` objects
    with float64 arrays; an episode starts at each ``reset`` and ends at termination or truncation.
    """

    def __init__(self, env: gymnasium.Env) -> None:
        super().__init__(env)
        self._finished: list[Episode] = []
        self._steps: list[tuple[np.ndarray, np.ndarray, np.ndarray, float, bool, bool]] = []
        self._obs: np.ndarray | None = None

    def reset(self, **kwargs: Any) -> tuple[Any, dict]:
        self._close_episode()
        obs, info = self.env.reset(**kwargs)
        self._obs = np.array(obs, np.float64)
        return obs, info

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        act = np.array(action, np.float64).reshape(self.env.action_space.shape)
        next_obs = np.array(obs, np.float64)
        self._steps.append((self._obs, act, next_obs, float(reward), bool(terminated), bool(truncated)))
        self._obs = next_obs
        if terminated or truncated:
            self._close_episode()
        return obs, reward, terminated, truncated, info

    def _running(self) -> list[Episode]:
        """The episode in progress as a one-element list (empty before its first step)."""
        if not self._steps:
            return []
        obs, act, next_obs, rew, term, trunc = (np.array(col) for col in zip(*self._steps))
        return [Episode(obs, act, next_obs, rew, term, trunc, total_reward=float(rew.sum()))]

    def _close_episode(self) -> None:
        self._finished += self._running()
        self._steps = []

    def episodes(self) -> list[Episode]:
        """The recorded episodes in the order they happened (the running one last, cut where it stands)."""
        return self._finished + self._running()


def train_sac(
    spec: EnvSpec,
    steps: int,
    *,
    seed: int = 0,
    max_steps: int | None = None,
    device: str = "auto",
    progress: bool = False,
    sac_kwargs: dict[str, Any] | None = None,
) -> tuple[list[Episode], Any]:
    """Train SB3's SAC (its default hyperparameters, ``sac_kwargs`` on top) for ``steps`` env steps on ``spec``.

    Returns ``(episodes, agent)``: every transition SAC experienced, episode by episode as it happened (the
    last one cut at ``steps``), and the trained agent. ``seed`` seeds SAC (torch, numpy, the env's first reset).
    """
    require_sb3()
    from stable_baselines3 import SAC
    from stable_baselines3.common.callbacks import BaseCallback
    from tqdm.auto import tqdm

    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"SAC steps must be a positive int, got {steps!r}")

    class StepBar(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.bar = tqdm(total=steps, desc=f"SAC {spec.name}", unit="step", disable=not progress)

        def _on_step(self) -> bool:
            self.bar.update(1)
            return True

        def _on_training_end(self) -> None:
            self.bar.close()

    env = TransitionRecorder(spec.make(max_episode_steps=max_steps or spec.episode_length))
    try:
        agent = SAC("MlpPolicy", env, seed=int(seed), device=device, verbose=0, **(sac_kwargs or {}))
        agent.learn(total_timesteps=steps, callback=StepBar())
        return env.episodes(), agent
    finally:
        env.close()


def agent_bytes(agent: Any) -> bytes:
    """The SB3 ``.zip`` of ``agent`` as bytes (written atomically by the caller)."""
    buf = io.BytesIO()
    agent.save(buf)
    return buf.getvalue()


def load_agent(path: str | Path, device: str = "auto") -> Any:
    """Load a saved SB3 agent of any algorithm (SAC, TD3, DDPG, PPO, A2C), found from its policy class.

    ValueError (one line) for a missing or unreadable file, or a policy class no SB3 algorithm owns.
    """
    require_sb3()
    import stable_baselines3 as sb3
    from stable_baselines3.common.save_util import load_from_zip_file

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"SB3 agent {path} does not exist")
    try:
        data, _, _ = load_from_zip_file(path, device="cpu")
    except Exception as err:  # zipfile.BadZipFile, ValueError, pickle errors, ...
        raise ValueError(f"{path} is not a readable SB3 agent ({type(err).__name__}: {err})") from None
    policy_class = (data or {}).get("policy_class")
    for algo in (sb3.SAC, sb3.TD3, sb3.DDPG, sb3.PPO, sb3.A2C):
        owned = tuple(algo.policy_aliases.values())
        if isinstance(policy_class, type) and issubclass(policy_class, owned):
            return algo.load(path, device=device)
    raise ValueError(f"{path} is not an SB3 agent of SAC, TD3, DDPG, PPO or A2C (policy class {policy_class!r})")


class SB3Policy:
    """A saved SB3 agent as a :class:`pets.data.rollout.Policy`: the agent's stochastic policy (seeded per episode
    from the episode's generator) or, with ``deterministic``, its mean action."""

    def __init__(self, path: str | Path, spec: EnvSpec, *, deterministic: bool = False, device: str = "auto") -> None:
        self.agent = load_agent(path, device)
        obs_shape, act_shape = self.agent.observation_space.shape, self.agent.action_space.shape
        if obs_shape != (spec.obs_dim,) or act_shape != (spec.act_dim,):
            raise ValueError(
                f"SB3 agent {path} acts on observations {obs_shape} and actions {act_shape}, but {spec.name} has "
                f"({spec.obs_dim},) and ({spec.act_dim},); roll it on the env it was trained on"
            )
        self.deterministic = bool(deterministic)
        self.name = f"sb3:{Path(path).name}{':deterministic' if deterministic else ''}"

    def reset(self, rng: np.random.Generator) -> None:
        import torch

        torch.manual_seed(int(rng.integers(2**63 - 1)))  # SB3 samples actions from torch's global generator

    def act(self, obs: np.ndarray) -> np.ndarray:
        action, _ = self.agent.predict(np.asarray(obs), deterministic=self.deterministic)
        return np.asarray(action, np.float64)
