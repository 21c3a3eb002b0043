"""Where a run's CPU goes, per trial: the rows of its metrics.csv (planning, model training, the terminal value's fit,
all of the trial), for the committed cost breakdown of the locomotion preset (docs/studies/locomotion_gate.md,
its ``locomotion-cost`` block, made by ``pets.compare report``).

    python docs/scripts/cost_breakdown.py RUN_DIR [RUN_DIR ...] --out docs/results/locomotion_cost_breakdown.csv

Each run must have recorded ``train_cpu_s`` and ``value_cpu_s`` (runs made since the columns exist). A run's rows
replace its earlier rows in ``--out``; other runs' rows are kept.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pets.experiments import gate
from pets.experiments.report import write_rounded_csv

COLUMNS = ["run", "env", "head", "seed", "trial", "env_steps", "plan_cpu_s", "train_cpu_s", "value_cpu_s", "cpu_s"]


def run_rows(run_dir: Path) -> list[dict[str, object]]:
    """One row per trial of ``run_dir``: its CPU seconds by part, and all of the trial's (``cpu_s``)."""
    cfg, metrics = gate.read_run(run_dir)
    if not metrics or "train_cpu_s" not in metrics[0]:
        sys.exit(f"cost_breakdown.py: error: {run_dir} has no train_cpu_s column (made before it existed)")
    rows, before = [], 0.0
    for m in metrics:
        total = float(m["cpu_time_s"])
        rows.append(
            {"run": run_dir.name, "env": cfg["env"], "head": cfg["head"], "seed": cfg["seed"]}
            | {k: m[k] for k in ("trial", "env_steps", "plan_cpu_s", "train_cpu_s", "value_cpu_s")}
            | {"cpu_s": round(total - before, 3)}
        )
        before = total
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", type=Path, nargs="+")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args()
    new = [row for run_dir in args.runs for row in run_rows(run_dir)]
    write_rounded_csv(args.out, new, COLUMNS, keep=("run",))  # other runs' committed rows kept
    print(f"{len(new)} rows of {len(args.runs)} run(s) written to {args.out}")


if __name__ == "__main__":
    main()
