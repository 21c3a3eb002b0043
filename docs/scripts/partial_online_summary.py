"""The summary of an online study that is still running, from a snapshot of its run directories.

    python docs/scripts/partial_online_summary.py STUDY_OUT SNAPSHOT --envs ant --models delta,gem --seeds 0,1,2,3,4
        --trials 50 [--final-window 3] [--metrics-to DIR]

Copies every run's metrics.csv, config.yaml and history.csv (not the checkpoints) from ``STUDY_OUT/runs`` to
``SNAPSHOT/runs`` and writes the study's summary there (``pets.experiments.studies.online.summarise_online``: the
runs with all their trials enter the statistics, the others are listed as incomplete). Safe while the sweep runs:
it never writes under ``STUDY_OUT`` and starts no run. ``--metrics-to DIR`` also copies every run's metrics.csv
to ``DIR/RUN.csv`` (what to commit so that a lost machine loses no finished trial's numbers).
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

from pets.experiments.studies.online import summarise_online


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("study", type=Path)
    parser.add_argument("snapshot", type=Path)
    parser.add_argument("--envs", required=True)
    parser.add_argument("--models", required=True)
    parser.add_argument("--seeds", required=True)
    parser.add_argument("--trials", type=int, required=True)
    parser.add_argument("--final-window", type=int, default=3)
    parser.add_argument("--metrics-to", type=Path, default=None)
    args = parser.parse_args(argv)
    runs = sorted(p for p in (args.study / "runs").iterdir() if (p / "metrics.csv").is_file())
    for run in runs:
        dest = args.snapshot / "runs" / run.name
        dest.mkdir(parents=True, exist_ok=True)
        for name in ("metrics.csv", "config.yaml", "history.csv"):
            if (run / name).is_file():
                shutil.copy2(run / name, dest / name)
        if args.metrics_to is not None:
            args.metrics_to.mkdir(parents=True, exist_ok=True)
            shutil.copy2(run / "metrics.csv", args.metrics_to / f"{run.name}.csv")
    seeds = [int(s) for s in args.seeds.split(",")]
    rows = summarise_online(
        args.snapshot, args.envs.split(","), args.models.split(","), seeds, args.trials, args.final_window
    )
    complete = sum(int(r["n_seeds"]) + int(r["n_diverged"]) for r in rows)
    print(f"{len(runs)} runs copied, {complete} complete; summary in {args.snapshot / 'summary.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
