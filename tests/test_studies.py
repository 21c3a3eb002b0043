"""A study is its metric table (pets.experiments.studies): a new metric is one line of it and appears in the summary
CSV, the markdown table and the headline row, with no column name typed anywhere else (the offline study: a new error
metric the runs record is in its CSV, and one line of its table gives it its table in prediction.md; the planning
study: a new per-run value is one line and reaches its CSV and its table)."""

from __future__ import annotations

import csv
import math
from dataclasses import replace

import numpy as np
import pytest

from pets.experiments.offline_summary import env_section
from pets.experiments.report import BOOT_SEED, fmt_ci, fmt_interval, write_csv
from pets.experiments.studies import offline, planning
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
from pets.experiments.studies.planning import summary_row
from pets.stats.bootstrap import summarise

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


def _offline_evals(metric_names: list[str]) -> dict[str, list[dict]]:
    """One env's evaluations: delta and gem, 5 seeds, horizons 1 and 5, gem's errors 0.8 of delta's (below the
    no-information level: no run diverged)."""
    rng = np.random.default_rng(0)
    evals = {}
    for scale, model in ((1.0, "delta"), (0.8, "gem")):
        evals[model] = [
            {
                "seed": seed,
                "data_seed": 0,
                "pair": seed,
                "starts": 4,
                "horizons": {
                    str(h): {m: scale * h * (0.1 + 0.01 * rng.random()) for m in metric_names} for h in (1, 5)
                },
            }
            for seed in range(5)
        ]
    return evals


def test_a_new_offline_metric_is_one_line_and_gets_its_table_in_prediction_md(tmp_path) -> None:
    """The offline study's summary has a row per error metric every run records; its metric table says which get a
    table in prediction.md: a new metric recorded by the runs is in the CSV, and one line of the table shows it."""
    study = replace(offline.STUDY, metrics=(*offline.STUDY.metrics, offline.ErrorMetric("max_step_error", table=True)))
    evals = _offline_evals(["mean_step_error", "standardized_error", "rotation_error", "max_step_error"])
    runs = [e for rs in evals.values() for e in rs]
    horizons, metrics = offline.shared_horizons_and_metrics(runs)
    assert horizons == [1, 5] and metrics[:3] == ["mean_step_error", "rotation_error", "standardized_error"]
    assert offline.mark_divergences("reacher", list(evals), evals, math.sqrt(2)) == []
    stats, summary, relative = offline.env_summary_rows("reacher", list(evals), evals, horizons, metrics, math.sqrt(2))

    write_csv(tmp_path / "summary.csv", summary, study.summary_columns())  # the CSV
    with open(tmp_path / "summary.csv", newline="") as f:
        written = [r for r in csv.DictReader(f) if r["metric"] == "max_step_error"]
    assert [(r["model"], r["horizon"]) for r in written] == [("delta", "1"), ("delta", "5"), ("gem", "1"), ("gem", "5")]
    gem = [e["horizons"]["5"]["max_step_error"] for e in evals["gem"]]
    assert min(gem) <= float(written[3]["iqm"]) <= max(gem) and written[3]["n_pairs"] == "5"
    assert 0.75 < float(written[3]["ratio_to_delta"]) < 0.85 and float(written[3]["p_improvement"]) == 1.0
    assert {r["metric"] for r in relative} == set(metrics)

    def section(study: offline.OfflineStudy, evals: dict[str, list[dict]]) -> str:  # the table
        runs = [e for rs in evals.values() for e in rs]
        return "\n".join(env_section("reacher", [1, 5], horizons, metrics, list(evals), stats, runs, study))

    assert "### max_step_error" in section(study, evals) and "P(max_step_error < delta's)" in section(study, evals)
    assert "### max_step_error" not in section(offline.STUDY, evals)
    assert "### rotation_error" in section(study, evals)  # nonzero: not where the env's rotation errors are all 0
    for e in evals["delta"] + evals["gem"]:
        e["horizons"] = {h: {**v, "rotation_error": 0.0} for h, v in e["horizons"].items()}
    assert "### rotation_error" not in section(study, evals)


def test_the_offline_columns_follow_the_study() -> None:
    """summary.csv: the keys, a model's own statistics, the comparison with delta; relative_error.csv the same
    without the horizon, with the relative IQM [CI] and the horizons averaged over; prediction_runs.csv the run keys,
    the errors in the evaluator's order, then the other values."""
    study = offline.STUDY
    assert study.summary_columns() == [*study.keys, *offline.OWN, *offline.COMPARED]
    assert study.relative_columns()[:9] == ["env", "model", "metric", "iqm", "ci_low", "ci_high", *offline.RELATIVE]
    assert study.relative_columns()[-1] == "horizons" and "horizon" not in study.relative_columns()
    keys = ["nonfinite_fraction", "standardized_error", "zeta_error", "mean_step_error"]
    assert study.run_columns(keys)[len(study.run_keys) :] == [
        "mean_step_error",
        "standardized_error",
        "zeta_error",
        "nonfinite_fraction",
    ]
    assert study.figure_metric() == "mean_step_error"
    assert study.headline_metrics() == ("standardized_error", "rotation_error", "mean_step_error")


def test_a_new_planning_metric_is_one_line_and_reaches_the_csv_and_the_table(tmp_path) -> None:
    """The planning study's metric table: a new per-run value is one line, with its mean [CI] over seeds in the
    summary CSV and its column in the markdown table; the paired difference stays with the paired metric."""
    study = replace(
        planning.STUDY, metrics=(*planning.STUDY.metrics, planning.RewardMetric("best_step", "best_step", "best step"))
    )
    rng = np.random.default_rng(0)
    results = {
        model: {
            seed: {
                name: {"mean": float(rng.normal()) + shift} for name in ("mean_reward_per_step", "total", "best_step")
            }
            for seed in range(5)
        }
        for shift, model in enumerate(("delta", "gem"))
    }
    rows, table = zip(*(summary_row(results, ("reacher", "cem", m), 20, study) for m in results))

    write_csv(tmp_path / "closedloop.csv", rows, study.columns())  # the CSV
    with open(tmp_path / "closedloop.csv", newline="") as f:
        written = list(csv.DictReader(f))
    assert list(written[0])[-len(planning.PAIRED) - 3 :][:3] == [
        "best_step_mean",
        "best_step_ci_low",
        "best_step_ci_high",
    ]
    best = [r["best_step"]["mean"] for r in results["gem"].values()]
    assert float(written[1]["best_step_mean"]) == pytest.approx(np.mean(best), rel=1e-12)
    totals = [results["gem"][s]["total"]["mean"] - results["delta"][s]["total"]["mean"] for s in range(5)]
    assert float(written[1]["diff_to_delta"]) == pytest.approx(np.mean(totals), rel=1e-12)
    assert written[0]["diff_to_delta"] == "" and written[1]["n_pairs"] == "5"

    header = study.table_header()  # the markdown table
    assert header[-2:] == ["best step", "total - delta (paired)"] and len(table[1]) == len(header)
    assert table[1][header.index("best step")] == fmt_ci(summarise(best, seed=BOOT_SEED))
    assert table[0][-1] == "-" and table[1][-1].endswith(f"p {float(written[1]['p_value_exact']):.3g}")
