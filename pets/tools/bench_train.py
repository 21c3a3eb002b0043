"""Model-training benchmark: epochs per second and holdout error, fp32 against bf16 autocast, one process.

    python -m pets.bench_train [--env halfcheetah] [--model delta] [--preset research] [--transitions 5000]
                               [--epochs 5] [--repeats 3] [key=value ...]

Trains the configured ensemble (``model.*``; research: 7 x 4 x 200, batch 256) on ``--transitions`` random
transitions for exactly ``--epochs`` epochs (no early stopping) per precision, ``--repeats`` times with the
precisions taking turns (so load changes hit both), from the same initial weights and generator seed. Prints
the median epochs per second and the final holdout error (``ModelTrainer``'s standardised one-step error)
of each precision, and the bf16 / fp32 ratios.
"""

from __future__ import annotations

import statistics
import sys
import time

import numpy as np
import torch
from omegaconf import DictConfig

import envs
from pets import builder
from pets.cli import OneLineParser, fail
from pets.config import ConfigError, make_config, parse_overrides
from pets.hardware import cpu_isa
from pets.models import make_model
from pets.tools.bench import collect_random

PRECISIONS = ("fp32", "bf16")


def train_once(
    cfg: DictConfig, spec: envs.EnvSpec, data: tuple[np.ndarray, ...], precision: str, epochs: int
) -> tuple[float, float]:
    """Seconds for ``epochs`` epochs and the final holdout error of one fresh model trained in ``precision``."""
    device = builder.resolve_device(cfg.device)
    torch.manual_seed(cfg.seed)
    model = make_model(cfg, spec, device)
    trainer = builder.make_trainer(cfg, model)
    trainer.precision, trainer.max_epochs, trainer.patience = precision, epochs, epochs + 1
    obs, act, nxt = (torch.as_tensor(x, device=device) for x in data)
    t0 = time.perf_counter()
    result = trainer.train(obs, act, nxt, torch.Generator(device=device).manual_seed(cfg.seed + 1))
    return time.perf_counter() - t0, result.val_loss


def main(argv: list[str] | None = None) -> int:
    from pets.config import HEADS, PRESETS

    ap = OneLineParser(prog="pets.bench_train", description=__doc__.splitlines()[0])
    ap.add_argument("--env", default="halfcheetah")
    ap.add_argument("--model", choices=HEADS, default="delta")
    ap.add_argument("--preset", choices=tuple(PRESETS), default="research")
    ap.add_argument("--transitions", type=int, default=5000)
    ap.add_argument("--epochs", type=int, default=5)
    ap.add_argument("--repeats", type=int, default=3)
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
    print(
        f"{cfg.env} / {cfg.head} on {cfg.device} ({torch.get_num_threads()} threads, CPU: {cpu_isa()}): ensemble "
        f"{m.ensemble_size}x{m.num_layers}x{m.hidden_size}, batch {m.batch_size}, {args.transitions} transitions, "
        f"{args.epochs} epochs"
    )
    data = collect_random(spec, args.transitions, cfg.seed)
    seconds: dict[str, list[float]] = {p: [] for p in PRECISIONS}
    errors: dict[str, float] = {}
    for _ in range(args.repeats):
        for p in PRECISIONS:
            s, err = train_once(cfg, spec, data, p, args.epochs)
            seconds[p].append(s)
            errors[p] = err  # the same every repeat (same seeds, same machine)
    rate = {p: args.epochs / statistics.median(seconds[p]) for p in PRECISIONS}
    for p in PRECISIONS:
        print(f"{p}: {rate[p]:.3f} epochs/s (median of {args.repeats}), holdout error {errors[p]:.5f}")
    print(
        f"bf16 / fp32: speed {rate['bf16'] / rate['fp32']:.2f}x, holdout error "
        f"{errors['bf16'] / errors['fp32']:.4f} (relative difference {errors['bf16'] / errors['fp32'] - 1:+.2%})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
