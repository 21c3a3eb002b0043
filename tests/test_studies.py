"""A study is its metric table (pets.experiments.studies): a new metric is one line of it and appears in the summary
CSV, the markdown table and the headline row, with no column name typed anywhere else."""

from __future__ import annotations

import csv
import math
from dataclasses import replace

import numpy as np

from pets.experiments.report import fmt_interval, write_csv
from pets.experiments.studies.base import (
    HIGHER,
    Metric,
    arm_statistics,
    headline_columns,
    headline_row,
    headline_table,
    holm_over_summary,
    table_cells,
    table_header,
)
from pets.experiments.studies.online import OUTCOME, STUDY

#: The metrics over the runs that reached the env's threshold: none did here.
REACHED = [m.name for m in STUDY.metrics if m.group and m.group.reached]


def _runs(metric_names: list[str]) -> dict[str, list[dict[str, float]]]:
    """5 seeds of delta and gem, gem 1.0 higher on every metric, nothing reached a threshold."""
    rng = np.random.default_rng(0)
    runs = {}
    for shift, arm in enumerate(("delta", "gem")):
        runs[arm] = [
            {
                "seed": seed,
                "diverged": None,
                **{name: float(rng.normal()) + shift for name in metric_names},
                **dict.fromkeys(REACHED, math.nan),
            }
            for seed in range(5)
        ]
    return runs


def test_a_new_metric_is_one_line_and_reaches_the_csv_the_table_and_the_headline(tmp_path) -> None:
    study = replace(
        STUDY,
        metrics=(*STUDY.metrics, Metric("best_reward", "best", HIGHER, OUTCOME, label="best reward", headline="best")),
    )
    runs = _runs([m.name for m in study.metrics if m.name not in REACHED])
    stats = arm_statistics(study, runs, {"delta": None, "gem": "delta"}, reps=200)
    rows = [
        {"env": "reacher", "model": arm, "planner": "", "trials": 5, "final_window": 3, **s, "threshold": None}
        for arm, s in stats.items()
    ]
    holm_over_summary(study, rows)

    write_csv(tmp_path / "summary.csv", rows, study.summary_columns())  # the CSV
    with open(tmp_path / "summary.csv", newline="") as f:
        written = list(csv.DictReader(f))
    assert {"best_iqm", "best_ci_low", "best_ci_high"} <= set(written[0])
    gem_best = [r["best_reward"] for r in runs["gem"]]
    assert min(gem_best) <= float(written[1]["best_iqm"]) <= max(gem_best)
    assert float(written[1]["best_ci_low"]) <= float(written[1]["best_iqm"]) <= float(written[1]["best_ci_high"])

    header = table_header(study, compared=True, threshold=None)  # the markdown table
    assert "best reward" in header and header.index("best reward") == header.index("AUC") + 1
    cells = table_cells(study, rows[1], compared=True, is_baseline=False)
    assert len(cells) == len(header)
    best = [float(written[1][c]) for c in ("best_iqm", "best_ci_low", "best_ci_high")]
    assert cells[header.index("best reward")] == fmt_interval(*best)

    columns = headline_columns(study)  # the headline row and table, with delta's value beside
    assert columns[columns.index("best_ci_high") + 1 :][:3] == [
        "delta_best_iqm",
        "delta_best_ci_low",
        "delta_best_ci_high",
    ]
    line = headline_row(study, written[1], written[0])
    assert line["best_iqm"] == float(written[1]["best_iqm"]) and line["delta_best_iqm"] == float(written[0]["best_iqm"])
    assert set(line) | {"env", "model", "source"} == set(columns)
    header, (cells,) = headline_table(study, [{"env": "reacher", "model": "gem", **line}], lambda r, k: "P")
    assert "best" in header and "delta's best" in header and len(cells) == len(header)
    assert cells[header.index("best")] == fmt_interval(*best)


def test_the_online_table_follows_the_metric_table() -> None:
    """The summary's columns are the metric table's: keys, counts, context, each metric's statistic, then the
    comparisons with the baseline; what one run records is the keys, the seed and every metric."""
    columns = STUDY.summary_columns()
    assert columns[: len(STUDY.keys)] == list(STUDY.keys)
    for m in STUDY.metrics:
        assert set(m.columns()) <= set(columns) and set(m.baseline_columns()) <= set(columns)
    against = [c for m in STUDY.metrics for c in m.baseline_columns()]
    assert columns[-len(against) :] == against
    assert STUDY.run_columns()[-len(STUDY.metrics) :] == [m.name for m in STUDY.metrics]
    assert STUDY.primary().name == "final_reward" and STUDY.primary().direction == HIGHER
