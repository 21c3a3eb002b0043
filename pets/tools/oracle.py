"""MPC with the true simulator as its model: is a failure the planner's or the learned model's?

    python -m pets.oracle --env ENV [--preset fast] [--steps N] [--episodes K] [--seed S] [--quiet]
                          [--json OUT] [--value-from RUN_DIR] [planner.KEY=VALUE ...]

The configured planner (``planner.*`` of the env's config and preset, overrides as in ``run_pets.py``) plans
every step as PETS' MPC agent does (:class:`pets.agent.MPCAgent`: warm start, ``replan_every``), but every
candidate action sequence is scored by MuJoCo itself: a second copy of the env is set to the live env's exact
state (``qpos``, ``qvel``) and stepped through the sequence, summing the env's own rewards up to and including
a terminating step. So the planner sees the exact returns of its candidates over its horizon, with no model
error and no sampling noise. If it still fails, the planner (its horizon, population, action
parameterisation, the objective's ties) is the cause; if it succeeds where ``run_pets.py`` fails, the learned
model or its data is. ``--value-from RUN_DIR`` adds the terminal value that run learned (``value.enabled``;
pets.planning.value) to every candidate that does not terminate, as the run's own planner does: with the true
dynamics and the run's value, a failure is the value's or the planner's, not the model's. Episode ``i`` resets
with ``pets.data.collect.episode_seeds(seed, i)[0]``; the planner draws from one ``torch.Generator`` seeded with
``seed``.

A diagnostic, not a hot path: candidates are simulated one at a time in Python (about ``population x
iterations x horizon`` simulator steps per MPC step; at InvertedDoublePendulum's fast preset, feedback candidates
over 60 steps, 0.3-0.7 s per step, so a whole 1000-step episode takes 5-12 min: ``--steps`` shortens it).
Model settings (``model.*``, ``planner.particles``, ``planner.propagation``, ``planner.precision``) and
``value.*`` have no effect (the value is a run's, with ``--value-from``). Output: per episode the steps, the
reward, whether the env terminated, and (for the cart-pole envs) the cart's largest distance from the centre.
"""

from __future__ import annotations

import itertools
import json
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from pets.runs.fileio import atomic_write_bytes, run_dir_error, writable_dir_error
from pets.tools.cli import EXIT_FAILED, OneLineParser, fail

PROG = "pets.oracle"


def not_mujoco(env: Any) -> str | None:
    """Why ``env`` (unwrapped) cannot be the oracle's simulator (a user's env of another simulator), or None."""
    if hasattr(env, "data") and hasattr(env, "set_state"):
        return None
    return (
        f"the env {type(env).__name__} is not a MuJoCo env (no data.qpos and set_state): pets.oracle scores each "
        "candidate on a copy of the simulator set to the live env's state"
    )


class SimulatorEvaluator:
    """The planner's objective with the true simulator: ``(obs, actions (N, H, A), generator) -> returns (N,)``.

    Scores from the current state of ``env`` (a live gymnasium MuJoCo env; ``obs`` is ignored, the full
    simulator state is used): per candidate, a private copy of the env is set to that state and stepped through
    the actions, summing rewards until the horizon ends or the env terminates (the terminating step's reward
    counts; ``termination_penalty`` is then subtracted, as in the learned model's evaluator), plus
    ``terminal_value`` of the last observation where it did not terminate. The live env is not touched. With
    ``feedback`` (pets.planning.feedback) a candidate is the gains of a feedback law, rolled out in closed loop for
    ``feedback.horizon`` steps from ``obs``.
    """

    def __init__(
        self,
        env: Any,
        make_env: Any,
        feedback: Any = None,
        termination_penalty: float = 0.0,
        terminal_value: Callable[[Tensor], Tensor] | None = None,
    ) -> None:
        from pets.config import ConfigError

        self.env = env.unwrapped
        if problem := not_mujoco(self.env):
            raise ConfigError(problem)
        self.feedback = feedback
        self.termination_penalty = termination_penalty
        self.terminal_value = terminal_value
        self.sim = make_env().unwrapped
        self.sim.reset(seed=0)  # gymnasium requires a reset before step; the state is overwritten per candidate

    def __call__(self, obs: Tensor, actions: Tensor, generator: torch.Generator | None = None) -> Tensor:
        qpos, qvel = self.env.data.qpos.copy(), self.env.data.qvel.copy()
        returns = np.zeros(actions.shape[0])
        survived: dict[int, np.ndarray] = {}  # candidate -> its last observation, where it did not terminate
        fb = self.feedback
        start = torch.as_tensor(obs, dtype=torch.float32).reshape(1, -1).cpu()
        for i, candidate in enumerate(actions.detach().cpu()):
            self.sim.set_state(qpos, qvel)
            state = start
            for t in range(candidate.shape[0] if fb is None else fb.horizon):
                action = candidate[t] if fb is None else fb.actions(candidate.unsqueeze(0), state)[0]
                next_obs, reward, terminated, _, _ = self.sim.step(action.numpy().astype(np.float64))
                returns[i] += reward
                if terminated:
                    returns[i] -= self.termination_penalty
                    break
                if fb is not None:
                    state = torch.as_tensor(next_obs, dtype=torch.float32).reshape(1, -1)
            else:
                survived[i] = next_obs
        if self.terminal_value is not None and survived:
            with torch.no_grad():
                last = torch.as_tensor(np.stack(list(survived.values())), dtype=torch.float32)
                returns[list(survived)] += self.terminal_value(last).double().numpy()
        return torch.as_tensor(returns, dtype=actions.dtype, device=actions.device)


def run_episode(
    cfg: Any,
    spec: Any,
    seed: int,
    episode: int,
    steps: int | None = None,
    terminal_value: Callable[[Tensor], Tensor] | None = None,
) -> dict[str, Any]:
    """One episode (at most ``steps`` long; default the env's own limit) of MPC with :class:`SimulatorEvaluator`:
    steps, reward, terminated, largest |cart x| (cart-pole envs), seconds."""
    from pets.agent import MPCAgent
    from pets.builder import make_feedback, make_planner
    from pets.data.collect import episode_seeds
    from pets.data.rollout import MPCPolicy, RandomPolicy, run_steps
    from pets.data.rollout import run_episode as run_policy
    from pets.loop import SEED_PHASE, episode_reset_seed

    limit = steps or spec.episode_length
    env = spec.make(max_episode_steps=limit)
    device = torch.device("cpu")
    feedback = make_feedback(cfg, spec, device)
    if feedback is not None and not feedback.fixed_scale:  # the features' scale from random steps, as PETS' seed data
        random_steps = run_steps(
            env,
            RandomPolicy(spec.action_low, spec.action_high),
            max(cfg.seed_steps, 2),
            max_steps=limit,
            reset_seeds=(episode_reset_seed(seed, SEED_PHASE + i) for i in itertools.count()),
            rng=np.random.default_rng(seed),
        )
        feedback.fit_scale(torch.as_tensor(np.concatenate([e.obs for e in random_steps]), dtype=torch.float32))
    agent = MPCAgent(
        make_planner(cfg, spec, device, feedback),
        SimulatorEvaluator(env, spec.make, feedback, cfg.planner.termination_penalty, terminal_value),
        replan_every=cfg.planner.replan_every,
        action_low=spec.action_low,
        action_high=spec.action_high,
        device=device,
        generator=torch.Generator(device=device).manual_seed(seed),
        feedback=feedback,
    )
    start = time.perf_counter()
    ep = run_policy(env, MPCPolicy(agent), max_steps=limit, reset_seed=episode_seeds(seed, episode)[0])
    seconds = time.perf_counter() - start
    env.close()
    result = {"steps": len(ep), "reward": ep.total_reward, "terminated": bool(ep.terminated[-1]), "seconds": seconds}
    if spec.name in ("invertedpendulum", "inverteddoublependulum"):  # observation 0 is the cart's position
        result["max_abs_cart_x"] = float(np.abs(ep.next_obs[:, 0]).max())
    return result


def build_parser() -> OneLineParser:
    p = OneLineParser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("--env", required=True, help="environment: a catalogue name or a gymnasium id")
    p.add_argument("--preset", default="research", help="config preset: research (default), fast or locomotion")
    p.add_argument("--steps", type=int, default=None, help="episode length (default: the env's own)")
    p.add_argument("--episodes", type=int, default=1, help="episodes (default 1)")
    p.add_argument("--seed", type=int, default=0, help="seed of the env resets and the planner")
    p.add_argument("--json", type=Path, default=None, help="also write the results as JSON to this file")
    p.add_argument("--quiet", action="store_true", help="no line per episode while running")
    p.add_argument(
        "--value-from",
        type=Path,
        default=None,
        metavar="RUN_DIR",
        help="add the terminal value this run learned (value.enabled) to the candidates that do not terminate",
    )
    p.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides: planner.*, threads, seed_steps")
    return p


#: The config keys besides ``planner.*`` that the oracle reads (the threads; the random steps that scale feedback).
ORACLE_KEYS = ("threads", "seed_steps")


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_intermixed_args(argv)
    for name, low in (("steps", 1), ("episodes", 1), ("seed", 0)):
        value = getattr(args, name)
        if value is not None and value < low:
            fail(PROG, f"--{name} must be >= {low}, got {value}")
    if args.json is not None:
        problem = "is a directory; give a file name" if args.json.is_dir() else writable_dir_error(args.json.parent)
        if problem:
            fail(PROG, f"cannot write --json {args.json}: {problem}")
    from omegaconf import OmegaConf

    import envs
    from pets.builder import check_memory
    from pets.config import ConfigError, make_config, parse_overrides
    from pets.data.rollout import EnvFailed

    try:
        overrides = parse_overrides(args.overrides)
        unused = [k for k in overrides if not k.startswith("planner.") and k not in ORACLE_KEYS]
        if unused:  # a model or training key would be silently ignored: no model plans here
            raise ConfigError(
                f"the key {unused[0]} is not read when planning with the true dynamics; the keys are planner.* and "
                + ", ".join(ORACLE_KEYS)
            )
        cfg = make_config(args.env, "delta", args.preset, {**overrides, "device": "cpu"})  # it plans on the CPU
        spec = envs.get(cfg.env)
        if problem := not_mujoco(spec.make().unwrapped):  # before any work: one line
            raise ConfigError(problem)
        check_memory(cfg, spec, steps=0)  # population x horizon this machine cannot hold: one line, no OOM kill
    except (ValueError, KeyError) as err:  # ConfigError is a ValueError
        fail(PROG, str(err).strip("'\""))
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    value = None if args.value_from is None else _run_value(args.value_from, spec)
    p = cfg.planner
    print(
        f"{PROG}: {spec.name}, {p.name}, horizon {p.horizon}, population {p.population}, "
        f"{p.iterations} iterations, true dynamics"
        + (f", the terminal value of {args.value_from}" if args.value_from else ""),
        file=sys.stderr,
    )
    results = []
    for episode in range(args.episodes):
        try:
            result = run_episode(cfg, spec, args.seed, episode, args.steps, value)
        except ConfigError as err:
            fail(PROG, str(err))
        except EnvFailed as err:  # your env's step raised or returned what is not an observation: one line, exit 3
            fail(PROG, f"episode {episode}: {err}", EXIT_FAILED)
        results.append(result)
        if not args.quiet:
            extra = f", max |cart x| {result['max_abs_cart_x']:.2f}" if "max_abs_cart_x" in result else ""
            print(
                f"episode {episode}: {result['steps']} steps, reward {result['reward']:.1f}, "
                f"{'terminated' if result['terminated'] else 'time limit'}{extra}, {result['seconds']:.0f} s"
            )
    if args.json is not None:
        record = {"planner": OmegaConf.to_container(p), "episodes": results}
        if args.value_from is not None:
            record["value_from"] = str(args.value_from)
        atomic_write_bytes(args.json, json.dumps(record, indent=1).encode())
    return 0


def _run_value(run_dir: Path, spec: Any) -> Any:
    """The terminal value that the run in ``run_dir`` learned, for this env; one line and exit 2 otherwise."""
    from pets.builder import load_value
    from pets.config import ConfigError, load_config
    from pets.runs import rundir

    if problem := run_dir_error(run_dir):
        fail(PROG, f"--value-from {problem}")
    try:
        run_cfg = load_config(str(run_dir / rundir.CONFIG_FILE))
        if run_cfg.env != spec.name:
            raise ConfigError(f"--value-from {run_dir} is a run of {run_cfg.env}, not of {spec.name}")
        if not run_cfg.value.enabled:
            raise ConfigError(f"--value-from {run_dir} learned no terminal value (its value.enabled is false)")
        value = load_value(run_dir, run_cfg, spec)
    except (ValueError, OSError) as err:  # ConfigError is a ValueError
        fail(PROG, str(err))
    return value.eval()


if __name__ == "__main__":
    sys.exit(main())
