"""Offline summary: prediction error and open-loop reward per env, model and seed, with statistics, tables and plots.

Files: ``prediction.md``, ``prediction.csv`` (per env, model and horizon: the mean step-wise error
``mean_step_error`` over seeds with its 95 % bootstrap CI and IQM), ``prediction_runs.csv`` (per
run and horizon), ``relative_error.png`` (the paper's Fig. 2: per env one bar per model, the
step-wise error averaged over the horizons, divided by the largest model's value in that env, so
the worst model is 1; error bars: the CI divided by the same number), ``absolute_error_ENV.png``
(Fig. 3: error vs horizon per model with CI bands; log y axis when the values span a factor 10 or
more). With ``--openloop``: ``openloop.md``, ``openloop.csv`` (per env, planner and model: the mean
reward per step and the total reward of the open-loop plans, mean and CI over seeds) and
``openloop_ENV.png`` (reward vs step per model, one panel per planner).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pets.experiments.plots import model_colors, plot_absolute, plot_openloop, plot_relative
from pets.experiments.report import BOOT_SEED, fmt, fmt_ci, md_table, write_csv
from pets.experiments.rundirs import json_matches, run_name
from pets.experiments.statistics import summarise
from pets.fileio import atomic_write_bytes


def load_evals(
    out: Path, env: str, models: Sequence[str], seeds: Sequence[int], request: Mapping[str, Any]
) -> dict[str, list[dict[str, Any]]]:
    """{model: [eval.json of each seed that has one for this request]}."""
    found: dict[str, list[dict[str, Any]]] = {}
    for model in models:
        for seed in seeds:
            path = out / "runs" / run_name(env, model, seed) / "eval.json"
            req = {**request, "data": f"data/{env}-test.npz"}
            if json_matches(path, req):
                found.setdefault(model, []).append({**json.loads(path.read_text()), "seed": seed})
    return found


def summarise_offline(
    out: Path,
    env_names: Sequence[str],
    models: Sequence[str],
    seeds: Sequence[int],
    request: Mapping[str, Any],
    failed: Mapping[str, str] | None = None,
) -> list[dict[str, Any]]:
    """Write prediction.md, prediction.csv, prediction_runs.csv, relative_error.png, absolute_error_ENV.png."""
    out = Path(out)
    rows, per_run, relative, text = [], [], {}, []
    text += [
        "# Offline comparison: long-horizon prediction error",
        "",
        "Mean step-wise error (pets.evaluate, ensemble-mean rollouts on the test data, the same start "
        "points for every model and seed of an env) per horizon; mean over seeds with the 95 % "
        "percentile-bootstrap CI in brackets.",
        "",
    ]
    for env in env_names:
        evals = load_evals(out, env, models, seeds, request)
        if not evals:
            continue
        common = sorted(set.intersection(*[set(map(int, e["horizons"])) for runs in evals.values() for e in runs]))
        table, curves = [], {}
        for model, runs in evals.items():
            by_h = {h: [float(e["horizons"][str(h)]["mean_step_error"]) for e in runs] for h in common}
            for e in runs:
                for h, m in e["horizons"].items():
                    per_run.append(
                        {"env": env, "model": model, "seed": e["seed"], "horizon": int(h), "starts": e["starts"], **m}
                    )
            stats_h = {}
            for h in common:
                s = summarise(by_h[h], seed=BOOT_SEED)
                finals = [float(e["horizons"][str(h)]["final_step_error"]) for e in runs]
                nonfinite = [float(e["horizons"][str(h)]["nonfinite_fraction"]) for e in runs]
                rows.append(
                    {
                        "env": env,
                        "model": model,
                        "horizon": h,
                        "n_seeds": s["n"],
                        "mean_step_error": s["mean"],
                        "ci_low": s["ci_low"],
                        "ci_high": s["ci_high"],
                        "iqm": s["iqm"],
                        "final_step_error": float(np.mean(finals)),
                        "nonfinite_fraction": float(np.mean(nonfinite)),
                    }
                )
                stats_h[h] = s
            curves[model] = (common, stats_h)
            table.append([model, str(len(runs))] + [fmt_ci(stats_h[h]) for h in common])
            # Fig. 2: per seed the error averaged over the horizons, then the statistics over seeds
            relative.setdefault(env, {})[model] = summarise(
                [float(np.mean([e["horizons"][str(h)]["mean_step_error"] for h in common])) for e in runs],
                seed=BOOT_SEED,
            )
        asked = set(request["horizons"])
        skipped = sorted(asked - set(common))
        note = f"; skipped: {', '.join(map(str, skipped))} (longer than the test episodes)" if skipped else ""
        text += [
            f"## {env} (horizons {', '.join(map(str, common))}{note})",
            "",
            md_table(["model", "seeds"] + [f"h={h}" for h in common], table),
            "",
            f"![absolute error](absolute_error_{env}.png)",
            "",
        ]
        plot_absolute(out / f"absolute_error_{env}.png", env, curves)
    write_csv(
        out / "prediction.csv",
        rows,
        [
            "env",
            "model",
            "horizon",
            "n_seeds",
            "mean_step_error",
            "ci_low",
            "ci_high",
            "iqm",
            "final_step_error",
            "nonfinite_fraction",
        ],
    )
    write_csv(
        out / "prediction_runs.csv",
        per_run,
        [
            "env",
            "model",
            "seed",
            "horizon",
            "starts",
            "mean_step_error",
            "final_step_error",
            "position_error",
            "velocity_error",
            "other_error",
            "nonfinite_fraction",
        ],
    )
    if relative:
        plot_relative(out / "relative_error.png", relative)
        text += [
            "## Relative error (Fig. 2)",
            "",
            "Step-wise error averaged over the horizons, divided by the largest model's mean in the env.",
            "",
            md_table(
                ["env"] + list(models),
                [
                    [env]
                    + [
                        fmt(vals[m]["mean"] / max(v["mean"] for v in vals.values())) if m in vals else "-"
                        for m in models
                    ]
                    for env, vals in relative.items()
                ],
            ),
            "",
            "![relative error](relative_error.png)",
            "",
        ]
    missing = [
        run_name(e, m, s)
        for e in env_names
        for m in models
        for s in seeds
        if not json_matches(out / "runs" / run_name(e, m, s) / "eval.json", {**request, "data": f"data/{e}-test.npz"})
    ]
    if missing:
        text += ["## Missing runs (not in the statistics)", ""]
        text += [f"- {m}{': ' + failed[m] if failed and m in failed else ''}" for m in missing] + [""]
    atomic_write_bytes(out / "prediction.md", "\n".join(text).encode())
    return rows


def summarise_openloop(
    out: Path,
    env_names: Sequence[str],
    models: Sequence[str],
    seeds: Sequence[int],
    planners: Sequence[str],
    request: Mapping[str, Any],
) -> list[dict[str, Any]]:
    """Write openloop.md, openloop.csv and openloop_ENV.png from the runs' openloop_PLANNER.json files."""
    out = Path(out)
    rows, text = (
        [],
        [
            "# Open-loop planning (GEM paper section 5.2)",
            "",
            f"Each trained model plans {request['steps']} actions once from the initial state of "
            f"{request['episodes']} episodes (seed {request['seed']}); the actions run in the real env "
            "without feedback (rewards after a real termination count as 0). Per seed: the mean over "
            "episodes; then mean over seeds with the 95 % percentile-bootstrap CI.",
            "",
        ],
    )
    colors = model_colors(list(models))
    for env in env_names:
        table, panels = [], {}
        for planner in planners:
            for model in models:
                results = []
                for seed in seeds:
                    path = out / "runs" / run_name(env, model, seed) / f"openloop_{planner}.json"
                    if json_matches(path, {**request, "planner": planner}):
                        results.append(json.loads(path.read_text()))
                if not results:
                    continue
                per_step = summarise([r["mean_reward_per_step"]["mean"] for r in results], seed=BOOT_SEED)
                total = summarise([r["total"]["mean"] for r in results], seed=BOOT_SEED)
                rows.append(
                    {
                        "env": env,
                        "planner": planner,
                        "model": model,
                        "n_seeds": per_step["n"],
                        "steps": request["steps"],
                        "reward_per_step_mean": per_step["mean"],
                        "reward_per_step_ci_low": per_step["ci_low"],
                        "reward_per_step_ci_high": per_step["ci_high"],
                        "reward_per_step_iqm": per_step["iqm"],
                        "total_mean": total["mean"],
                        "total_ci_low": total["ci_low"],
                        "total_ci_high": total["ci_high"],
                    }
                )
                table.append([planner, model, str(per_step["n"]), fmt_ci(per_step), fmt_ci(total)])
                panels.setdefault(planner, {})[model] = np.array([r["reward_per_step"]["mean"] for r in results])
        if not table:
            continue
        text += [
            f"## {env}",
            "",
            md_table(["planner", "model", "seeds", "reward per step", "total reward"], table),
            "",
            f"![open loop](openloop_{env}.png)",
            "",
        ]
        plot_openloop(out / f"openloop_{env}.png", env, panels, colors)
    write_csv(
        out / "openloop.csv",
        rows,
        [
            "env",
            "planner",
            "model",
            "n_seeds",
            "steps",
            "reward_per_step_mean",
            "reward_per_step_ci_low",
            "reward_per_step_ci_high",
            "reward_per_step_iqm",
            "total_mean",
            "total_ci_low",
            "total_ci_high",
        ],
    )
    atomic_write_bytes(out / "openloop.md", "\n".join(text).encode())
    return rows
