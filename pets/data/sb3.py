"""Stable-Baselines3 agents as data sources: SAC trained while every transition it experiences is recorded,
and a saved SB3 agent (any algorithm) rolled as a :class:`pets.data.rollout.Policy`.

Needs the ``sac`` extra (``pip install -e ".[sac]"``); every import of stable-baselines3 happens inside a
function, so the rest of the package works without it. docs/data.md lists SAC's wall time per env.
"""

from __future__ import annotations

import io
import pickle
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

    def resume(self, episodes: list[Episode]) -> None:
        """Go on after ``episodes`` (a checkpoint's): they count as finished, the running one included."""
        self._finished, self._steps = list(episodes), []


#: Env steps between the checkpoints of a SAC collection (:func:`train_sac` with ``checkpoint``).
CHECKPOINT_EVERY = 10_000


def sac_checkpoint_path(out: Path) -> Path:
    """The checkpoint of the SAC collection that writes the data set ``out``: ``OUT.sac-checkpoint`` beside it."""
    out = Path(out)
    return out.with_name(out.name + ".sac-checkpoint")


def _checkpoint_settings(spec: EnvSpec, steps: int, seed: int, max_steps: int | None, sac_kwargs: Any) -> dict:
    """What a SAC checkpoint must have been written for to be resumed (compared on load)."""
    return {"env": spec.name, "steps": steps, "seed": int(seed), "max_steps": max_steps, "sac_kwargs": sac_kwargs}


def read_sac_checkpoint(path: Path, settings: dict[str, Any]) -> dict[str, Any] | None:
    """The checkpoint at ``path`` (None if there is none); ValueError (one line) if it is unreadable or was
    written for other settings."""
    if not path.is_file():
        return None
    try:
        with open(path, "rb") as f:
            state = pickle.load(f)
        got = state["settings"]
    except Exception as err:  # a truncated or foreign file: say which and what to do
        raise ValueError(
            f"cannot read the SAC checkpoint {path} ({type(err).__name__}); delete it to start over"
        ) from None
    if got != settings:
        diff = "; ".join(f"{k}: {got.get(k)!r} != {v!r}" for k, v in settings.items() if got.get(k) != v)
        raise ValueError(f"the SAC checkpoint {path} was written for other settings ({diff}); delete it or pass them")
    return state


def sac_steps_done(
    out: Path, spec: EnvSpec, steps: int, seed: int, max_steps: int | None, sac_kwargs: Any = None
) -> int:
    """The env steps that the SAC collection writing the data set ``out`` (with these settings, as
    :func:`train_sac` takes them) has done so far: its checkpoint's, 0 where there is none (a collection not begun,
    or finished). ValueError (:func:`read_sac_checkpoint`'s one line) where the checkpoint cannot be read or was
    written for other settings: the collection refuses it too."""
    settings = _checkpoint_settings(spec, steps, seed, max_steps, sac_kwargs)
    state = read_sac_checkpoint(sac_checkpoint_path(out), settings)
    return 0 if state is None else int(state["steps_done"])


def refill_replay_buffer(agent: Any, episodes: list[Episode]) -> None:
    """Put ``episodes`` into ``agent``'s (empty) replay buffer as SB3's off-policy learner stores transitions: the
    observation, the true next observation, the action scaled to [-1, 1], the reward, done (terminated or
    truncated) and the timeout flag. (SB3's own buffer file would hold all of its 1M rows, used or not.)"""
    buf = agent.replay_buffer
    for ep in episodes:
        scaled = agent.policy.scale_action(ep.act)
        for t in range(len(ep.act)):
            done, timeout = bool(ep.terminated[t] or ep.truncated[t]), bool(ep.truncated[t] and not ep.terminated[t])
            info = [{"TimeLimit.truncated": timeout}]
            buf.add(
                ep.obs[t][None],
                ep.next_obs[t][None],
                scaled[t][None],
                np.array([ep.rewards[t]]),
                np.array([done]),
                info,
            )


def train_sac(
    spec: EnvSpec,
    steps: int,
    *,
    seed: int = 0,
    max_steps: int | None = None,
    device: str = "auto",
    progress: bool = False,
    sac_kwargs: dict[str, Any] | None = None,
    checkpoint: Path | None = None,
    checkpoint_every: int = CHECKPOINT_EVERY,
) -> tuple[list[Episode], Any, list[int]]:
    """Train SB3's SAC (its default hyperparameters, ``sac_kwargs`` on top) for ``steps`` env steps on ``spec``.

    Returns ``(episodes, agent, resumed_at)``: every transition SAC experienced, episode by episode as it
    happened (the last one cut at ``steps``), the trained agent, and the env steps at which this collection went
    on from a checkpoint (empty when it ran in one go). ``seed`` seeds SAC (torch, numpy, the env's first reset).

    ``checkpoint``: a file that holds the agent and the episodes so far (its replay buffer is refilled from them,
    :func:`refill_replay_buffer`), written atomically every ``checkpoint_every`` steps; if it exists (written for
    the same settings, else ValueError), training goes on from it. A resumed collection is a valid SAC data set
    but not the uninterrupted one: the episode running at the checkpoint ends there (the env is reset, seeded with
    ``seed`` + the steps done), and the gradient step of that env step is not taken. The file is the caller's to
    delete once the data are saved.
    """
    require_sb3()
    from stable_baselines3 import SAC
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.logger import Logger
    from tqdm.auto import tqdm

    from pets.runs.fileio import atomic_write_bytes

    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"SAC steps must be a positive int, got {steps!r}")
    if checkpoint_every < 1:
        raise ValueError(f"checkpoint_every must be >= 1, got {checkpoint_every}")
    settings = _checkpoint_settings(spec, steps, seed, max_steps, sac_kwargs)
    checkpoint = None if checkpoint is None else Path(checkpoint)
    state = None if checkpoint is None else read_sac_checkpoint(checkpoint, settings)
    resumed_at = [*state["resumed_at"], state["steps_done"]] if state else []
    env = TransitionRecorder(spec.make(max_episode_steps=max_steps or spec.episode_length))

    class StepBar(BaseCallback):
        """The progress bar, and the checkpoint after every ``checkpoint_every``-th step's transition is stored."""

        def __init__(self) -> None:
            super().__init__()
            done = state["steps_done"] if state else 0
            self.bar = tqdm(total=steps, initial=done, desc=f"SAC {spec.name}", unit="step", disable=not progress)

        def _on_step(self) -> bool:
            self.bar.update(1)
            return True

        def _on_rollout_end(self) -> None:
            done = self.model.num_timesteps
            if checkpoint is None or done % checkpoint_every or done >= steps:
                return
            saved = {"settings": settings, "steps_done": done, "resumed_at": resumed_at, "episodes": env.episodes()}
            saved["agent"] = agent_bytes(self.model)  # not its replay buffer: the episodes are its transitions
            atomic_write_bytes(checkpoint, pickle.dumps(saved, protocol=pickle.HIGHEST_PROTOCOL))

        def _on_training_end(self) -> None:
            self.bar.close()

    try:
        if state is None:
            agent = SAC("MlpPolicy", env, seed=int(seed), device=device, verbose=0, **(sac_kwargs or {}))
            agent.set_logger(Logger(folder=None, output_formats=[]))  # else learn() makes an empty /tmp/SB3-<date>
            agent.learn(total_timesteps=steps, callback=StepBar())
        else:
            agent = SAC.load(io.BytesIO(state["agent"]), env=env, device=device)
            agent.set_logger(Logger(folder=None, output_formats=[]))
            refill_replay_buffer(agent, state["episodes"])
            agent.set_random_seed(int(seed) + state["steps_done"])
            env.resume(state["episodes"])
            remaining = steps - state["steps_done"]
            agent.learn(total_timesteps=remaining, callback=StepBar(), reset_num_timesteps=False)
        return env.episodes(), agent, resumed_at
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
