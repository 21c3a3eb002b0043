"""Open-loop planning with a trained model (the GEM paper's section 5.2, "Planning"), or MPC with it frozen.

    python -m pets.openloop --run RUN_DIR [--planner cem|mppi|icem] [--steps 50] [--episodes K] [--seed S]
                            [--closed-loop] [--device D] [--threads T] [--json OUT] [--video DIR]
                            [planner.KEY=VALUE ...]

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
- Seeding: episode i resets the env with the seed ``pets.collect.episode_seeds(seed, i)[0]`` (stored
  as ``reset_seeds``); the planner draws from one ``torch.Generator`` seeded with ``seed``.

Output (printed table and ``--json``): ``reward_per_step`` (mean over episodes and its 95 %
percentile-bootstrap CI at every step), ``total`` (summed reward per episode: mean, CI, values),
``mean_reward_per_step`` (total / steps), the planned ``actions`` and raw ``rewards`` of every episode,
and ``predicted_return`` (the planner's own estimate of each plan's return under the model); ``videos``: the
MP4 files of ``--video DIR`` (``DIR/episode-N.mp4``, one frame per executed step).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Mapping, Sequence
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from pets.cli import OneLineParser, fail
from pets.fileio import atomic_write_bytes, writable_dir_error

PROG = "pets.openloop"
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

    from pets.config import ConfigError, all_keys, validate

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
        try:
            OmegaConf.update(cfg, key, value, merge=True)
        except Exception as err:  # omegaconf's validation errors carry a multi-line message
            raise ConfigError(f"bad value for {key}: {str(err).splitlines()[0]}") from None
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
    ``pets.collect.episode_seeds(seed, i)[0]``); rewards after a termination count as 0. ``after(i)`` of the policy,
    where it has one, runs after each episode. Returns the arrays and the statistics of the JSON result."""
    from tqdm.auto import tqdm

    from pets.collect import episode_seeds
    from pets.experiments.bootstrap import bootstrap_band, summarise
    from pets.rollout import run_episode

    env = spec.make(max_episode_steps=steps)
    recorder = None
    if video is not None:
        from pets.video import EpisodeRecorder

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

    ``video``: a directory that gets ``episode-N.mp4`` of every executed episode (:mod:`pets.video`).
    ValueError / ConfigError (one-line messages) for bad input.
    """
    import torch

    from pets import builder
    from pets.rollout import MPCPolicy

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


def build_parser() -> OneLineParser:
    p = OneLineParser(
        prog=PROG,
        description="Plan once from the initial state with a trained model and execute "
        "the plan in the real env without feedback.",
        epilog="Planner settings can be overridden as planner.KEY=VALUE, e.g. planner.population=200.",
    )
    p.add_argument("--run", type=Path, required=True, help="run directory (run_pets.py or pets.train)")
    p.add_argument("--planner", default="cem", help="planner: cem (default), mppi or icem")
    p.add_argument(
        "--steps",
        type=int,
        help=f"plan length = steps executed (default {DEFAULT_STEPS}); with --closed-loop the episode length "
        f"(default {DEFAULT_CLOSED_STEPS})",
    )
    p.add_argument(
        "--closed-loop",
        action="store_true",
        help="MPC with the frozen model instead: the run's planner replans as in training, no data, no training",
    )
    p.add_argument("--episodes", type=int, default=DEFAULT_EPISODES, help=f"episodes (default {DEFAULT_EPISODES})")
    p.add_argument("--seed", type=int, default=0, help="seed of the env resets and the planner (default 0)")
    p.add_argument("--device", choices=("cpu", "cuda", "auto"), default="auto", help="where the model runs")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (default 0: torch's default)")
    p.add_argument("--json", type=Path, help="write the result as JSON here (atomically)")
    p.add_argument("--video", type=Path, metavar="DIR", help="write an MP4 of every episode here (episode-N.mp4)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("overrides", nargs="*", metavar="planner.KEY=VALUE", help="planner setting overrides")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_intermixed_args(argv)
    if args.steps is None:
        args.steps = DEFAULT_CLOSED_STEPS if args.closed_loop else DEFAULT_STEPS
    if args.steps < 1:
        fail(PROG, f"--steps must be >= 1, got {args.steps}")
    if args.episodes < 1:
        fail(PROG, f"--episodes must be >= 1, got {args.episodes}")
    if args.seed < 0:
        fail(PROG, f"--seed must be >= 0, got {args.seed}")
    if args.threads < 0:
        fail(PROG, f"--threads must be >= 0 (0: torch's default), got {args.threads}")
    if not (args.run / "config.yaml").is_file():
        fail(PROG, f"{args.run} is not a run directory (no config.yaml)")
    if args.json is not None and args.json.is_dir():
        fail(PROG, f"--json {args.json} is a directory; give a file name")
    problem = None if args.json is None else writable_dir_error(args.json.parent)
    if problem:
        fail(PROG, f"cannot write --json {args.json}: {problem}")
    from omegaconf.errors import OmegaConfBaseException

    from pets.config import ConfigError, load_config, parse_overrides

    if args.video is not None:
        problem = writable_dir_error(args.video)
        if problem:
            fail(PROG, f"cannot write --video {args.video}: {problem}")
    try:
        if args.video is not None:
            from pets.video import require_video

            require_video()
        overrides = parse_overrides(args.overrides)
        cfg = load_config(str(args.run / "config.yaml"))
        planning_config(cfg, args.planner, args.steps, overrides, closed=args.closed_loop)
        if not (args.run / "checkpoint.pt").is_file():
            raise ConfigError(f"{args.run} has no checkpoint.pt yet (no trained model)")
    except (ValueError, OmegaConfBaseException) as err:  # ConfigError is a ValueError
        fail(PROG, str(err))
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    from envs.render import RenderingUnavailable
    from pets.cli import EXIT_FAILED
    from pets.planners import PlanningFailed

    try:
        result = open_loop(
            args.run,
            args.planner,
            args.steps,
            args.episodes,
            args.seed,
            overrides,
            args.device,
            progress=not args.quiet,
            video=args.video,
            closed=args.closed_loop,
        )
    except (ConfigError, RenderingUnavailable) as err:  # e.g. device=cuda without CUDA; no headless GL for --video
        fail(PROG, str(err))
    except PlanningFailed as err:  # the run's model predicts non-finite states
        fail(PROG, f"{args.run}: {err}", EXIT_FAILED)
    print(format_table(result))
    if args.json is not None:
        from pets.cli import write_failed

        try:
            atomic_write_bytes(args.json, (json.dumps(result, indent=1) + "\n").encode())
        except OSError as err:  # a full disk: the temporary file is removed
            write_failed(PROG, err, "the results are printed above; free space or pick another --json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
