"""The ``pets.train`` command: offline training of a dynamics model on a collected data set, into a run directory.

    python -m pets.train --data FILE.npz --model MODEL --out RUN_DIR [--seed S] [--device D]
                         [--epochs N] [--preset research|fast|locomotion] [--protocol pets|paper] [--quiet]
                         [key=value ...]

What it does, and what it writes: :mod:`pets.learning.offline`.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

from pets.data.datasets import env_name, load_dataset, missing_data_file
from pets.learning.offline import OFFLINE_DEFAULTS, offline_config, train_offline
from pets.runs.fileio import writable_dir_error
from pets.tools.cli import (
    EXIT_FAILED,
    EXIT_INTERRUPTED,
    OneLineParser,
    fail,
    import_given,
    interruptible,
    stopped,
    write_failed,
)

PROG = "pets.train"


def build_parser() -> OneLineParser:
    from pets.config import DEVICES, HEADS, PRESETS
    from pets.data.protocols import PROTOCOLS

    p = OneLineParser(
        prog=PROG,
        description="Train a dynamics ensemble offline on a collected .npz data set.",
        epilog="Any config key can be overridden as key=value, e.g. model.hidden_size=200.",
    )
    p.add_argument("--data", type=Path, required=True, help="data set written by pets.collect")
    p.add_argument("--model", required=True, help=f"dynamics model: {', '.join(HEADS)} (docs/models.md)")
    p.add_argument("--out", type=Path, required=True, help="run directory to create")
    p.add_argument("--seed", type=int, help="seed (default 0)")
    p.add_argument("--device", choices=DEVICES, help="training device (default auto)")
    p.add_argument(
        "--epochs",
        type=int,
        help=f"max epochs (offline default {OFFLINE_DEFAULTS['model.max_epochs']}, "
        f"patience {OFFLINE_DEFAULTS['model.patience']})",
    )
    p.add_argument("--preset", choices=tuple(PRESETS), default="research", help="config preset (model sizes)")
    p.add_argument(
        "--protocol",
        choices=tuple(PROTOCOLS),
        default="pets",
        help="pets: bootstrap ensemble, early stopping (default); paper: the GEM paper's (pets.data.protocols)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides")
    return p


@interruptible(PROG, "no run was written (a run is written only when its training is complete)")
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_intermixed_args(argv)
    from pets.config import ConfigError, parse_overrides
    from pets.models import unknown_model

    try:  # your own models register in the modules of imports=[...]: imported before --model is looked up
        import_given(args.overrides)
    except ConfigError as err:
        fail(PROG, str(err))
    if problem := unknown_model(args.model):
        fail(PROG, problem)
    if problem := missing_data_file(args.data):
        fail(PROG, problem)
    if args.epochs is not None and args.epochs < 1:
        fail(PROG, f"--epochs must be >= 1, got {args.epochs}")
    if (args.out / "config.yaml").exists():
        fail(PROG, f"{args.out} already holds a run; pick another --out")

    try:  # validate everything up front (torch only where needed); errors in training keep their traceback
        overrides = parse_overrides(args.overrides)
        arrays = load_dataset(args.data)
        cfg = offline_config(
            env_name(arrays),
            args.model,
            overrides,
            preset=args.preset,
            seed=args.seed,
            device=args.device,
            epochs=args.epochs,
            protocol=args.protocol,
        )
        import envs
        from pets.builder import resolve_device

        spec = envs.get(cfg.env)
        if spec.name != cfg.env:
            raise ValueError(f"data set env {cfg.env!r} is not a canonical env name; re-collect it with pets.collect")
        for field, need in (("obs", spec.obs_dim), ("act", spec.act_dim)):
            width = arrays[field].shape[-1]
            if width != need:
                raise ValueError(
                    f"{args.data}: its '{field}' entries are {width} wide, but {cfg.env} (its 'env' field) has "
                    f"{field}_dim {need}; a data set of another env or version: collect it again with pets.collect"
                )
        resolve_device(cfg.device)
    except (ValueError, ConfigError) as err:  # ConfigError is a ValueError; named for the reader
        fail(PROG, str(err))
    from pets.learning.trainer import TrainingDiverged
    from pets.runs.fileio import DirectoryInUse, remove_if_unused

    created = not args.out.exists()
    problem = writable_dir_error(args.out)  # before training, not after
    if problem:
        fail(PROG, f"{problem}; pick another --out")

    try:
        out = train_offline(
            args.data,
            args.model,
            args.out,
            overrides,
            preset=args.preset,
            seed=args.seed,
            device=args.device,
            epochs=args.epochs,
            protocol=args.protocol,
            progress=not args.quiet,
        )
    except TrainingDiverged as err:  # nothing was written: train_offline writes the run only after training
        remove_if_unused(args.out, created)
        fail(PROG, f"{err}; no run directory was written", EXIT_FAILED)
    except DirectoryInUse as err:
        fail(PROG, f"{err}; wait for it to finish, or pick another --out")
    except ConfigError as err:  # a config this machine cannot hold; another process completed a run in --out
        remove_if_unused(args.out, created)  # only a folder this command made and left empty (or with its lock)
        fail(PROG, str(err))
    except OSError as err:  # a full disk: the files written before it are removed, no run is left half-written
        write_failed(PROG, err, "no run was written; free space or pick another --out, then train again")
    except KeyboardInterrupt:
        return _interrupted(args.out, created)
    try:
        _report(out, args.model)
    except KeyboardInterrupt:
        return _interrupted(args.out, created)
    return 0


def _interrupted(out: Path, created: bool) -> int:
    """Ctrl-C or SIGTERM during training or its report: one line saying whether the run in ``out`` is complete
    (written before the interrupt) or was not written (nothing of it is left; a folder this command made is
    removed)."""
    from pets.runs import rundir
    from pets.runs.fileio import remove_if_unused

    if (out / rundir.CONFIG_FILE).exists():
        print(f"\n{PROG}: {stopped()}; the run in {out} was complete before it", file=sys.stderr)
    else:
        remove_if_unused(out, created)
        print(f"\n{PROG}: {stopped()}; no run was written (a run is written only when complete)", file=sys.stderr)
    return EXIT_INTERRUPTED


def _report(out: Path, model: str) -> None:
    """Print the trained run's architecture search and result."""
    from pets.runs import rundir

    row = rundir.read_metrics(out / rundir.METRICS_FILE)[0]
    for c in rundir.load_checkpoint(out)["offline"]["search"]:
        print(f"  hidden layers {c['num_layers']} x {c['hidden_size']}: validation error {c['val_error']:.4g}")
    val = row["model_val_loss"]
    holdout = (
        f"holdout error {val:.4g} (standardised; no change ~ 1)"
        if math.isfinite(val)
        else "no holdout error (too few transitions to hold any out: more data gives one)"
    )
    print(
        f"{out}: {model} model trained on {int(row['env_steps'])} transitions, {int(row['model_epochs'])} "
        f"epochs, train loss {row['model_train_loss']:.4g}, {holdout}"
    )


if __name__ == "__main__":
    sys.exit(main())
