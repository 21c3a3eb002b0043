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
(``pets.evaluate.METRICS`` first, in that order, then the others alphabetically).

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
- ``prediction.md``: per env a table per metric (mean_step_error, standardized_error, and
  rotation_error where the env has rotations): per model its seeds and per horizon IQM [CI] with the
  runs diverged there ("(k diverged)", or "all diverged"), and P against delta; the Fig. 2 table; the
  diverged runs with their horizons; the missing runs.
- ``relative_error.png`` (Fig. 2 as the paper normalises it), ``ratio_to_delta.png`` (Fig. 2 as the
  paired ratio to delta with its CI) and ``absolute_error_ENV.png`` (Fig. 3: IQM of the error vs
  horizon per model with CI bands; log y axis when the values span a factor 10 or more).

With ``--openloop``: ``openloop.md``, ``openloop.csv`` (per env, planner and model: the mean reward
per step and the total reward of the open-loop plans, mean and CI over seeds) and ``openloop_ENV.png``
(reward vs step per model, one panel per planner).

The study's metric table and statistics: :mod:`pets.experiments.studies.offline`; the text of prediction.md:
:mod:`pets.experiments.offline_tables`.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from pets.experiments.offline_tables import (
    FIGURE_METRIC,
    env_section,
    fig2_section,
    prediction_header,
    runs_behind,
    runs_sections,
)
from pets.experiments.plots import plot_absolute, plot_ratio, plot_relative
from pets.experiments.report import write_csv
from pets.experiments.rundirs import env_stem, json_matches, precision_note, run_name
from pets.experiments.statistics import REPS
from pets.experiments.studies.offline import (
    INTERVAL,
    N_DIVERGED,
    RATIO,
    RELATIVE_COLUMNS,
    STUDY,
    SUMMARY_COLUMNS,
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
    """The ``data`` entry of an evaluation request on data set ``data_seed`` (pets.experiments.offline.data_paths)."""
    return f"data/{env}-d{data_seed}-test.npz" if data_seed else f"data/{env}-test.npz"


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
) -> list[dict[str, Any]]:
    """Write summary.csv, relative_error.csv, prediction_runs.csv, prediction.md and the figures (module
    docstring) from the runs' eval.json files; returns the summary.csv rows."""
    out = Path(out)
    summary, relative_rows, per_run, diverged_runs, text = [], [], [], [], []
    included: list[Path] = []
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
    text = prediction_header() + primary_markdown(primary) + text
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
