"""Planning with the trained models of an offline study: open loop (``--openloop``) and MPC with the frozen
model (``--closedloop``), per env, planner and model, with paired statistics against delta.

Per run the mean over its episodes of the total reward (and of the reward per step); then per env, planner and
model the mean over seeds with the 95 % percentile-bootstrap CI (:func:`pets.stats.bootstrap.summarise`)
and, paired by seed (same data, same episodes' reset seeds), the difference model - delta of the total reward:
its mean with the bootstrap CI and the exact sign-flip p-value (secondary: no multiplicity correction).

The study's metric table and statistics: :mod:`pets.experiments.studies.planning`. Files: ``KIND.csv``
(:data:`COLUMNS`), ``KIND.md`` and ``KIND_ENV.png`` (reward vs step per model, a panel per
planner), KIND ``openloop`` or ``closedloop``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pets.experiments.plots import model_colors, plot_openloop
from pets.experiments.report import disagreement_lines, md_table, write_csv
from pets.experiments.rundirs import env_stem, json_matches, run_name
from pets.experiments.studies.planning import COLUMNS, STUDY, summary_row
from pets.runs.fileio import atomic_write_bytes

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
                row, cells = summary_row(results, (env, planner, model), request["steps"])
                rows.append(row)
                table.append(cells)
                curves = [r["reward_per_step"]["mean"] for r in by_seed.values()]
                panels.setdefault(planner, {})[model] = np.array(curves)
        if not table:
            continue
        notes = disagreement_lines([r for r in rows if r["env"] == env])
        table_md = md_table(STUDY.table_header(), table)
        text += [f"## {env}", "", table_md, "", *notes, f"![{kind}]({kind}_{env_stem(env)}.png)", ""]
        plot_openloop(out / f"{kind}_{env_stem(env)}.png", env, panels, colors, kind.replace("loop", "-loop"))
    write_csv(out / f"{kind}.csv", rows, COLUMNS)
    atomic_write_bytes(out / f"{kind}.md", "\n".join(text).encode())
    return rows
