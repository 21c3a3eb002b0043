"""The composition study (docs/studies/composition.md, issue 53): is GEM's gain on the 3D bodies its inputs or its
composition? Every number is made from the study's committed per-run rows (``composition_runs.csv``: one row per
run and horizon, the run's data set named by its test file) and its data sets' no-information levels
(``composition_levels.csv``).

- :func:`primary_rows` (the pre-registered family): per env, ``gem`` and ``gem-se`` against ``delta-groupfeat`` on
  the offline primary endpoint (:mod:`pets.experiments.studies.primary`, ``delta-groupfeat``'s median setting the
  tracking horizons), paired by (data set, seed), Holm over the registered 4 tests (:data:`FAMILY`; one not yet run
  enters with p = 1, an upper bound: the amendment of 2026-11-30 in docs/studies/composition.md).
- :func:`secondary_rows` (labelled so): the same ratios of ``rotation_error`` at those horizons (a non-finite
  error counts as the largest possible, every angle pi); and the paper's long-horizon claim, ``gem / delta`` of the
  standardized error at h = 50 where ``delta``'s median there is below the level (clipped at it), exact p, no Holm.
- :func:`horizon_rows`: per env, arm, metric and horizon the IQM of the runs with its CI (the figure's points).
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pets.experiments.design import Design, Job
from pets.experiments.publication import FIGURES, RESULTS, Product, Publication, results_path
from pets.experiments.report import fmt, fmt_interval, md_table
from pets.experiments.statistics import sign_flip_p
from pets.experiments.studies import primary as offline_primary
from pets.experiments.studies.base import P_EXACT, P_HOLM, RATIO
from pets.experiments.studies.primary import (
    LOSS,
    WIN,
    Run,
    endpoint,
    median_inf,
    paired_ratio,
    run_iqm_ci,
    tracking_horizons,
)

#: The baseline of the primary family (GEM's inputs, delta's targets) and the arms tested against it.
BASELINE = "delta-groupfeat"
ARMS = ("gem", "gem-se")
#: The registered primary family: each arm against the baseline on each env whose torso is on SO(3).
FAMILY = tuple((env, arm) for env in ("ant", "humanoid") for arm in ARMS)
#: The long-horizon secondary: ``model / versus`` at ``horizon``.
LONG_HORIZON = ("gem", "delta", 50)
METRICS = ("standardized_error", "rotation_error")
#: The registered pairs per comparison (3 data sets x 5 seeds): a row with fewer is a snapshot, with no verdict.
PAIRS = 15
SECONDARY_COLUMNS = ["endpoint", "env", "model", "versus", "horizons", "n_pairs", "n_data_sets", "ratio",
                     "ratio_ci_low", "ratio_ci_high", P_EXACT, "n_lower", "note"]  # fmt: skip
HORIZON_COLUMNS = ["env", "model", "metric", "horizon", "n_runs", "iqm", "ci_low", "ci_high"]
LEVEL_COLUMNS = ["env", "data_seed", "level"]


def data_seed(test_file: str) -> int:
    """The data set of a run from its test file's name (``ant-test.npz``: 0, ``ant-d2-test.npz``: 2)."""
    found = re.search(r"-d(\d+)-test\.npz$", test_file)
    return int(found.group(1)) if found else 0


def with_data_seed(rows: Iterable[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """The runs' rows with ``data_seed`` read from their ``data`` column."""
    return [{**r, "data_seed": data_seed(str(r["data"]))} for r in rows]


def env_levels(level_rows: Iterable[Mapping[str, Any]]) -> dict[str, tuple[float, str]]:
    """{env: (level, source)}: the mean of the no-information levels of the env's data sets."""
    by_env: dict[str, dict[int, float]] = {}
    for r in level_rows:
        by_env.setdefault(str(r["env"]), {})[int(r["data_seed"])] = float(r["level"])
    return {
        env: (float(np.mean(list(v.values()))), f"mean of data sets {', '.join(map(str, sorted(v)))}")
        for env, v in by_env.items()
    }


def primary_rows(rows: Iterable[Mapping[str, Any]], levels: Mapping[str, tuple[float, str]]) -> list[dict[str, Any]]:
    """The pre-registered family (:data:`PRIMARY_COLUMNS`): ``delta-groupfeat``'s row, then gem's and gem-se's."""
    return offline_primary.primary_rows(with_data_seed(rows), levels, baseline=BASELINE, arms=ARMS, family=FAMILY)


def _by_run(rows: Iterable[Mapping[str, Any]], metric: str) -> dict[str, dict[str, dict[Run, dict[int, float]]]]:
    """{env: {model: {(data seed, seed): {horizon: metric}}}}, a missing or non-finite value as inf."""
    out: dict[str, dict[str, dict[Run, dict[int, float]]]] = {}
    for r in with_data_seed(rows):
        value = float(r[metric]) if r.get(metric) not in (None, "") else math.inf
        runs = out.setdefault(str(r["env"]), {}).setdefault(str(r["model"]), {})
        runs.setdefault((r["data_seed"], int(r["seed"])), {})[int(r["horizon"])] = (
            value if math.isfinite(value) else math.inf
        )
    return out


def worst_rotation(env: str) -> float:
    """The largest ``rotation_error`` the env's layout allows: pi for every rotation group's geodesic angle."""
    import envs
    from gem_head.codecs import CODECS

    groups = sum(CODECS[g.kind].is_rotation for g in envs.get(env).layout.groups)
    return math.pi * math.sqrt(groups)


def _ratio_row(endpoint_name: str, env: str, model: str, versus: str, hs: Sequence[int],
               e: Mapping[Run, float], ev: Mapping[Run, float]) -> dict[str, Any]:  # fmt: skip
    pairs, ratios, ci = paired_ratio(e, ev)
    return {
        "endpoint": endpoint_name, "env": env, "model": model, "versus": versus, "horizons": " ".join(map(str, hs)),
        "n_pairs": len(pairs), "n_data_sets": len({d for d, _ in pairs}),
        **dict(zip(("ratio", "ratio_ci_low", "ratio_ci_high"), ci)),
        P_EXACT: sign_flip_p(np.log(ratios)), "n_lower": int((ratios < 1).sum()), "note": "",
    }  # fmt: skip


def secondary_rows(rows: Sequence[Mapping[str, Any]], levels: Mapping[str, tuple[float, str]]) -> list[dict[str, Any]]:
    """The pre-registered secondary endpoints (:data:`SECONDARY_COLUMNS`; no Holm): ``rotation_error`` of each arm
    against ``delta-groupfeat`` at the primary's tracking horizons, then ``gem / delta`` at h = 50."""
    std, rot = _by_run(rows, METRICS[0]), _by_run(rows, METRICS[1])
    out = []
    for env, models in std.items():
        level = levels[env][0]
        hs = tracking_horizons(models.get(BASELINE, {}), level) if BASELINE in models else []
        worst = worst_rotation(env)
        for arm in ARMS:
            if hs and arm in models:
                e, eb = ({run: float(np.mean([min(v[h], worst) for h in hs])) for run, v in rot[env][m].items()
                          if all(h in v for h in hs)} for m in (arm, BASELINE))  # fmt: skip
                out.append(_ratio_row("rotation_error", env, arm, BASELINE, hs, e, eb))
        model, versus, h = LONG_HORIZON
        if model in models and versus in models:
            base = {run: v for run, v in models[versus].items() if h in v}
            median = median_inf(v[h] for v in base.values())  # none: NaN, which does not track either
            if not median < level:
                why = f"{versus} no longer tracks at h = {h} (its median is past the level): the claim cannot be tested"
                out.append({"endpoint": f"standardized_error at h = {h}", "env": env, "model": model, "versus": versus,
                            "horizons": str(h), "note": why})  # fmt: skip
                continue
            e, ev = ({run: endpoint(v, [h], level) for run, v in models[m].items() if h in v} for m in (model, versus))
            out.append(_ratio_row(f"standardized_error at h = {h}", env, model, versus, [h], e, ev))
    return out


def horizon_rows(rows: Sequence[Mapping[str, Any]], levels: Mapping[str, tuple[float, str]]) -> list[dict[str, Any]]:
    """Per env, arm, metric and horizon (:data:`HORIZON_COLUMNS`): the IQM over the runs with its CI (two-level
    over several data sets), a non-finite error counted at its cap (the level; every angle pi)."""
    out = []
    for metric in METRICS:
        for env, models in _by_run(rows, metric).items():
            cap = levels[env][0] if metric == METRICS[0] else worst_rotation(env)
            for model, runs in models.items():
                for h in sorted({h for v in runs.values() for h in v}):
                    values = {run: min(v[h], cap) for run, v in runs.items() if h in v}
                    ci = run_iqm_ci(values)
                    out.append({"env": env, "model": model, "metric": metric, "horizon": h,
                                "n_runs": len(values), **dict(zip(("iqm", "ci_low", "ci_high"), ci))})  # fmt: skip
    return out


def _p(x: float | None) -> str:
    return "" if x is None else fmt(x, 3)


def _pairs(r: Mapping[str, Any]) -> str:
    return f"{r['n_pairs']} ({r['n_data_sets']})" if r.get("n_pairs") is not None else ""


def _primary_line(r: Mapping[str, Any]) -> list[str]:
    ratio = fmt_interval(r.get(RATIO[0]), r.get(RATIO[1]), r.get(RATIO[2]), missing="", digits=3)
    cells = [r["env"], r["model"], _pairs(r), r["tracking_horizons"] or "", ratio]
    n = int(r.get("n_pairs") or 0)
    verdict = r["verdict"] if n >= PAIRS else f"none yet (a snapshot: {n} of {PAIRS} pairs)"
    return cells + [_p(r.get(P_EXACT)), _p(r.get(P_HOLM)), verdict]


def _secondary_line(r: Mapping[str, Any]) -> list[str]:
    ratio = fmt_interval(r.get("ratio"), r.get("ratio_ci_low"), r.get("ratio_ci_high"), missing="", digits=3)
    lower = "" if r.get("n_lower") is None else str(r["n_lower"])
    cells = [r["endpoint"], r["env"], f"{r['model']} / {r['versus']}", _pairs(r), ratio, _p(r.get(P_EXACT))]
    return cells + [lower, r.get("note") or ""]


def markdown(primary: Sequence[Mapping[str, Any]], secondary: Sequence[Mapping[str, Any]]) -> str:
    """The study's generated block: the primary family, then the secondary endpoints."""
    head = ["env", "arm", "pairs (data sets)", "tracking horizons", "ratio [CI]", "exact p", "Holm p", "verdict"]
    second = ["endpoint", "env", "model / versus", "pairs (data sets)", "ratio [CI]", "exact p", "lower in", "note"]
    lines = [
        "Primary (a family of 4 tests registered, Holm over the 4: a test not yet run enters with p = 1): "
        "arm / delta-groupfeat of the "
        "standardized error averaged over delta-groupfeat's tracking horizons, IQM [95 % CI] of the per-pair ratios.",
        "",
        md_table(head, [_primary_line(r) for r in primary if r["model"] != BASELINE]),
        "",
        "Secondary (pre-registered, no Holm): rotation_error at the same horizons; the paper's long-horizon claim.",
        "",
        md_table(second, [_secondary_line(r) for r in secondary]),
    ]
    return "\n".join(lines) + "\n"


def plot(horizons: Sequence[Mapping[str, Any]], path: Path) -> None:
    """The four arms' error per horizon (one column per env; standardized error, rotation error), CI bands."""
    from pets.experiments.plots import figure_bytes, model_colors, pyplot
    from pets.runs.fileio import atomic_write_bytes

    envs = list(dict.fromkeys(r["env"] for r in horizons))
    models = (BASELINE, *ARMS, LONG_HORIZON[1])
    colors = model_colors(models)
    fig, axes = pyplot().subplots(2, len(envs), figsize=(5 * len(envs), 7), squeeze=False)
    for col, env in enumerate(envs):
        for row, metric in enumerate(METRICS):
            ax = axes[row][col]
            for model in models:
                pts = [r for r in horizons if r["env"] == env and r["metric"] == metric and r["model"] == model]
                if pts:
                    h, c = [r["horizon"] for r in pts], colors[model]
                    ax.plot(h, [r["iqm"] for r in pts], marker="o", color=c, label=f"{model} ({pts[0]['n_runs']} runs)")
                    ax.fill_between(h, [r["ci_low"] for r in pts], [r["ci_high"] for r in pts], color=c, alpha=0.2)
            ax.set(xscale="log", xlabel="horizon (steps)", ylabel=f"{metric.replace('_', ' ')} (IQM, 95 % CI)")
            ax.set_title(env)
            ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, figure_bytes(fig))


#: The envs of the design (the torso on SO(3)).
ENVS = ("ant", "humanoid")


def answer_line(primary: Sequence[Mapping[str, str]]) -> str:
    """The answer table's line "inputs or composition" from the generated primary family (CSV rows), per env of the
    design, by the rule of docs/studies/composition.md (amendment of 2026-11-30): *composition adds beyond the
    inputs* where ``gem`` or ``gem-se`` has a lower error than ``delta-groupfeat`` at family-wise 0.05; *composition
    costs* where neither does and one has a higher error; *no difference shown* where neither differs; *not yet*
    before both arms have their :data:`PAIRS` pairs. Each names both arms' ratio [CI] and Holm p."""
    rows = {(r["env"], r["model"]): r for r in primary}
    parts = []
    for env in ENVS:
        arms = {arm: rows.get((env, arm), {}) for arm in ARMS}
        pairs = {arm: int(float(r.get("n_pairs") or 0)) for arm, r in arms.items()}
        if min(pairs.values()) < PAIRS:
            counts = ", ".join(f"{arm} {n}" for arm, n in pairs.items())
            parts.append(f"{env}: not yet (pairs of {PAIRS}: {counts})")
            continue
        verdicts = [r["verdict"] for r in arms.values()]
        word = ("composition adds beyond the inputs" if WIN in verdicts else "composition costs" if LOSS in verdicts
                else "no difference shown")  # fmt: skip
        detail = "; ".join(
            f"{arm} / {BASELINE} {fmt_interval(*(float(r[k]) for k in RATIO), digits=3)}, "
            f"Holm p {fmt(float(r[P_HOLM]), 3)}"
            for arm, r in arms.items()
        )
        parts.append(f"{env}: **{word}** ({detail})")
    return (
        f"**Inputs or composition** (the composition study, docs/studies/composition.md: `gem` and `gem-se` against "
        f"`{BASELINE}`, GEM's inputs with delta's targets, offline, {PAIRS} pairs over 3 data sets): "
        + "; ".join(parts) + "."
    )  # fmt: skip


#: The study's committed inputs and generated outputs (``pets.compare report``), relative to the results folder.
RUNS, LEVELS = "composition_runs.csv", "composition_levels.csv"
OUTPUTS = tuple(f"composition_{name}.csv" for name in ("summary", "primary", "secondary", "horizons"))
FIGURE = "composition.png"


def write_products(results: Path, figures: Path) -> None:
    """Every generated file of the study from its committed runs and levels: the offline summary (each arm
    against ``delta``, :func:`pets.experiments.studies.offline.summary_from_runs`), the primary family, the
    secondary endpoints, the per-horizon points and their figure."""
    from pets.experiments.report import read_csv_rows, write_csv
    from pets.experiments.studies.offline import SUMMARY_COLUMNS, summary_from_runs

    rows = read_csv_rows(results / RUNS)
    levels = env_levels(read_csv_rows(results / LEVELS))
    missing = sorted({r["env"] for r in rows} - set(levels))
    if missing:
        raise ValueError(f"{results / LEVELS}: no level for {', '.join(missing)} (partial_offline_runs.py --levels)")
    summary = []
    for env in dict.fromkeys(r["env"] for r in rows):
        summary += summary_from_runs(with_data_seed(r for r in rows if r["env"] == env), levels[env][0])[0]
    horizons = horizon_rows(rows, levels)
    tables = (
        (summary, SUMMARY_COLUMNS),
        (primary_rows(rows, levels), offline_primary.PRIMARY_COLUMNS),
        (secondary_rows(rows, levels), SECONDARY_COLUMNS),
        (horizons, HORIZON_COLUMNS),
    )
    for name, (table, columns) in zip(OUTPUTS, tables, strict=True):
        write_csv(results / name, table, columns)
    plot(horizons, figures / FIGURE)


#: The registered data sets (SAC data seeds) of each env, and the models each sweep trains: every arm of the study.
DATA_SETS, SEEDS, MODELS = (0, 1, 2), tuple(range(5)), (BASELINE, *ARMS, LONG_HORIZON[1])


def _sweep(env: str, data_set: int, seed: int) -> Job:
    """The sweep of one model seed on one data set, every arm."""
    data = ("--seeds", str(seed), "--data-seeds", str(data_set), "--policy", "sac", "--protocol", "paper")
    args = ("offline", "--envs", env, "--models", ",".join(MODELS), *data, "--workers", "1", "--threads", "1")
    return Job(f"{env}-d{data_set}-s{seed}", seed, "composition", "compare", (*args, "--out", "{out}/results"))


def design_jobs(tree: Path) -> list[Job]:
    """The study's sweeps, data set by data set (Ant's, then Humanoid's), one per model seed with every arm."""
    return [_sweep(env, d, seed) for env in ENVS for d in DATA_SETS for seed in SEEDS]


def design_done(tree: Path) -> set[str]:
    """The sweeps of every data set whose (model, seed) runs are all in the committed rows: a data set and its runs
    are made on one machine (docs/studies/composition.md, amendment of 2026-11-28), so a data set's finished sweeps
    count only with the rest of it (on the same machine the sweep reuses its finished runs)."""
    from pets.experiments.offline_data import data_paths
    from pets.experiments.report import read_csv_rows

    runs = {(r["env"], r["model"], r["data"], int(r["seed"])) for r in read_csv_rows(tree / RESULTS / RUNS)}
    return {
        _sweep(env, d, seed).name
        for env in ENVS
        for d in DATA_SETS
        if all((env, m, data_paths(Path(), env, d)[1].name, s) in runs for m in MODELS for s in SEEDS)
        for seed in SEEDS
    }


#: The study's registered sweeps (:mod:`pets.experiments.design`), made from its pinned commit.
DESIGN = Design(
    "composition", 53, "975e50e", design_jobs, design_done,
    rule="a data set's five sweeps count only together: a data set and its 20 runs are made on one machine",
)  # fmt: skip


def study_table(tree: Path) -> str:
    """The generated block of docs/studies/composition.md, from the generated primary and secondary files."""
    from pets.experiments.report import read_csv_rows

    def value(text: str) -> Any:
        try:
            return None if text == "" else float(text)
        except ValueError:
            return text

    def numbers(path: Path) -> list[dict[str, Any]]:
        return [{k: v if "horizons" in k else value(v) for k, v in r.items()} for r in read_csv_rows(path)]

    results = tree / RESULTS
    primary, secondary = (numbers(results / name) for name in OUTPUTS[1:3])
    for r in (*primary, *secondary):
        for k in ("n_pairs", "n_data_sets", "n_lower"):
            if r.get(k) is not None:
                r[k] = int(r[k])
    return markdown(primary, secondary)


#: What the study publishes (:mod:`pets.experiments.publication`): its summary, primary family, secondary endpoints
#: and figure from its committed runs and data sets' levels, and the block of its page.
PUBLICATION = Publication(
    "composition",
    raw=(results_path(RUNS), results_path(LEVELS)),
    products=(
        Product(
            "composition study",
            (*(results_path(n) for n in OUTPUTS), f"{FIGURES}/{FIGURE}"),
            (results_path(RUNS), results_path(LEVELS)),
            lambda: write_products(Path(RESULTS), Path(FIGURES)),
        ),
    ),
    blocks={"composition": study_table, "composition-progress": DESIGN.progress},
    pages=("docs/studies/composition.md",),
)
