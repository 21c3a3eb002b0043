"""A study as one declaration: what one run records and one table of its metrics, from which one generic
summariser makes the summary columns, the statistics per (env, arm), the markdown table and the headline columns.

A :class:`Metric` is one line of that table: the per-run value it reads, its direction, its statistic over seeds
(IQM with its CI, bootstrapped with the other metrics of its :class:`Group`, or the mean), and against the baseline
arm: P(better than the baseline) (``versus``), the paired difference with its exact sign-flip p and Holm's
adjustment over the summary (``paired``: the primary endpoint), and whether the headline carries it. Column names are
made here from the metric's ``column`` prefix and nowhere typed again.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pets.experiments.report import BOOT_SEED, csv_number, fmt, fmt_interval, md_table
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

HIGHER, LOWER = 1, -1
#: The columns of a study's paired difference (its primary endpoint): ``n_pairs`` and the note are unprefixed.
PAIRED = ("{p}_to_" + BASELINE, "{p}_ci_low", "{p}_ci_high", "n_pairs", "{p}_p_signflip", "{p}_p_holm", "ci_exact_note")
INTERVAL = ("iqm", "ci_low", "ci_high")
#: The columns of a paired ratio to the baseline (IQM [CI] of the per-pair ratios) and of its exact and Holm p.
RATIO = (f"ratio_to_{BASELINE}", "ratio_ci_low", "ratio_ci_high")
P_EXACT, P_HOLM = "p_value_exact", "p_value_holm"


@dataclass(frozen=True)
class Group:
    """Metrics bootstrapped together (one stratified bootstrap over the same runs). ``reached``: the group is over
    the runs where its first metric is finite (counted in ``n_reached``; the env's ``threshold`` column before it),
    and its comparisons with the baseline exist only where the env has a threshold and a run of the arm or of the
    baseline reached it. ``missing``: a table cell
    without a value."""

    name: str
    reached: bool = False
    missing: str = "n/a"


@dataclass(frozen=True)
class Metric:
    """One line of a study's metric table (module docstring). ``name``: the per-run value; ``column``: the prefix of
    its summary columns (``COLUMN_iqm`` ... or ``COLUMN_mean``); ``group``: None for the mean over every complete
    run; ``versus``: the prefix of its P(better than the baseline) columns; ``paired``: the prefix of its paired
    difference (one per study); ``label``, ``scale``, ``digits``: its table cell; ``headline``: its label in the
    headline ("" for none: the IQM [CI], or over the runs that reached a threshold the IQM alone, each beside the
    baseline's), ``headline_versus``: the label of its P there."""

    name: str
    column: str
    direction: int = HIGHER
    group: Group | None = None
    versus: str = ""
    versus_label: str = ""
    paired: str = ""
    label: str = ""
    scale: float = 1.0
    digits: int = 3
    headline: str = ""
    headline_versus: str = ""

    def headline_own(self) -> list[str]:
        """Its columns in the headline (the baseline's beside each)."""
        return self.columns()[:1] if self.group and self.group.reached else self.columns()

    def columns(self) -> list[str]:
        """Its own statistic's summary columns."""
        return [f"{self.column}_{s}" for s in INTERVAL] if self.group else [f"{self.column}_mean"]

    def baseline_columns(self) -> list[str]:
        """Its columns against the baseline (empty for the baseline itself)."""
        cols = [f"{self.versus}{s}" for s in ("", "_ci_low", "_ci_high")] if self.versus else []
        return cols + ([c.format(p=self.paired) for c in PAIRED] if self.paired else [])


@dataclass(frozen=True)
class Study:
    """A study: its ``keys`` (what identifies a summary row), its ``context`` (columns of the run set), what one
    run records and its :class:`Metric` table."""

    name: str
    keys: tuple[str, ...]
    context: tuple[str, ...]
    metrics: tuple[Metric, ...]

    def groups(self) -> list[Group]:
        return list(dict.fromkeys(m.group for m in self.metrics if m.group))

    def run_columns(self) -> list[str]:
        """What one run records: the keys, its seed, the context's trials, whether it diverged, each metric."""
        return [*self.keys, "seed", self.context[0], "diverged", *(m.name for m in self.metrics)]

    def summary_columns(self) -> list[str]:
        """The summary.csv columns: keys, counts, context, each group's metrics, the means, then against the
        baseline."""
        cols = [*self.keys, "n_seeds", "n_diverged", *self.context]
        for g in self.groups():
            cols += ["threshold", "n_reached"] if g.reached else []
            cols += [c for m in self.metrics if m.group == g for c in m.columns()]
        cols += [c for m in self.metrics if not m.group for c in m.columns()]
        return cols + [c for m in self.metrics for c in m.baseline_columns()]

    def primary(self) -> Metric:
        """The metric whose paired difference is the primary endpoint."""
        return next(m for m in self.metrics if m.paired)


def _finite(x: float | None) -> float | None:
    """``x`` as a float, None if absent or not finite (an empty CSV cell, "n/a" in a table)."""
    return None if x is None or not math.isfinite(x) else float(x)


def arm_statistics(
    study: Study,
    runs: Mapping[str, Sequence[Mapping[str, Any]]],
    baselines: Mapping[str, str | None],
    *,
    reps: int = REPS,
    seed: int = BOOT_SEED,
    threshold: bool = False,
) -> dict[str, dict[str, Any]]:
    """{arm: statistics} of one env: ``n_seeds``, ``n_diverged`` and every statistic column (None where absent or
    not finite). ``runs``: {arm: its complete runs, each with ``"seed"``, ``"diverged"`` and the metrics};
    ``baselines``: {arm: the arm it is compared with, or None}; ``threshold``: whether the env has one."""
    good = {arm: {r["seed"]: r for r in rs if not r["diverged"]} for arm, rs in runs.items()}
    columns = study.summary_columns()
    out: dict[str, dict[str, Any]] = {}
    for arm, rs in runs.items():
        s: dict[str, Any] = dict.fromkeys(columns[len(study.keys) + 2 + len(study.context) :])
        s.update(n_seeds=len(good[arm]), n_diverged=len(rs) - len(good[arm]))
        for g in study.groups():
            metrics = [m for m in study.metrics if m.group == g]
            use = list(good[arm].values())
            if g.reached:  # the runs that never reached it are counted (n_reached of n_seeds), not averaged in
                use = [r for r in use if math.isfinite(r[metrics[0].name])]
                s["n_reached"] = len(use)
            if use:
                scores = np.array([[r[m.name] for m in metrics] for r in use])
                ci = iqm_ci_finite if g.reached else iqm_ci  # reached: a column may be NaN (older runs)
                iqm, low, high = ci(scores, reps=reps, seed=seed)
                for j, m in enumerate(metrics):
                    s.update(dict(zip(m.columns(), (iqm[j], low[j], high[j]))))
        for m in study.metrics:  # an ungrouped metric (a cost): the mean over the runs that record it
            if not m.group:
                recorded = [r[m.name] for r in rs if math.isfinite(r[m.name])]
                s[m.columns()[0]] = float(np.mean(recorded)) if recorded else math.nan
        base = baselines.get(arm)
        if base is not None and base in runs:
            for m in study.metrics:
                if m.versus and not (m.group and m.group.reached and not _any_reached(m, runs, arm, base, threshold)):
                    s.update(_versus(m, runs[arm], runs[base], reps=reps, seed=seed))
                if m.paired:
                    s.update(_paired(m, runs, good, arm, base, reps=reps, seed=seed))
        out[arm] = {k: _finite(v) if isinstance(v, float) else v for k, v in s.items()}
    return out


def _any_reached(
    m: Metric, runs: Mapping[str, Sequence[Mapping[str, Any]]], arm: str, base: str, threshold: bool
) -> bool:
    """Whether the env has a threshold and a run of ``arm`` or ``base`` that did not diverge reached it (``m``
    finite): where neither did, P(the arm is better) is not measured (not "0.5, all ties")."""
    return threshold and any(not r["diverged"] and math.isfinite(r[m.name]) for a in (arm, base) for r in runs[a])


def _versus(m: Metric, arm: Sequence[Mapping[str, Any]], base: Sequence[Mapping[str, Any]], **kw: Any) -> dict:
    """P(the arm's ``m`` is better than the baseline's) with its CI; a diverged run (NaN) is the worst value."""
    x = [math.nan if r["diverged"] else r[m.name] for r in arm]
    y = [math.nan if r["diverged"] else r[m.name] for r in base]
    (p,), (low,), (high,) = p_improvement_ci(x, y, higher_is_better=m.direction == HIGHER, **kw)
    return dict(zip(m.baseline_columns()[:3], (p, low, high)))


def _paired(
    m: Metric,
    runs: Mapping[str, Sequence[Mapping[str, Any]]],
    good: Mapping[str, Mapping[Any, Mapping[str, Any]]],
    arm: str,
    base: str,
    **kw: Any,
) -> dict[str, Any]:
    """The paired difference arm - baseline of ``m`` over the seeds both have (IQM [CI]) and its exact sign-flip p,
    a diverged run entering the exact test as the env's worst value of ``m``."""
    diff, low_c, high_c, n_c, p_c, _, note_c = m.baseline_columns()[-len(PAIRED) :]
    s: dict[str, Any] = {}
    pairs, diffs = paired_differences(*({k: r[m.name] for k, r in good[a].items()} for a in (arm, base)))
    s[n_c] = len(pairs)
    if pairs:
        (d,), (low,), (high,) = iqm_ci(diffs, **kw)
        s.update({diff: d, low_c: low, high_c: high})
    values = [r[m.name] for rs_ in good.values() for r in rs_.values()]
    worst = (min if m.direction == HIGHER else max)(values, default=math.nan)
    worst_of = {a: {r["seed"]: worst if r["diverged"] else r[m.name] for r in runs[a]} for a in (arm, base)}
    _, all_diffs = paired_differences(worst_of[arm], worst_of[base])
    if all_diffs.size and np.isfinite(all_diffs).all():
        s[p_c] = sign_flip_p(all_diffs[:, 0])
        s[note_c] = ci_exact_note(s.get(low_c), s.get(high_c), 0.0, s[p_c])
    return s


def holm_over_summary(study: Study, summary: Sequence[dict[str, Any]]) -> None:
    """Set the Holm column: Holm's adjustment over the family of every arm-vs-baseline test of the primary endpoint
    in the summary (envs x arms)."""
    p_col, holm_col = study.primary().baseline_columns()[-3:-1]
    adjusted = holm([math.nan if r.get(p_col) is None else r[p_col] for r in summary])
    for row, p_adj in zip(summary, adjusted):
        row[holm_col] = _finite(p_adj)


def _cell(m: Metric, value: float | None) -> str:
    if value is None:
        return "-"
    return f"{value * m.scale:.0f}" if m.digits == 0 else fmt(value * m.scale, m.digits)


def table_header(study: Study, compared: bool, threshold: float | None) -> list[str]:
    """The metric columns of a study's markdown table (after model, planner, seeds, diverged)."""
    header = []
    for g in study.groups():
        if g.reached and threshold is None:
            continue
        metrics = [m for m in study.metrics if m.group == g]
        header += [f"reached {threshold:g}"] if g.reached else []
        header += [m.label for m in metrics]
        for m in metrics if compared else ():
            header += [m.versus_label] if m.versus else []
            header += [f"{m.column} - {BASELINE}", "pairs", "p (sign-flip)", "p (Holm)"] if m.paired else []
    return header + [m.label for m in study.metrics if not m.group]


def table_cells(study: Study, r: Mapping[str, Any], compared: bool, is_baseline: bool) -> list[str]:
    """The cells of :func:`table_header` for the summary row ``r``."""
    cells = []
    for g in study.groups():
        if g.reached and r.get("threshold") is None:
            continue
        metrics = [m for m in study.metrics if m.group == g]
        none = "all diverged" if r["n_seeds"] == 0 and not g.reached else g.missing
        cells += [f"{r['n_reached']}/{r['n_seeds']}"] if g.reached else []
        cells += [fmt_interval(*(r[c] for c in m.columns()), none) for m in metrics]
        for m in metrics if compared else ():
            cols = m.baseline_columns()
            n = (1 if m.versus else 0) + (4 if m.paired else 0)
            if is_baseline:
                cells += ["-"] * n
                continue
            cells += [fmt_interval(*(r[c] for c in cols[:3]), g.missing)] if m.versus else []
            if m.paired:
                d, low, high, n_pairs, p, p_holm = cols[-7:-1]
                cells += [fmt_interval(r[d], r[low], r[high]), "-" if r[n_pairs] is None else str(r[n_pairs])]
                cells += ["-" if r[k] is None else fmt(r[k], 3) for k in (p, p_holm)]
    return cells + [_cell(m, r[m.columns()[0]]) for m in study.metrics if not m.group]


def env_tables(study: Study, rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """Markdown: one table per env of a study's summary rows (numbers or None; :func:`table_cells`), each row its
    model (and planner, where any row has one), its seeds and the metric cells with the baseline comparisons."""
    tables = []
    for env in dict.fromkeys(r["env"] for r in rows):
        mine = [r for r in rows if r["env"] == env]
        planner = any(r.get("planner") for r in mine)
        header = ["env", "model", *(["planner"] if planner else []), "seeds"]
        header += table_header(study, True, mine[0].get("threshold"))
        body = [[r["env"], r["model"], *([r["planner"] or "-"] if planner else []), str(r["n_seeds"]),
                 *table_cells(study, r, True, r["model"] == BASELINE)] for r in mine]  # fmt: skip
        tables.append(md_table(header, body))
    return tables


def _headline_metrics(study: Study, group: Group) -> list[Metric]:
    return [m for m in study.metrics if m.group == group and m.headline]


def headline_columns(study: Study) -> list[str]:
    """The headline's columns of a study, per non-baseline arm: its metrics flagged ``headline`` with the baseline's
    beside them, and their comparisons with the baseline (``n_pairs`` aside: the headline's pairs are its seeds)."""
    cols = ["env", "model", "n_seeds", study.context[0]]
    for g in study.groups():
        metrics = _headline_metrics(study, g)
        cols += ["threshold", "n_reached", f"{BASELINE}_n_reached"] if g.reached and metrics else []
        for m in metrics:
            own = m.headline_own()
            cols += own + [f"{BASELINE}_{c}" for c in own]
            cols += [c for c in m.baseline_columns() if c != "n_pairs"]
    return cols + ["source"]


def headline_row(study: Study, row: Mapping[str, str], base: Mapping[str, str]) -> dict[str, Any]:
    """The :func:`headline_columns` values (numbers as floats, NaN where empty; counts as written) of a summary.csv
    ``row`` against its baseline's row ``base``; the CI-vs-exact-test note recomputed from the row's CI and p."""

    out: dict[str, Any] = {
        "n_seeds": int(csv_number(row["n_seeds"])),
        study.context[0]: int(csv_number(row[study.context[0]])),
    }
    for g in study.groups():
        metrics = _headline_metrics(study, g)
        if g.reached and metrics:
            out.update(threshold=csv_number(row.get("threshold")), n_reached=row.get("n_reached", ""))
            out[f"{BASELINE}_n_reached"] = base.get("n_reached", "")
        for m in metrics:
            for c in m.headline_own():
                out.update({c: csv_number(row.get(c)), f"{BASELINE}_{c}": csv_number(base.get(c))})
            note = m.baseline_columns()[-1] if m.paired else None  # text: recomputed from the CI and p
            out.update({c: csv_number(row.get(c)) for c in m.baseline_columns() if c not in ("n_pairs", note)})
            if m.paired:
                _, low, high, _, p, _, _ = m.baseline_columns()[-len(PAIRED) :]
                out[note] = ci_exact_note(out[low], out[high], 0.0, out[p])
    return out


def headline_table(
    study: Study, rows: Sequence[Mapping[str, Any]], p_cell: Callable[[Mapping[str, Any], str], str]
) -> tuple[list[str], list[list[str]]]:
    """``(header, body)`` of the headline's table of a study: per :func:`headline_row` row, each headline metric
    beside the baseline's, its P (``p_cell(row, column)``), the paired difference with its exact and Holm p."""
    header = ["env", "model", "seeds", study.context[0]]
    body = [[r["env"], r["model"], str(r["n_seeds"]), str(r[study.context[0]])] for r in rows]

    def number(v: float) -> str:
        return fmt(v) if math.isfinite(v) else "-"

    for g in study.groups():
        metrics = _headline_metrics(study, g)
        if g.reached and metrics:
            header.append(f"reached (model, {BASELINE})")
            for r, cells in zip(rows, body):
                cells.append(f"{r['n_reached']}, {r[f'{BASELINE}_n_reached']}" if r["n_reached"] != "" else "-")
        for m in metrics:
            own = m.headline_own()
            base = [f"{BASELINE}_{c}" for c in own]
            if g.reached:
                header.append(f"{m.headline} (model, {BASELINE})")
            else:
                header += [m.headline, f"{BASELINE}'s {m.headline}"]
            header += [m.headline_versus] if m.versus else []
            header += ["paired diff", "p (exact)", "p (Holm)"] if m.paired else []
            for r, cells in zip(rows, body):
                if g.reached:
                    cells.append(", ".join(number(r[c]) for c in (*own, *base)))
                else:
                    cells += [fmt_interval(*(r[c] for c in own)), fmt_interval(*(r[c] for c in base))]
                cells += [p_cell(r, m.versus)] if m.versus else []
                if m.paired:
                    d, low, high, _, p, p_holm, _ = m.baseline_columns()[-len(PAIRED) :]
                    cells += [fmt_interval(r[d], r[low], r[high])]
                    cells += [fmt(r[k], 3) if math.isfinite(r[k]) else "-" for k in (p, p_holm)]
    return header, body
