"""The ``pets.evaluate`` command: long-horizon prediction error of a trained model on recorded trajectories.

    python -m pets.evaluate --run RUN_DIR --data FILE.npz [--train-data TRAIN.npz] [--horizons 1,5,10,25,50]
                            [--starts K] [--seed S] [--mode mean|sample] [--device D] [--json OUT.json]
                            [--tensorboard]

What it does, and what it writes: :mod:`pets.learning.evaluation`.
"""

from __future__ import annotations

import sys
from pathlib import Path

from pets.learning.evaluation import (
    DEFAULT_HORIZONS,
    DEFAULT_STARTS,
    MODES,
    PROG,
    evaluate_loaded,
    format_table,
    load_inputs,
    parse_horizons,
    write_events,
)
from pets.runs.fileio import run_dir_error, writable_dir_error
from pets.tools.cli import OneLineParser, add_threads_option, fail, set_threads, write_json_result


def build_parser() -> OneLineParser:
    p = OneLineParser(prog=PROG, description="Long-horizon prediction error of a trained model on recorded data.")
    p.add_argument("--run", type=Path, required=True, help="run directory (run_pets.py or pets.train)")
    p.add_argument("--data", type=Path, required=True, help="data set written by pets.collect")
    p.add_argument(
        "--train-data",
        type=Path,
        help="the model's training data set: its observation std scales standardized_error (default: --data)",
    )
    p.add_argument(
        "--horizons", default=",".join(map(str, DEFAULT_HORIZONS)), help="comma-separated (default 1,5,10,25,50)"
    )
    p.add_argument("--starts", type=int, default=DEFAULT_STARTS, help=f"start points K (default {DEFAULT_STARTS})")
    p.add_argument("--seed", type=int, default=0, help="seed of the start points and of sampling (default 0)")
    p.add_argument("--mode", choices=MODES, default="mean", help="mean (ensemble mean, default) or sample (TS-inf)")
    p.add_argument("--device", choices=("cpu", "cuda", "auto"), default="auto", help="where the model runs")
    add_threads_option(p)
    p.add_argument("--json", type=Path, help="write the results as JSON here (atomically)")
    p.add_argument(
        "--tensorboard",
        action="store_true",
        help="also write the per-horizon errors as TensorBoard scalars eval/METRIC (step = horizon) in "
        "RUN/eval/DATA (the latest evaluation on DATA replaces an earlier one)",
    )
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        horizons = parse_horizons(args.horizons)
    except ValueError as err:
        fail(PROG, str(err))
    if args.starts < 1:
        fail(PROG, f"--starts must be >= 1, got {args.starts}")
    if problem := run_dir_error(args.run):
        fail(PROG, problem)
    from pets.data.datasets import missing_data_file

    for what, path in (("data file", args.data), ("train data file", args.train_data)):
        if path is not None and (problem := missing_data_file(path, what)):
            fail(PROG, problem)
    if args.json is not None and args.json.is_dir():
        fail(PROG, f"--json {args.json} is a directory; give a file name")
    problem = None if args.json is None else writable_dir_error(args.json.parent)
    if problem:
        fail(PROG, f"cannot write --json {args.json}: {problem}")

    from omegaconf.errors import OmegaConfBaseException

    from pets.config import ConfigError

    try:  # bad input fails here in one line; errors in the evaluation itself keep their traceback
        inputs = load_inputs(args.run, args.data, horizons, args.starts, args.mode, args.device, args.train_data)
    except (ValueError, ConfigError, OmegaConfBaseException) as err:  # the last: a config.yaml off the schema
        fail(PROG, str(err))
    set_threads(args.threads)
    result = evaluate_loaded(inputs, args.seed)
    print(format_table(result))
    if args.json is not None:
        write_json_result(PROG, args.json, result)
    if args.tensorboard:
        write_events(args.run, args.data, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
