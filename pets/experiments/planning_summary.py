"""Planning with the trained models of an offline study: open loop (``--openloop``) and MPC with the frozen
model (``--closedloop``), per env, planner and model, with paired statistics against delta.

Per run the mean over its episodes of the total reward (and of the reward per step); then per env, planner and
model the mean over seeds with the 95 % percentile-bootstrap CI (:func:`pets.stats.bootstrap.summarise`)
and, paired by seed (same data, same episodes' reset seeds), the difference model - delta of the total reward:
its mean with the bootstrap CI and the exact sign-flip p-value (secondary: no multiplicity correction).

Files: ``KIND.csv`` (:data:`COLUMNS`), ``KIND.md`` and ``KIND_ENV.png`` (reward vs step per model, a panel per
planner), KIND ``openloop`` or ``closedloop``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pets.experiments.plots import model_colors, plot_openloop
from pets.experiments.report import BOOT_SEED, disagreement_lines, fmt_ci, md_table, write_csv
from pets.experiments.rundirs import env_stem, json_matches, run_name
from pets.experiments.statistics import BASELINE, ci_exact_note, sign_flip_p
from pets.runs.fileio import atomic_write_bytes
from pets.stats.bootstrap import bootstrap_ci, summarise

COLUMNS = [
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
    "n_pairs",
    "diff_to_delta",
    "diff_ci_low",
    "diff_ci_high",
    "p_value_exact",
    "ci_exact_note",
]
_TITLES = {
    "openloop": (
        "Open-loop planning (GEM paper section 5.2)",
        "Each trained model plans {steps} actions once from the initial state of {episodes} episodes (seed "
        "{seed}); the actions run in the real env without feedback (rewards after a real termination count as 0).",
    ),
    "closedloop": (
        "Planning with a pre-trained model, closed loop (MPC with the frozen model)",
        "Each trained model drives MPC (the run's planner, replanning as in training) for up to {steps} steps in "
        "{episodes} episodes (seed {seed}), with no data collected and no training (rewards after a real "
        "termination count as 0).",
    ),
}


def _paired(results: Mapping[str, Mapping[int, Mapping[str, Any]]], model: str) -> dict[str, Any]:
    """Per-seed difference model - delta of the mean total reward, its mean, CI and exact p."""
    if model == BASELINE or BASELINE not in results:
        return {}
    seeds = sorted(set(results[model]) & set(results[BASELINE]))
    if not seeds:
        return {"n_pairs": 0}
    d = np.array([results[model][s]["total"]["mean"] - results[BASELINE][s]["total"]["mean"] for s in seeds])
    if not np.isfinite(d).all():
        return {"n_pairs": len(seeds)}
    low, high = bootstrap_ci(d, seed=BOOT_SEED)
    p = sign_flip_p(d)
    return {"n_pairs": len(seeds), "diff_to_delta": float(d.mean()), "diff_ci_low": low, "diff_ci_high": high,
            "p_value_exact": p, "ci_exact_note": ci_exact_note(low, high, 0.0, p)}  # fmt: skip


def _fmt_diff(row: Mapping[str, Any]) -> str:
    if row.get("diff_to_delta") is None:
        return "-"
    ci = f"[{row['diff_ci_low']:.4g}, {row['diff_ci_high']:.4g}]"
    return f"{row['diff_to_delta']:.4g} {ci}, p {row['p_value_exact']:.3g}"


def summarise_openloop(
    out: Path,
    env_names: Sequence[str],
    models: Sequence[str],
    seeds: Sequence[int],
    planners: Sequence[str],
    request: Mapping[str, Any],
    kind: str = "openloop",
) -> list[dict[str, Any]]:
    """Write KIND.md, KIND.csv and KIND_ENV.png from the runs' ``KIND_PLANNER.json`` files (module docstring)."""
    if kind not in _TITLES:
        raise ValueError(f"kind must be one of {', '.join(_TITLES)}, got {kind!r}")
    out = Path(out)
    title, intro = _TITLES[kind]
    intro = intro.format(**request) + (" Per seed: the mean over episodes; then the mean over seeds with the 95 % "
             "percentile-bootstrap CI; total - delta: paired by seed, mean [CI], exact sign-flip p (no correction for "
             "the many cells).")  # fmt: skip
    if request.get("overrides"):
        intro += (
            " Planner settings over each run's own: "
            + ", ".join(f"{k}={v}" for k, v in request["overrides"].items())
            + "."
        )
    text = [f"# {title}", "", intro, ""]
    rows: list[dict[str, Any]] = []
    colors = model_colors(list(models))
    for env in env_names:
        table, panels = [], {}
        for planner in planners:
            results: dict[str, dict[int, Any]] = {}
            for model in models:
                for seed in seeds:
                    path = out / "runs" / run_name(env, model, seed) / f"{kind}_{planner}.json"
                    if json_matches(path, {**request, "planner": planner}):
                        results.setdefault(model, {})[seed] = json.loads(path.read_text())
            for model, by_seed in results.items():
                per_step = summarise([r["mean_reward_per_step"]["mean"] for r in by_seed.values()], seed=BOOT_SEED)
                total = summarise([r["total"]["mean"] for r in by_seed.values()], seed=BOOT_SEED)
                row = {
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
                    **_paired(results, model),
                }
                rows.append(row)
                table.append([planner, model, str(per_step["n"]), fmt_ci(per_step), fmt_ci(total), _fmt_diff(row)])
                curves = [r["reward_per_step"]["mean"] for r in by_seed.values()]
                panels.setdefault(planner, {})[model] = np.array(curves)
        if not table:
            continue
        headers = ["planner", "model", "seeds", "reward per step", "total reward", f"total - {BASELINE} (paired)"]
        notes = disagreement_lines([r for r in rows if r["env"] == env])
        text += [f"## {env}", "", md_table(headers, table), "", *notes, f"![{kind}]({kind}_{env_stem(env)}.png)", ""]
        plot_openloop(out / f"{kind}_{env_stem(env)}.png", env, panels, colors, kind.replace("loop", "-loop"))
    write_csv(out / f"{kind}.csv", rows, COLUMNS)
    atomic_write_bytes(out / f"{kind}.md", "\n".join(text).encode())
    return rows
