"""docs/results.md's generated blocks of the offline study, rendered from its committed summaries: the table of one
paper-protocol study (:func:`paper_table`, the ``offline-paper-STUDY`` blocks), one arm against another
(:func:`versus_table`), the paper's own comparison (:func:`own_comparison_table`), and whether the verdicts hold up
(issue 37's checks): the primary endpoint on each new data set alone and at 5x the paper's iterations
(:func:`data_sets_table`, from ``paper_data3_per_data_set.csv`` and ``paper_50k_primary.csv``), and where the models'
holdout error stands when training stops (:func:`curves_table`, from the committed learning curves).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from pets.experiments.publication import RESULTS
from pets.experiments.report import csv_number, fmt, fmt_interval, md_table, read_csv_rows
from pets.experiments.statistics import BASELINE
from pets.experiments.studies.offline import INTERVAL, N_DIVERGED, N_SEEDS, P_EXACT, RATIO, STUDY

#: The metrics of the body-frame composition study's per-env tables: the whole state, then the root's pieces.
GEMSE_METRICS = ("standardized_error", "translation_error", "rotation_error", "velocity_error")
#: What a paper-protocol table shows (the legend under it).
PAPER_LEGEND = (
    "Per metric and horizon: the baseline's IQM over seeds [95 % CI]; every other model its paired ratio to the "
    "baseline (IQM of the per-seed ratios [95 % CI]) and the exact sign-flip p, uncorrected (secondary: read a single "
    "cell with care, a consistent row with more confidence; with n pairs it cannot go below 2^(1-n)). A run past the "
    "env's no-information level at a horizon is diverged there: counted, left out of the IQM and the ratios."
)


def _paper_cell(r: Mapping[str, str] | None, baseline: bool) -> str:
    """A cell: the baseline's IQM [CI], another model's ratio [CI] and exact p, with its diverged runs; "-" for a
    horizon the study did not evaluate."""
    if r is None:
        return "-"
    n, diverged = int(float(r[N_SEEDS])), int(float(r[N_DIVERGED]))
    if n == 0:
        return "all diverged"
    text = fmt_interval(*(csv_number(r[c]) for c in INTERVAL), digits=3) if baseline else ratio_cell(r)
    return text + (f" ({diverged} diverged)" if diverged else "")


def ratio_cell(r: Mapping[str, str]) -> str:
    """``ratio [CI], p P`` of a row with the ratio-to-delta columns and the exact p; ``n/a`` without a ratio."""
    ratio = fmt_interval(*(csv_number(r[c]) for c in RATIO), digits=3)
    return ratio if ratio == "n/a" else f"{ratio}, p {fmt(csv_number(r[P_EXACT]), 2)}"


def _shown_metrics(rows: Sequence[Mapping[str, str]]) -> list[str]:
    """The study's headline metrics that have a value > 0 somewhere in ``rows`` (an env without such coordinates
    has zeros)."""
    has = {r["metric"] for r in rows if csv_number(r[INTERVAL[0]]) > 0}
    return [m for m in STUDY.headline_metrics() if m in has]


def paper_table(tree: Path, study: str, env: str | None = None, metrics: Sequence[str] = ()) -> str:
    """The table of ``paper_STUDY_summary.csv`` under ``tree`` (of ``env`` where the study has several): per metric
    (``metrics``, else the shown ones, :func:`_shown_metrics`) a row per model (delta's IQM, the others' ratios to
    it), a column per horizon; then :data:`PAPER_LEGEND`."""
    rows = [r for r in read_csv_rows(tree / RESULTS / f"paper_{study}_summary.csv") if env in (None, r["env"])]
    horizons = sorted({int(r["horizon"]) for r in rows})
    models = list(dict.fromkeys(r["model"] for r in rows))
    cells = {(r["metric"], r["model"], int(r["horizon"])): r for r in rows}
    table = [
        [metric.replace("_", " ") if i == 0 else "", model]
        + [_paper_cell(cells.get((metric, model, h)), model == BASELINE) for h in horizons]
        for metric in (metrics or _shown_metrics(rows))
        for i, model in enumerate(models)
    ]
    return md_table(["metric", "model", *(f"h={h}" for h in horizons)], table) + "\n\n" + PAPER_LEGEND


def versus_table(tree: Path, study: str) -> str:
    """``paper_STUDY_primary_versus.csv`` as a table: per env, one arm against another on the primary endpoint (a
    secondary comparison: IQM of the per-seed ratios [95 % CI], exact sign-flip p, pairs where the arm is lower)."""
    rows = read_csv_rows(tree / RESULTS / f"paper_{study}_primary_versus.csv")
    table = [
        [r["env"], f"{r['model']} / {r['versus']}", r["tracking_horizons"],
         fmt_interval(*(csv_number(r[c]) for c in ("ratio", "ratio_ci_low", "ratio_ci_high"))),
         fmt(csv_number(r[P_EXACT]), 2), f"{r['n_lower']} of {r['n_pairs']}"]
        for r in rows
    ]  # fmt: skip
    header = ["env", "arm / other arm", "tracking horizons", "ratio [95 % CI]", "exact p", "arm lower in"]
    return md_table(header, table)


def own_comparison_table(tree: Path) -> str:
    """``paper_own_comparison.csv`` as a table: per env, GEM's deterministic model against the baseline's of the
    same kind (the paper's own comparison), per shown metric, a column per horizon."""
    rows = read_csv_rows(tree / RESULTS / "paper_own_comparison.csv")
    horizons = sorted({int(r["horizon"]) for r in rows})
    cells = {(r["env"], r["model"], r["metric"], int(r["horizon"])): r for r in rows}
    pairs = list(dict.fromkeys((r["env"], r["model"], r["baseline"]) for r in rows))
    table = [
        [env, f"{model} / {baseline}", metric.replace("_", " ")]
        + [_paper_cell(cells.get((env, model, metric, h)), False) for h in horizons]
        for env, model, baseline in pairs
        for metric in _shown_metrics([r for r in rows if r["env"] == env])
        if metric != STUDY.figure_metric()
    ]
    header = ["env", "model / its baseline", "metric", *(f"h={h}" for h in horizons)]
    return md_table(header, table) + "\n\n" + PAPER_LEGEND


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
