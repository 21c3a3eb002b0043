"""Model-training benchmark: epochs per second and holdout error of two training paths, one process.

    python -m pets.bench_train [--env halfcheetah] [--model delta] [--preset research] [--device auto]
                               [--transitions 5000] [--epochs 5] [--repeats 3] [--compile] [key=value ...]

Trains the configured ensemble (``model.*``; research: 7 x 4 x 200, batch 256) on ``--transitions`` random
transitions for exactly ``--epochs`` epochs (no early stopping) per row, ``--repeats`` times with the rows
taking turns (so load changes hit both), from the same initial weights and generator seed. Rows: fp32 against
bf16 autocast (eager); with ``--compile``, the eager step against ``model.compile=true`` at the config's
``model.precision``. The compiled row keeps one trainer per repeat's model but compiles once per process (a
warm-up training first, timed apart: the one-off compile cost). Prints per row the median epochs per second by
wall clock and by process CPU time (``time.process_time``: what a loaded machine does not inflate), and the final
holdout error (``ModelTrainer``'s standardised one-step error), then the ratios; first, the machine and the command
(:func:`pets.tools.measure.machine`). ``--transitions`` must leave a holdout row (``model.holdout_ratio``).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import dataclass

import numpy as np
import torch
from omegaconf import DictConfig

import envs
from pets import builder
from pets.config import ConfigError, make_config, parse_overrides
from pets.data.rollout import collect_random
from pets.learning.trainer import ModelTrainer
from pets.models import make_model
from pets.tools.cli import OneLineParser, fail, import_given, positive_int
from pets.tools.measure import command_line, machine, machine_line

PROG = "pets.bench_train"


@dataclass(frozen=True)
class Row:
    """One benchmarked training path."""

    name: str
    precision: str
    compile: bool


def train_once(
    cfg: DictConfig,
    spec: envs.EnvSpec,
    data: tuple[np.ndarray, ...],
    row: Row,
    epochs: int,
    compiled: dict[str, ModelTrainer] | None = None,
) -> tuple[float, float, float]:
    """Wall seconds, process CPU seconds for ``epochs`` epochs and the final holdout error of one fresh model
    trained on ``row``'s path. ``compiled``: trainers by row name whose compiled step a compiled row reuses
    (torch.compile's cache is per function object: a fresh trainer would compile again)."""
    device = builder.resolve_device(cfg.device)
    torch.manual_seed(cfg.seed)
    model = make_model(cfg, spec, device)
    trainer = builder.make_trainer(cfg, model)
    trainer.precision, trainer.max_epochs, trainer.patience = row.precision, epochs, epochs + 1
    trainer.compile = row.compile
    if row.compile and compiled is not None:
        if row.name in compiled:  # the fresh weights into the compiled trainer's model, its Adam state reset
            trainer = compiled[row.name]
            trainer.model.load_state_dict(model.state_dict())
            trainer.optimizer.state.clear()
        else:
            compiled[row.name] = trainer
    obs, act, nxt = (torch.as_tensor(x, device=device) for x in data)
    t0, c0 = time.perf_counter(), time.process_time()
    result = trainer.train(obs, act, nxt, torch.Generator(device=device).manual_seed(cfg.seed + 1))
    return time.perf_counter() - t0, time.process_time() - c0, result.val_loss


def _arguments(argv: list[str] | None) -> tuple[argparse.Namespace, DictConfig]:
    """The options and the config, every check done before any training; bad input exits 2 with one line."""
    from pets.config import HEADS, PRESETS
    from pets.models import unknown_model

    ap = OneLineParser(prog=PROG, description=__doc__.splitlines()[0])
    ap.add_argument("--env", default="halfcheetah", help="a catalogue name, a gymnasium id or package.module:ATTR")
    ap.add_argument("--model", default="delta", help=f"dynamics model: {', '.join(HEADS)} or your own (imports=[...])")
    ap.add_argument("--preset", choices=tuple(PRESETS), default="research")
    ap.add_argument("--device", choices=("cpu", "cuda", "auto"), help="training device (default: the config's, auto)")
    ap.add_argument("--transitions", type=positive_int, default=5000, help="random transitions to train on")
    ap.add_argument("--epochs", type=positive_int, default=5, help="epochs per training (no early stopping)")
    ap.add_argument("--repeats", type=positive_int, default=3, help="trainings per row (default 3; medians)")
    ap.add_argument("--compile", action="store_true", help="eager against model.compile=true (else fp32 vs bf16)")
    ap.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides, e.g. threads=1")
    args = ap.parse_intermixed_args(argv)
    try:
        import_given(args.overrides)  # your own models register there: before --model is looked up
        if problem := unknown_model(args.model):
            raise ConfigError(problem)
        overrides = parse_overrides(args.overrides)
        if args.device is not None:
            overrides["device"] = args.device
        cfg = make_config(envs.get(args.env).name, args.model, args.preset, overrides)
        builder.resolve_device(cfg.device)  # cuda without one: one line
        m = cfg.model
        if min(int(args.transitions * m.holdout_ratio), m.max_holdout) < 1:  # pets.learning.sampling.split_holdout
            raise ConfigError(
                f"--transitions {args.transitions} leaves no holdout rows at model.holdout_ratio={m.holdout_ratio}, "
                f"model.max_holdout={m.max_holdout}: the holdout error could not be measured; give more "
                "--transitions or a larger model.holdout_ratio"
            )
    except (ConfigError, ValueError) as err:
        fail(PROG, str(err))
    return args, cfg


def main(argv: list[str] | None = None) -> int:
    args, cfg = _arguments(argv)
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    spec = envs.get(cfg.env)
    m = cfg.model
    if args.compile:
        rows = [Row(f"eager {m.precision}", m.precision, False), Row(f"compiled {m.precision}", m.precision, True)]
    else:
        rows = [Row("fp32", "fp32", False), Row("bf16", "bf16", False)]
    device = builder.resolve_device(cfg.device)
    print(f"{machine_line(machine(device))}\ncommand: {command_line(PROG, argv)}")
    print(
        f"{cfg.env} / {cfg.head} on {device}: ensemble "
        f"{m.ensemble_size}x{m.num_layers}x{m.hidden_size}, batch {m.batch_size}, {args.transitions} transitions, "
        f"{args.epochs} epochs"
    )
    data = collect_random(spec, args.transitions, cfg.seed)
    compiled: dict[str, ModelTrainer] = {}
    for row in rows:
        if row.compile:  # the one-off cost: compile (cold or warm inductor cache) + the warm-up epochs
            wall, cpu, _ = train_once(cfg, spec, data, row, args.epochs, compiled)
            print(f"{row.name}: first training (compiles) {wall:.2f} s wall, {cpu:.2f} s CPU")
    wall_s: dict[str, list[float]] = {r.name: [] for r in rows}
    cpu_s: dict[str, list[float]] = {r.name: [] for r in rows}
    errors: dict[str, float] = {}
    for _ in range(args.repeats):
        for row in rows:
            wall, cpu, err = train_once(cfg, spec, data, row, args.epochs, compiled)
            wall_s[row.name].append(wall)
            cpu_s[row.name].append(cpu)
            errors[row.name] = err  # the same every repeat (same seeds, same machine)
    rate = {r.name: args.epochs / statistics.median(wall_s[r.name]) for r in rows}
    cpu_rate = {r.name: args.epochs / statistics.median(cpu_s[r.name]) for r in rows}
    for r in rows:
        print(
            f"{r.name}: {rate[r.name]:.3f} epochs/s wall, {cpu_rate[r.name]:.3f} epochs/s CPU (medians of "
            f"{args.repeats}; CPU s per epoch {1 / cpu_rate[r.name]:.3f}), holdout error {errors[r.name]:.5f}"
        )
    base, other = rows[0].name, rows[1].name
    ratio = errors[other] / errors[base]
    print(
        f"{other} / {base}: speed {rate[other] / rate[base]:.2f}x wall, {cpu_rate[other] / cpu_rate[base]:.2f}x CPU, "
        f"holdout error {ratio:.4f} (relative difference {ratio - 1:+.2%})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
