"""Projected CPU-hours of an online study, from short pilot runs of its arms (one thread each).

    python docs/scripts/study_cost.py PILOT_RUN_DIR [PILOT_RUN_DIR ...] --trials 50 --seeds 5 [--epochs 8]

Each pilot is a ``run_pets.py`` run directory of one arm at the study's config (at least 2 trials). From its
``metrics.csv`` (trial 0 excluded: it includes the one-off compile and start-up):

- planning: ``plan_seconds_per_step`` per env step (median over the trials), times the episode length;
- training: the rest of a trial's wall time, ``(delta wall - plan seconds) / (epochs x transitions)``, i.e. CPU
  seconds per epoch and transition (epochs over the whole data set, so training grows with the data);
- the one-off cost: trial 0's wall time minus what the model above gives for it.

Projection per run: the one-off cost + the sum over trials k of (planning + per-epoch-transition cost x epochs x
data at trial k), with ``--epochs`` epochs per trial (default: the pilots' mean; early stopping decides it in the
real runs) and every episode at full length (episodes that terminate early cost less). Printed per arm and for
the whole study (runs = arms x seeds); one thread per run, so CPU-hours = run-hours.
"""

from __future__ import annotations

import argparse
import csv
import statistics
import sys
from pathlib import Path

import yaml


def pilot_figures(run_dir: Path) -> dict[str, float]:
    rows = list(csv.DictReader(open(run_dir / "metrics.csv")))
    if len(rows) < 2:
        raise SystemExit(f"{run_dir}: a pilot needs at least 2 trials, found {len(rows)}")
    cfg = yaml.safe_load(open(run_dir / "config.yaml"))
    plan = statistics.median(float(r["plan_seconds_per_step"]) for r in rows[1:])
    per_epoch_transition, epochs = [], []
    for prev, row in zip(rows, rows[1:]):
        trial_s = float(row["wall_time_s"]) - float(prev["wall_time_s"])
        train_s = trial_s - float(row["plan_seconds_per_step"]) * int(row["episode_length"])
        per_epoch_transition.append(max(train_s, 0.0) / (int(row["model_epochs"]) * int(row["env_steps"])))
        epochs.append(int(row["model_epochs"]))
    c = statistics.median(per_epoch_transition)
    first = rows[0]
    first_model = float(first["plan_seconds_per_step"]) * int(first["episode_length"])
    first_model += c * int(first["model_epochs"]) * int(first["env_steps"])
    return {
        "head": cfg["head"],
        "plan_s_per_step": plan,
        "train_s_per_epoch_transition": c,
        "epochs": statistics.mean(int(r["model_epochs"]) for r in rows),
        "one_off_s": max(float(first["wall_time_s"]) - first_model, 0.0),
        "seed_steps": int(cfg["seed_steps"]),
        "episode_length": int(cfg["episode_length"]),
    }


def projected_run_seconds(f: dict[str, float], trials: int, epochs: float) -> float:
    length, total = f["episode_length"], f["one_off_s"]
    for k in range(trials):
        data = f["seed_steps"] + length * (k + 1)
        total += f["plan_s_per_step"] * length + f["train_s_per_epoch_transition"] * epochs * data
    return total


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("pilots", nargs="+", type=Path)
    parser.add_argument("--trials", type=int, required=True)
    parser.add_argument("--seeds", type=int, required=True)
    parser.add_argument("--epochs", type=float, default=None, help="epochs per trial (default: the pilots' mean)")
    args = parser.parse_args(argv)
    total = 0.0
    print("| arm | plan s/step | train s per epoch x 1k transitions | epochs/trial | one-off s | CPU-h per run |")
    print("|---|---|---|---|---|---|")
    for run in args.pilots:
        f = pilot_figures(run)
        epochs = f["epochs"] if args.epochs is None else args.epochs
        hours = projected_run_seconds(f, args.trials, epochs) / 3600
        total += hours * args.seeds
        print(
            f"| {f['head']} | {f['plan_s_per_step']:.3f} | {1000 * f['train_s_per_epoch_transition']:.3f} | "
            f"{epochs:.1f} | {f['one_off_s']:.0f} | {hours:.2f} |"
        )
    print(f"whole study: {len(args.pilots)} arms x {args.seeds} seeds x {args.trials} trials = {total:.1f} CPU-hours")
    return 0


if __name__ == "__main__":
    sys.exit(main())
