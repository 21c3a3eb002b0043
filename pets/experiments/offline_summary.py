"""Offline summary: prediction error and open-loop reward per env, model and seed, with statistics, tables and plots.

The prediction-error statistics (:mod:`pets.experiments.statistics`, rliable): per env, model, horizon
and error metric the IQM over seeds with its 95 % stratified-bootstrap CI; the probability that the
model's error is lower than delta's (P, with CI); the paired per-seed ratio model / delta (IQM and
CI over the seeds both have). Divergence is per horizon
(:func:`pets.experiments.statistics.divergences` at the env's no-information level,
:func:`pets.experiments.primary.env_level`): a run diverged at a horizon is left out of the IQM, CI and ratios
at that horizon, counted in ``n_diverged`` there, and enters P as error ``+inf`` there; at its other horizons
it counts normally. The error averaged over the horizons counts only the runs that diverged at none of them. The
metrics are the eval.json keys ending in ``_error`` that every run of the env has
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
  horizons (per seed, then the statistics over the seeds that diverged at none of them), plus
  ``relative`` (the IQM divided by the largest model's IQM in the env, as the paper normalises Fig. 2)
  with its CI divided by the same number.
- ``primary.csv``: the pre-registered primary endpoint per env and arm (:mod:`pets.experiments.primary`: the
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
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pets.experiments.plots import plot_absolute, plot_ratio, plot_relative
from pets.experiments.primary import (
    PAST_LEVEL_COLUMNS,
    PRIMARY_COLUMNS,
    env_level,
    past_level_rows,
    primary_markdown,
    primary_rows,
)
from pets.experiments.report import BOOT_SEED, fmt_interval, md_table, write_csv
from pets.experiments.rundirs import json_matches, precision_note, run_name
from pets.experiments.statistics import (
    BASELINE,
    MIN_SEEDS,
    REPS,
    SMALL_SAMPLE_NOTE,
    divergences,
    iqm_ci_finite,
    p_improvement_ci,
    paired_ratios,
    sign_flip_p,
)
from pets.learning.evaluation import METRICS as EVALUATE_METRICS
from pets.runs.fileio import atomic_write_bytes

#: Metrics that get a table in prediction.md (rotation_error only where the env has rotations).
TABLE_METRICS = ("mean_step_error", "standardized_error", "rotation_error")
#: The metric of Fig. 2 and Fig. 3.
FIGURE_METRIC = "mean_step_error"
_DELTA_COLUMNS = [
    "p_improvement",
    "p_improvement_ci_low",
    "p_improvement_ci_high",
    "ratio_to_delta",
    "ratio_ci_low",
    "ratio_ci_high",
    "n_pairs",
    "p_value_exact",
]
SUMMARY_COLUMNS = [
    "env",
    "model",
    "horizon",
    "metric",
    "iqm",
    "ci_low",
    "ci_high",
    "n_seeds",
    "n_diverged",
    *_DELTA_COLUMNS,
]
RELATIVE_COLUMNS = [
    "env",
    "model",
    "metric",
    "iqm",
    "ci_low",
    "ci_high",
    "relative",
    "relative_ci_low",
    "relative_ci_high",
    "n_seeds",
    "n_diverged",
    *_DELTA_COLUMNS,
]
#: The horizon label of the columns averaged over the horizons (relative_error.csv, Fig. 2).
AVERAGE = "average"


def _test_label(env: str, data_seed: int) -> str:
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
    ``data_seed`` and ``pair`` (the key runs pair by: the seed alone with one data set, else (data seed, seed))."""
    found: dict[str, list[dict[str, Any]]] = {}
    for model in models:
        for d in data_seeds:
            for seed in seeds:
                path = out / "runs" / run_name(env, model, seed, data_seed=d) / "eval.json"
                if json_matches(path, {**request, "data": _test_label(env, d)}):
                    pair = seed if len(data_seeds) == 1 else (d, seed)
                    e = {**json.loads(path.read_text()), "seed": seed, "data_seed": d, "pair": pair}
                    found.setdefault(model, []).append(e)
    return found


def order_metrics(keys: Sequence[str]) -> list[str]:
    """The ``*_error`` keys among ``keys``: :data:`EVALUATE_METRICS` first in their order, then the rest sorted."""
    errors = {k for k in keys if k.endswith("_error")}
    return [m for m in EVALUATE_METRICS if m in errors] + sorted(errors - set(EVALUATE_METRICS))


def _finite(x: float | None) -> float | None:
    """``x`` as a float, None if absent or not finite (an empty CSV cell, "n/a" in a table)."""
    return None if x is None or not math.isfinite(x) else float(x)


def _run_scores(e: Mapping[str, Any], metrics: Sequence[str], horizons: Sequence[int]) -> np.ndarray:
    """One run's errors per column: each metric at each horizon, then each metric averaged over the horizons.
    NaN where the run diverged (``e["diverged"]``: {horizon: why}): at that horizon, and in the average
    when at any of ``horizons``, since an average over a diverged horizon means nothing."""
    per_h = np.array([[float(e["horizons"][str(h)][m]) for h in horizons] for m in metrics])
    per_h[:, [str(h) in e["diverged"] for h in horizons]] = np.nan
    return np.concatenate([per_h.ravel(), per_h.mean(axis=1)])


def env_statistics(
    evals: Mapping[str, Sequence[Mapping[str, Any]]],
    metrics: Sequence[str],
    horizons: Sequence[int],
    *,
    reps: int = REPS,
    seed: int = BOOT_SEED,
) -> dict[str, dict[tuple[str, int | str], dict[str, Any]]]:
    """{model: {(metric, horizon): statistics}} of one env; horizon :data:`AVERAGE` is the error averaged
    over ``horizons`` per run. Each entry has the :data:`SUMMARY_COLUMNS` statistics (None where absent).

    Divergence is per horizon (every run's ``"diverged"``, {horizon: why}, must be set): a run diverged at
    h is left out of the IQM, CI and ratios at h, counted in ``n_diverged`` there and enters P as error
    ``+inf`` there; at its other horizons it counts normally. The :data:`AVERAGE` column counts only the
    runs that diverged at none of ``horizons``. The ratio to delta at h pairs the seeds where neither
    model diverged at h (``n_pairs``).
    """
    columns = [(m, h) for m in metrics for h in horizons] + [(m, AVERAGE) for m in metrics]
    scores = {model: {e["pair"]: _run_scores(e, metrics, horizons) for e in runs} for model, runs in evals.items()}
    out: dict[str, dict[tuple[str, int | str], dict[str, Any]]] = {}
    for model, runs in scores.items():
        x = np.array(list(runs.values()))
        iqm, low, high = iqm_ci_finite(x, reps=reps, seed=seed)
        n_good = np.isfinite(x).sum(axis=0)
        nan = np.full(len(columns), np.nan)
        p = p_low = p_high = ratio = r_low = r_high = p_exact = nan
        n_pairs = None
        if model != BASELINE and BASELINE in scores:
            base = scores[BASELINE]
            # a diverged (NaN) error counts as +inf in P: worse than every run that did not diverge there
            p, p_low, p_high = p_improvement_ci(x, np.array(list(base.values())), reps=reps, seed=seed)
            pairs, ratios = paired_ratios(runs, base)  # NaN where either run diverged
            n_pairs = np.zeros(len(columns), int)
            if pairs:
                n_pairs = np.sum([np.isfinite(runs[s]) & np.isfinite(base[s]) for s in pairs], axis=0)
                ratio, r_low, r_high = iqm_ci_finite(ratios, reps=reps, seed=seed)
                p_exact = np.array([_sign_flip_log(ratios[:, j]) for j in range(len(columns))])
        out[model] = {
            col: {
                "iqm": _finite(iqm[j]),
                "ci_low": _finite(low[j]),
                "ci_high": _finite(high[j]),
                "n_seeds": int(n_good[j]),
                "n_diverged": len(x) - int(n_good[j]),
                "p_improvement": _finite(p[j]),
                "p_improvement_ci_low": _finite(p_low[j]),
                "p_improvement_ci_high": _finite(p_high[j]),
                "ratio_to_delta": _finite(ratio[j]),
                "ratio_ci_low": _finite(r_low[j]),
                "ratio_ci_high": _finite(r_high[j]),
                "n_pairs": None if n_pairs is None else int(n_pairs[j]),
                "p_value_exact": _finite(p_exact[j]),
            }
            for j, col in enumerate(columns)
        }
    return out


def _sign_flip_log(ratios: np.ndarray) -> float:
    """Exact sign-flip p-value of the mean log ratio over the finite pairs of one column (NaN without pairs)."""
    r = ratios[np.isfinite(ratios) & (ratios > 0)]
    return sign_flip_p(np.log(r)) if r.size else math.nan


def _divergence_text(diverged: Mapping[str, str]) -> str:
    """A run's divergences ({horizon: why}) in one line, by horizon: "why at h=5; why at h=50"."""
    return "; ".join(f"{why} at h={h}" for h, why in sorted(diverged.items(), key=lambda item: int(item[0])))


def _has_rotations(runs: Sequence[Mapping[str, Any]]) -> bool:
    """Whether an env's runs report a rotation error (a finite value > 0: the env has rotation groups)."""
    values = [v.get("rotation_error", 0.0) for e in runs for v in e["horizons"].values()]
    return any(math.isfinite(float(v)) and float(v) > 0 for v in values)


def _metric_tables(
    metric: str, models: Sequence[str], stats: Mapping[str, Mapping[tuple[str, Any], Mapping[str, Any]]], hs: Sequence
) -> list[str]:
    """Markdown: the IQM [CI] table of one metric per model and horizon (with the runs diverged at each
    horizon, :func:`_fmt_iqm`), then P of improvement over delta."""
    rows = [
        [model, str(_runs(stats[model][(metric, hs[0])]))] + [_fmt_iqm(stats[model][(metric, h)]) for h in hs]
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


def _runs(s: Mapping[str, Any]) -> int:
    """The runs behind a statistic: the seeds in it and the seeds diverged there."""
    return s["n_seeds"] + s["n_diverged"]


def _fmt_iqm(s: Mapping[str, Any]) -> str:
    """IQM [CI] of one column, then "(k diverged)" if k runs diverged there; "all diverged" if every run did."""
    if s["n_seeds"] == 0:
        return "all diverged"
    return fmt_interval(s["iqm"], *_ci(s)) + (f" ({s['n_diverged']} diverged)" if s["n_diverged"] else "")


def _small(s: Mapping[str, Any]) -> bool:
    """Whether a statistic rests on fewer than :data:`MIN_SEEDS` seeds (and at least one)."""
    return 0 < s["n_seeds"] < MIN_SEEDS


def _ci(s: Mapping[str, Any], key: str = "ci") -> tuple[Any, Any]:
    return s[f"{key}_low"], s[f"{key}_high"]


def _fmt_p(s: Mapping[str, Any]) -> str:
    return fmt_interval(s["p_improvement"], *_ci(s, "p_improvement_ci"), "n/a")


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
        common = sorted(set.intersection(*[set(map(int, e["horizons"])) for e in runs]))
        metrics = order_metrics(sorted(set.intersection(*[set(v) for e in runs for v in e["horizons"].values()])))
        if not common or not metrics:
            text += [f"## {env}", "", "No horizon or error metric that every run has: no statistics.", ""]
            continue
        for model in env_models:
            for e in evals[model]:
                e["diverged"] = divergences(e["horizons"], level[0])
                if e["diverged"]:
                    name = run_name(env, model, e["seed"], data_seed=e["data_seed"])
                    diverged_runs.append(f"{name}: {_divergence_text(e['diverged'])}")
                for h, m in e["horizons"].items():
                    per_run.append(
                        {
                            "env": env,
                            "model": model,
                            "seed": e["seed"],
                            "data_seed": e["data_seed"],
                            "horizon": int(h),
                            "starts": e["starts"],
                            "diverged": e["diverged"].get(h, ""),
                            **m,
                        }
                    )
                    run_columns += [k for k in m if k not in run_columns]
        stats = env_statistics(evals, metrics, common, reps=reps)
        for model in env_models:
            for (metric, h), s in stats[model].items():
                row = {"env": env, "model": model, "metric": metric, **s}
                if h == AVERAGE:
                    relative_rows.append(row)
                else:
                    summary.append({**row, "horizon": h})
        for metric in metrics:  # Fig. 2 as the paper normalises: by the largest model's IQM in the env
            rows = [r for r in relative_rows if r["env"] == env and r["metric"] == metric]
            top = max([r["iqm"] for r in rows if r["iqm"] is not None], default=None)
            for r in rows:
                for key, value in (
                    ("relative", r["iqm"]),
                    ("relative_ci_low", r["ci_low"]),
                    ("relative_ci_high", r["ci_high"]),
                ):
                    r[key] = value / top if value is not None and top else None
                if metric == FIGURE_METRIC:
                    fig2.setdefault(env, {})[r["model"]] = r
        asked = set(request["horizons"])
        skipped = sorted(asked - set(common))
        note = f"; skipped: {', '.join(map(str, skipped))} (longer than the test episodes)" if skipped else ""
        env_small = any(_small(stats[m][(metrics[0], h)]) for m in env_models for h in common)
        text += [f"## {env} (horizons {', '.join(map(str, common))}{note})", ""]
        text += [SMALL_SAMPLE_NOTE, ""] if env_small else []
        for metric in TABLE_METRICS:
            if metric in metrics and (metric != "rotation_error" or _has_rotations(runs)):
                text += _metric_tables(metric, env_models, stats, common)
        text += [f"![absolute error](absolute_error_{env}.png)", ""]
        plot_absolute(
            out / f"absolute_error_{env}.png",
            env,
            {
                m: {
                    "horizons": common,
                    "iqm": [stats[m][(FIGURE_METRIC, h)]["iqm"] for h in common],
                    "ci_low": [stats[m][(FIGURE_METRIC, h)]["ci_low"] for h in common],
                    "ci_high": [stats[m][(FIGURE_METRIC, h)]["ci_high"] for h in common],
                    "n_runs": _runs(stats[m][(FIGURE_METRIC, common[0])]),
                    "n_diverged": [stats[m][(FIGURE_METRIC, h)]["n_diverged"] for h in common],
                }
                for m in env_models
            },
        )
    write_csv(out / "summary.csv", summary, SUMMARY_COLUMNS)
    write_csv(out / "relative_error.csv", relative_rows, RELATIVE_COLUMNS)
    errors = order_metrics(run_columns)
    write_csv(
        out / "prediction_runs.csv",
        per_run,
        ["env", "model", "seed", "data_seed", "horizon", "starts", "diverged", *errors]
        + [k for k in run_columns if k not in errors],
    )
    header = [
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
    primary = primary_rows(per_run, levels, reps=reps)
    write_csv(out / "primary.csv", primary, PRIMARY_COLUMNS)
    write_csv(out / "past_level.csv", past_level_rows(per_run, levels), PAST_LEVEL_COLUMNS)
    text = header + primary_markdown(primary) + text
    if fig2:
        plot_relative(out / "relative_error.png", fig2)
        has_ratio = any(r["ratio_to_delta"] is not None for vals in fig2.values() for r in vals.values())
        if has_ratio:
            plot_ratio(out / "ratio_to_delta.png", fig2)
        fig2_small = any(_small(r) for vals in fig2.values() for r in vals.values())
        text += [
            "## Fig. 2: error averaged over the horizons",
            "",
            f"Per seed the {FIGURE_METRIC} averaged over the env's horizons, then the IQM over seeds [95 % CI]. "
            "relative: divided by the largest model's IQM in the env, as the paper normalises (the CI divided "
            f"by the same number). ratio to {BASELINE}: IQM [CI] of the per-seed ratios over the seeds both "
            "models have (paired: same seed, data and start points). A run diverged at any horizon is left out "
            "of the average and counted under diverged.",
            "",
        ]
        text += [SMALL_SAMPLE_NOTE, ""] if fig2_small else []
        text += [
            md_table(
                [
                    "env",
                    "model",
                    "seeds",
                    "diverged",
                    "relative",
                    f"ratio to {BASELINE}",
                    "pairs",
                    f"P(error < {BASELINE}'s)",
                ],
                [
                    [
                        env,
                        m,
                        str(r["n_seeds"]),
                        str(r["n_diverged"]),
                        fmt_interval(
                            r["relative"], *_ci(r, "relative_ci"), "all diverged" if not r["n_seeds"] else "n/a"
                        ),
                        "-" if m == BASELINE else fmt_interval(r["ratio_to_delta"], *_ci(r, "ratio_ci")),
                        "-" if r["n_pairs"] is None else str(r["n_pairs"]),
                        "-" if m == BASELINE else _fmt_p(r),
                    ]
                    for env, vals in fig2.items()
                    for m, r in vals.items()
                ],
            ),
            "",
            "![relative error](relative_error.png)" + (" ![ratio to delta](ratio_to_delta.png)" if has_ratio else ""),
            "",
        ]
    text += precision_note(included)
    if diverged_runs:
        text += (
            ["## Diverged runs (counted, not in the IQMs at these horizons nor in the average)", ""]
            + [f"- {d}" for d in diverged_runs]
            + [""]
        )
    missing = [
        run_name(e, m, s, data_seed=d)
        for e in env_names
        for m in models
        for d in data_seeds
        for s in seeds
        if not json_matches(
            out / "runs" / run_name(e, m, s, data_seed=d) / "eval.json", {**request, "data": _test_label(e, d)}
        )
    ]
    if missing:
        text += ["## Missing runs (not in the statistics)", ""]
        text += [f"- {m}{': ' + failed[m] if failed and m in failed else ''}" for m in missing] + [""]
    atomic_write_bytes(out / "prediction.md", "\n".join(text).encode())
    return summary
