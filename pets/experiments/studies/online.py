"""The online study, one unit: its metric table (:data:`STUDY`; what one run records, :data:`RUN_COLUMNS`, and the
summary columns, :data:`SUMMARY_COLUMNS`, follow from it), a run's numbers from its metrics.csv
(:func:`online_run_stats`), the summary of a comparison's run directories (:func:`summarise_online`) and the same
summary from the committed per-run rows (:func:`summary_from_runs`, for ``pets.compare report``).

Per run: ``final`` = mean episode reward of the last W trials (W = ``--final-window``, default 3, at most N); ``auc``
= mean episode reward over all N trials; the run's wall-clock time and median seconds per planning step. A run with a
non-finite episode reward is diverged (:func:`reward_divergence`), and so is a run that stopped because its model
training diverged or no plan had a finite return (:func:`pets.runs.rundir.read_divergence`; a rerun reuses it: the
same seed and config diverge again). Per (env, arm) over the runs that did not diverge
(:mod:`pets.experiments.statistics`, the same statistics as the offline summary): IQM of final and auc with its 95 %
stratified-bootstrap CI; against the baseline arm (:data:`BASELINE` with the same planner) P(final > baseline's) with
its CI (diverged runs: the worst final) and the IQM [CI] of the per-seed difference of final rewards, with the exact
paired sign-flip p-value of its mean (``diff_p_signflip``; a diverged run enters as the env's lowest final reward)
and Holm's adjustment of those p-values over every arm-vs-baseline test of the summary (``diff_p_holm``). Diverged
runs are counted (``n_diverged``), never averaged in; the cost columns are means over all complete runs (a run that
stopped diverged ran only part of its trials: not in them).

Time to threshold (:data:`THRESHOLDS`, per env): the wall-clock minutes (``wall_time_s`` of the first trial whose
episode reward reaches the threshold, i.e. at the end of that trial, its model training included), the env steps and
the process CPU minutes (``cpu_time_s``; empty for runs made before the column) until then. Per arm over the runs
that did not diverge: ``n_reached`` of ``n_seeds`` reached it (counted), and the IQM [CI] of each over the runs that
reached it (never averaged with the ones that did not). Against the baseline, ``p_fewer_steps``: P(the arm needs
fewer env steps to the threshold than the baseline) with its CI, a run that never reached it (or diverged) counting
as the most steps; empty where no run of either reached it (not measured).

Files: ``summary.md``, ``summary.csv`` (per env and arm, :data:`SUMMARY_COLUMNS`; the baseline columns empty for the
baseline itself and where it has no run), ``summary_runs.csv`` (per run, with ``diverged``), ``rewards_ENV.png``
(episode reward vs env steps per arm: every seed's curve interpolated linearly onto a common grid of 200 env-step
values over the range all its seeds cover, then the IQM over seeds with its CI band at each grid point; the raw
curves faintly behind) and ``walltime_ENV.png`` (the same against the run's wall-clock hours: reward per unit of
compute).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pets.experiments.plots import arm_colors, model_colors, plot_online
from pets.experiments.report import csv_number, disagreement_lines, md_table, write_csv
from pets.experiments.rundirs import arm_label, arm_run_dir, env_stem, online_arms, precision_note
from pets.experiments.statistics import BASELINE, MIN_SEEDS, REPS, SMALL_SAMPLE_NOTE
from pets.experiments.studies.base import (
    HIGHER,
    LOWER,
    Group,
    Metric,
    Study,
    arm_statistics,
    env_tables,
    holm_over_summary,
    table_cells,
    table_header,
)
from pets.experiments.studies.online_text import online_provenance, runs_sections, summary_header
from pets.runs.fileio import atomic_write_bytes

#: Reward thresholds of the time-to-threshold columns (``docs/performance.md``): InvertedPendulum's maximum
#: (1000 = balanced for the whole 1000-step episode), Reacher -5 (near the target for most of the episode)
#: and HalfCheetah 1000 at the fast preset (a steady forward gait; PETS' research config reaches ~10x that).
THRESHOLDS: dict[str, float] = {
    "invertedpendulum": 1000.0,
    "inverteddoublependulum": 9000.0,  # issue 16's mark; a full 1000-step episode earns about 9,350
    "reacher": -5.0,
    "halfcheetah": 1000.0,
    # The Ant study's mark (docs/results.md, fixed before its runs): 500 in a 300-step episode, about 1 m/s of
    # forward speed on top of the healthy reward; the true-dynamics planner reaches ~2,300 there.
    "ant": 500.0,
}
#: The time-to-threshold columns of a run (:func:`time_to_threshold`).
THRESHOLD_KEYS = ("minutes_to_threshold", "steps_to_threshold", "cpu_minutes_to_threshold")
#: Cost columns of a run: their mean over the complete runs of an arm (``KEY_mean``).
COST_KEYS = ("env_steps", "wall_time_s", "cpu_time_s", "plan_seconds_per_step")


def online_rows(run_dir: Path) -> list[dict[str, float]]:
    """The metrics rows of a run directory (empty if it has none yet)."""
    from pets.runs import rundir

    path = run_dir / rundir.METRICS_FILE
    return rundir.read_metrics(path) if path.is_file() else []


def reward_divergence(rows: Sequence[Mapping[str, float]]) -> str | None:
    """Why a run counts as diverged (its first non-finite episode reward), or None."""
    for i, r in enumerate(rows):
        v = float(r["episode_reward"])
        if not math.isfinite(v):
            return f"episode_reward {v} at trial {int(r.get('trial', i))}"
    return None


def time_to_threshold(rows: Sequence[Mapping[str, float]], threshold: float | None) -> dict[str, float]:
    """{:data:`THRESHOLD_KEYS`: value} at the end of the first trial whose episode reward is >= ``threshold``:
    ``wall_time_s`` / 60, ``env_steps`` and ``cpu_time_s`` / 60 of that row (NaN for a run without the CPU
    column); NaN for all when no trial reaches it or there is no threshold."""
    if threshold is not None:
        for r in rows:
            if float(r["episode_reward"]) >= threshold:
                cpu = float(r.get("cpu_time_s", math.nan))
                return dict(zip(THRESHOLD_KEYS, (float(r["wall_time_s"]) / 60.0, float(r["env_steps"]), cpu / 60.0)))
    return dict.fromkeys(THRESHOLD_KEYS, math.nan)


def online_run_stats(
    rows: Sequence[Mapping[str, float]],
    trials: int,
    final_window: int,
    threshold: float | None = None,
    cut: bool = False,
) -> dict[str, Any]:
    """Per-run numbers from the first ``trials`` metrics rows: diverged (:func:`reward_divergence`: None or
    why), final (mean of the last ``final_window`` episode rewards), auc (mean episode reward over all
    trials), the :data:`THRESHOLD_KEYS` (:func:`time_to_threshold`), env_steps, wall_time_s (the run's
    wall-clock seconds: planning, simulation and model training), cpu_time_s (its process CPU seconds; NaN for a
    run without the column) and
    plan_seconds_per_step (median over the planned trials; 0 if every trial was random). ``cut``: the last
    episode was cut by the run's env-step budget (:func:`pets.experiments.rundirs.cut_by_budget`), so it is not in final
    or auc. No rows (a run that stopped before its first trial ended): NaN for every number."""
    use = list(rows)[:trials]
    if not use:
        return {"diverged": None, **dict.fromkeys(("final_reward", "auc", *THRESHOLD_KEYS, *COST_KEYS), math.nan)}
    to_threshold = time_to_threshold(use, threshold)
    outcomes = use[:-1] if cut and len(use) > 1 else use
    rewards = np.array([r["episode_reward"] for r in outcomes], dtype=np.float64)
    w = min(final_window, len(outcomes))
    planned = [r["plan_seconds_per_step"] for r in use if r.get("plan_seconds_per_step", 0.0) > 0]
    with np.errstate(invalid="ignore"):  # inf - inf in a diverged run: NaN, reported as such
        final, auc = float(rewards[-w:].mean()), float(rewards.mean())
    return {
        "diverged": reward_divergence(use),
        "final_reward": final,
        "auc": auc,
        **to_threshold,
        "env_steps": float(use[-1]["env_steps"]),
        "wall_time_s": float(use[-1]["wall_time_s"]),
        "cpu_time_s": float(use[-1].get("cpu_time_s", math.nan)),
        "plan_seconds_per_step": float(np.median(planned)) if planned else 0.0,
    }


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
            run = {k: csv_number(r.get(k)) for k in ("final_reward", "auc", *THRESHOLD_KEYS, *COST_KEYS)}
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
    command: str | None = None,
) -> list[dict[str, Any]]:
    """Write summary.md, summary.csv, summary_runs.csv, rewards_ENV.png and walltime_ENV.png (module
    docstring) from the complete runs; returns the summary.csv rows. ``thresholds``: the reward threshold
    per env of the time-to-threshold columns (an env without one gets none). ``until_threshold``: a run that
    reached its env's threshold is complete with fewer rows (``pets.compare online --until-threshold``).
    ``command``: the command line that made the summary, named in summary.md with the seeds and machines."""
    out = Path(out)
    found: dict[str, list] = {"per_run": [], "missing": [], "diverged": [], "included": [], "budgeted": []}
    summary, text = [], []
    envs_done: list[tuple[str, list[dict[str, Any]]]] = []
    arms = online_arms(models, planners)
    labels, baselines = arm_baselines(arms)
    compared = any(b is not None for b in baselines.values())
    w = min(final_window, trials)
    for env in env_names:
        runs, curves = _env_runs(
            out, env, arms, labels, seeds, trials, final_window, failed, thresholds, until_threshold, found
        )
        if not runs:
            continue
        rows_env, stats = env_summary_rows(env, runs, arms, trials, w, thresholds, reps=reps)
        summary += rows_env
        envs_done.append((env, rows_env))
        _plot_env(out, env, curves, stats, planners, reps)
    holm_over_summary(STUDY, summary)
    for env, rows_env in envs_done:
        text += _env_section(env, rows_env, planners is not None, compared, baselines)
    write_csv(out / "summary.csv", summary, SUMMARY_COLUMNS)
    write_csv(out / "summary_runs.csv", found["per_run"], RUN_COLUMNS)
    text = (
        summary_header(trials, w, compared, planners is not None, until_threshold, bool(found["budgeted"]))
        + online_provenance(list(seeds), found["included"], command)
        + text
        + precision_note(found["included"])
    )
    text += runs_sections(found["diverged"], found["missing"])
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
    from pets.experiments.rundirs import budget_of, cut_by_budget
    from pets.runs.rundir import read_divergence, stopped

    runs: dict[str, list[dict[str, Any]]] = {}
    curves: dict[str, list[list[dict[str, float]]]] = {}
    for model, planner in arms:
        label = labels[(model, planner)]
        for seed in seeds:
            run_dir = arm_run_dir(out / "runs", env, model, seed, planner)  # as the sweep found it
            name = run_dir.name
            rows, reached = _complete_rows(run_dir, thresholds.get(env, math.inf), until_threshold)
            budget, length = budget_of(run_dir)
            short = len(rows) < trials and not reached  # a divergence after the trials summarised does not count
            why = read_divergence(run_dir) if short else None
            if short and not stopped(rows, None, budget) and why is None:
                found["missing"].append(
                    f"{name} ({len(rows)}/{trials} trials"
                    f"{'; failed: ' + failed[name] if failed and name in failed else ''})"
                )
                continue
            cut = not reached and cut_by_budget(rows[:trials], budget, length)
            found["budgeted"] += [name] if budget is not None else []
            s = {"seed": seed, **online_run_stats(rows, trials, final_window, thresholds.get(env), cut)}
            if why is not None:  # stopped diverged (training or planning): the worst outcome, never dropped; its
                s |= dict.fromkeys(COST_KEYS, math.nan)  # cost is of the trials it ran: not in the cost means
                s["diverged"] = f"stopped after {len(rows)} of {trials} trials: {why}"
            found["per_run"].append({"env": env, "model": model, "planner": planner or "", "trials": trials, **s})
            found["per_run"][-1]["diverged"] = s["diverged"] or ""
            unknown = (*THRESHOLD_KEYS, *COST_KEYS)  # never reached; a run without the CPU column; stopped diverged
            found["per_run"][-1].update({k: "" for k in unknown if not math.isfinite(s[k])})
            runs.setdefault(label, []).append(s)
            found["included"].append(run_dir)
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


def _env_section(
    env: str,
    rows: Sequence[Mapping[str, Any]],
    with_planner: bool,
    compared: bool,
    baselines: Mapping[str, str | None],
) -> list[str]:
    """Markdown of one env: the small-sample note where needed, the table of its arms (its metric columns from
    the study's metric table), its two figures."""
    threshold = rows[0]["threshold"] if rows else None
    header = ["model", *(["planner"] if with_planner else []), "seeds", "diverged"]
    header += table_header(STUDY, compared, threshold)
    table = []
    for r in rows:
        cells = [r["model"], *([r["planner"]] if with_planner else []), str(r["n_seeds"]), str(r["n_diverged"])]
        is_baseline = baselines[arm_label(r["model"], r["planner"] or None)] is None
        table.append(cells + table_cells(STUDY, r, compared, is_baseline))
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
