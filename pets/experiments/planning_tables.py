"""docs/results.md's table of the planning study (planning with frozen pre-trained models, issue 38), rendered from
the committed per-env summaries (``planning_ENV_summary.csv``, ``openloop_ENV_summary.csv``), Holm's step from the
headline's planning rows (``headline/headline_planning.csv``), and the exploratory planner check: per env and model,
the closed loop (the primary, Holm over the envs for gem) and the open loop (secondary), each as the mean total
reward and the paired difference to delta."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

from pets.experiments.published import PLANNING_ENVS, RESULTS
from pets.experiments.report import csv_number, fmt, fmt_interval, md_table, read_csv_rows
from pets.experiments.statistics import BASELINE
from pets.experiments.studies.base import P_EXACT, P_HOLM

#: The difference to delta (mean [95 % CI]) of a planning row.
DIFF = ("diff_to_delta", "diff_ci_low", "diff_ci_high")
#: Exploratory runs beside the study (not pre-registered): their summaries and what they changed.
EXPLORATORY = {"planning_walker2d_cem_summary.csv": "closed loop with CEM in place of MPPI (exploratory)"}


def _total(r: Mapping[str, str]) -> str:
    return fmt_interval(*(csv_number(r[c]) for c in ("total_mean", "total_ci_low", "total_ci_high")), digits=3)


def _diff(r: Mapping[str, str] | None) -> str:
    """``difference [CI], p P`` (and Holm's p where the row has one), ``-`` for delta or a loop not run."""
    if r is None or r["model"] == BASELINE:
        return "-"
    text = f"{fmt_interval(*(csv_number(r[c]) for c in DIFF), digits=3)}, p {fmt(csv_number(r[P_EXACT]), 2)}"
    holm = csv_number(r.get(P_HOLM))
    return text + (f", Holm {fmt(holm, 2)}" if math.isfinite(holm) else "")


def planning_table(tree: Path) -> str:
    """Per env and model: closed loop (total reward per episode, its difference to delta) and open loop (total over
    the planned actions, its difference), from the per-env summaries; Holm's p from the headline's rows."""
    holm = {
        (r["env"], r["model"]): r[P_HOLM]
        for r in read_csv_rows(tree / RESULTS / "headline" / "headline_planning.csv")
        if r["loop"] == "closed"
    }
    table = []
    for env in PLANNING_ENVS:
        closed = {r["model"]: r for r in read_csv_rows(tree / RESULTS / f"planning_{env}_summary.csv")}
        opened = {r["model"]: r for r in read_csv_rows(tree / RESULTS / f"openloop_{env}_summary.csv")}
        for model in dict.fromkeys([*closed, *opened]):
            c, o = closed.get(model), opened.get(model)
            c = c and {**c, P_HOLM: holm.get((env, model), "")}
            table.append([env, model, _total(c) if c else "-", _diff(c), _total(o) if o else "-", _diff(o)])
    for name, label in EXPLORATORY.items():
        for r in read_csv_rows(tree / RESULTS / name):
            table.append([r["env"], f"{r['model']}: {label}", _total(r), _diff(r), "-", "-"])
    header = ["env", "model", "closed loop: total reward [95 % CI]", "minus delta [95 % CI], exact p",
              "open loop: total reward [95 % CI]", "minus delta [95 % CI], exact p"]  # fmt: skip
    return md_table(header, table)
