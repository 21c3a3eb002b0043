"""Collect trajectories from a catalogue env into an ``.npz`` data set (format: :mod:`pets.datasets`).

    python -m pets.collect --env ENV --policy random|smooth-random[:BETA]|run:RUN_DIR
                           [--episodes N] [--seed S] [--max-steps T] [--device D] [--quiet] --out FILE.npz

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

Seeding: episode ``i`` uses ``np.random.SeedSequence([seed, i])``: its first 32-bit word is the
``env.reset`` seed (stored as ``reset_seeds``), the sequence itself seeds the policy's numpy
generator. So a file is a pure function of its arguments (byte-identical for the same seed on the
same machine) and the first k episodes do not depend on ``--episodes``.

Episodes end at termination, at the env's time limit, or after ``--max-steps`` steps (which
replaces the env's own time limit, so it can also lengthen episodes).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pets.cli import OneLineParser, fail
from pets.datasets import save_dataset
from pets.fileio import writable_dir_error
from pets.rollout import MPCPolicy, Policy, RandomPolicy, run_episode

if TYPE_CHECKING:
    from envs import EnvSpec

PROG = "pets.collect"
POLICIES = ("random", "smooth-random[:BETA]", "run:RUN_DIR")
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
    """The MPC agent of a trained run directory (its model and its config's planner)."""

    def __init__(self, run_dir: str | Path, seed: int = 0, device: str = "auto") -> None:
        import torch

        from pets import builder

        self.run_dir = Path(run_dir)
        dev = builder.resolve_device(device)
        self.cfg, self.spec, self.model = builder.load_model(self.run_dir, dev)
        self.generator = torch.Generator(device=dev).manual_seed(int(seed))
        super().__init__(
            builder.make_agent(self.cfg, self.spec, self.model, dev, self.generator), f"run:{self.run_dir}"
        )


def parse_policy(text: str) -> tuple[str, Any]:
    """Split a ``--policy`` string into (kind, argument): ``("random", None)``, ``("smooth-random", beta)``,
    ``("run", Path)``. ValueError for anything else (no file access, no heavy imports)."""
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
    raise ValueError(f"unknown policy {text!r}; accepted: {', '.join(POLICIES)}")


def make_policy(text: str, spec: EnvSpec, seed: int = 0, device: str = "auto") -> Policy:
    """Build the policy named by ``text`` (see :func:`parse_policy`) for env ``spec``.

    A ``run:`` policy must come from a run on the same env (ValueError otherwise).
    """
    kind, arg = parse_policy(text)
    if kind == "random":
        return RandomPolicy(spec.action_low, spec.action_high)
    if kind == "smooth-random":
        return SmoothRandomPolicy(spec.action_low, spec.action_high, arg)
    run_env = run_env_name(arg)
    if run_env != spec.name:
        raise ValueError(
            f"run {arg} was trained on {run_env}, not on {spec.name}; collect on its env or pick another run"
        )
    return AgentPolicy(arg, seed=seed, device=device)


def run_env_name(run_dir: Path) -> str:
    """The env of a run directory (ValueError if it is not one or has no trained model yet)."""
    from pets import rundir
    from pets.config import load_config

    run_dir = Path(run_dir)
    if not (run_dir / rundir.CONFIG_FILE).is_file():
        raise ValueError(f"{run_dir} is not a run directory (no {rundir.CONFIG_FILE})")
    if not (run_dir / rundir.CHECKPOINT_FILE).is_file():
        raise ValueError(f"{run_dir} has no {rundir.CHECKPOINT_FILE} yet (no trained model)")
    return str(load_config(str(run_dir / rundir.CONFIG_FILE)).env)


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

    Returns the data set arrays of :mod:`pets.datasets` (NaN-padded to the longest episode) plus
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

    lengths = np.array([len(ep) for ep in episodes_run], np.int64)
    n, t = episodes, int(lengths.max())
    obs_arr = np.full((n, t + 1, spec.obs_dim), np.nan)
    act_arr = np.full((n, t, spec.act_dim), np.nan)
    rew_arr = np.full((n, t), np.nan)
    term_arr = np.zeros((n, t), bool)
    for i, (ep, k) in enumerate(zip(episodes_run, lengths)):
        obs_arr[i, : k + 1] = ep.states
        act_arr[i, :k] = ep.act
        rew_arr[i, :k] = ep.rewards
        term_arr[i, :k] = ep.terminated
    return {
        "obs": obs_arr,
        "act": act_arr,
        "rew": rew_arr,
        "terminated": term_arr,
        "lengths": lengths,
        "env": np.array(spec.name),
        "policy": np.array(policy.name),
        "seed": np.array(int(seed), np.int64),
        "reset_seeds": np.array(reset_seeds, np.int64),
    }


def build_parser() -> OneLineParser:
    p = OneLineParser(prog=PROG, description="Collect trajectories from a catalogue env into an .npz data set.")
    p.add_argument("--env", help="environment (catalogue name or gymnasium id); optional with --policy run:DIR")
    p.add_argument(
        "--policy", required=True, help="random | smooth-random[:BETA] (BETA in [0,1), default 0.9) | run:RUN_DIR"
    )
    p.add_argument("--episodes", type=int, default=10, help="number of episodes (default 10)")
    p.add_argument("--seed", type=int, default=0, help="seed of resets and policy (default 0)")
    p.add_argument("--max-steps", type=int, help="steps per episode at most (default: the env's episode length)")
    p.add_argument("--device", choices=("cpu", "cuda", "auto"), default="auto", help="device of a run: policy")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (default 0: torch's default)")
    p.add_argument("--out", type=Path, required=True, help="output .npz file (written atomically)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.episodes < 1:
        fail(PROG, f"--episodes must be >= 1, got {args.episodes}")
    if args.max_steps is not None and args.max_steps < 1:
        fail(PROG, f"--max-steps must be >= 1, got {args.max_steps}")
    if args.seed < 0:
        fail(PROG, f"--seed must be >= 0, got {args.seed}")
    if args.threads < 0:
        fail(PROG, f"--threads must be >= 0 (0: torch's default), got {args.threads}")
    try:
        kind, arg = parse_policy(args.policy)
    except ValueError as err:
        fail(PROG, str(err))
    if kind == "run" and not arg.is_dir():
        fail(PROG, f"run directory {arg} does not exist")
    if kind != "run" and not args.env:
        fail(PROG, "--env is required (except with --policy run:RUN_DIR, which uses the run's env)")
    if args.out.is_dir():
        fail(PROG, f"--out {args.out} is a directory; give a file name such as data.npz")
    problem = writable_dir_error(args.out.parent)  # before collecting, not after
    if problem:
        fail(PROG, f"cannot write --out {args.out}: {problem}")

    from omegaconf.errors import OmegaConfBaseException

    import envs
    from pets.config import ConfigError

    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    try:
        name = args.env if args.env else run_env_name(arg)
        spec = envs.get(name)
        policy = make_policy(args.policy, spec, seed=args.seed, device=args.device)
    except (ValueError, ConfigError, OmegaConfBaseException) as err:  # the last: a config.yaml off the schema
        fail(PROG, str(err))
    data = collect(spec, policy, args.episodes, args.seed, args.max_steps, progress=not args.quiet)
    save_dataset(args.out, data)
    lengths = data["lengths"]
    print(
        f"{args.out}: {spec.name}, {len(lengths)} episodes, {int(lengths.sum())} transitions "
        f"(lengths {int(lengths.min())}..{int(lengths.max())}), policy {policy.name}, "
        f"mean episode reward {float(np.nansum(data['rew'], axis=1).mean()):.3f}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
