"""Trajectory pictures of an offline study: truth against each model's open-loop prediction, one figure per env.

    python docs/scripts/trajectory_figures.py STUDY_DIR --envs ant,reacher --models delta,gem --seed 0 \
        --figures docs/figures [--steps 0,15,45] [--start 200] [--threads 1]

For every env: the runs ``STUDY_DIR/runs/ENV-MODEL-sSEED`` (the study's data set 0), rendered by
``pets.visualize`` on the study's test set (``STUDY_DIR/data/ENV-test.npz``), the same start point for every
model: episode 0 from step ``--start`` (earlier when the episode is too short; the longest episode when episode 0
is shorter than the last column). Columns ``--steps`` (default t = 0, 15, 45) and, where it is earlier, the first
evaluated horizon at which delta no longer tracks the state (the study's ``primary.csv``: the horizons outside
``tracking_horizons``).
Writes ``FIGURES/trajectories_ENV.png`` and prints one line per figure (env, episode, start, columns).
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np
import torch

from pets.data.datasets import load_dataset
from pets.tools.visualize import visualize


def first_untracked_horizon(study: Path, env: str) -> int | None:
    """The shortest evaluated horizon of ``env`` outside delta's tracking horizons (None: it tracks at all)."""
    with open(study / "summary.csv", newline="") as f:
        evaluated = {int(r["horizon"]) for r in csv.DictReader(f) if r["env"] == env}
    with open(study / "primary.csv", newline="") as f:
        rows = [r for r in csv.DictReader(f) if r["env"] == env and r["model"] == "delta"]
    if not rows:
        raise SystemExit(f"{study}/primary.csv has no delta row for {env}")
    tracking = {int(h) for h in rows[0]["tracking_horizons"].split()}
    untracked = sorted(evaluated - tracking)
    return untracked[0] if untracked else None


def start_point(lengths: np.ndarray, last: int, start: int) -> tuple[int, int]:
    """(episode, start step): episode 0 from ``start`` or as late as fits, else the longest episode from 0."""
    episode = 0 if lengths[0] > last else int(np.argmax(lengths))
    if lengths[episode] <= last:
        raise SystemExit(f"no test episode is longer than {last} steps (longest {int(lengths.max())})")
    return episode, min(start, int(lengths[episode]) - last)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("study", type=Path, help="output directory of pets.compare offline")
    parser.add_argument("--envs", required=True, help="comma-separated envs")
    parser.add_argument("--models", default="delta,gem", help="comma-separated models, one row each")
    parser.add_argument("--seed", type=int, default=0, help="model seed of the runs (default 0)")
    parser.add_argument("--steps", default="0,15,45", help="columns: steps k (default 0,15,45)")
    parser.add_argument("--start", type=int, default=200, help="step of the test episode to start at (default 200)")
    parser.add_argument("--figures", type=Path, default=Path("docs/figures"), help="output directory")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    models, columns = args.models.split(","), [int(k) for k in args.steps.split(",")]
    args.figures.mkdir(parents=True, exist_ok=True)
    for env in args.envs.split(","):
        untracked = first_untracked_horizon(args.study, env)
        steps = sorted({*columns, *([untracked] if untracked is not None and untracked < max(columns) else [])})
        data = args.study / "data" / f"{env}-test.npz"
        episode, start = start_point(np.asarray(load_dataset(data)["lengths"]), max(steps), args.start)
        runs = [args.study / "runs" / f"{env}-{model}-s{args.seed}" for model in models]
        missing = [str(r) for r in runs if not (r / "checkpoint.pt").is_file()]
        if missing:
            raise SystemExit(f"no trained run at {', '.join(missing)}")
        out = args.figures / f"trajectories_{env}.png"
        visualize(runs, data, out, steps=steps, episode=episode, start=start, labels=models, size=(224, 168), env=env)
        print(f"{out}: {env}, {data.name} episode {episode} from step {start}, t = {', '.join(map(str, steps))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
