"""The offline summary's statistics: the runs' evaluations and, per env, model, metric and horizon, the statistics
over seeds (:mod:`pets.experiments.offline_summary` describes them and writes them out).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pets.experiments.report import BOOT_SEED
from pets.experiments.rundirs import json_matches, run_name
from pets.experiments.statistics import (
    BASELINE,
    REPS,
    ci_exact_note,
    iqm_ci_finite,
    p_improvement_ci,
    paired_ratios,
    sign_flip_p,
)
from pets.learning.evaluation import METRICS as EVALUATE_METRICS

#: The horizon label of the columns averaged over the horizons (relative_error.csv, Fig. 2).
AVERAGE = "average"
#: The offline study's comparison with delta per (metric, horizon), its columns named here once (the summary, the
#: relative-error table and the headline compose theirs from these): P(lower error than delta's) with its CI, the
#: IQM of the per-pair ratios with its CI, and the exact sign-flip test of the mean log ratio.
P_LOWER = ("p_improvement", "p_improvement_ci_low", "p_improvement_ci_high")
RATIO = ("ratio_to_delta", "ratio_ci_low", "ratio_ci_high")
N_PAIRS, P_EXACT, NOTE = EXACT = ("n_pairs", "p_value_exact", "ci_exact_note")
#: The statistics of one model and column: its IQM [CI] and counts.
OWN = ("iqm", "ci_low", "ci_high", "n_seeds", "n_diverged")


def test_label(env: str, data_seed: int) -> str:
    """The ``data`` entry of an evaluation request on data set ``data_seed`` (pets.experiments.offline.data_paths)."""
    return f"data/{env}-d{data_seed}-test.npz" if data_seed else f"data/{env}-test.npz"


def pair_key(data_seed: int, seed: int, n_data_sets: int) -> int | tuple[int, int]:
    """What runs pair by: the model seed alone with one data set, else (data seed, seed)."""
    return seed if n_data_sets == 1 else (data_seed, seed)


def load_evals(
    out: Path,
    env: str,
    models: Sequence[str],
    seeds: Sequence[int],
    request: Mapping[str, Any],
    data_seeds: Sequence[int] = (0,),
) -> dict[str, list[dict[str, Any]]]:
    """{model: [eval.json of each (data seed, seed) that has one for this request]}; each with ``seed``,
    ``data_seed`` and ``pair`` (:func:`pair_key`)."""
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


def order_metrics(keys: Sequence[str]) -> list[str]:
    """The ``*_error`` keys among ``keys``: :data:`EVALUATE_METRICS` first in their order, then the rest sorted."""
    errors = {k for k in keys if k.endswith("_error")}
    return [m for m in EVALUATE_METRICS if m in errors] + sorted(errors - set(EVALUATE_METRICS))


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
    over ``averaged`` (default: all ``horizons``) per run. Each entry has the :data:`SUMMARY_COLUMNS`
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
        out[model] = {
            col: {
                **dict(
                    zip(
                        OWN,
                        (_finite(iqm[j]), _finite(low[j]), _finite(high[j]), int(n_good[j]), len(x) - int(n_good[j])),
                    )
                ),
                **dict(zip(P_LOWER, (_finite(p[j]), _finite(p_low[j]), _finite(p_high[j])))),
                **dict(zip(RATIO, (_finite(ratio[j]), _finite(r_low[j]), _finite(r_high[j])))),
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
