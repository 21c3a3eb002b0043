"""Open-loop planning with a trained model (the GEM paper's section 5.2, "Planning"), or MPC with it frozen.

The command ``python -m pets.openloop`` is :mod:`pets.tools.openloop`.

``--closed-loop`` (:func:`closed_loop`): MPC as in training, the run's planner (horizon, candidates, replanning)
with the frozen model, ``--steps`` (default 300) steps per episode, no data collected, no training; the result has
the same keys but the plan's ``actions`` and ``predicted_return``. The rest of this docstring is the open loop.

For each of K episodes: reset the real env, plan ``--steps`` actions ONCE from the initial
observation with the run's model (planner horizon = steps), then execute all of them in the real
env without any feedback (no replanning, no model update). The reward of every step is recorded.

- Model: the run's trained model (online ``run_pets.py`` or offline ``pets.train`` run directory).
- Planner: ``planner.name`` = ``--planner`` and ``planner.horizon`` = ``--steps``; every other planner
  setting (population, particles, propagation, iterations, ...) comes from the run's config, and can
  be overridden with ``planner.KEY=VALUE``. It is built by ``pets.builder.make_agent`` (the agent's
  planner and trajectory evaluator, as MPC uses them); the planner's objective is the expected
  return over the horizon under the model and the env's exact reward/termination functions (without a run's
  terminal value, ``value.*``: what is measured is the plan's own horizon).
- Env: ``spec.make(max_episode_steps=steps)``, so the env's own time limit never cuts a plan short.
- Termination: when the real env terminates at step t, the episode stops there; the rewards of the
  steps after t are 0 (the plan's remaining actions are not executed). ``lengths`` gives the number
  of executed steps, ``terminated`` whether the env terminated.
- Seeding: episode i resets the env with the seed ``pets.data.collect.episode_seeds(seed, i)[0]`` (stored
  as ``reset_seeds``); the planner draws from one ``torch.Generator`` seeded with ``seed``.

Output (printed table and ``--json``): ``reward_per_step`` (mean over episodes and its 95 %
percentile-bootstrap CI at every step), ``total`` (summed reward per episode: mean, CI, values),
``mean_reward_per_step`` (total / steps), the planned ``actions`` and raw ``rewards`` of every episode,
and ``predicted_return`` (the planner's own estimate of each plan's return under the model); ``videos``: the
MP4 files of ``--video DIR`` (``DIR/episode-N.mp4``, one frame per executed step).
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

DEFAULT_STEPS = 50
DEFAULT_EPISODES = 5
#: Steps of a closed-loop (MPC) episode with a frozen model (``--closed-loop``).
DEFAULT_CLOSED_STEPS = 300
#: Planner keys that open-loop planning sets itself (and why), so they cannot be overridden.
_FIXED = {
    "planner.name": "--planner",
    "planner.horizon": "--steps",
    "planner.replan_every": "one plan per episode, never replanned",
    "planner.candidates": "open-loop planning plans action sequences",
}


def planner_names() -> tuple[str, ...]:
    """The planner names the config accepts (``pets.config.PLANNERS``), read at run time."""
    from pets import config

    return tuple(config.PLANNERS)


def planning_config(
    cfg: Any, planner: str, steps: int, overrides: Mapping[str, Any] | None = None, closed: bool = False
) -> Any:
    """A copy of the run config ``cfg`` with ``planner.name`` = ``planner``, ``planner.horizon`` = ``steps``
    and the ``planner.*`` ``overrides`` applied (values parsed against the schema), then validated.
    ``closed``: for MPC with the frozen model (:func:`closed_loop`): the run's own horizon, candidates and
    replanning are kept (overridable), only ``planner.name`` is set.

    ConfigError for an unknown planner, a key outside ``planner.*``, ``planner.name``/``planner.horizon``
    among the overrides (use ``planner``/``steps``), or a bad value.
    """
    from omegaconf import OmegaConf

    from pets.config import ConfigError, all_keys, set_value, validate

    names = planner_names()
    if planner not in names:
        raise ConfigError(f"unknown planner {planner!r}; accepted: {', '.join(names)}")
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ConfigError(f"steps must be a positive int, got {steps!r}")
    cfg = OmegaConf.merge(cfg)  # a typed deep copy
    keys = set(all_keys())
    for key, value in (overrides or {}).items():
        if not key.startswith("planner.") or key not in keys:
            accepted = ", ".join(k for k in all_keys() if k.startswith("planner.") and k not in _FIXED)
            raise ConfigError(f"open-loop overrides must be planner keys; got {key!r}; accepted: {accepted}")
        if key in _FIXED and (key == "planner.name" or not closed):
            raise ConfigError(f"{key} is set by open-loop planning itself ({_FIXED[key]}), not by an override")
        set_value(cfg, key, value)
    cfg.planner.name = planner
    if closed:
        validate(cfg)
        return cfg
    cfg.planner.horizon = steps
    cfg.planner.replan_every = 1  # unused here (one plan per episode); keeps validate() happy for short plans
    cfg.planner.candidates = "open_loop"  # a run planned with feedback candidates is replayed open loop here
    validate(cfg)
    return cfg


class OpenLoopPolicy:
    """Plans once, from the first observation of an episode, with an MPC agent's planner and evaluator, then
    replays that plan; ``plan`` (float64) and ``predicted_return`` (the evaluator's) are the last episode's."""

    name = "open-loop"

    def __init__(self, agent: Any) -> None:
        self.planner, self.evaluator, self.generator = agent.planner, agent.evaluator, agent.generator
        self.device = agent.device
        self.plan: np.ndarray | None = None
        self.predicted_return = float("nan")
        self._t = 0

    def reset(self, rng: np.random.Generator) -> None:
        self.planner.reset()  # iCEM: no elites carried over from another episode
        self.plan, self._t = None, 0

    def act(self, obs: np.ndarray) -> np.ndarray:
        import torch

        if self.plan is None:
            obs0 = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
            gen, evaluator = self.generator, self.evaluator
            with torch.no_grad():
                plan = self.planner.plan(partial(evaluator, obs0, generator=gen), None, gen)  # (steps, act)
                self.predicted_return = float(evaluator(obs0, plan[None], gen)[0])
            self.plan = plan.detach().cpu().numpy().astype(np.float64)
        self._t += 1
        return self.plan[self._t - 1]


def _play(
    spec: Any, policy: Any, steps: int, episodes: int, seed: int, progress: bool, desc: str, video: Any = None
) -> dict[str, Any]:
    """Run ``episodes`` real episodes of at most ``steps`` steps with ``policy`` (episode i reset with
    ``pets.data.collect.episode_seeds(seed, i)[0]``); rewards after a termination count as 0. ``after(i)`` of the
    policy, where it has one, runs after each episode. Returns the arrays and the statistics of the JSON result."""
    from tqdm.auto import tqdm

    from pets.data.collect import episode_seeds
    from pets.data.rollout import run_episode
    from pets.stats.bootstrap import bootstrap_band, summarise

    env = spec.make(max_episode_steps=steps)
    recorder = None
    if video is not None:
        from pets.runs.video import EpisodeRecorder

        recorder = EpisodeRecorder(spec, env)
    videos: list[str] = []
    rewards = np.zeros((episodes, steps))
    executed = np.zeros((episodes, steps, spec.act_dim))
    lengths = np.zeros(episodes, np.int64)
    terminated = np.zeros(episodes, bool)
    reset_seeds = []
    try:
        for i in tqdm(range(episodes), desc=f"{desc} {spec.name}", unit="episode", disable=not progress):
            reset_seed = episode_seeds(seed, i)[0]
            if recorder is not None:
                recorder.start()
            capture = None if recorder is None else (lambda _: recorder.capture())
            episode = run_episode(env, policy, max_steps=steps, reset_seed=reset_seed, on_step=capture)
            if recorder is not None:
                videos.append(str(Path(video) / f"episode-{i}.mp4"))
                recorder.save(videos[-1])
            if hasattr(policy, "after"):
                policy.after(i)
            rewards[i, : len(episode)] = episode.rewards
            executed[i, : len(episode)] = episode.act
            lengths[i] = len(episode)
            terminated[i] = bool(episode.terminated[-1])
            reset_seeds.append(int(reset_seed))
    finally:
        if recorder is not None:
            recorder.close()
        env.close()
    totals = rewards.sum(axis=1)
    low, high = bootstrap_band(rewards, seed=seed)
    return {
        "reward_per_step": {"mean": rewards.mean(axis=0).tolist(), "ci_low": low.tolist(), "ci_high": high.tolist()},
        "total": {**summarise(totals, seed=seed), "values": totals.tolist()},
        "mean_reward_per_step": summarise(totals / steps, seed=seed),
        "rewards": rewards.tolist(),
        "executed_actions": executed.tolist(),
        "lengths": lengths.tolist(),
        "terminated": terminated.tolist(),
        "reset_seeds": reset_seeds,
        "videos": videos,
    }


def _header(
    run_dir: Any, run_cfg: Any, cfg: Any, spec: Any, steps: int, episodes: int, seed: int, dev: Any
) -> dict[str, Any]:
    """The first keys of a planning result: what ran, with which planner settings."""
    from omegaconf import OmegaConf

    return {
        "run": str(run_dir),
        "env": spec.name,
        "model": str(run_cfg.head),
        "planner": str(cfg.planner.name),
        "steps": steps,
        "episodes": episodes,
        "seed": seed,
        "device": str(dev),
        "planner_config": OmegaConf.to_container(cfg.planner),
    }


def _check_episodes_seed(episodes: int, seed: int) -> None:
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"episodes must be a positive int, got {episodes!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed must be an int >= 0, got {seed!r}")


def open_loop(
    run_dir: str | Path,
    planner: str = "cem",
    steps: int = DEFAULT_STEPS,
    episodes: int = DEFAULT_EPISODES,
    seed: int = 0,
    overrides: Mapping[str, Any] | None = None,
    device: str = "auto",
    progress: bool = False,
    video: str | Path | None = None,
    closed: bool = False,
) -> dict[str, Any]:
    """Open-loop planning with the model of ``run_dir`` (module docstring); returns the JSON-ready result.
    ``closed``: MPC with the frozen model instead (:func:`closed_loop`).

    ``video``: a directory that gets ``episode-N.mp4`` of every executed episode (:mod:`pets.runs.video`).
    ValueError / ConfigError (one-line messages) for bad input.
    """
    import torch

    from pets import builder
    from pets.data.rollout import MPCPolicy

    _check_episodes_seed(episodes, seed)
    dev = builder.resolve_device(device)
    run_cfg, spec, model = builder.load_model(run_dir, dev)
    cfg = planning_config(run_cfg, planner, steps, overrides, closed=closed)
    generator = torch.Generator(device=dev).manual_seed(int(seed))
    agent = builder.make_agent(cfg, spec, model, dev, generator)
    head = {**_header(run_dir, run_cfg, cfg, spec, steps, episodes, seed, dev), "mode": "closed" if closed else "open"}
    if closed:
        with torch.no_grad():
            return {**head, **_play(spec, MPCPolicy(agent), steps, episodes, seed, progress, "closed loop", video)}
    policy = OpenLoopPolicy(agent)
    actions = np.zeros((episodes, steps, spec.act_dim))
    predicted: list[float] = []

    def after(i: int) -> None:
        actions[i] = policy.plan
        predicted.append(policy.predicted_return)

    policy.after = after
    played = _play(spec, policy, steps, episodes, seed, progress, "open loop", video)
    played.pop("executed_actions")
    return {**head, **played, "actions": actions.tolist(), "predicted_return": predicted}


def closed_loop(
    run_dir: str | Path, planner: str = "cem", steps: int = DEFAULT_CLOSED_STEPS, **kwargs: Any
) -> dict[str, Any]:
    """MPC with the run's frozen model: the run's planner (``planner.name`` = ``planner``, its horizon, candidates
    and replanning, ``planner.*`` overrides) acts for ``steps`` steps or until the env terminates, replanning as
    MPC does, with no data collected and no training: what a user of a pre-trained model gets. The result keys
    of :func:`open_loop` with ``executed_actions`` (zeros after a termination) in place of the plan's ``actions``
    and ``predicted_return``; ``mode`` "closed" ("open" there). ``kwargs``: those of :func:`open_loop`."""
    return open_loop(run_dir, planner, steps, closed=True, **kwargs)


def format_table(result: Mapping[str, Any]) -> str:
    """Reward per step (mean over episodes, 95 % CI) and the totals as a fixed-width text table."""
    r = result["reward_per_step"]
    kind = "closed loop" if result.get("mode") == "closed" else "open loop"
    lines = [
        f"{kind}: {result['env']} / {result['model']} / {result['planner']} / {result['steps']} steps / "
        f"{result['episodes']} episodes / seed {result['seed']}",
        f"{'step':>5}  {'reward':>12}  {'ci_low':>12}  {'ci_high':>12}",
    ]
    for t, (m, lo, hi) in enumerate(zip(r["mean"], r["ci_low"], r["ci_high"])):
        lines.append(f"{t:>5}  {m:>12.5g}  {lo:>12.5g}  {hi:>12.5g}")
    tot, per = result["total"], result["mean_reward_per_step"]
    lines.append(
        f"total reward {tot['mean']:.5g} [{tot['ci_low']:.5g}, {tot['ci_high']:.5g}]; "
        f"reward per step {per['mean']:.5g} [{per['ci_low']:.5g}, {per['ci_high']:.5g}]; "
        f"episodes terminated early: {sum(result['terminated'])}/{result['episodes']}"
    )
    return "\n".join(lines)
