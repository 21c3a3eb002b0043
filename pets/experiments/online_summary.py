"""Online summary: per-run numbers from metrics.csv, statistics over seeds, summary tables and reward plots.

Per run: ``final`` = mean episode reward of the last W trials (W = ``--final-window``, default 3,
at most N); ``auc`` = mean episode reward over all N trials (the area under the reward-per-trial
curve divided by N); the run's wall-clock time and median seconds per planning step. Per (env, model)
over seeds: mean, 95 % percentile-bootstrap CI and IQM (:mod:`pets.experiments.statistics`) of final and
auc, means of the rest. Files: ``summary.md``, ``summary.csv`` (per env and model), ``summary_runs.csv`` (per
run), ``rewards_ENV.png`` (episode reward vs env steps per model: every seed's curve interpolated
linearly onto a common grid of 200 env-step values spanning the range that all seeds of the model
cover, then the mean over seeds with the pointwise bootstrap band; each seed's raw curve faintly
behind it) and ``walltime_ENV.png`` (the same against the run's wall-clock hours: reward per unit
of compute, e.g. for planners or heads of different cost).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pets.experiments.plots import arm_colors, model_colors, plot_online
from pets.experiments.report import BOOT_SEED, fmt, fmt_ci, md_table, write_csv
from pets.experiments.rundirs import arm_label, online_arms, run_name
from pets.experiments.statistics import summarise
from pets.fileio import atomic_write_bytes


def online_rows(run_dir: Path) -> list[dict[str, float]]:
    """The metrics rows of a run directory (empty if it has none yet)."""
    from pets import rundir

    path = run_dir / rundir.METRICS_FILE
    return rundir.read_metrics(path) if path.is_file() else []


def online_run_stats(rows: Sequence[Mapping[str, float]], trials: int, final_window: int) -> dict[str, float]:
    """Per-run numbers from the first ``trials`` metrics rows: final (mean of the last ``final_window``
    episode rewards), auc (mean episode reward over all trials), env_steps, wall_time_s (the run's
    wall-clock seconds: planning, simulation and model training) and plan_seconds_per_step (median over
    the planned trials; 0 if every trial was random)."""
    use = list(rows)[:trials]
    rewards = np.array([r["episode_reward"] for r in use], dtype=np.float64)
    w = min(final_window, len(use))
    planned = [r["plan_seconds_per_step"] for r in use if r.get("plan_seconds_per_step", 0.0) > 0]
    return {
        "final_reward": float(rewards[-w:].mean()),
        "auc": float(rewards.mean()),
        "env_steps": float(use[-1]["env_steps"]),
        "wall_time_s": float(use[-1]["wall_time_s"]),
        "plan_seconds_per_step": float(np.median(planned)) if planned else 0.0,
    }


def summarise_online(
    out: Path,
    env_names: Sequence[str],
    models: Sequence[str],
    seeds: Sequence[int],
    trials: int,
    final_window: int,
    failed: Mapping[str, str] | None = None,
    planners: Sequence[str] | None = None,
) -> list[dict[str, Any]]:
    """Write summary.md, summary.csv, summary_runs.csv, rewards_ENV.png and walltime_ENV.png from the complete runs."""
    out = Path(out)
    per_run, summary, missing = [], [], []
    curves: dict[tuple[str, str], list[list[dict[str, float]]]] = {}
    arms = online_arms(models, planners)
    for env in env_names:
        for model, planner in arms:
            label = arm_label(model, planner)
            finals, aucs, stats = [], [], []
            for seed in seeds:
                name = run_name(env, model, seed, planner)
                rows = online_rows(out / "runs" / name)
                if len(rows) < trials:
                    missing.append(
                        f"{name} ({len(rows)}/{trials} trials"
                        f"{'; failed: ' + failed[name] if failed and name in failed else ''})"
                    )
                    continue
                s = online_run_stats(rows, trials, final_window)
                per_run.append(
                    {"env": env, "model": model, "planner": planner or "", "seed": seed, "trials": trials, **s}
                )
                finals.append(s["final_reward"])
                aucs.append(s["auc"])
                stats.append(s)
                curves.setdefault((env, label), []).append(rows[:trials])
            if not finals:
                continue
            f, a = summarise(finals, seed=BOOT_SEED), summarise(aucs, seed=BOOT_SEED)
            summary.append(
                {
                    "env": env,
                    "model": model,
                    "planner": planner or "",
                    "n_seeds": f["n"],
                    "trials": trials,
                    "final_window": min(final_window, trials),
                    "final_mean": f["mean"],
                    "final_ci_low": f["ci_low"],
                    "final_ci_high": f["ci_high"],
                    "final_iqm": f["iqm"],
                    "auc_mean": a["mean"],
                    "auc_ci_low": a["ci_low"],
                    "auc_ci_high": a["ci_high"],
                    "auc_iqm": a["iqm"],
                    **{
                        f"{k}_mean": float(np.mean([s[k] for s in stats]))
                        for k in ("env_steps", "wall_time_s", "plan_seconds_per_step")
                    },
                }
            )
    write_csv(out / "summary.csv", summary, SUMMARY_COLUMNS)
    write_csv(
        out / "summary_runs.csv",
        per_run,
        [
            "env",
            "model",
            "planner",
            "seed",
            "trials",
            "final_reward",
            "auc",
            "env_steps",
            "wall_time_s",
            "plan_seconds_per_step",
        ],
    )
    w = min(final_window, trials)
    text = [
        f"# Online comparison ({trials} trials per run)",
        "",
        f"final = mean episode reward of the last {w} trial{'s' if w > 1 else ''} of each run; "
        f"AUC = mean episode reward over all {trials} trials. Mean over seeds with the 95 % "
        "percentile-bootstrap CI in brackets; IQM = interquartile mean over seeds. Plan s/step: median "
        "seconds per planning step of a run (mean over seeds); wall h: the run's wall-clock hours "
        "(planning, simulation, model training; mean over seeds).",
        "",
    ]
    arm_header = ["model"] if planners is None else ["model", "planner"]
    for env in env_names:
        rows = [r for r in summary if r["env"] == env]
        if not rows:
            continue
        text += [
            f"## {env}",
            "",
            md_table(
                [
                    *arm_header,
                    "seeds",
                    "final reward",
                    "final IQM",
                    "AUC",
                    "AUC IQM",
                    "env steps",
                    "plan s/step",
                    "wall h",
                ],
                [
                    [
                        *([r["model"]] if planners is None else [r["model"], r["planner"]]),
                        str(r["n_seeds"]),
                        fmt_ci({"mean": r["final_mean"], "ci_low": r["final_ci_low"], "ci_high": r["final_ci_high"]}),
                        fmt(r["final_iqm"]),
                        fmt_ci({"mean": r["auc_mean"], "ci_low": r["auc_ci_low"], "ci_high": r["auc_ci_high"]}),
                        fmt(r["auc_iqm"]),
                        f"{r['env_steps_mean']:.0f}",
                        fmt(r["plan_seconds_per_step_mean"], 3),
                        fmt(r["wall_time_s_mean"] / 3600, 3),
                    ]
                    for r in rows
                ],
            ),
            "",
            f"![rewards](rewards_{env}.png) ![wall-clock](walltime_{env}.png)",
            "",
        ]
        labels = [arm_label(m, p) for m, p in arms]
        runs = {label: curves[(env, label)] for label in labels if (env, label) in curves}
        colors = model_colors(list(runs)) if planners is None else arm_colors(list(runs))
        plot_online(out / f"rewards_{env}.png", env, runs, colors)
        plot_online(out / f"walltime_{env}.png", env, runs, colors, x_key="wall_time_s")
    if missing:
        text += ["## Missing or incomplete runs (not in the statistics)", ""] + [f"- {m}" for m in missing] + [""]
    atomic_write_bytes(out / "summary.md", "\n".join(text).encode())
    return summary


SUMMARY_COLUMNS = [
    "env",
    "model",
    "planner",
    "n_seeds",
    "trials",
    "final_window",
    "final_mean",
    "final_ci_low",
    "final_ci_high",
    "final_iqm",
    "auc_mean",
    "auc_ci_low",
    "auc_ci_high",
    "auc_iqm",
    "env_steps_mean",
    "wall_time_s_mean",
    "plan_seconds_per_step_mean",
]
