"""Does model training work? One-step prediction of a briefly trained model vs the untrained network and "no change".

    python -m pets.onestep [--envs all|ENV,...] [--models delta,gem,...] [--episodes N] [--max-steps T]
                           [--epochs N] [--seed S] [--csv OUT.csv] [key=value ...]

Per env: train data from ``smooth-random:0.9`` (collect seed ``seed``), held-out data from a different policy,
``smooth-random:0.5`` (collect seed ``seed + 1``). Per model: ``pets.train``'s config (research preset,
overrides applied, ``model.max_epochs = --epochs``), trained on all train transitions. On every held-out
transition the one-step prediction (mean over the elites, as ``pets.evaluate --mode mean``) of

- the trained model, - the untrained network (same seed, normalisers fitted, no gradient step), - "no change"
  (next observation = current one),

is scored by two errors: ``std``: mean over the predicted observation entries of the squared error divided by
the variance of ``next_obs - obs`` on the train data (the trainer's holdout criterion, ``obs_change_scale``,
on the mean prediction of the elites); ``l2``: the Euclidean step error of ``pets.evaluate`` (groups compared on
the group). ``val_initial`` and ``val_final`` are the trainer's holdout criterion before and after training.
"""

from __future__ import annotations

import csv
import io
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from pets.runs.fileio import atomic_write_bytes, writable_dir_error
from pets.tools.cli import OneLineParser, fail

PROG = "pets.onestep"
TRAIN_POLICY = "smooth-random:0.9"
HELDOUT_POLICY = "smooth-random:0.5"
COLUMNS = (
    "env",
    "model",
    "transitions",
    "epochs",
    "val_initial",
    "val_final",
    "std_trained",
    "std_untrained",
    "std_nochange",
    "l2_trained",
    "l2_untrained",
    "l2_nochange",
)


def _errors(pred: Any, obs: Any, next_obs: Any, scale: Any, predicted: Any, layout: Any) -> tuple[float, float]:
    from pets.learning.evaluation import step_errors

    std = float((((pred - next_obs)[:, predicted] / scale) ** 2).mean())
    return std, float(step_errors(pred, next_obs, layout)["total"].mean())


def one_step_check(
    env: str,
    models: Sequence[str],
    *,
    episodes: int = 60,
    max_steps: int | None = 200,
    epochs: int = 40,
    seed: int = 0,
    overrides: Mapping[str, Any] | None = None,
) -> list[dict[str, Any]]:
    """One row (:data:`COLUMNS`) per model for ``env``; see the module docstring."""
    import torch

    import envs
    from pets import builder
    from pets.data.collect import collect
    from pets.data.datasets import transitions
    from pets.learning.offline import offline_config
    from pets.learning.trainer import obs_change_scale
    from pets.models import make_model

    spec = envs.get(env)
    train = [
        torch.as_tensor(a, dtype=torch.float32)
        for a in transitions(collect(spec, TRAIN_POLICY, episodes, seed=seed, max_steps=max_steps))
    ]
    held = [
        torch.as_tensor(a, dtype=torch.float32)
        for a in transitions(collect(spec, HELDOUT_POLICY, episodes, seed=seed + 1, max_steps=max_steps))
    ]
    predicted = list(spec.layout.predicted_indices)
    scale = obs_change_scale(train[0], train[2], torch.tensor(predicted))  # the trainer's holdout units
    obs, act, next_obs = held
    nochange = _errors(obs, obs, next_obs, scale, predicted, spec.layout)
    rows = []
    for name in models:
        cfg = offline_config(
            spec.name, name, {**dict(overrides or {}), "model.max_epochs": epochs}, seed=seed, device="cpu"
        )
        scores = {}
        for label, max_epochs in (("untrained", 0), ("trained", cfg.model.max_epochs)):
            torch.manual_seed(cfg.seed)
            model = make_model(cfg, spec, torch.device("cpu"))
            trainer = builder.make_trainer(cfg, model)
            trainer.max_epochs = max_epochs
            result = trainer.train(*train, torch.Generator().manual_seed(cfg.seed + 1))
            pred = model.rollout(obs, act[:, None])[:, 0]
            scores[label] = _errors(pred, obs, next_obs, scale, predicted, spec.layout)
        rows.append(
            {
                "env": spec.name,
                "model": name,
                "transitions": int(train[0].shape[0]),
                "epochs": result.epochs,
                "val_initial": result.initial_val_loss,
                "val_final": result.val_loss,
                "std_trained": scores["trained"][0],
                "std_untrained": scores["untrained"][0],
                "std_nochange": nochange[0],
                "l2_trained": scores["trained"][1],
                "l2_untrained": scores["untrained"][1],
                "l2_nochange": nochange[1],
            }
        )
    return rows


def _write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=COLUMNS)
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_bytes(path, buf.getvalue().encode())


def main(argv: list[str] | None = None) -> int:
    import envs
    from pets.config import HEADS, ConfigError, parse_overrides
    from pets.learning.offline import offline_config
    from pets.models import models_for

    parser = OneLineParser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", default="all", help="all, or a comma list of env names")
    parser.add_argument(
        "--models", default=None, help=f"comma list of --model values (default: those of {', '.join(HEADS)} that apply)"
    )
    parser.add_argument("--episodes", type=int, default=60, help="episodes of train and of held-out data")
    parser.add_argument("--max-steps", type=int, default=200, help="episode length cap")
    parser.add_argument("--epochs", type=int, default=40, help="model.max_epochs")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--csv", type=Path, default=None, help="also write the rows to this CSV file")
    parser.add_argument("overrides", nargs="*", help="config key=value overrides (e.g. threads=1)")
    args = parser.parse_intermixed_args(argv)
    try:
        names = envs.names() if args.envs == "all" else [envs.get(e).name for e in args.envs.split(",")]
        if min(args.episodes, args.max_steps, args.epochs) < 1 or args.seed < 0:
            raise ValueError("--episodes, --max-steps and --epochs must be >= 1, --seed >= 0")
        overrides = parse_overrides(args.overrides)
        if "device" in overrides:
            raise ValueError("pets.onestep runs on the CPU; device is not one of its keys")
        problem = None if args.csv is None else writable_dir_error(args.csv.resolve().parent)
        if problem:  # before the training, not after it
            raise ValueError(f"cannot write --csv {args.csv}: {problem}")
        models = {n: args.models.split(",") if args.models else models_for(envs.get(n)) for n in names}
        for name in names:  # every (env, model) config is valid before anything runs
            for model in models[name]:
                offline_config(name, model, {**overrides, "model.max_epochs": args.epochs}, seed=args.seed)
    except (ConfigError, ValueError) as err:
        fail(PROG, str(err))
    rows = []
    print(
        "| env | model | n | epochs | val initial -> final | std: trained / untrained / no change "
        "| l2: trained / untrained / no change |\n|---|---|---|---|---|---|---|"
    )
    for name in names:
        for row in one_step_check(
            name,
            models[name],
            episodes=args.episodes,
            max_steps=args.max_steps,
            epochs=args.epochs,
            seed=args.seed,
            overrides=overrides,
        ):
            rows.append(row)
            print(
                f"| {row['env']} | {row['model']} | {row['transitions']} | {row['epochs']} | "
                f"{row['val_initial']:.3g} -> {row['val_final']:.3g} | {row['std_trained']:.3f} / "
                f"{row['std_untrained']:.3f} / {row['std_nochange']:.3f} | {row['l2_trained']:.4g} / "
                f"{row['l2_untrained']:.4g} / {row['l2_nochange']:.4g} |",
                flush=True,
            )
            if args.csv:  # rewritten after every row, atomically: a long run keeps what it measured
                _write_csv(args.csv, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
