"""The online study's record and statistics: what one run records (:data:`RUN_COLUMNS`), the statistics over seeds
per env and arm (:func:`arm_statistics`, :data:`SUMMARY_COLUMNS`), and the summary rows made either from the runs'
metrics (:mod:`pets.experiments.online_summary`) or from the committed per-run rows (:func:`summary_from_runs`, for
``pets.compare report``). The statistics are described in :mod:`pets.experiments.online_summary`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from pets.experiments.online_runs import COST_KEYS, THRESHOLD_KEYS, THRESHOLDS
from pets.experiments.report import BOOT_SEED
from pets.experiments.rundirs import arm_label
from pets.experiments.statistics import (
    BASELINE,
    REPS,
    ci_exact_note,
    holm,
    iqm_ci,
    iqm_ci_finite,
    p_improvement_ci,
    paired_differences,
    sign_flip_p,
)

_BASELINE_COLUMNS = [
    "p_improvement",
    "p_improvement_ci_low",
    "p_improvement_ci_high",
    "diff_to_delta",
    "diff_ci_low",
    "diff_ci_high",
    "n_pairs",
    "diff_p_signflip",
    "diff_p_holm",
    "ci_exact_note",
    "p_fewer_steps",
    "p_fewer_steps_ci_low",
    "p_fewer_steps_ci_high",
]
SUMMARY_COLUMNS = [
    "env",
    "model",
    "planner",
    "n_seeds",
    "n_diverged",
    "trials",
    "final_window",
    "final_iqm",
    "final_ci_low",
    "final_ci_high",
    "auc_iqm",
    "auc_ci_low",
    "auc_ci_high",
    "threshold",
    "n_reached",
    *[f"{k}_{stat}" for k in THRESHOLD_KEYS for stat in ("iqm", "ci_low", "ci_high")],
    *[f"{k}_mean" for k in COST_KEYS],
    *_BASELINE_COLUMNS,
]
RUN_COLUMNS = [
    "env",
    "model",
    "planner",
    "seed",
    "trials",
    "diverged",
    "final_reward",
    "auc",
    *THRESHOLD_KEYS,
    *COST_KEYS,
]


def _finite(x: float | None) -> float | None:
    """``x`` as a float, None if absent or not finite (an empty CSV cell, "n/a" in a table)."""
    return None if x is None or not math.isfinite(x) else float(x)


def arm_statistics(
    runs: Mapping[str, Sequence[Mapping[str, Any]]],
    baselines: Mapping[str, str | None],
    *,
    reps: int = REPS,
    seed: int = BOOT_SEED,
    threshold: bool = False,
) -> dict[str, dict[str, Any]]:
    """{arm: statistics} of one env: ``n_seeds``, ``n_diverged`` and the :data:`SUMMARY_COLUMNS` from
    ``final_iqm`` on (None where absent or not finite).

    ``runs``: {arm: the :func:`online_run_stats` of its complete runs, each with its ``"seed"``};
    ``baselines``: {arm: the arm it is compared with, None for the baseline itself or when there is none};
    ``threshold``: whether the env has a threshold (then ``p_fewer_steps`` against the baseline).
    """
    good = {arm: {r["seed"]: r for r in rs if not r["diverged"]} for arm, rs in runs.items()}
    out: dict[str, dict[str, Any]] = {}
    for arm, rs in runs.items():
        s: dict[str, Any] = dict.fromkeys(SUMMARY_COLUMNS[SUMMARY_COLUMNS.index("final_iqm") :])
        s.update(n_seeds=len(good[arm]), n_diverged=len(rs) - len(good[arm]))
        if good[arm]:
            scores = np.array([[r["final_reward"], r["auc"]] for r in good[arm].values()])
            iqm, low, high = iqm_ci(scores, reps=reps, seed=seed)
            for j, key in enumerate(("final", "auc")):
                s.update({f"{key}_iqm": iqm[j], f"{key}_ci_low": low[j], f"{key}_ci_high": high[j]})
        reached = [r for r in good[arm].values() if math.isfinite(r["minutes_to_threshold"])]
        s["n_reached"] = len(reached)
        if reached:  # the runs that never reached it are counted (n_reached of n_seeds), not averaged in
            times = np.array([[r[k] for k in THRESHOLD_KEYS] for r in reached])
            iqm, low, high = iqm_ci_finite(times, reps=reps, seed=seed)  # CPU minutes: NaN in runs without them
            for j, key in enumerate(THRESHOLD_KEYS):
                s.update({f"{key}_iqm": iqm[j], f"{key}_ci_low": low[j], f"{key}_ci_high": high[j]})
        s.update({f"{k}_mean": float(np.mean([r[k] for r in rs])) for k in COST_KEYS})
        base = baselines.get(arm)
        if base is not None and base in runs:
            s.update(_against_baseline(runs, good, arm, base, reps=reps, seed=seed, threshold=threshold))
        out[arm] = {k: _finite(v) if isinstance(v, float) else v for k, v in s.items()}
    return out


def _against_baseline(
    runs: Mapping[str, Sequence[Mapping[str, Any]]],
    good: Mapping[str, Mapping[Any, Mapping[str, Any]]],
    arm: str,
    base: str,
    *,
    reps: int,
    seed: int,
    threshold: bool,
) -> dict[str, Any]:
    """The baseline columns of ``arm`` against ``base``: P(final > baseline's), the paired differences, the exact
    sign-flip p-value and, with a ``threshold``, P(fewer steps to it). ``runs`` and ``good`` ({arm: {seed: run}} of
    the runs that did not diverge) as in :func:`arm_statistics`."""
    s: dict[str, Any] = {}
    # diverged runs enter P as NaN, i.e. the worst final reward
    x = [math.nan if r["diverged"] else r["final_reward"] for r in runs[arm]]
    y = [math.nan if r["diverged"] else r["final_reward"] for r in runs[base]]
    (p,), (p_low,), (p_high,) = p_improvement_ci(x, y, higher_is_better=True, reps=reps, seed=seed)
    s.update(p_improvement=p, p_improvement_ci_low=p_low, p_improvement_ci_high=p_high)
    final = {k: r["final_reward"] for k, r in good[arm].items()}
    pairs, diffs = paired_differences(final, {k: r["final_reward"] for k, r in good[base].items()})
    s["n_pairs"] = len(pairs)
    if pairs:
        (d,), (d_low,), (d_high,) = iqm_ci(diffs, reps=reps, seed=seed)
        s.update(diff_to_delta=d, diff_ci_low=d_low, diff_ci_high=d_high)
    # The exact test counts a diverged run as the worst outcome: the lowest finite final reward of the env.
    worst = min((r["final_reward"] for rs_ in good.values() for r in rs_.values()), default=math.nan)
    worst_of = {a: {r["seed"]: worst if r["diverged"] else r["final_reward"] for r in runs[a]} for a in (arm, base)}
    _, all_diffs = paired_differences(worst_of[arm], worst_of[base])
    if all_diffs.size and np.isfinite(all_diffs).all():
        s["diff_p_signflip"] = sign_flip_p(all_diffs[:, 0])
        s["ci_exact_note"] = ci_exact_note(s.get("diff_ci_low"), s.get("diff_ci_high"), 0.0, s["diff_p_signflip"])
    if threshold:  # steps as errors: never reached or diverged = NaN, the most steps
        x = [math.nan if r["diverged"] else r["steps_to_threshold"] for r in runs[arm]]
        y = [math.nan if r["diverged"] else r["steps_to_threshold"] for r in runs[base]]
        (p,), (p_low,), (p_high,) = p_improvement_ci(x, y, reps=reps, seed=seed)
        s.update(p_fewer_steps=p, p_fewer_steps_ci_low=p_low, p_fewer_steps_ci_high=p_high)
    return s


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
    stats = arm_statistics(runs, baselines, reps=reps, threshold=env in thresholds)
    rows = []
    for model, planner in arms:
        label = labels[(model, planner)]
        if label in stats:
            row = {"env": env, "model": model, "planner": planner or "", "trials": trials, "final_window": final_window}
            rows.append({**row, **stats[label], "threshold": thresholds.get(env)})
    return rows, stats


def holm_over_summary(summary: Sequence[dict[str, Any]]) -> None:
    """Set ``diff_p_holm``: Holm over the family of every arm-vs-baseline test of the primary endpoint in the
    summary (envs x arms)."""
    adjusted = holm([math.nan if r.get("diff_p_signflip") is None else r["diff_p_signflip"] for r in summary])
    for row, p_adj in zip(summary, adjusted):
        row["diff_p_holm"] = _finite(p_adj)


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
    holm_over_summary(summary)
    return summary
