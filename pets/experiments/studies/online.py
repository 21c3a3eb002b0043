"""The online study: its metric table (:data:`STUDY`; what one run records, :data:`RUN_COLUMNS`, and the summary
columns, :data:`SUMMARY_COLUMNS`, follow from it) and its summary rows, made either from the runs' metrics
(:mod:`pets.experiments.online_summary`) or from the committed per-run rows (:func:`summary_from_runs`, for
``pets.compare report``). The statistics are described in :mod:`pets.experiments.online_summary`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from pets.experiments.online_runs import COST_KEYS, THRESHOLD_KEYS, THRESHOLDS
from pets.experiments.rundirs import arm_label
from pets.experiments.statistics import BASELINE, REPS
from pets.experiments.studies.base import (
    HIGHER,
    LOWER,
    Group,
    Metric,
    Study,
    arm_statistics,
    env_tables,
    holm_over_summary,
)

#: The online study's metric table (:mod:`pets.experiments.studies.base`): one line per metric.
OUTCOME = Group("outcome")
REACHED = Group("reached", reached=True, missing="-")
STUDY = Study(
    name="online",
    keys=("env", "model", "planner"),
    context=("trials", "final_window"),
    metrics=(
        Metric("final_reward", "final", HIGHER, OUTCOME, "p_improvement", f"P(final > {BASELINE}'s)", "diff",
               "final reward", headline="final", headline_versus=f"P(final > {BASELINE}'s)"),
        Metric("auc", "auc", HIGHER, OUTCOME, label="AUC"),
        Metric("minutes_to_threshold", "minutes_to_threshold", LOWER, REACHED, label="minutes to it"),
        Metric("steps_to_threshold", "steps_to_threshold", LOWER, REACHED, "p_fewer_steps",
               f"P(fewer steps than {BASELINE})", label="env steps to it", headline="env steps to threshold",
               headline_versus="P(fewer steps)"),
        Metric("cpu_minutes_to_threshold", "cpu_minutes_to_threshold", LOWER, REACHED, label="CPU minutes to it"),
        Metric("env_steps", "env_steps", label="env steps", digits=0),
        Metric("wall_time_s", "wall_time_s", label="wall h", scale=1 / 3600),
        Metric("cpu_time_s", "cpu_time_s", label="CPU h", scale=1 / 3600),
        Metric("plan_seconds_per_step", "plan_seconds_per_step", label="plan s/step"),
    ),
)  # fmt: skip
SUMMARY_COLUMNS = STUDY.summary_columns()
RUN_COLUMNS = STUDY.run_columns()


def arm_baselines(
    arms: Sequence[tuple[str, str | None]],
) -> tuple[dict[tuple[str, str | None], str], dict[str, str | None]]:
    """``(labels, baselines)`` of the (model, planner) arms: {arm: its label}, {label: the label of the baseline
    with the same planner, None for the baseline itself or where there is none}."""
    labels = {arm: arm_label(*arm) for arm in arms}
    baselines = {
        labels[(m, p)]: labels[(BASELINE, p)] if m != BASELINE and (BASELINE, p) in labels else None for m, p in arms
    }
    return labels, baselines


def env_summary_rows(
    env: str,
    runs: Mapping[str, Sequence[Mapping[str, Any]]],
    arms: Sequence[tuple[str, str | None]],
    trials: int,
    final_window: int,
    thresholds: Mapping[str, float],
    *,
    reps: int = REPS,
) -> tuple[list[dict[str, Any]], dict[str, dict[str, Any]]]:
    """``(summary.csv rows, {label: statistics})`` of one env from ``runs`` ({label: the :func:`online_run_stats`
    of its complete runs, each with its ``"seed"``}); ``final_window``: the one used (at most ``trials``)."""
    labels, baselines = arm_baselines(arms)
    stats = arm_statistics(STUDY, runs, baselines, reps=reps, threshold=env in thresholds)
    rows = []
    for model, planner in arms:
        label = labels[(model, planner)]
        if label in stats:
            row = {"env": env, "model": model, "planner": planner or "", "trials": trials, "final_window": final_window}
            rows.append({**row, **stats[label], "threshold": thresholds.get(env)})
    return rows, stats


def _number(text: str | None) -> float:
    return math.nan if text in ("", None) else float(text)


def summary_from_runs(
    rows: Sequence[Mapping[str, str]],
    final_window: int = 3,
    thresholds: Mapping[str, float] = THRESHOLDS,
    *,
    reps: int = REPS,
) -> list[dict[str, Any]]:
    """summary.csv rows recomputed from per-run rows (``summary_runs.csv`` of ``pets.compare online``, committed as
    ``docs/results/*_runs.csv``; columns a run of an older version lacks count as not measured): the statistics
    ``summarise_online`` computes from the runs' metrics, arms in the order the rows give them."""
    summary: list[dict[str, Any]] = []
    for env in dict.fromkeys(r["env"] for r in rows):
        mine = [r for r in rows if r["env"] == env]
        arms = list(dict.fromkeys((r["model"], r["planner"] or None) for r in mine))
        labels, _ = arm_baselines(arms)
        runs: dict[str, list[dict[str, Any]]] = {}
        for r in mine:
            run = {k: _number(r.get(k)) for k in ("final_reward", "auc", *THRESHOLD_KEYS, *COST_KEYS)}
            run.update(seed=int(r["seed"]), diverged=r["diverged"] or None)
            runs.setdefault(labels[(r["model"], r["planner"] or None)], []).append(run)
        trials = int(mine[0]["trials"])
        summary += env_summary_rows(env, runs, arms, trials, min(final_window, trials), thresholds, reps=reps)[0]
    holm_over_summary(STUDY, summary)
    return summary


def study_table(tree: Path, study: str | Sequence[str]) -> str:
    """An online study's block in docs/results.md: its summary recomputed from the committed
    ``docs/results/STUDY_runs.csv`` (:func:`summary_from_runs`; several files: one summary, Holm over all their
    arm-vs-delta tests), one table per env."""
    from pets.experiments.report import read_csv_rows

    names = [study] if isinstance(study, str) else list(study)
    rows = [r for name in names for r in read_csv_rows(tree / "docs" / "results" / f"{name}_runs.csv")]
    return "\n\n".join(env_tables(STUDY, summary_from_runs(rows)))
