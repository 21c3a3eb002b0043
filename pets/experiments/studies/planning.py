"""The planning study: planning with the trained models of an offline study, open loop (``--openloop``) or MPC with
the frozen model (``--closedloop``). Its metric table (:data:`STUDY`): what a run's ``KIND_PLANNER.json`` gives per
seed (a value's mean over the run's episodes) and, per env, planner and model, its mean over seeds with the 95 %
percentile-bootstrap CI (:func:`pets.stats.bootstrap.summarise`), and against delta the paired difference of one of
them. The summary's columns (:data:`COLUMNS`), its markdown cells and the headline's planning columns follow from it;
:mod:`pets.experiments.planning_summary` writes the files.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from pets.experiments.report import BOOT_SEED, fmt_ci
from pets.experiments.statistics import BASELINE, ci_exact_note, sign_flip_p
from pets.experiments.studies.base import P_EXACT
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
