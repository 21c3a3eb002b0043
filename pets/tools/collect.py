"""The ``pets.collect`` command: trajectories from a catalogue env into an ``.npz`` data set.

    python -m pets.collect --env ENV --policy random|smooth-random[:BETA]|run:RUN_DIR|sb3:AGENT.zip
                           [--episodes N] [--seed S] [--max-steps T] [--device D] [--deterministic] [--quiet]
                           --out FILE.npz [imports=[MODULE,...]]
    python -m pets.collect --env ENV --policy sac:STEPS [--seed S] [--max-steps T] [--save-agent SAC.zip]
                           --out FILE.npz [imports=[MODULE,...]]

What it does, and what it writes: :mod:`pets.data.collect`. Of the config keys it takes ``imports`` only (modules
imported before the env is built, e.g. one that registers the group codec of ``--env my_env:SPEC``'s layout,
:mod:`pets.imports`); its other settings are its options.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from pets.data.collect import collect, collect_sac, make_policy, parse_policy, run_env_name
from pets.data.datasets import save_dataset
from pets.runs.fileio import atomic_write_bytes, writable_dir_error
from pets.tools.cli import OneLineParser, add_threads_option, fail, interruptible, set_threads

PROG = "pets.collect"


def build_parser() -> OneLineParser:
    p = OneLineParser(prog=PROG, description="Collect trajectories from a catalogue env into an .npz data set.")
    p.add_argument("--env", help="env (catalogue name, gymnasium id or module:ATTR); optional with --policy run:DIR")
    p.add_argument(
        "--policy",
        required=True,
        help="random | smooth-random[:BETA] (BETA in [0,1), default 0.9) | run:RUN_DIR | sb3:AGENT.zip | "
        "sac:STEPS (train SAC for STEPS env steps and write every transition it experienced)",
    )
    p.add_argument("--episodes", type=int, help="number of episodes (default 10; not with sac:STEPS)")
    p.add_argument("--seed", type=int, default=0, help="seed of resets and policy (default 0)")
    p.add_argument("--max-steps", type=int, help="steps per episode at most (default: the env's episode length)")
    p.add_argument("--device", choices=("cpu", "cuda", "auto"), default="auto", help="device of a run/sb3/sac policy")
    p.add_argument("--deterministic", action="store_true", help="sb3: policies take their mean action")
    p.add_argument("--save-agent", type=Path, help="sac:STEPS only: save the trained agent here (SB3 .zip)")
    add_threads_option(p)
    p.add_argument("--out", type=Path, required=True, help="output .npz file, new (written atomically)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument(
        "overrides",
        nargs="*",
        metavar="imports=[MODULE,...]",
        help="modules imported before the env is built (your own codecs, models, planners register there)",
    )
    return p


def _import_given(items: list[str]) -> None:
    """Import the modules of ``imports=[...]``, the one config key pets.collect takes; exit 2 (one line) for
    another key or a module that fails."""
    from pets.config import ConfigError, parse_overrides
    from pets.imports import import_modules

    try:
        given = parse_overrides(items)
        other = [f"{key}={value}" for key, value in given.items() if key != "imports"]
        if other:
            raise ConfigError(
                f"pets.collect takes one config key, imports=[MODULE,...], got {' '.join(other)}; its other settings "
                "are options (--seed, --max-steps, --device, --threads)"
            )
        import_modules(given.get("imports", []))
    except ConfigError as err:
        fail(PROG, str(err))


def _train_sac(args: argparse.Namespace, spec: Any, steps: int) -> tuple[dict[str, np.ndarray], float]:
    """SAC's data set (going on from ``OUT.sac-checkpoint`` if there is one) and its seconds; the agent saved to
    ``--save-agent`` if given."""
    from pets.data.sb3 import agent_bytes, sac_checkpoint_path
    from pets.tools.cli import write_failed

    start = time.perf_counter()
    try:
        data, agent = collect_sac(
            spec,
            steps,
            args.seed,
            args.max_steps,
            device=args.device,
            progress=not args.quiet,
            checkpoint=sac_checkpoint_path(args.out),
        )
    except ValueError as err:  # a checkpoint of other settings, or unreadable
        fail(PROG, str(err))
    seconds = time.perf_counter() - start
    if args.save_agent is not None:
        try:
            atomic_write_bytes(args.save_agent, agent_bytes(agent))
        except OSError as err:
            write_failed(PROG, err, "no data set was written either; free space, then collect again")
    return data, seconds


def _check_outputs(out: Path, save_agent: Path | None) -> None:
    """Exit 2 (one line) unless ``--out`` (an .npz) and ``--save-agent`` are new files in writable folders."""
    if out.suffix != ".npz":
        fail(PROG, f"--out {out} must name an .npz file (e.g. {out.with_suffix('.npz').name})")
    for option, path in (("--out", out), ("--save-agent", save_agent)):
        if path is None:
            continue
        if path.is_dir():
            fail(PROG, f"{option} {path} is a directory; give a file name")
        if path.exists():
            fail(PROG, f"{option} {path} exists; pets.collect never writes over a file: pick another name or delete it")
        problem = writable_dir_error(path.parent)  # before collecting, not after
        if problem:
            fail(PROG, f"cannot write {option} {path}: {problem}")


@interruptible(
    PROG,
    "nothing was written (the data set is written only when the collection is complete; sac:STEPS goes on from "
    "its checkpoint OUT.sac-checkpoint, written every 10,000 steps, when the same command runs again)",
)
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_intermixed_args(argv)
    try:
        kind, arg = parse_policy(args.policy)
    except ValueError as err:
        fail(PROG, str(err))
    if kind == "sac" and args.episodes is not None:
        fail(PROG, "--episodes does not apply to sac:STEPS (it collects every step SAC trains on); drop it")
    if kind != "sac" and args.save_agent is not None:
        fail(PROG, "--save-agent applies only to --policy sac:STEPS")
    if args.deterministic and kind != "sb3":
        fail(PROG, "--deterministic applies only to --policy sb3:AGENT.zip")
    episodes = 10 if args.episodes is None else args.episodes
    if episodes < 1:
        fail(PROG, f"--episodes must be >= 1, got {episodes}")
    if args.max_steps is not None and args.max_steps < 1:
        fail(PROG, f"--max-steps must be >= 1, got {args.max_steps}")
    if args.seed < 0:
        fail(PROG, f"--seed must be >= 0, got {args.seed}")
    if kind == "run" and not arg.is_dir():
        fail(PROG, f"run directory {arg} does not exist")
    if kind == "sb3" and not arg.is_file():
        fail(PROG, f"SB3 agent {arg} does not exist")
    if kind != "run" and not args.env:
        fail(PROG, "--env is required (except with --policy run:RUN_DIR, which uses the run's env)")
    _check_outputs(args.out, args.save_agent)
    if kind in ("sac", "sb3"):
        from pets.data.sb3 import INSTALL_HINT, require_sb3

        try:
            require_sb3()
        except ImportError:
            fail(PROG, INSTALL_HINT)

    from omegaconf.errors import OmegaConfBaseException

    import envs
    from pets.config import ConfigError

    set_threads(args.threads)
    _import_given(args.overrides)  # before the env: its layout may use a codec such a module registers
    try:
        name = args.env if args.env else run_env_name(arg)
        spec = envs.get(name)
        policy = None if kind == "sac" else make_policy(args.policy, spec, args.seed, args.device, args.deterministic)
    except (ValueError, ConfigError, OmegaConfBaseException) as err:  # the last: a config.yaml off the schema
        fail(PROG, str(err))
    if kind == "sac":
        data, seconds = _train_sac(args, spec, arg)
    else:
        from pets.data.rollout import EnvFailed
        from pets.planning.planners import PlanningFailed
        from pets.tools.cli import EXIT_FAILED

        try:
            data = collect(spec, policy, episodes, args.seed, args.max_steps, progress=not args.quiet)
        except (PlanningFailed, EnvFailed) as err:  # a run: policy whose model predicts non-finite states; your env
            fail(PROG, f"{policy.name}: {err}; nothing was written", EXIT_FAILED)
    from pets.tools.cli import write_failed

    try:
        save_dataset(args.out, data)
    except OSError as err:  # a full disk: the temporary file is removed, an older --out file stays as it was
        write_failed(PROG, err, "nothing was written; free space or pick another --out, then collect again")
    if kind == "sac":
        from pets.data.sb3 import sac_checkpoint_path

        sac_checkpoint_path(args.out).unlink(missing_ok=True)  # the data set is written: nothing left to resume
    lengths = data["lengths"]
    rewards = np.nansum(data["rew"], axis=1)
    print(
        f"{args.out}: {spec.name}, {len(lengths)} episodes, {int(lengths.sum())} transitions "
        f"(lengths {int(lengths.min())}..{int(lengths.max())}), policy {data['policy']}, "
        f"mean episode reward {float(rewards.mean()):.3f}"
    )
    if kind == "sac":
        last = rewards[-min(10, len(rewards)) :]
        at = data.get("sac_resumed_at")
        resumed = (
            f" ({arg / seconds:.0f} steps/s)"
            if at is None
            else f" (this session; went on from its checkpoint at step {int(at[-1])})"
        )
        print(
            f"SAC: {arg} steps in {seconds:.1f} s{resumed}; mean reward of the last "
            f"{len(last)} episodes {float(last.mean()):.3f}"
            + (f"; agent saved to {args.save_agent}" if args.save_agent is not None else "")
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
