"""Model-training benchmark: epochs per second and holdout error of two training paths, one process.

    python -m pets.bench_train [--env halfcheetah] [--model delta] [--preset research] [--transitions 5000]
                               [--epochs 5] [--repeats 3] [--compile] [key=value ...]

Trains the configured ensemble (``model.*``; research: 7 x 4 x 200, batch 256) on ``--transitions`` random
transitions for exactly ``--epochs`` epochs (no early stopping) per row, ``--repeats`` times with the rows
taking turns (so load changes hit both), from the same initial weights and generator seed. Rows: fp32 against
bf16 autocast (eager); with ``--compile``, the eager step against ``model.compile=true`` at the config's
``model.precision``. The compiled row keeps one trainer per repeat's model but compiles once per process (a
warm-up training first, timed apart: the one-off compile cost). Prints per row the median epochs per second by
wall clock and by process CPU time (``time.process_time``: what a loaded machine does not inflate), and the final
holdout error (``ModelTrainer``'s standardised one-step error), then the ratios.
"""

from __future__ import annotations

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
from pets.runs.hardware import cpu_isa
from pets.tools.cli import OneLineParser, fail


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


def main(argv: list[str] | None = None) -> int:
    from pets.config import HEADS, PRESETS

    ap = OneLineParser(prog="pets.bench_train", description=__doc__.splitlines()[0])
    ap.add_argument("--env", default="halfcheetah")
    ap.add_argument("--model", choices=HEADS, default="delta")
    ap.add_argument("--preset", choices=tuple(PRESETS), default="research")
    ap.add_argument("--transitions", type=int, default=5000)
    ap.add_argument("--epochs", type=int, default=5)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--compile", action="store_true", help="eager against model.compile=true (else fp32 vs bf16)")
    ap.add_argument("overrides", nargs="*", metavar="key=value")
    args = ap.parse_intermixed_args(argv)
    try:
        if min(args.transitions, args.epochs, args.repeats) < 1:
            raise ConfigError("--transitions, --epochs and --repeats must be >= 1")
        cfg = make_config(envs.get(args.env).name, args.model, args.preset, parse_overrides(args.overrides))
    except (ConfigError, ValueError) as err:
        fail("pets.bench_train", str(err))
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    spec = envs.get(cfg.env)
    m = cfg.model
    if args.compile:
        rows = [Row(f"eager {m.precision}", m.precision, False), Row(f"compiled {m.precision}", m.precision, True)]
    else:
        rows = [Row("fp32", "fp32", False), Row("bf16", "bf16", False)]
    print(
        f"{cfg.env} / {cfg.head} on {cfg.device} ({torch.get_num_threads()} threads, CPU: {cpu_isa()}): ensemble "
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
