"""Online summary: per-run numbers from metrics.csv, rliable statistics over seeds, summary tables and reward plots.

Per run: ``final`` = mean episode reward of the last W trials (W = ``--final-window``, default 3, at
most N); ``auc`` = mean episode reward over all N trials; the run's wall-clock time and median
seconds per planning step. A run with a non-finite episode reward is diverged (:func:`reward_divergence`).
Per (env, arm) over the runs that did not diverge (:mod:`pets.experiments.statistics`, the same
statistics as the offline summary): IQM of final and auc with its 95 % stratified-bootstrap CI; against
the baseline arm (:data:`BASELINE` with the same planner) P(final > baseline's) with its CI (diverged
runs: the worst final) and the IQM [CI] of the per-seed difference of final rewards, with the exact paired
sign-flip p-value of its mean (``diff_p_signflip``; a diverged run enters as the env's lowest final reward) and
Holm's adjustment of those p-values over every arm-vs-baseline test of the summary (``diff_p_holm``). Diverged runs
are counted (``n_diverged``), never averaged in; the cost columns are means over all complete runs.

Time to threshold (:data:`THRESHOLDS`, per env): the wall-clock minutes (``wall_time_s`` of the first trial
whose episode reward reaches the threshold, i.e. at the end of that trial, its model training included), the
env steps and the process CPU minutes (``cpu_time_s``; empty for runs made before the column) until then. Per
arm over the runs that did not diverge: ``n_reached`` of ``n_seeds`` reached it (counted), and the IQM [CI] of
each over the runs that reached it (never averaged with the ones that did not). Against the baseline,
``p_fewer_steps``: P(the arm needs fewer env steps to the threshold than the baseline) with its CI, a run that
never reached it (or diverged) counting as the most steps.

Files: ``summary.md``, ``summary.csv`` (per env and arm, :data:`SUMMARY_COLUMNS`; the baseline columns
empty for the baseline itself and where it has no run), ``summary_runs.csv`` (per run, with
``diverged``), ``rewards_ENV.png`` (episode reward vs env steps per arm: every seed's curve interpolated
linearly onto a common grid of 200 env-step values over the range all its seeds cover, then the IQM
over seeds with its CI band at each grid point; the raw curves faintly behind) and ``walltime_ENV.png``
(the same against the run's wall-clock hours: reward per unit of compute).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pets.experiments.online_runs import COST_KEYS, THRESHOLD_KEYS, THRESHOLDS, online_rows, online_run_stats
from pets.experiments.plots import arm_colors, model_colors, plot_online
from pets.experiments.report import BOOT_SEED, disagreement_lines, fmt, fmt_interval, md_table, write_csv
from pets.experiments.rundirs import arm_label, env_stem, online_arms, precision_note, run_name
from pets.experiments.statistics import (
    BASELINE,
    MIN_SEEDS,
    REPS,
    SMALL_SAMPLE_NOTE,
    ci_exact_note,
    holm,
    iqm_ci,
    iqm_ci_finite,
    p_improvement_ci,
    paired_differences,
    sign_flip_p,
)
from pets.runs.fileio import atomic_write_bytes

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


def summarise_online(
    out: Path,
    env_names: Sequence[str],
    models: Sequence[str],
    seeds: Sequence[int],
    trials: int,
    final_window: int,
    failed: Mapping[str, str] | None = None,
    planners: Sequence[str] | None = None,
    *,
    reps: int = REPS,
    thresholds: Mapping[str, float] = THRESHOLDS,
    until_threshold: bool = False,
) -> list[dict[str, Any]]:
    """Write summary.md, summary.csv, summary_runs.csv, rewards_ENV.png and walltime_ENV.png (module
    docstring) from the complete runs; returns the summary.csv rows. ``thresholds``: the reward threshold
    per env of the time-to-threshold columns (an env without one gets none). ``until_threshold``: a run that
    reached its env's threshold is complete with fewer rows (``pets.compare online --until-threshold``)."""
    out = Path(out)
    found: dict[str, list] = {"per_run": [], "missing": [], "diverged": [], "included": []}
    summary, text = [], []
    envs_done: list[tuple[str, list[dict[str, Any]]]] = []
    arms = online_arms(models, planners)
    labels = {arm: arm_label(*arm) for arm in arms}
    baselines = {
        labels[(m, p)]: labels[(BASELINE, p)] if m != BASELINE and (BASELINE, p) in labels else None for m, p in arms
    }
    compared = any(b is not None for b in baselines.values())
    w = min(final_window, trials)
    for env in env_names:
        runs, curves = _env_runs(
            out, env, arms, labels, seeds, trials, final_window, failed, thresholds, until_threshold, found
        )
        if not runs:
            continue
        stats = arm_statistics(runs, baselines, reps=reps, threshold=env in thresholds)
        rows_env = []
        for model, planner in arms:
            label = labels[(model, planner)]
            if label in stats:
                row = {"env": env, "model": model, "planner": planner or "", "trials": trials, "final_window": w}
                rows_env.append({**row, **stats[label], "threshold": thresholds.get(env)})
        summary += rows_env
        envs_done.append((env, rows_env))
        _plot_env(out, env, curves, stats, planners, reps)
    # Holm over the family of every arm-vs-baseline test of the primary endpoint in this summary (envs x arms).
    adjusted = holm([math.nan if r.get("diff_p_signflip") is None else r["diff_p_signflip"] for r in summary])
    for row, p_adj in zip(summary, adjusted):
        row["diff_p_holm"] = _finite(p_adj)
    for env, rows_env in envs_done:
        text += _env_section(env, rows_env, planners is not None, compared, baselines)
    write_csv(out / "summary.csv", summary, SUMMARY_COLUMNS)
    write_csv(out / "summary_runs.csv", found["per_run"], RUN_COLUMNS)
    text = (
        _header(trials, w, compared, planners is not None, until_threshold) + text + precision_note(found["included"])
    )
    text += _runs_sections(found["diverged"], found["missing"])
    atomic_write_bytes(out / "summary.md", "\n".join(text).encode())
    return summary


def _env_runs(
    out: Path,
    env: str,
    arms: Sequence[tuple[str, str | None]],
    labels: Mapping[tuple[str, str | None], str],
    seeds: Sequence[int],
    trials: int,
    final_window: int,
    failed: Mapping[str, str] | None,
    thresholds: Mapping[str, float],
    until_threshold: bool,
    found: Mapping[str, list],
) -> tuple[dict[str, list[dict[str, Any]]], dict[str, list[list[dict[str, float]]]]]:
    """``(runs, curves)`` of one env: {arm: :func:`online_run_stats` of each complete run} and {arm: the metrics rows
    of each complete run that did not diverge}; adds to ``found``'s lists the per-run rows, the missing and the
    diverged runs and the directories included."""
    runs: dict[str, list[dict[str, Any]]] = {}
    curves: dict[str, list[list[dict[str, float]]]] = {}
    for model, planner in arms:
        label = labels[(model, planner)]
        for seed in seeds:
            name = run_name(env, model, seed, planner)
            rows, reached = _complete_rows(out / "runs" / name, thresholds.get(env, math.inf), until_threshold)
            if len(rows) < trials and not reached:
                found["missing"].append(
                    f"{name} ({len(rows)}/{trials} trials"
                    f"{'; failed: ' + failed[name] if failed and name in failed else ''})"
                )
                continue
            s = {"seed": seed, **online_run_stats(rows, trials, final_window, thresholds.get(env))}
            found["per_run"].append({"env": env, "model": model, "planner": planner or "", "trials": trials, **s})
            found["per_run"][-1]["diverged"] = s["diverged"] or ""
            unknown = (*THRESHOLD_KEYS, "cpu_time_s")  # never reached; a run without the CPU column
            found["per_run"][-1].update({k: "" for k in unknown if not math.isfinite(s[k])})
            runs.setdefault(label, []).append(s)
            found["included"].append(out / "runs" / name)
            curves.setdefault(label, [])
            if s["diverged"]:
                found["diverged"].append(f"{name}: {s['diverged']}")
            else:
                curves[label].append(rows[:trials])
    return runs, curves


def _complete_rows(run_dir: Path, limit: float, until_threshold: bool) -> tuple[list[dict[str, float]], bool]:
    """``(rows, reached)``: a run's metrics rows and, with ``until_threshold``, whether one reached ``limit`` (then the
    rows end there: a run to the threshold ends there, a longer run is cut at it)."""
    rows = online_rows(run_dir)
    reached = False
    if until_threshold:
        hit = next((i for i, r in enumerate(rows) if r["episode_reward"] >= limit), None)
        reached = hit is not None
        rows = rows[: hit + 1] if reached else rows
    return rows, reached


def _plot_env(
    out: Path,
    env: str,
    curves: Mapping[str, Sequence[Sequence[Mapping[str, float]]]],
    stats: Mapping[str, Mapping[str, Any]],
    planners: Sequence[str] | None,
    reps: int,
) -> None:
    """rewards_ENV.png and walltime_ENV.png: reward vs env steps and vs wall-clock hours per arm."""
    colors = model_colors(list(curves)) if planners is None else arm_colors(list(curves))
    n_div = {label: stats[label]["n_diverged"] for label in curves}
    plot_online(out / f"rewards_{env_stem(env)}.png", env, curves, colors, diverged=n_div, reps=reps)
    plot_online(
        out / f"walltime_{env_stem(env)}.png", env, curves, colors, x_key="wall_time_s", diverged=n_div, reps=reps
    )


def _header(trials: int, w: int, compared: bool, with_planner: bool, until_threshold: bool) -> list[str]:
    """The top of summary.md: what the columns mean."""
    base_name = BASELINE if not with_planner else f"{BASELINE} with the same planner"
    if until_threshold:
        runs_line = f"# Online comparison (runs to the threshold, at most {trials} trials each)"
        span = "the trials up to the one that reached the threshold (or all, if none did)"
    else:
        runs_line, span = f"# Online comparison ({trials} trials per run)", f"all {trials} trials"
    return [
        runs_line,
        "",
        f"final = mean episode reward of the last {w} trial{'s' if w > 1 else ''} of each run; "
        f"AUC = mean episode reward over {span}. Per arm: the interquartile mean (IQM) over seeds "
        "with its 95 % stratified-bootstrap CI in brackets (rliable)."
        + (
            f" P(final > {BASELINE}'s): the probability that a random seed of the arm ends with a higher final "
            f"reward than a random seed of {base_name} (ties count half), with its CI. final - {BASELINE}: IQM "
            "[CI] of the per-seed difference of the final rewards over the seeds both arms have (same seed: "
            "the same random seed data and env reset seeds). p (sign-flip): the exact paired permutation p-value of "
            f"the mean final - {BASELINE} over the seeds both arms ran, a diverged run entered as the env's lowest "
            "final reward (at 5 pairs it cannot go below 0.0625); p (Holm): Holm's adjustment over every "
            "arm-vs-baseline test of this summary (envs x arms)."
            if compared
            else ""
        )
        + " A run with a non-finite episode reward is diverged: counted, left out of the IQMs, CIs and "
        "differences, and the worst final reward in P. Plan s/step: median seconds per planning step of "
        "a run; wall h: the run's wall-clock hours (planning, simulation, model training); CPU h: its process "
        "CPU hours (what other jobs on the machine do not inflate; - for runs made before the column existed); "
        "each the mean over the complete runs, diverged ones included. To threshold: how many of the runs that "
        "did not diverge reached the env's reward threshold, and over those that did the IQM [CI] of the "
        "wall-clock minutes, env steps and process CPU minutes until the end of the first trial that reached it "
        "(the others counted, not averaged in).",
        "",
    ]


def _runs_sections(diverged_runs: Sequence[str], missing: Sequence[str]) -> list[str]:
    """Markdown of the diverged runs and of the missing or incomplete ones."""
    text = []
    if diverged_runs:
        text += ["## Diverged runs (counted, not in the IQMs)", ""] + [f"- {d}" for d in diverged_runs] + [""]
    if missing:
        text += ["## Missing or incomplete runs (not in the statistics)", ""] + [f"- {m}" for m in missing] + [""]
    return text


def _env_section(
    env: str,
    rows: Sequence[Mapping[str, Any]],
    with_planner: bool,
    compared: bool,
    baselines: Mapping[str, str | None],
) -> list[str]:
    """Markdown of one env: the small-sample note where needed, the table of its arms, its two figures."""
    header = ["model", *(["planner"] if with_planner else []), "seeds", "diverged", "final reward", "AUC"]
    if compared:
        header += [f"P(final > {BASELINE}'s)", f"final - {BASELINE}", "pairs", "p (sign-flip)", "p (Holm)"]
    threshold = rows[0]["threshold"] if rows else None
    if threshold is not None:
        header += [f"reached {threshold:g}", "minutes to it", "env steps to it", "CPU minutes to it"]
        header += [f"P(fewer steps than {BASELINE})"] if compared else []
    header += ["env steps", "plan s/step", "wall h", "CPU h"]
    table = []
    for r in rows:
        none = "all diverged" if r["n_seeds"] == 0 else "n/a"
        cells = [r["model"], *([r["planner"]] if with_planner else []), str(r["n_seeds"]), str(r["n_diverged"])]
        cells += [fmt_interval(r[f"{k}_iqm"], r[f"{k}_ci_low"], r[f"{k}_ci_high"], none) for k in ("final", "auc")]
        if compared:
            if baselines[arm_label(r["model"], r["planner"] or None)] is None:
                cells += ["-"] * 5
            else:
                cells += [
                    fmt_interval(r["p_improvement"], r["p_improvement_ci_low"], r["p_improvement_ci_high"]),
                    fmt_interval(r["diff_to_delta"], r["diff_ci_low"], r["diff_ci_high"]),
                    "-" if r["n_pairs"] is None else str(r["n_pairs"]),
                    *("-" if r[k] is None else fmt(r[k], 3) for k in ("diff_p_signflip", "diff_p_holm")),
                ]
        if threshold is not None:
            cells.append(f"{r['n_reached']}/{r['n_seeds']}")
            for k in THRESHOLD_KEYS:
                cells.append(fmt_interval(r[f"{k}_iqm"], r[f"{k}_ci_low"], r[f"{k}_ci_high"], "-"))
            if compared:
                cells.append(
                    fmt_interval(r["p_fewer_steps"], r["p_fewer_steps_ci_low"], r["p_fewer_steps_ci_high"], "-")
                )
        cells += [
            f"{r['env_steps_mean']:.0f}",
            fmt(r["plan_seconds_per_step_mean"], 3),
            fmt(r["wall_time_s_mean"] / 3600, 3),
            "-" if r["cpu_time_s_mean"] is None else fmt(r["cpu_time_s_mean"] / 3600, 3),
        ]
        table.append(cells)
    small = any(r["n_seeds"] < MIN_SEEDS for r in rows)
    return [
        f"## {env}",
        "",
        *([SMALL_SAMPLE_NOTE, ""] if small else []),
        md_table(header, table),
        "",
        *disagreement_lines(rows),
        f"![rewards](rewards_{env_stem(env)}.png) ![wall-clock](walltime_{env_stem(env)}.png)",
        "",
    ]
