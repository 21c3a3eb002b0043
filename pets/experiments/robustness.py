"""Whether the offline verdicts hold up (issue 37's checks), as docs/results.md's generated blocks: the primary
endpoint on each new data set alone and at 5x the paper's iterations (:func:`data_sets_table`, from
``paper_data3_per_data_set.csv`` and ``paper_50k_primary.csv``), and where the models' holdout error stands when
training stops (:func:`curves_table`, from the committed learning curves)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from pets.experiments.offline_tables import ratio_cell
from pets.experiments.published import RESULTS
from pets.experiments.report import csv_number, fmt, md_table, read_csv_rows
from pets.experiments.statistics import BASELINE
from pets.experiments.studies.base import RATIO

#: The learning curves' checkpoints (training steps) of the paper's budget and of the 5x rerun.
PAPER_STEPS, LONG_STEPS = (2000, 5000, 8000, 10000), (10000, 40000, 50000)


def _rule(long: Mapping[str, str], short: Mapping[str, str]) -> str:
    """The pre-registered rule of the 5x rerun: the verdict changes if the 50k ratio lies on the other side of 1
    than the 10k ratio, or if its CI excludes the 10k ratio's IQM."""
    r50, low, high = (csv_number(long[c]) for c in RATIO)
    r10 = csv_number(short[RATIO[0]])
    changes = (r50 < 1) != (r10 < 1) or not low <= r10 <= high
    return "changes" if changes else "does not change"


def data_sets_table(tree: Path) -> str:
    """Per env and data set, gem / delta on the primary endpoint over that data set's 5 pairs; then data set 0 at
    5x the iterations, with the pre-registered rule's reading against data set 0 at the paper's budget."""
    per = [r for r in read_csv_rows(tree / RESULTS / "paper_data3_per_data_set.csv") if r["model"] != BASELINE]
    long = {r["env"]: r for r in read_csv_rows(tree / RESULTS / "paper_50k_primary.csv") if r["model"] != BASELINE}
    rows = [
        [r["env"], f"data set {r['data_seed']}", "10k (the paper's)", r["tracking_horizons"], r["n_pairs"],
         ratio_cell(r), ""]
        for r in per
    ]  # fmt: skip
    for env, r in long.items():
        short = next(s for s in per if s["env"] == env and s["data_seed"] == "0")
        rule = f"verdict {_rule(r, short)}"
        rows.append([env, "data set 0", "50k (5x)", r["tracking_horizons"], r["n_pairs"], ratio_cell(r), rule])
    rows.sort(key=lambda row: row[0])
    header = ["env", "data", "iterations", "tracking horizons", "pairs", "gem / delta [95 % CI], exact p", "5x rule"]
    return md_table(header, rows)


def curves_table(tree: Path) -> str:
    """Holdout error (one step, standardised) at the checkpoints of the paper's budget (one seed per env and
    model) and of the 5x rerun (median over its seeds), and the last checkpoint over the one before: below 1,
    still falling when training stopped."""
    rows = []
    for name, steps, runs_word in (("paper", PAPER_STEPS, "seed 0"), ("50k", LONG_STEPS, "median of seeds")):
        curves: dict[tuple[str, str], dict[str, dict[int, float]]] = {}
        for r in read_csv_rows(tree / RESULTS / f"learning_curves_{name}.csv"):
            run = curves.setdefault((r["env"], r["model"]), {}).setdefault(r["run"], {})
            run[int(r["step"])] = float(r["holdout_error"])
        for (env, model), runs in curves.items():
            at = [float(np.median([c.get(s, math.nan) for c in runs.values()])) for s in steps]
            cells = " / ".join(fmt(v, 3) for v in at)
            rows.append([env, model, f"{len(runs)} ({runs_word})", " / ".join(f"{s // 1000}k" for s in steps), cells,
                         fmt(at[-1] / at[-2], 3)])  # fmt: skip
    header = ["env", "model", "runs", "steps", "holdout error at those steps", "last / the one before"]
    return md_table(header, rows)
