"""The offline prediction study: its metric table (:data:`STUDY`; the columns of summary.csv, relative_error.csv and
prediction_runs.csv follow from it and from the statistics' columns named here once) and its statistics per env,
model, error metric and horizon, made either from the runs' eval.json files (:mod:`pets.experiments.offline_summary`,
which describes them and writes them out) or from the committed per-run rows (:func:`summary_from_runs`, for
``pets.compare report``).

Unlike the online study (:mod:`pets.experiments.studies.base`), a row here is one error metric at one horizon (or
averaged over the tracking horizons): the metrics are the eval.json keys ending in ``_error`` that every run of an env
has (:func:`order_metrics`), each with the same statistics (:data:`OWN`, :data:`COMPARED`); the metric table says
where each is shown (its markdown table, Fig. 2 and 3, the headline).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pets.experiments.report import BOOT_SEED
from pets.experiments.rundirs import run_name
from pets.experiments.statistics import (
    BASELINE,
    REPS,
    ci_exact_note,
    divergences,
    iqm_ci_finite,
    p_improvement_ci,
    paired_ratios,
    sign_flip_p,
)
from pets.experiments.studies.base import INTERVAL, P_EXACT, RATIO
from pets.experiments.studies.primary import METRIC as PRIMARY_METRIC
from pets.experiments.studies.primary import tracking_horizons
from pets.learning.evaluation import METRICS as EVALUATE_METRICS

#: The horizon label of the columns averaged over the horizons (relative_error.csv, Fig. 2).
AVERAGE = "average"
#: The statistics of one model and column: its IQM [CI] (:data:`INTERVAL`, as the online study's) and counts.
IQM, CI_LOW, CI_HIGH, N_SEEDS, N_DIVERGED = OWN = (*INTERVAL, "n_seeds", "n_diverged")
#: The comparison with delta per (metric, horizon): P(lower error than delta's) with its CI, the IQM of the per-pair
#: ratios with its CI, and the exact sign-flip test of the mean log ratio.
P_LOWER = ("p_improvement", "p_improvement_ci_low", "p_improvement_ci_high")
N_PAIRS, NOTE = "n_pairs", "ci_exact_note"
EXACT = (N_PAIRS, P_EXACT, NOTE)
COMPARED = (*P_LOWER, *RATIO, *EXACT)
#: Fig. 2 as the paper normalises it: the IQM [CI] divided by the largest model's IQM of the env.
RELATIVE = ("relative", "relative_ci_low", "relative_ci_high")


@dataclass(frozen=True)
class ErrorMetric:
    """One line of the offline study's metric table: an eval.json error (lower is better) and where it is shown.
    ``table``: its IQM table and P against delta in prediction.md (``nonzero``: only where a run of the env has a
    finite value > 0, i.e. the env has those coordinates); ``figure``: the metric of Fig. 2 and Fig. 3;
    ``headline``: its place among the headline's offline metrics (1 first; 0: not there)."""

    name: str
    table: bool = False
    nonzero: bool = False
    figure: bool = False
    headline: int = 0

    def shown(self, runs: Sequence[Mapping[str, Any]]) -> bool:
        """Whether an env's runs get its table (``nonzero``: a finite value > 0 at some horizon)."""
        if not self.nonzero:
            return True
        values = [float(v.get(self.name, 0.0)) for e in runs for v in e["horizons"].values()]
        return any(math.isfinite(v) and v > 0 for v in values)


@dataclass(frozen=True)
class OfflineStudy:
    """The offline study: its row ``keys``, what a run records per horizon besides its errors (``run_keys``) and
    its :class:`ErrorMetric` table."""

    name: str
    keys: tuple[str, ...]
    run_keys: tuple[str, ...]
    metrics: tuple[ErrorMetric, ...]

    def summary_columns(self) -> list[str]:
        """summary.csv: per env, model, horizon and metric its own statistics, then against delta."""
        return [*self.keys, *OWN, *COMPARED]

    def relative_columns(self) -> list[str]:
        """relative_error.csv: summary.csv's without the horizon, the relative IQM [CI] after the IQM [CI], the
        horizons averaged over last."""
        return [
            *(k for k in self.keys if k != "horizon"),
            *INTERVAL,
            *RELATIVE,
            N_SEEDS,
            N_DIVERGED,
            *COMPARED,
            "horizons",
        ]

    def run_columns(self, keys: Sequence[str]) -> list[str]:
        """prediction_runs.csv: the run keys, then of the value ``keys`` the errors first, then the others."""
        errors = order_metrics(keys)
        return [*self.run_keys, *errors, *(k for k in keys if k not in errors)]

    def headline_columns(self) -> list[str]:
        """headline_offline.csv: per env, model, metric and horizon the ratio to delta, P(lower error), the exact p
        with its note, the pairs and the divergences (the model's and delta's), then the summary it came from."""
        env, model, horizon, metric = self.keys
        compared = [*RATIO, *P_LOWER, P_EXACT, NOTE, N_PAIRS, N_DIVERGED, f"{BASELINE}_{N_DIVERGED}"]
        return [env, model, metric, horizon, *compared, "source"]

    def table_metrics(self) -> list[ErrorMetric]:
        return [m for m in self.metrics if m.table]

    def figure_metric(self) -> str:
        return next(m.name for m in self.metrics if m.figure)

    def headline_metrics(self) -> tuple[str, ...]:
        return tuple(m.name for m in sorted(self.metrics, key=lambda m: m.headline) if m.headline)


#: The offline study's metric table: one line per error metric shown (every error every run has is in the CSVs).
STUDY = OfflineStudy(
    name="offline",
    keys=("env", "model", "horizon", "metric"),
    run_keys=("env", "model", "seed", "data_seed", "horizon", "starts", "diverged"),
    metrics=(
        ErrorMetric("mean_step_error", table=True, figure=True, headline=3),
        ErrorMetric(PRIMARY_METRIC, table=True, headline=1),
        ErrorMetric("rotation_error", table=True, nonzero=True, headline=2),
    ),
)
SUMMARY_COLUMNS = STUDY.summary_columns()
RELATIVE_COLUMNS = STUDY.relative_columns()


def pair_key(data_seed: int, seed: int, n_data_sets: int) -> int | tuple[int, int]:
    """What runs pair by: the model seed alone with one data set, else (data seed, seed)."""
    return seed if n_data_sets == 1 else (data_seed, seed)


def order_metrics(keys: Sequence[str]) -> list[str]:
    """The ``*_error`` keys among ``keys``: :data:`EVALUATE_METRICS` first in their order, then the rest sorted."""
    errors = {k for k in keys if k.endswith("_error")}
    return [m for m in EVALUATE_METRICS if m in errors] + sorted(errors - set(EVALUATE_METRICS))


def shared_horizons_and_metrics(runs: Sequence[Mapping[str, Any]]) -> tuple[list[int], list[str]]:
    """The horizons and the error metrics (:func:`order_metrics`) that every run of an env has."""
    common = sorted(set.intersection(*[set(map(int, e["horizons"])) for e in runs]))
    metrics = order_metrics(sorted(set.intersection(*[set(v) for e in runs for v in e["horizons"].values()])))
    return common, metrics


def divergence_text(diverged: Mapping[str, str]) -> str:
    """A run's divergences ({horizon: why}) in one line, by horizon: "why at h=5; why at h=50"."""
    return "; ".join(f"{why} at h={h}" for h, why in sorted(diverged.items(), key=lambda item: int(item[0])))


def mark_divergences(
    env: str, models: Sequence[str], evals: Mapping[str, Sequence[dict[str, Any]]], level: float
) -> list[str]:
    """Set every run's ``"diverged"`` ({horizon: why}) at the env's no-information ``level``; a line per diverged
    run."""
    lines = []
    for model in models:
        for e in evals[model]:
            e["diverged"] = divergences(e["horizons"], level)
            if e["diverged"]:
                name = run_name(env, model, e["seed"], data_seed=e["data_seed"])
                lines.append(f"{name}: {divergence_text(e['diverged'])}")
    return lines


def _finite(x: float | None) -> float | None:
    """``x`` as a float, None if absent or not finite (an empty CSV cell, "n/a" in a table)."""
    return None if x is None or not math.isfinite(x) else float(x)


def _run_scores(
    e: Mapping[str, Any], metrics: Sequence[str], horizons: Sequence[int], averaged: Sequence[int]
) -> np.ndarray:
    """One run's errors per column: each metric at each horizon, then each metric averaged over ``averaged`` (a
    subset of ``horizons``). NaN where the run diverged (``e["diverged"]``: {horizon: why}): at that horizon, and
    in the average when at any of ``averaged``, since an average over a diverged horizon means nothing; NaN in
    the average when ``averaged`` is empty."""
    per_h = np.array([[float(e["horizons"][str(h)][m]) for h in horizons] for m in metrics])
    per_h[:, [str(h) in e["diverged"] for h in horizons]] = np.nan
    columns = [horizons.index(h) for h in averaged]
    average = per_h[:, columns].mean(axis=1) if columns else np.full(len(metrics), np.nan)
    return np.concatenate([per_h.ravel(), average])


def env_statistics(
    evals: Mapping[str, Sequence[Mapping[str, Any]]],
    metrics: Sequence[str],
    horizons: Sequence[int],
    *,
    averaged: Sequence[int] | None = None,
    reps: int = REPS,
    seed: int = BOOT_SEED,
) -> dict[str, dict[tuple[str, int | str], dict[str, Any]]]:
    """{model: {(metric, horizon): statistics}} of one env; horizon :data:`AVERAGE` is the error averaged
    over ``averaged`` (default: all ``horizons``) per run. Each entry has the :data:`OWN` and :data:`COMPARED`
    statistics (None where absent).

    Divergence is per horizon (every run's ``"diverged"``, {horizon: why}, must be set): a run diverged at
    h is left out of the IQM, CI and ratios at h, counted in ``n_diverged`` there and enters P as error
    ``+inf`` there; at its other horizons it counts normally. The :data:`AVERAGE` column counts only the
    runs that diverged at none of ``averaged``. The ratio to delta at h pairs the seeds where neither
    model diverged at h (``n_pairs``).
    """
    horizons = list(horizons)
    averaged = horizons if averaged is None else list(averaged)
    columns = [(m, h) for m in metrics for h in horizons] + [(m, AVERAGE) for m in metrics]
    scores = {
        model: {e["pair"]: _run_scores(e, metrics, horizons, averaged) for e in runs} for model, runs in evals.items()
    }
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
        own = (iqm, low, high)
        out[model] = {
            col: {
                **{k: _finite(v[j]) for k, v in zip(OWN, own)},
                N_SEEDS: int(n_good[j]),
                N_DIVERGED: len(x) - int(n_good[j]),
                **{k: _finite(v[j]) for k, v in zip(P_LOWER, (p, p_low, p_high))},
                **{k: _finite(v[j]) for k, v in zip(RATIO, (ratio, r_low, r_high))},
                N_PAIRS: None if n_pairs is None else int(n_pairs[j]),
                P_EXACT: _finite(p_exact[j]),
                NOTE: ci_exact_note(_finite(r_low[j]), _finite(r_high[j]), 1.0, _finite(p_exact[j])),
            }
            for j, col in enumerate(columns)
        }
    return out


def _sign_flip_log(ratios: np.ndarray) -> float:
    """Exact sign-flip p-value of the mean log ratio over the finite pairs of one column (NaN without pairs)."""
    r = ratios[np.isfinite(ratios) & (ratios > 0)]
    return sign_flip_p(np.log(r)) if r.size else math.nan


def figure_horizons(
    evals: Mapping[str, Sequence[Mapping[str, Any]]], horizons: Sequence[int], level: float
) -> list[int]:
    """Fig. 2's horizons: delta's tracking horizons (:func:`pets.experiments.studies.primary.tracking_horizons` of its
    standardized error at the no-information ``level``); all ``horizons`` where the env has no delta run or no
    standardized error."""
    base = evals.get(BASELINE, [])
    if not base or any(PRIMARY_METRIC not in e["horizons"][str(h)] for e in base for h in horizons):
        return list(horizons)
    runs = {e["pair"]: {h: float(e["horizons"][str(h)][PRIMARY_METRIC]) for h in horizons} for e in base}
    return tracking_horizons(runs, level)


def env_summary_rows(
    env: str,
    models: Sequence[str],
    evals: Mapping[str, Sequence[Mapping[str, Any]]],
    horizons: Sequence[int],
    metrics: Sequence[str],
    level: float,
    reps: int = REPS,
) -> tuple[dict[str, Any], list[dict[str, Any]], list[dict[str, Any]]]:
    """(statistics, summary.csv rows, relative_error.csv rows) of one env's runs (``evals``: {model: [eval]}, each
    with ``pair`` and ``diverged`` set); the relative rows average over :func:`figure_horizons`."""
    averaged = figure_horizons(evals, horizons, level)
    stats = env_statistics(evals, metrics, horizons, averaged=averaged, reps=reps)
    summary, relative = [], []
    for model in models:
        for (metric, h), s in stats[model].items():
            row = {"env": env, "model": model, "metric": metric, **s}
            if h == AVERAGE:
                relative.append({**row, "horizons": " ".join(map(str, averaged))})
            else:
                summary.append({**row, "horizon": h})
    _normalise(relative, metrics)
    return stats, summary, relative


def _normalise(relative: Sequence[dict[str, Any]], metrics: Sequence[str]) -> None:
    """Fig. 2 as the paper normalises: set :data:`RELATIVE` of one env's rows, the IQM [CI] divided by the largest
    model's IQM of that metric in the env."""
    for metric in metrics:
        rows = [r for r in relative if r["metric"] == metric]
        top = max([r[IQM] for r in rows if r[IQM] is not None], default=None)
        for r in rows:
            for key, own in zip(RELATIVE, INTERVAL):
                r[key] = r[own] / top if r[own] is not None and top else None


def summary_from_runs(rows: Sequence[Mapping[str, str]], level: float, reps: int = REPS) -> tuple[list, list]:
    """(summary.csv rows, relative_error.csv rows) recomputed from per-run rows (``prediction_runs.csv``, committed
    as ``docs/results/paper_ENV_runs.csv``: env, model, seed, [data_seed,] horizon, starts, the error metrics) with
    the divergence rule at the no-information ``level``: the statistics ``summarise_offline`` computes from eval.json
    files, for studies whose run directories are gone."""
    evals: dict[str, dict[str, dict[tuple, dict[str, Any]]]] = {}
    for r in rows:
        key = (int(r.get("data_seed") or 0), int(r["seed"]))
        runs = evals.setdefault(r["env"], {}).setdefault(r["model"], {})
        e = runs.setdefault(key, {"seed": key[1], "data_seed": key[0], "horizons": {}})
        values = {k: v for k, v in r.items() if (k.endswith("_error") or k == "nonfinite_fraction") and v}
        e["horizons"][str(int(r["horizon"]))] = {k: float(v) for k, v in values.items()}  # empty cell: absent
    summary, relative = [], []
    for env, by_model in evals.items():
        data_seeds = {k[0] for runs in by_model.values() for k in runs}
        env_evals = {
            m: [{**e, "pair": pair_key(*k, len(data_seeds))} for k, e in runs.items()] for m, runs in by_model.items()
        }
        models = list(env_evals)
        horizons, metrics = shared_horizons_and_metrics([e for runs in env_evals.values() for e in runs])
        mark_divergences(env, models, env_evals, level)
        _, env_summary, env_relative = env_summary_rows(env, models, env_evals, horizons, metrics, level, reps)
        summary += env_summary
        relative += env_relative
    return summary, relative
