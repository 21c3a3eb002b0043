"""The offline summary's markdown, prediction.md: the header, a section per env, Fig. 2's table, the diverged and the
missing runs (:mod:`pets.experiments.offline_summary` writes it); and docs/results.md's table of one paper-protocol
study, rendered from its committed summary (:func:`paper_table`, the ``offline-paper-STUDY`` blocks).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from pets.experiments.published import RESULTS
from pets.experiments.report import csv_number, fmt, fmt_interval, md_table, read_csv_rows
from pets.experiments.rundirs import env_stem
from pets.experiments.statistics import BASELINE, MIN_SEEDS, SMALL_SAMPLE_NOTE
from pets.experiments.studies.offline import (
    INTERVAL,
    N_DIVERGED,
    N_PAIRS,
    N_SEEDS,
    P_EXACT,
    P_LOWER,
    RATIO,
    RELATIVE,
    STUDY,
    OfflineStudy,
)

#: The metric of Fig. 2 and Fig. 3 (the study's metric table).
FIGURE_METRIC = STUDY.figure_metric()


def _metric_tables(
    metric: str, models: Sequence[str], stats: Mapping[str, Mapping[tuple[str, Any], Mapping[str, Any]]], hs: Sequence
) -> list[str]:
    """Markdown: the IQM [CI] table of one metric per model and horizon (with the runs diverged at each
    horizon, :func:`_fmt_iqm`), then P of improvement over delta."""
    rows = [
        [model, str(runs_behind(stats[model][(metric, hs[0])]))] + [_fmt_iqm(stats[model][(metric, h)]) for h in hs]
        for model in models
    ]
    text = [f"### {metric}", "", md_table(["model", "seeds"] + [f"h={h}" for h in hs], rows), ""]
    others = [m for m in models if m != BASELINE]
    if BASELINE in models and others:
        text += [
            f"P({metric} < {BASELINE}'s) [95 % CI]:",
            "",
            md_table(
                ["model"] + [f"h={h}" for h in hs],
                [[m] + [_fmt_p(stats[m][(metric, h)]) for h in hs] for m in others],
            ),
            "",
        ]
    return text


def runs_behind(s: Mapping[str, Any]) -> int:
    """The runs behind a statistic: the seeds in it and the seeds diverged there."""
    return s[N_SEEDS] + s[N_DIVERGED]


def _fmt_iqm(s: Mapping[str, Any]) -> str:
    """IQM [CI] of one column, then "(k diverged)" if k runs diverged there; "all diverged" if every run did."""
    if s[N_SEEDS] == 0:
        return "all diverged"
    return fmt_interval(*_values(s, INTERVAL)) + (f" ({s[N_DIVERGED]} diverged)" if s[N_DIVERGED] else "")


def small_sample(s: Mapping[str, Any]) -> bool:
    """Whether a statistic rests on fewer than :data:`MIN_SEEDS` seeds (and at least one)."""
    return 0 < s[N_SEEDS] < MIN_SEEDS


def _values(s: Mapping[str, Any], columns: Sequence[str]) -> list[Any]:
    return [s[c] for c in columns]


def _fmt_p(s: Mapping[str, Any]) -> str:
    return fmt_interval(*_values(s, P_LOWER), "n/a")


def prediction_header() -> list[str]:
    """The top of prediction.md: what the tables show."""
    return [
        "# Offline comparison: long-horizon prediction error",
        "",
        "Step-wise errors of pets.evaluate (ensemble-mean rollouts on the test data, the same start points for "
        "every model and seed of an env) per horizon. Per model: the interquartile mean (IQM) over seeds with "
        "its 95 % stratified-bootstrap CI in brackets (rliable). P: the probability that the model's error "
        f"is lower than {BASELINE}'s (a random seed of each; ties count half) with its CI. A run is diverged at a "
        "horizon when a value of its evaluation there is not finite, some predictions went non-finite, or its "
        "standardized_error is at or past the env's no-information level (the error of predicting a random "
        "training observation; primary.csv gives it): its prediction no longer tracks the state. At that "
        "horizon it is counted ('(k diverged)' after the IQM; 'all diverged' when every run did), left out of the "
        "IQM, CI and ratios, and counts as an infinite error in P; at its other horizons it counts normally. "
        "seeds: the model's evaluated runs.",
        "",
    ]


def env_section(
    env: str,
    asked: Sequence[int],
    common: Sequence[int],
    metrics: Sequence[str],
    models: Sequence[str],
    stats: Mapping[str, Mapping[tuple[str, Any], Mapping[str, Any]]],
    runs: Sequence[Mapping[str, Any]],
    study: OfflineStudy = STUDY,
) -> list[str]:
    """Markdown of one env: its horizons (and the ``asked`` ones it skipped), the small-sample note where needed, a
    table per metric of the ``study``'s metric table flagged ``table`` that it has (and shows), its Fig. 3."""
    skipped = sorted(set(asked) - set(common))
    note = f"; skipped: {', '.join(map(str, skipped))} (longer than the test episodes)" if skipped else ""
    env_small = any(small_sample(stats[m][(metrics[0], h)]) for m in models for h in common)
    text = [f"## {env} (horizons {', '.join(map(str, common))}{note})", ""]
    text += [SMALL_SAMPLE_NOTE, ""] if env_small else []
    for metric in study.table_metrics():
        if metric.name in metrics and metric.shown(runs):
            text += _metric_tables(metric.name, models, stats, common)
    return text + [f"![absolute error](absolute_error_{env_stem(env)}.png)", ""]


def fig2_section(fig2: Mapping[str, Mapping[str, Mapping[str, Any]]], has_ratio: bool) -> list[str]:
    """Markdown of Fig. 2: per env and model the error averaged over the env's tracking horizons, relative and as a
    ratio to delta."""
    fig2_small = any(small_sample(r) for vals in fig2.values() for r in vals.values())
    text = [
        "## Fig. 2: error averaged over the tracking horizons",
        "",
        f"Per seed the {FIGURE_METRIC} averaged over the env's tracking horizons (those where {BASELINE}'s median "
        "standardized error is below the no-information level, as in the primary endpoint; all horizons when "
        f"there is no {BASELINE} run), then the IQM over seeds [95 % CI]. "
        "relative: divided by the largest model's IQM in the env, as the paper normalises (the CI divided "
        f"by the same number). ratio to {BASELINE}: IQM [CI] of the per-seed ratios over the seeds both "
        "models have (paired: same seed, data and start points). A run diverged at any of those horizons is left out "
        "of the average and counted under diverged.",
        "",
    ]
    text += [SMALL_SAMPLE_NOTE, ""] if fig2_small else []
    header = ["env", "horizons", "model", "seeds", "diverged", "relative", f"ratio to {BASELINE}", "pairs"]
    rows = [_fig2_row(env, m, r) for env, vals in fig2.items() for m, r in vals.items()]
    return text + [
        md_table([*header, f"P(error < {BASELINE}'s)"], rows),
        "",
        "![relative error](relative_error.png)" + (" ![ratio to delta](ratio_to_delta.png)" if has_ratio else ""),
        "",
    ]


def _fig2_row(env: str, m: str, r: Mapping[str, Any]) -> list[str]:
    """One row of Fig. 2's table."""
    return [
        env,
        r.get("horizons") or "none",
        m,
        str(r[N_SEEDS]),
        str(r[N_DIVERGED]),
        fmt_interval(*_values(r, RELATIVE), "all diverged" if not r[N_SEEDS] else "n/a"),
        "-" if m == BASELINE else fmt_interval(*_values(r, RATIO)),
        "-" if r[N_PAIRS] is None else str(r[N_PAIRS]),
        "-" if m == BASELINE else _fmt_p(r),
    ]


def runs_sections(diverged_runs: Sequence[str], missing: Sequence[str], failed: Mapping[str, str] | None) -> list[str]:
    """Markdown of the diverged runs (with their horizons) and the missing ones (with why, where they failed)."""
    text = []
    if diverged_runs:
        text += (
            ["## Diverged runs (counted, not in the IQMs at these horizons nor in the average)", ""]
            + [f"- {d}" for d in diverged_runs]
            + [""]
        )
    if missing:
        text += ["## Missing runs (not in the statistics)", ""]
        text += [f"- {m}{': ' + failed[m] if failed and m in failed else ''}" for m in missing] + [""]
    return text


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
