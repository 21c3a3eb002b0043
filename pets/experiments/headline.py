"""The headline answer across studies: per env, does a model beat delta, from ``pets.compare`` summary files.

``python -m pets.compare headline --offline A/summary.csv ... --online B/summary.csv ... --out DIR`` reads the
summaries that ``pets.compare offline`` and ``online`` wrote (no statistics are recomputed: every number is the
summary's, from rliable) and writes:

- ``headline_offline.csv``: per env, compared model and metric, at the requested horizon (or the env's longest one below
  it, named in ``horizon``): the paired ratio model / delta with its CI, P(model error < delta's) with its CI,
  the seed pairs and the runs diverged there.
- ``headline_online.csv``: per online env and model: the final reward and the env steps to the threshold against
  delta's, P(final > delta's), the paired difference and P(fewer env steps to the threshold than delta).
- ``headline.md``: the same as tables.
- ``headline_ratio.png``: the paired ratio to delta per horizon and env (one panel per metric), CI bars.
- With ``--relative`` (the studies' relative_error.csv files): the paper's Fig. 2 across the envs, both
  normalisations: ``headline_relative.png`` (divided by the env's worst model) and ``headline_fig2_ratio.png``
  (paired ratio to delta), for the error averaged over each env's tracking horizons (relative_error.csv's
  ``horizons``; mean_step_error, as the paper).
- With ``--openloop`` / ``--closedloop`` (the openloop.csv / closedloop.csv of ``pets.compare offline``):
  ``headline_planning.csv``, planning with a pre-trained model: per env, planner and non-delta model, the total
  reward against delta's and the paired difference with its CI and exact p, as the planning summary computed them;
  for ``--model`` in closed loop (the pre-registered primary of planning) Holm's adjustment over the envs given.
- With ``--primary`` (primary.csv files): the pre-registered offline primary endpoint first, one table per file.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from pets.experiments.plots import plot_headline_ratios
from pets.experiments.report import csv_number, disagreement_lines, fmt, fmt_interval, md_table, write_csv
from pets.experiments.statistics import BASELINE, ci_exact_note, holm
from pets.experiments.studies import planning
from pets.experiments.studies.base import P_HOLM, headline_columns, headline_row, headline_table
from pets.experiments.studies.offline import IQM, N_DIVERGED, N_PAIRS, NOTE, P_EXACT, P_LOWER, RATIO
from pets.experiments.studies.offline import STUDY as OFFLINE_STUDY
from pets.experiments.studies.online import STUDY as ONLINE_STUDY
from pets.experiments.studies.primary import primary_markdown, read_csv_rows, read_primary  # read_csv_rows: report's
from pets.runs.fileio import atomic_write_bytes

#: Offline metrics of the headline, in order (the offline study's metric table flags them): the whole state, then
#: the group coordinates (where GEM composes).
OFFLINE_METRICS = OFFLINE_STUDY.headline_metrics()
OFFLINE_COLUMNS = OFFLINE_STUDY.headline_columns()
#: Online: the columns the online study's metric table flags for the headline (:mod:`pets.experiments.studies`).
ONLINE_COLUMNS = headline_columns(ONLINE_STUDY)


#: Planning with a pre-trained model (``--openloop``, ``--closedloop``): the planning study's paired metric (its
#: mean [CI] beside delta's mean) and its difference to delta, as read from a planning summary.
_PLANNING_OWN = planning.STUDY.paired().columns()[:3]
_PLANNING_READ = planning.PAIRED[:-1]  # the note is recomputed from the CI and p
PLANNING_COLUMNS = ["env", "loop", "planner", "model", "steps", "n_seeds", *_PLANNING_OWN,
                    f"{BASELINE}_{_PLANNING_OWN[0]}", *_PLANNING_READ, P_HOLM, planning.NOTE,
                    "source"]  # fmt: skip
_PLANNING_NEEDED = {*planning.STUDY.keys, "steps", _PLANNING_OWN[0], *_PLANNING_READ}


class HeadlineError(ValueError):
    """A summary file that cannot give the headline (missing, of neither kind, or without delta)."""


def read_summary(path: Path) -> tuple[str, list[dict[str, str]]]:
    """(``"offline"`` or ``"online"``, rows) of a ``pets.compare`` summary.csv."""
    if not path.is_file():
        raise HeadlineError(f"{path}: no such file (give the summary.csv that pets.compare wrote)")
    rows = read_csv_rows(path, HeadlineError)
    columns = set(rows[0]) if rows else set()
    if {*OFFLINE_STUDY.keys, RATIO[0]} <= columns:
        kind = "offline"
    elif {"env", "model", "final_iqm", "p_improvement"} <= columns:
        kind = "online"
    else:
        raise HeadlineError(
            f"{path}: not a pets.compare summary.csv (offline: env, model, horizon, metric, ratio_to_delta; "
            "online: env, model, final_iqm, p_improvement)"
        )
    if not any(r["model"] == BASELINE for r in rows):
        raise HeadlineError(f"{path}: has no {BASELINE} rows, so nothing is compared with {BASELINE}")
    return kind, rows


def offline_rows(
    rows: Sequence[Mapping[str, str]], horizon: int, source: str, tracking: Mapping[str, set[int]] | None = None
) -> list[dict[str, Any]]:
    """Per env, non-delta model and headline metric: the summary's comparison at ``horizon`` (or the longest
    horizon below it that the env has and, where ``tracking`` names the env's tracking horizons, at which delta
    still tracks the state)."""
    out = []
    tracking = tracking or {}
    by_key = {(r["env"], r["model"], int(r["horizon"]), r["metric"]): r for r in rows}
    for env in dict.fromkeys(r["env"] for r in rows):
        horizons = sorted({h for (e, _, h, _) in by_key if e == env and h <= horizon and h in tracking.get(env, [h])})
        if not horizons:
            continue
        h = horizons[-1]
        for model in dict.fromkeys(r["model"] for r in rows if r["env"] == env and r["model"] != BASELINE):
            for metric in OFFLINE_METRICS:
                row, base = by_key.get((env, model, h, metric)), by_key.get((env, BASELINE, h, metric))
                if row is None or base is None or math.isnan(csv_number(row[P_LOWER[0]])):
                    continue
                if csv_number(row[IQM]) == 0 and csv_number(base[IQM]) == 0:  # the env has no such coordinates
                    continue
                p = csv_number(row.get(P_EXACT))  # summaries from before the exact test lack it
                note = ci_exact_note(csv_number(row[RATIO[1]]), csv_number(row[RATIO[2]]), 1.0, p)
                out.append(
                    {
                        "env": env,
                        "model": model,
                        "metric": metric,
                        "horizon": h,
                        **{k: csv_number(row[k]) for k in (*RATIO, *P_LOWER)},
                        P_EXACT: p,
                        NOTE: note,
                        N_PAIRS: int(csv_number(row[N_PAIRS]) if row[N_PAIRS] else 0),
                        N_DIVERGED: int(csv_number(row[N_DIVERGED])),
                        f"{BASELINE}_{N_DIVERGED}": int(csv_number(base[N_DIVERGED])),
                        "source": source,
                    }
                )
    return out


def online_rows(rows: Sequence[Mapping[str, str]], source: str) -> list[dict[str, Any]]:
    """Per env and non-delta arm of an online summary: the metrics its study flags for the headline against delta's
    (delta with the same planner where planners were compared)."""
    out = []
    base = {(r["env"], r.get("planner", "")): r for r in rows if r["model"] == BASELINE}
    for row in rows:
        b = base.get((row["env"], row.get("planner", "")))
        if row["model"] == BASELINE or b is None:
            continue
        model = row["model"] + (f"+{row['planner']}" if row.get("planner") else "")
        out.append({"env": row["env"], "model": model, **headline_row(ONLINE_STUDY, row, b), "source": source})
    return out


def planning_rows(path: Path, loop: str) -> list[dict[str, Any]]:
    """Per env, planner and non-delta model of a planning summary (openloop.csv or closedloop.csv, ``loop``
    ``"open"`` or ``"closed"``): its total reward against delta's with the paired difference."""
    if not path.is_file():
        raise HeadlineError(f"{path}: no such file (give the {loop}loop.csv that pets.compare offline wrote)")
    rows = read_csv_rows(path, HeadlineError)
    if not rows or not _PLANNING_NEEDED <= set(rows[0]):
        raise HeadlineError(f"{path}: not a pets.compare {loop}loop.csv (needs {', '.join(sorted(_PLANNING_NEEDED))})")
    base = {(r["env"], r["planner"]): r for r in rows if r["model"] == BASELINE}
    out = []
    for row in rows:
        b = base.get((row["env"], row["planner"]))
        if row["model"] == BASELINE or b is None:
            continue
        out.append(
            {
                "env": row["env"],
                "loop": loop,
                "planner": row["planner"],
                "model": row["model"],
                "steps": int(csv_number(row["steps"])),
                "n_seeds": int(csv_number(row["n_seeds"])),
                **{k: csv_number(row[k]) for k in _PLANNING_OWN},
                f"{BASELINE}_{_PLANNING_OWN[0]}": csv_number(b[_PLANNING_OWN[0]]),
                **{k: csv_number(row[k]) for k in _PLANNING_READ},
                P_HOLM: math.nan,  # set for the primary family by write_headline
                planning.NOTE: _diff_note(row, csv_number(row[planning.P_EXACT])),
                "source": str(path),
            }
        )
    return out


def _diff_note(row: Mapping[str, str], p: float) -> str:
    """The CI-vs-exact-test note of a summary row's paired difference to delta, with its exact ``p``."""
    return ci_exact_note(csv_number(row[planning.DIFF_LOW]), csv_number(row[planning.DIFF_HIGH]), 0.0, p)


def planning_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """One line per env, loop, planner and model: total rewards and the paired difference to delta."""
    header = ["env", "loop", "planner", "steps", "model", "pairs", "total reward", "delta's", "model - delta"]
    header += ["p", "Holm p"]
    body = [
        [
            r["env"],
            r["loop"],
            r["planner"],
            str(r["steps"]),
            r["model"],
            str(int(r[planning.N_PAIRS])) if math.isfinite(r[planning.N_PAIRS]) else "0",
            fmt_interval(*(r[c] for c in _PLANNING_OWN)),
            fmt(r[f"{BASELINE}_{_PLANNING_OWN[0]}"]),
            fmt_interval(*(r[c] for c in (planning.DIFF, planning.DIFF_LOW, planning.DIFF_HIGH)), missing="-"),
            fmt(r[planning.P_EXACT]) if math.isfinite(r[planning.P_EXACT]) else "-",
            fmt(r[P_HOLM]) if math.isfinite(r[P_HOLM]) else "-",
        ]
        for r in rows
    ]
    return md_table(header, body)


def _p(row: Mapping[str, Any], key: str = "p_improvement") -> str:
    """``P [low, high]``, bold when the CI excludes 0.5; "-" when absent."""
    p, low, high = row[key], row[f"{key}_ci_low"], row[f"{key}_ci_high"]
    if any(math.isnan(v) for v in (p, low, high)):
        return "-"
    text = fmt_interval(p, low, high)
    return f"**{text}**" if low > 0.5 or high < 0.5 else text


def offline_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """One line per env and model: each headline metric's ratio [CI] and P [CI] (bold: P's CI excludes 0.5)."""
    lines = {}
    for r in rows:
        key = (r["env"], r["model"])
        lines.setdefault(key, {"horizon": r["horizon"], "pairs": r["n_pairs"], "div": (0, 0)})
        ratio = fmt_interval(*(r[k] for k in RATIO))
        exact = f", p {fmt(r[P_EXACT], 3)}" if math.isfinite(r[P_EXACT]) else ""
        lines[key][r["metric"]] = f"{ratio}{exact}; P {_p(r)}"
        div = lines[key]["div"]
        lines[key]["div"] = (max(div[0], r["n_diverged"]), max(div[1], r["delta_n_diverged"]))
    header = ["env", "model", "h", "seed pairs", *(f"{m}: ratio to delta, exact p; P(lower)" for m in OFFLINE_METRICS)]
    header.append("diverged (model, delta)")
    body = [
        [
            env,
            model,
            str(v["horizon"]),
            str(v["pairs"]),
            *(v.get(m, "-") for m in OFFLINE_METRICS),
            "{}, {}".format(*v["div"]),
        ]
        for (env, model), v in lines.items()
    ]
    return md_table(header, body)


def online_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """One line per env and arm: the metrics the online study flags for the headline (final reward, P(final >
    delta's), paired difference, steps to threshold), each beside delta's."""
    return md_table(*headline_table(ONLINE_STUDY, rows, _p))


def relative_rows(path: Path, metric: str = "mean_step_error") -> dict[str, dict[str, dict[str, Any]]]:
    """``rows[env][model]`` of a relative_error.csv for ``metric``, as :func:`pets.experiments.plots.plot_relative`
    takes them (missing values None)."""
    if not path.is_file():
        raise HeadlineError(f"{path}: no such file (give the relative_error.csv that pets.compare offline wrote)")
    rows = read_csv_rows(path, HeadlineError)
    if not rows or not {"env", "model", "metric", "relative", RATIO[0]} <= set(rows[0]):
        raise HeadlineError(f"{path}: not a pets.compare relative_error.csv (env, model, metric, relative, ...)")
    out: dict[str, dict[str, dict[str, Any]]] = {}
    for r in rows:
        if r["metric"] != metric:
            continue
        text = ("env", "model", "metric", "ci_exact_note", "horizons")
        values = {k: (None if v in ("", None) else float(v)) for k, v in r.items() if k not in text}
        values["horizons"] = r.get("horizons") or ""  # the tracking horizons it averages (older files: none)
        values.update(n_seeds=int(values["n_seeds"] or 0), n_diverged=int(values["n_diverged"] or 0))
        out.setdefault(r["env"], {})[r["model"]] = values
    return out


def _blank_nan(rows: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Rows with missing values written empty, as the summaries write them."""
    return [{k: "" if isinstance(v, float) and math.isnan(v) else v for k, v in r.items()} for r in rows]


def _check_named(model: str, rows: Sequence[Mapping[str, Any]]) -> None:
    """HeadlineError where ``--model`` is in none of the rows (its plot and planning family would be left out)."""
    named = {r["model"] for r in rows}
    if named and model not in named:
        raise HeadlineError(f"--model {model} is in none of the summaries; they compare {', '.join(sorted(named))}")


def write_headline(
    offline: Sequence[Path],
    online: Sequence[Path],
    out: Path,
    horizon: int = 50,
    model: str = "gem",
    caption: str = "",
    relative: Sequence[Path] = (),
    figures: Path | None = None,
    openloop: Sequence[Path] = (),
    closedloop: Sequence[Path] = (),
    primary: Sequence[Path] = (),
) -> str:
    """Write the CSVs and headline.md to ``out`` and the figures (module docstring) to ``figures`` (default
    ``out``); returns the markdown, whose image links are relative to ``out``."""
    if not offline and not online and not openloop and not closedloop and not primary:
        raise HeadlineError("give at least one summary (--offline, --online, --openloop, --closedloop or --primary)")
    try:
        primary_rows = {path: read_primary(path) for path in primary}
    except ValueError as err:
        raise HeadlineError(str(err)) from None
    plan_rows = [r for loop, paths in (("open", openloop), ("closed", closedloop)) for p in paths
                 for r in planning_rows(p, loop)]  # fmt: skip
    family = [r for r in plan_rows if r["loop"] == "closed" and r["model"] == model]  # planning's primary
    for r, adjusted in zip(family, holm([r[planning.P_EXACT] for r in family])):
        r[P_HOLM] = adjusted
    fig2: dict[str, dict[str, dict[str, Any]]] = {}
    for path in relative:
        fig2.update(relative_rows(path))
    tracking: dict[str, set[int]] = {}  # each env's tracking horizons, where its relative_error.csv names them
    for env, models in fig2.items():
        if named := next(iter(models.values()))["horizons"]:
            tracking[env] = {int(h) for h in named.split()}
    off_rows: list[dict[str, Any]] = []
    on_rows: list[dict[str, Any]] = []
    curves: dict[str, list[dict[str, str]]] = {}
    for path, expected in [(p, "offline") for p in offline] + [(p, "online") for p in online]:
        kind, rows = read_summary(path)
        if kind != expected:
            raise HeadlineError(f"{path}: an {kind} summary given as --{expected}")
        if kind == "offline":
            off_rows += offline_rows(rows, horizon, str(path), tracking)
            curves[str(path)] = rows
        else:
            on_rows += online_rows(rows, str(path))
    _check_named(model, (*off_rows, *on_rows, *plan_rows))
    figures = out if figures is None else figures
    out.mkdir(parents=True, exist_ok=True)
    figures.mkdir(parents=True, exist_ok=True)
    link = Path(os.path.relpath(figures, out))
    write_csv(out / "headline_offline.csv", _blank_nan(off_rows), OFFLINE_COLUMNS)
    write_csv(out / "headline_online.csv", _blank_nan(on_rows), ONLINE_COLUMNS)
    if plan_rows:
        write_csv(out / "headline_planning.csv", _blank_nan(plan_rows), PLANNING_COLUMNS)
    parts = ["# Headline: each model against delta, paired seeds\n"]  # one primary table per file: its own family
    parts += [x for p, r in primary_rows.items() for x in primary_markdown(r, str(p) if len(primary) > 1 else None)]
    within = ", among its tracking horizons: delta still tracks the state there" if tracking else ""
    if off_rows:
        parts += [
            f"## Offline prediction error at horizon {horizon} (or the env's longest below it{within})\n",
            "Ratio: IQM of the per-seed ratio model / delta with its 95 % CI; P(lower): the probability that the "
            "model's error is lower than delta's, with its CI (bold: the CI excludes 0.5). From the summaries:\n",
            offline_table(off_rows),
            "",
            *disagreement_lines(off_rows),
        ]
        if any(r["model"] == model for r in off_rows):
            plot_headline_ratios(figures / "headline_ratio.png", curves, model, OFFLINE_METRICS[:2], caption)
            parts.append(f"![ratio to delta]({(link / 'headline_ratio.png').as_posix()})\n")
    if fig2:
        from pets.experiments.plots import plot_ratio, plot_relative

        plot_relative(figures / "headline_relative.png", fig2)
        plot_ratio(figures / "headline_fig2_ratio.png", fig2)
        rel, ratio = ((link / name).as_posix() for name in ("headline_relative.png", "headline_fig2_ratio.png"))
        parts.append(f"![Fig. 2, relative]({rel}) ![Fig. 2, ratio]({ratio})\n")
    if on_rows:
        parts += [
            "## Online reward (same planner and budget)\n",
            "IQM [95 % CI] over seeds; P: P(the model's final reward > delta's); paired diff: model - delta.\n",
            online_table(on_rows),
            "",
            *disagreement_lines(on_rows),
        ]
    if plan_rows:
        parts += [
            "## Planning with a pre-trained model (the offline runs' frozen models)\n",
            "Total reward per episode: mean [95 % CI] over seeds; model - delta: paired by seed, mean [CI] and the "
            "exact sign-flip p; Holm p: over the envs, for the closed loop of "
            f"{model} (the pre-registered primary; everything else secondary, uncorrected). open: one plan executed "
            "without feedback (the paper's Sec. 5.2); closed: MPC replanning with the frozen model.\n",
            planning_table(plan_rows),
            "",
            *disagreement_lines([{**r, "planner": f"{r['loop']} {r['planner']}"} for r in plan_rows]),
        ]
    sources = sorted({str(p) for p in (*primary, *offline, *online, *relative, *openloop, *closedloop)})
    parts.append("Sources: " + ", ".join(f"`{s}`" for s in sources) + "\n")
    text = "\n".join(parts)
    atomic_write_bytes(out / "headline.md", text.encode())
    return text
