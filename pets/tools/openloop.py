"""The ``pets.openloop`` command: open-loop planning with a trained model, or MPC with it frozen.

    python -m pets.openloop --run RUN_DIR [--planner NAME] [--steps 50] [--episodes K] [--seed S]
                            [--closed-loop] [--device D] [--threads T] [--json OUT] [--video DIR]
                            [planner.KEY=VALUE ...]

What it does, and what it writes: :mod:`pets.planning.openloop`.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

from pets.limits import SIZE_BOUNDS
from pets.planning.openloop import (
    DEFAULT_CLOSED_STEPS,
    DEFAULT_EPISODES,
    DEFAULT_STEPS,
    format_table,
    open_loop,
    planning_config,
)
from pets.runs.fileio import run_dir_error, writable_dir_error
from pets.tools.cli import EXIT_FAILED, OneLineParser, add_threads_option, fail, set_threads, write_json_result

PROG = "pets.openloop"


#: The most --steps: the planner's horizon bound.
STEPS_BOUND = SIZE_BOUNDS["planner.horizon"]


def build_parser() -> OneLineParser:
    p = OneLineParser(
        prog=PROG,
        description="Plan once from the initial state with a trained model and execute "
        "the plan in the real env without feedback.",
        epilog="Planner settings can be overridden as planner.KEY=VALUE, e.g. planner.population=200.",
    )
    p.add_argument("--run", type=Path, required=True, help="run directory (run_pets.py or pets.train)")
    p.add_argument(
        "--planner",
        default="cem",
        help="planner (planner.name; default cem): a name of the planner table, one registered by a module of the "
        "run's imports included (a name it lacks is refused with the accepted ones)",
    )
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
    add_threads_option(p)
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
    if args.steps > STEPS_BOUND:
        fail(PROG, f"--steps must be <= {STEPS_BOUND:,}, got {args.steps:,}")
    if args.episodes < 1:
        fail(PROG, f"--episodes must be >= 1, got {args.episodes}")
    if args.seed < 0:
        fail(PROG, f"--seed must be >= 0, got {args.seed}")
    if problem := run_dir_error(args.run):
        fail(PROG, problem)
    if args.json is not None and args.json.is_dir():
        fail(PROG, f"--json {args.json} is a directory; give a file name")
    problem = None if args.json is None else writable_dir_error(args.json.parent)
    if problem:
        fail(PROG, f"cannot write --json {args.json}: {problem}")
    from omegaconf.errors import OmegaConfBaseException

    import envs
    from pets.builder import check_memory
    from pets.config import ConfigError, load_config, parse_overrides

    if args.video is not None:
        problem = writable_dir_error(args.video)
        if problem:
            fail(PROG, f"cannot write --video {args.video}: {problem}")
    try:
        if args.video is not None:
            from pets.runs.video import require_video

            require_video()
        overrides = parse_overrides(args.overrides)
        cfg = load_config(str(args.run / "config.yaml"))
        planned = planning_config(cfg, args.planner, args.steps, overrides, closed=args.closed_loop)
        check_memory(planned, envs.get(planned.env), steps=0)  # the planner this machine cannot hold: one line
        if not (args.run / "checkpoint.pt").is_file():
            raise ConfigError(f"{args.run} has no checkpoint.pt yet (no trained model)")
    except (ValueError, OmegaConfBaseException) as err:  # ConfigError is a ValueError
        fail(PROG, str(err))
    set_threads(args.threads)
    from envs.render import RenderingUnavailable
    from pets.data.rollout import EnvFailed
    from pets.planning.planners import PlanningFailed

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
    except (PlanningFailed, EnvFailed) as err:  # the run's model predicts non-finite states; your env failed
        fail(PROG, f"{args.run}: {err}", EXIT_FAILED)
    print(format_table(result))
    if args.json is not None:
        write_json_result(PROG, args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
