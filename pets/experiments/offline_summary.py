"""Offline summary: prediction error and open-loop reward per env, model and seed, with statistics, tables and plots.

The prediction-error statistics (:mod:`pets.experiments.statistics`, rliable): per env, model, horizon
and error metric the IQM over seeds with its 95 % stratified-bootstrap CI; the probability that the
model's error is lower than delta's (P, with CI); the paired per-seed ratio model / delta (IQM and
CI over the seeds both have). Divergence is per horizon
(:func:`pets.experiments.statistics.divergences` at the env's no-information level,
:func:`pets.experiments.studies.primary.env_level`): a run diverged at a horizon is left out of the IQM, CI and ratios
at that horizon, counted in ``n_diverged`` there, and enters P as error ``+inf`` there; at its other horizons
it counts normally. The error averaged over the tracking horizons (Fig. 2) counts only the runs that diverged at
none of them. The metrics are the eval.json keys ending in ``_error`` that every run of the env has
(``pets.learning.evaluation.METRICS`` first, in that order, then the others alphabetically).

Files:

- ``summary.csv``: one row per env, model, horizon and metric (:data:`SUMMARY_COLUMNS`): ``iqm``,
  ``ci_low``, ``ci_high`` over the ``n_seeds`` runs that did not diverge at that horizon, ``n_diverged``;
  ``p_improvement`` (P(model error < delta's), ties half) with ``p_improvement_ci_low/high``;
  ``ratio_to_delta`` (IQM of the per-seed ratios over the ``n_pairs`` seeds where neither model diverged
  at that horizon) with ``ratio_ci_low/high`` and ``p_value_exact`` (the exact paired sign-flip p-value of the
  mean log ratio over those pairs; secondary: no multiplicity correction).
  The delta columns are empty for delta itself, where delta is not compared, and where a value
  does not exist (no run left, delta's error 0).
- ``relative_error.csv``: the same per env, model and metric for the error averaged over the env's
  tracking horizons (``horizons``: delta's, as in ``primary.csv``; all horizons where the env has no delta run;
  per seed, then the statistics over the seeds that diverged at none of them), plus ``relative`` (the IQM
  divided by the largest model's IQM in the env, as the paper normalises Fig. 2) with its CI divided by the
  same number.
- ``primary.csv``: the pre-registered primary endpoint per env and arm (:mod:`pets.experiments.studies.primary`: the
  no-information level, the tracking horizons, the paired ratio of the clipped standardized error averaged over
  them, its exact p-value and Holm's adjustment over the (env, arm) tests, the verdict), also at the top of
  ``prediction.md``; ``past_level.csv``: per env, model and horizon the runs at or past the level (how models fail).
- ``prediction_runs.csv``: every run and horizon with all its metrics and a ``diverged`` column
  (empty, or why the run counts as diverged at that horizon).
- ``prediction.md``: the seeds, the command and the machines (each run's eval.json ``machines``, where it was
  trained and evaluated: :func:`offline_provenance`); per env a table per metric (mean_step_error,
  standardized_error, and rotation_error where the env has rotations): per model its seeds and per horizon IQM
  [CI] with the runs diverged there ("(k diverged)", or "all diverged"), and P against delta; the Fig. 2 table; the
  diverged runs with their horizons; the missing runs.
- ``relative_error.png`` (Fig. 2 as the paper normalises it), ``ratio_to_delta.png`` (Fig. 2 as the
  paired ratio to delta with its CI) and ``absolute_error_ENV.png`` (Fig. 3: IQM of the error vs
  horizon per model with CI bands; log y axis when the values span a factor 10 or more).

With ``--openloop``: ``openloop.md``, ``openloop.csv`` (per env, planner and model: the mean reward
per step and the total reward of the open-loop plans, mean and CI over seeds) and ``openloop_ENV.png``
(reward vs step per model, one panel per planner).

The study's metric table and statistics: :mod:`pets.experiments.studies.offline`; the text of prediction.md is
made here (:func:`prediction_header`, :func:`env_section`, :func:`fig2_section`, :func:`runs_sections`).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from pets.experiments.plots import plot_absolute, plot_ratio, plot_relative
from pets.experiments.report import fmt_interval, md_table, provenance_lines, write_csv
from pets.experiments.rundirs import env_stem, json_matches, precision_note, run_name
from pets.experiments.statistics import BASELINE, MIN_SEEDS, REPS, SMALL_SAMPLE_NOTE
from pets.experiments.studies.offline import (
    INTERVAL,
    N_DIVERGED,
    N_PAIRS,
    N_SEEDS,
    P_LOWER,
    RATIO,
    RELATIVE,
    RELATIVE_COLUMNS,
    STUDY,
    SUMMARY_COLUMNS,
    OfflineStudy,
    env_summary_rows,
    mark_divergences,
    pair_key,
    shared_horizons_and_metrics,
)
from pets.experiments.studies.primary import (
    PAST_LEVEL_COLUMNS,
    PRIMARY_COLUMNS,
    env_level,
    past_level_rows,
    primary_markdown,
    primary_rows,
)
from pets.runs.fileio import atomic_write_bytes


def test_label(env: str, data_seed: int) -> str:
    """The ``data`` entry of an evaluation request on data set ``data_seed``: the test file's name as
    :func:`pets.experiments.offline_data.data_paths` writes it (an import path ``module:ATTR`` by its spec's name)."""
    from pets.experiments.offline_data import data_paths

    return f"data/{data_paths(Path('data'), env, data_seed)[1].name}"


def load_evals(
    out: Path,
    env: str,
    models: Sequence[str],
    seeds: Sequence[int],
    request: Mapping[str, Any],
    data_seeds: Sequence[int] = (0,),
) -> dict[str, list[dict[str, Any]]]:
    """{model: [eval.json of each (data seed, seed) that has one for this request]}; each with ``seed``,
    ``data_seed`` and ``pair`` (:func:`pets.experiments.studies.offline.pair_key`)."""
    found: dict[str, list[dict[str, Any]]] = {}
    for model in models:
        for d in data_seeds:
            for seed in seeds:
                path = out / "runs" / run_name(env, model, seed, data_seed=d) / "eval.json"
                if json_matches(path, {**request, "data": test_label(env, d)}):
                    pair = pair_key(d, seed, len(data_seeds))
                    e = {**json.loads(path.read_text()), "seed": seed, "data_seed": d, "pair": pair}
                    found.setdefault(model, []).append(e)
    return found


def summarise_offline(
    out: Path,
    env_names: Sequence[str],
    models: Sequence[str],
    seeds: Sequence[int],
    request: Mapping[str, Any],
    failed: Mapping[str, str] | None = None,
    *,
    reps: int = REPS,
    data_seeds: Sequence[int] = (0,),
    command: str | None = None,
) -> list[dict[str, Any]]:
    """Write summary.csv, relative_error.csv, prediction_runs.csv, prediction.md and the figures (module
    docstring) from the runs' eval.json files; returns the summary.csv rows. ``command``: the command line that made
    the summary, named in prediction.md with the seeds and machines."""
    out = Path(out)
    summary, relative_rows, per_run, diverged_runs, text = [], [], [], [], []
    included: list[Path] = []
    machines: list[list[str]] = []
    run_columns: list[str] = []
    fig2: dict[str, dict[str, dict[str, Any]]] = {}
    levels: dict[str, tuple[float, str]] = {}
    for env in env_names:
        evals = load_evals(out, env, models, seeds, request, data_seeds)
        if not evals:
            continue
        levels[env] = level = env_level(out / "data", env)
        env_models = [m for m in models if m in evals]
        runs = [e for m in env_models for e in evals[m]]
        included += [
            out / "runs" / run_name(env, m, e["seed"], data_seed=e["data_seed"]) for m in env_models for e in evals[m]
        ]
        machines += [[m for m in (e.get("machines") or {}).values() if isinstance(m, str)] for e in runs]
        common, metrics = shared_horizons_and_metrics(runs)
        if not common or not metrics:
            text += [f"## {env}", "", "No horizon or error metric that every run has: no statistics.", ""]
            continue
        diverged_runs += mark_divergences(env, env_models, evals, level[0])
        per_run += _run_rows(env, env_models, evals, run_columns)
        stats, env_summary, env_relative = env_summary_rows(env, env_models, evals, common, metrics, level[0], reps)
        summary += env_summary
        relative_rows += env_relative
        for r in env_relative:
            if r["metric"] == FIGURE_METRIC:
                fig2.setdefault(env, {})[r["model"]] = r
        text += env_section(env, request["horizons"], common, metrics, env_models, stats, runs)
        _plot_absolute(out, env, env_models, stats, common)
    _write_csvs(out, summary, relative_rows, per_run, run_columns)
    primary = primary_rows(per_run, levels, reps=reps)
    write_csv(out / "primary.csv", primary, PRIMARY_COLUMNS)
    write_csv(out / "past_level.csv", past_level_rows(per_run, levels), PAST_LEVEL_COLUMNS)
    text = (
        prediction_header()
        + primary_markdown(primary)
        + offline_provenance(seeds, data_seeds, machines, command)
        + text
    )
    if fig2:
        plot_relative(out / "relative_error.png", fig2)
        has_ratio = any(r[RATIO[0]] is not None for vals in fig2.values() for r in vals.values())
        if has_ratio:
            plot_ratio(out / "ratio_to_delta.png", fig2)
        text += fig2_section(fig2, has_ratio)
    text += precision_note(included)
    text += runs_sections(diverged_runs, _missing_runs(out, env_names, models, seeds, data_seeds, request), failed)
    atomic_write_bytes(out / "prediction.md", "\n".join(text).encode())
    return summary


def _run_rows(
    env: str, models: Sequence[str], evals: Mapping[str, Sequence[Mapping[str, Any]]], run_columns: list[str]
) -> list[dict[str, Any]]:
    """prediction_runs.csv's rows of one env, a row per run and horizon; adds the new value keys to
    ``run_columns``."""
    rows = []
    for model in models:
        for e in evals[model]:
            for h, m in e["horizons"].items():
                keys = (env, model, e["seed"], e["data_seed"], int(h), e["starts"], e["diverged"].get(h, ""))
                rows.append({**dict(zip(STUDY.run_keys, keys, strict=True)), **m})
                run_columns += [k for k in m if k not in run_columns]
    return rows


def _plot_absolute(
    out: Path,
    env: str,
    models: Sequence[str],
    stats: Mapping[str, Mapping[tuple[str, Any], Mapping[str, Any]]],
    common: Sequence[int],
) -> None:
    """Fig. 3 of one env: absolute_error_ENV.png."""
    plot_absolute(
        out / f"absolute_error_{env_stem(env)}.png",
        env,
        {
            m: {
                "horizons": common,
                **{k: [stats[m][(FIGURE_METRIC, h)][k] for h in common] for k in INTERVAL},
                "n_runs": runs_behind(stats[m][(FIGURE_METRIC, common[0])]),
                "n_diverged": [stats[m][(FIGURE_METRIC, h)][N_DIVERGED] for h in common],
            }
            for m in models
        },
    )


def _write_csvs(
    out: Path,
    summary: Sequence[Mapping[str, Any]],
    relative_rows: Sequence[Mapping[str, Any]],
    per_run: Sequence[Mapping[str, Any]],
    run_columns: Sequence[str],
) -> None:
    """summary.csv, relative_error.csv and prediction_runs.csv (the error metrics first, then the other keys)."""
    write_csv(out / "summary.csv", summary, SUMMARY_COLUMNS)
    write_csv(out / "relative_error.csv", relative_rows, RELATIVE_COLUMNS)
    write_csv(out / "prediction_runs.csv", per_run, STUDY.run_columns(run_columns))


def _missing_runs(
    out: Path,
    env_names: Sequence[str],
    models: Sequence[str],
    seeds: Sequence[int],
    data_seeds: Sequence[int],
    request: Mapping[str, Any],
) -> list[str]:
    """The runs without an eval.json for ``request``."""
    return [
        run_name(e, m, s, data_seed=d)
        for e in env_names
        for m in models
        for d in data_seeds
        for s in seeds
        if not json_matches(
            out / "runs" / run_name(e, m, s, data_seed=d) / "eval.json", {**request, "data": test_label(e, d)}
        )
    ]


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


def offline_provenance(
    seeds: Sequence[int], data_seeds: Sequence[int], machines: Sequence[Sequence[str]], command: str | None
) -> list[str]:
    """:func:`pets.experiments.report.provenance_lines` of an offline comparison: the machines each run was trained
    and evaluated on, from its eval.json (``machines``: per run summarised)."""
    listed = f"{', '.join(map(str, seeds))} ({len(seeds)})"
    if len(data_seeds) > 1:
        listed += f" on the data sets {', '.join(map(str, data_seeds))} ({len(data_seeds)})"
    paired = "data set and seed" if len(data_seeds) > 1 else "seed"
    return provenance_lines(
        f"{listed}; a model's run is paired with {BASELINE}'s run of the same {paired}",
        command,
        "each run's resolved config in runs/RUN/config.yaml, the data sets in data/",
        machines,
        "runs/RUN/eval.json, where each run was trained and evaluated",
    )


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
