"""The planning study: planning with the trained models of an offline study, open loop (``--openloop``) or MPC with
the frozen model (``--closedloop``), per env, planner and model, paired to delta.

- Its metric table (:data:`STUDY`): what a run's ``KIND_PLANNER.json`` gives per seed (a value's mean over the run's
  episodes) and, per env, planner and model, its mean over seeds with the 95 % percentile-bootstrap CI
  (:func:`pets.stats.bootstrap.summarise`), and against delta, paired by seed (same data, same episodes' reset
  seeds), the difference model - delta of the total reward: its mean with the bootstrap CI and the exact sign-flip
  p-value (secondary: no multiplicity correction). The summary's columns (:data:`COLUMNS`), its markdown cells and
  the headline's planning columns follow from it.
- The files of a comparison (:func:`summarise_openloop`): ``KIND.csv`` (:data:`COLUMNS`), ``KIND.md`` and
  ``KIND_ENV.png`` (reward vs step per model, a panel per planner), KIND ``openloop`` or ``closedloop``.
- docs/results.md's table (:func:`planning_table`), from the committed per-env summaries.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pets.experiments.plots import model_colors, plot_openloop
from pets.experiments.report import (
    BOOT_SEED,
    csv_number,
    disagreement_lines,
    fmt,
    fmt_ci,
    fmt_interval,
    md_table,
    read_csv_rows,
    write_csv,
)
from pets.experiments.rundirs import env_stem, json_matches, run_name
from pets.experiments.statistics import BASELINE, ci_exact_note, sign_flip_p
from pets.experiments.studies.base import P_EXACT, P_HOLM
from pets.runs.fileio import atomic_write_bytes
from pets.stats.bootstrap import bootstrap_ci, summarise

#: A metric's statistics over seeds (the keys of :func:`pets.stats.bootstrap.summarise`), the IQM only where asked.
MEAN_CI = ("mean", "ci_low", "ci_high")
#: The paired difference model - delta over the seeds both have: its count, mean [CI], exact sign-flip p (secondary:
#: no multiplicity correction) and the note where the bootstrap CI and the exact test disagree.
DIFF, DIFF_LOW, DIFF_HIGH = "diff_to_delta", "diff_ci_low", "diff_ci_high"
N_PAIRS, NOTE = "n_pairs", "ci_exact_note"
PAIRED = (N_PAIRS, DIFF, DIFF_LOW, DIFF_HIGH, P_EXACT, NOTE)


@dataclass(frozen=True)
class RewardMetric:
    """One line of the planning study's metric table: ``name``, the run's value (its ``"mean"`` over the episodes);
    ``column``, the prefix of its summary columns (``COLUMN_mean``, ``COLUMN_ci_low``, ``COLUMN_ci_high``, and
    ``COLUMN_iqm`` with ``iqm``); ``label``, its column in KIND.md; ``paired``: the study's difference to delta is
    of this metric (one per study)."""

    name: str
    column: str
    label: str
    iqm: bool = False
    paired: bool = False

    def statistics(self) -> tuple[str, ...]:
        return (*MEAN_CI, "iqm") if self.iqm else MEAN_CI

    def columns(self) -> list[str]:
        return [f"{self.column}_{s}" for s in self.statistics()]


@dataclass(frozen=True)
class PlanningStudy:
    """The planning study: its row ``keys``, the ``context`` columns after them and its :class:`RewardMetric`
    table."""

    name: str
    keys: tuple[str, ...]
    context: tuple[str, ...]
    metrics: tuple[RewardMetric, ...]

    def columns(self) -> list[str]:
        """KIND.csv: the keys, the context, each metric's statistics, then the paired difference to delta."""
        return [*self.keys, *self.context, *(c for m in self.metrics for c in m.columns()), *PAIRED]

    def paired(self) -> RewardMetric:
        return next(m for m in self.metrics if m.paired)

    def table_header(self) -> list[str]:
        """KIND.md's table header (after the env's section title)."""
        paired = f"{self.paired().column} - {BASELINE} (paired)"
        return ["planner", "model", "seeds", *(m.label for m in self.metrics), paired]


STUDY = PlanningStudy(
    name="planning",
    keys=("env", "planner", "model"),
    context=("n_seeds", "steps"),
    metrics=(
        RewardMetric("mean_reward_per_step", "reward_per_step", "reward per step", iqm=True),
        RewardMetric("total", "total", "total reward", paired=True),
    ),
)
COLUMNS = STUDY.columns()


def _paired(results: Mapping[str, Mapping[int, Mapping[str, Any]]], model: str, metric: RewardMetric) -> dict:
    """Per-seed difference model - delta of the run's mean ``metric``: its mean, CI and exact p (:data:`PAIRED`)."""
    if model == BASELINE or BASELINE not in results:
        return {}
    seeds = sorted(set(results[model]) & set(results[BASELINE]))
    if not seeds:
        return {N_PAIRS: 0}
    value = {m: {s: results[m][s][metric.name]["mean"] for s in seeds} for m in (model, BASELINE)}
    d = np.array([value[model][s] - value[BASELINE][s] for s in seeds])
    if not np.isfinite(d).all():
        return {N_PAIRS: len(seeds)}
    low, high = bootstrap_ci(d, seed=BOOT_SEED)
    p = sign_flip_p(d)
    return dict(zip(PAIRED, (len(seeds), float(d.mean()), low, high, p, ci_exact_note(low, high, 0.0, p))))


def _fmt_diff(row: Mapping[str, Any]) -> str:
    if row.get(DIFF) is None:
        return "-"
    return f"{row[DIFF]:.4g} [{row[DIFF_LOW]:.4g}, {row[DIFF_HIGH]:.4g}], p {row[P_EXACT]:.3g}"


def summary_row(
    results: Mapping[str, Mapping[int, Mapping[str, Any]]],
    keys: tuple[str, str, str],
    steps: int,
    study: PlanningStudy = STUDY,
) -> tuple[dict[str, Any], list[str]]:
    """``(KIND.csv row, KIND.md cells)`` of one env, planner and model (``keys``) from ``results`` ({model: {seed:
    the run's KIND_PLANNER.json}} of the env and planner): each metric's statistics over seeds, the difference to
    delta."""
    runs = results[keys[-1]].values()
    stats = {m: summarise([r[m.name]["mean"] for r in runs], seed=BOOT_SEED) for m in study.metrics}
    n_seeds = stats[study.metrics[0]]["n"]
    row = {**dict(zip(study.keys, keys)), **dict(zip(study.context, (n_seeds, steps)))}
    for m, s in stats.items():
        row.update({c: s[k] for c, k in zip(m.columns(), m.statistics())})
    row.update(_paired(results, keys[-1], study.paired()))
    return row, [*keys[1:], str(n_seeds), *(fmt_ci(s) for s in stats.values()), _fmt_diff(row)]


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


#: The envs of the committed study (their summaries in docs/results: ``openloop_ENV`` and ``planning_ENV``).
ENVS = (
    "invertedpendulum",
    "ant",
    "inverteddoublependulum",
    "reacher",
    "hopper",
    "walker2d",
    "halfcheetah",
    "humanoid",
)
#: Exploratory runs beside the study (not pre-registered): their summaries and what they changed.
EXPLORATORY = {"planning_walker2d_cem_summary.csv": "closed loop with CEM in place of MPPI (exploratory)"}


def _total(r: Mapping[str, str]) -> str:
    return fmt_interval(*(csv_number(r[c]) for c in ("total_mean", "total_ci_low", "total_ci_high")), digits=3)


def _diff(r: Mapping[str, str] | None) -> str:
    """``difference [CI], p P`` (and Holm's p where the row has one), ``-`` for delta or a loop not run."""
    if r is None or r["model"] == BASELINE:
        return "-"
    diff = fmt_interval(*(csv_number(r[c]) for c in (DIFF, DIFF_LOW, DIFF_HIGH)), digits=3)
    text = f"{diff}, p {fmt(csv_number(r[P_EXACT]), 2)}"
    holm = csv_number(r.get(P_HOLM))
    return text + (f", Holm {fmt(holm, 2)}" if math.isfinite(holm) else "")


def planning_table(tree: Path) -> str:
    """Per env and model: closed loop (total reward per episode, its difference to delta) and open loop (total over
    the planned actions, its difference), from the per-env summaries; Holm's p from the headline's rows."""
    results = tree / "docs" / "results"
    holm = {
        (r["env"], r["model"]): r[P_HOLM]
        for r in read_csv_rows(results / "headline" / "headline_planning.csv")
        if r["loop"] == "closed"
    }
    table = []
    for env in ENVS:
        closed = {r["model"]: r for r in read_csv_rows(results / f"planning_{env}_summary.csv")}
        opened = {r["model"]: r for r in read_csv_rows(results / f"openloop_{env}_summary.csv")}
        for model in dict.fromkeys([*closed, *opened]):
            c, o = closed.get(model), opened.get(model)
            c = c and {**c, P_HOLM: holm.get((env, model), "")}
            table.append([env, model, _total(c) if c else "-", _diff(c), _total(o) if o else "-", _diff(o)])
    for name, label in EXPLORATORY.items():
        for r in read_csv_rows(results / name):
            table.append([r["env"], f"{r['model']}: {label}", _total(r), _diff(r), "-", "-"])
    header = ["env", "model", "closed loop: total reward [95 % CI]", "minus delta [95 % CI], exact p",
              "open loop: total reward [95 % CI]", "minus delta [95 % CI], exact p"]  # fmt: skip
    return md_table(header, table)
