"""The offline comparison's pre-registered primary endpoint (docs/experiments.md, "Primary endpoints").

- **No-information level** ``L`` (:func:`no_information_level`): the ``standardized_error`` of a "model" that
  predicts a random training observation in place of every true one, measured on the data with the same
  formula as :func:`pets.learning.evaluation.step_errors` (about sqrt(2) = 1.41 when test and training observations
  share their distribution). A prediction past ``L`` carries no information about the state.
- **Tracking horizons** (:func:`tracking_horizons`): the horizons, from the shortest on, at which the baseline's
  median ``standardized_error`` over its runs is below ``L``; the first horizon at or past it ends them.
  Verdicts are read there; longer horizons describe how models fail (:func:`past_level_rows`).
- **Endpoint per run**: the mean over the tracking horizons of ``min(standardized_error, L)``, a non-finite
  error counting as ``L``. Past ``L`` every prediction is equally useless, so a diverged run scores the worst
  value and is never dropped, and one run's blow-up cannot outweigh the other seeds.
- **Per env and arm** (:func:`primary_rows`): the per-run ratio arm / baseline of the endpoint (paired by data
  set and seed: same data, seed and start points), its IQM with the 95 % stratified-bootstrap CI (with several
  data sets, the two-level bootstrap of :func:`pets.experiments.statistics.two_level_iqm_ci`), the exact paired
  sign-flip p-value of the mean log ratio (``p_value_exact``), Holm's adjustment over every (env, arm) test of the call
  (``p_value_holm``) and rliable's P(arm's endpoint < baseline's).
"""

from __future__ import annotations

import math
from collections.abc import Collection, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pets.experiments.report import read_csv_rows
from pets.experiments.statistics import (
    ALPHA,
    BASELINE,
    REPS,
    ci_exact_note,
    holm,
    iqm_ci,
    p_improvement_ci,
    sign_flip_p,
    two_level_iqm_ci,
)
from pets.experiments.studies.base import P_EXACT, P_HOLM, RATIO

#: The level used where the data sets are not at hand (e.g. summaries of committed runs CSVs): the standardized
#: error of an independent draw from the training distribution, sqrt(2) training standard deviations.
DEFAULT_LEVEL = math.sqrt(2.0)
DEFAULT_SOURCE = "sqrt(2): data not at hand"
#: The metric of the primary endpoint.
METRIC = "standardized_error"
PRIMARY_COLUMNS = [
    "env",
    "model",
    "level",
    "level_source",
    "tracking_horizons",
    "n_data_sets",
    "n_pairs",
    "endpoint_iqm",
    "endpoint_ci_low",
    "endpoint_ci_high",
    *RATIO,
    P_EXACT,
    P_HOLM,
    "p_improvement",
    "p_improvement_ci_low",
    "p_improvement_ci_high",
    "n_past_level",
    "verdict",
    "ci_exact_note",
]
#: The columns of the per-data-set file: the primary file's, without Holm's step and verdict (a secondary,
#: uncorrected comparison), after the data seed (:func:`per_data_set_rows`).
PER_DATA_SET_COLUMNS = ["data_seed", *(c for c in PRIMARY_COLUMNS if c not in ("p_value_holm", "verdict"))]
#: :func:`versus_rows`: one arm against another on the primary endpoint (a secondary comparison).
VERSUS_COLUMNS = [
    "env",
    "model",
    "versus",
    "tracking_horizons",
    "n_pairs",
    "ratio",
    "ratio_ci_low",
    "ratio_ci_high",
    P_EXACT,
    "n_lower",
]
PAST_LEVEL_COLUMNS = ["env", "model", "horizon", "n_runs", "n_past_level", "fraction_past_level", "median_error"]


def no_information_level(train: Mapping[str, np.ndarray], test: Mapping[str, np.ndarray], layout: Any) -> float:
    """``standardized_error`` of predicting, for each real test observation, a random real training observation
    (a fixed seed), standardized by the training data's per-entry std as :mod:`pets.evaluate` does."""
    import torch

    from pets.learning.evaluation import obs_std, step_errors

    def real(arrays: Mapping[str, np.ndarray]) -> np.ndarray:
        obs, lengths = np.asarray(arrays["obs"], dtype=np.float64), np.asarray(arrays["lengths"])
        return obs[np.arange(obs.shape[1])[None, :] <= lengths[:, None]]

    true, pool = real(test), real(train)
    pick = np.random.default_rng(0).integers(0, len(pool), size=len(true))
    errors = step_errors(torch.as_tensor(pool[pick]), torch.as_tensor(true), layout, obs_std(train))
    return float(errors["standardized"].mean())


def env_level(data_dir: Path, env: str) -> tuple[float, str]:
    """``(level, source)`` of an env: :func:`no_information_level` of ``DATA_DIR/ENV-train.npz`` and
    ``ENV-test.npz`` where both exist, else :data:`DEFAULT_LEVEL`."""
    from pets.experiments.offline_data import data_paths

    train, test = data_paths(Path(data_dir), env)
    if not (train.is_file() and test.is_file()):
        return DEFAULT_LEVEL, DEFAULT_SOURCE
    import envs
    from pets.data.datasets import load_dataset

    level = no_information_level(load_dataset(train), load_dataset(test), envs.get(env).layout)
    return level, f"data ({train.name} vs {test.name})"


def median_inf(values: Iterable[float]) -> float:
    """Median with non-finite values counted as +inf (a diverged run is past every level)."""
    x = np.array([v if math.isfinite(v) else math.inf for v in values], dtype=np.float64)
    return float(np.median(x)) if x.size else math.nan


Run = tuple[int, int]  # (data seed, model seed): what runs pair by


def _errors(rows: Iterable[Mapping[str, Any]]) -> dict[str, dict[str, dict[Run, dict[int, float]]]]:
    """{env: {model: {(data seed, seed): {horizon: standardized_error}}}} of per-run rows (``prediction_runs.csv``;
    data seed 0 where the rows have none)."""
    out: dict[str, dict[str, dict[Run, dict[int, float]]]] = {}
    for r in rows:
        value = r.get(METRIC)
        err = math.inf if value in (None, "") else float(value)
        runs = out.setdefault(str(r["env"]), {}).setdefault(str(r["model"]), {})
        run = (int(r.get("data_seed") or 0), int(r["seed"]))
        runs.setdefault(run, {})[int(r["horizon"])] = err if math.isfinite(err) else math.inf
    return out


def tracking_horizons(baseline: Mapping[Any, Mapping[int, float]], level: float) -> list[int]:
    """The horizons, shortest first, before the first one at which the median over the baseline's runs
    ({run: {horizon: standardized_error}}) reaches ``level``; only horizons every run has."""
    common = sorted(set.intersection(*[set(h) for h in baseline.values()])) if baseline else []
    out = []
    for h in common:
        if not median_inf(run[h] for run in baseline.values()) < level:
            break
        out.append(h)
    return out


def endpoint(run: Mapping[int, float], horizons: Sequence[int], level: float) -> float:
    """One run's endpoint: the mean over ``horizons`` of its error clipped at ``level`` (non-finite = level)."""
    return float(np.mean([min(run[h], level) if math.isfinite(run[h]) else level for h in horizons]))


#: The verdicts of a ratio at family-wise :data:`ALPHA`.
WIN, LOSS, NO_DIFFERENCE = "lower error (win)", "higher error (loss)", "no difference shown"


def _verdict(ratio: float, p_holm: float) -> str:
    if not math.isfinite(p_holm) or p_holm >= ALPHA:
        return NO_DIFFERENCE
    return WIN if ratio < 1 else LOSS


def run_iqm_ci(values: Mapping[Run, float], *, reps: int = REPS, seed: int = 0) -> tuple[float, float, float]:
    """The IQM [CI] of per-run values {(data seed, seed): value}: with several data sets the two-level bootstrap
    (:func:`pets.experiments.statistics.two_level_iqm_ci`, data sets outer), else the stratified one."""
    by_data: dict[int, list[float]] = {}
    for (d, _), x in values.items():
        by_data.setdefault(d, []).append(x)
    if len(by_data) > 1:
        return two_level_iqm_ci(by_data, reps=reps, seed=seed)
    return tuple(float(v[0]) for v in iqm_ci(np.array(list(values.values()))[:, None], reps=reps, seed=seed))


def paired_ratio(
    e: Mapping[Run, float], versus: Mapping[Run, float], *, reps: int = REPS, seed: int = 0
) -> tuple[list[Run], np.ndarray, tuple[float, float, float]]:
    """The pairs (data seed, seed) two arms share, their per-pair ratios ``e / versus`` and the IQM [CI] of those
    ratios (:func:`run_iqm_ci`)."""
    pairs = sorted(set(e) & set(versus))
    ratios = np.array([e[r] / versus[r] for r in pairs])
    return pairs, ratios, run_iqm_ci(dict(zip(pairs, ratios)), reps=reps, seed=seed)


def primary_rows(
    rows: Iterable[Mapping[str, Any]],
    levels: Mapping[str, tuple[float, str]] | None = None,
    *,
    reps: int = REPS,
    seed: int = 0,
    baseline: str = BASELINE,
    arms: Collection[str] | None = None,
    family: Collection[tuple[str, str]] = (),
) -> list[dict[str, Any]]:
    """The :data:`PRIMARY_COLUMNS` rows (one per env and arm, the baseline first) from per-run rows with ``env``,
    ``model``, ``seed``, ``horizon`` and ``standardized_error``; ``levels`` {env: (level, where it came from)},
    :data:`DEFAULT_LEVEL` for the envs it lacks. Envs without baseline runs or without a tracking horizon get
    no test (their rows say why in ``verdict``). ``baseline``: the arm whose median sets the tracking horizons and
    that every other arm is paired with; ``arms``: the arms tested (default: every other model of ``rows``).
    ``family``: the registered tests, ``(env, arm)``; one that has no test yet enters Holm's adjustment with p = 1,
    an upper bound on the Holm p of every test present (Holm's adjusted p of a test never grows when another test's
    p falls), so a verdict read before the whole family has run holds at the registered family-wise level."""
    levels = dict(levels or {})
    out: list[dict[str, Any]] = []
    for env, models in _errors(rows).items():
        level, source = levels.get(env, (DEFAULT_LEVEL, DEFAULT_SOURCE))
        base = models.get(baseline, {})
        hs = tracking_horizons(base, level) if base else []
        for model, runs in sorted(models.items(), key=lambda kv: (kv[0] != baseline, kv[0])):
            if arms is not None and model != baseline and model not in arms:
                continue
            row: dict[str, Any] = {"env": env, "model": model, "level": level, "level_source": source}
            row["tracking_horizons"] = " ".join(map(str, hs))
            if not hs:
                why = "no baseline runs" if not base else "the baseline's median is past the level at every horizon"
                out.append({**row, "verdict": f"no test: {why}"})
                continue
            e = {s: endpoint(r, hs, level) for s, r in runs.items() if all(h in r for h in hs)}
            vals = np.array(list(e.values()))[:, None]
            row["endpoint_iqm"], row["endpoint_ci_low"], row["endpoint_ci_high"] = (
                float(v[0]) for v in iqm_ci(vals, reps=reps, seed=seed)
            )
            row["n_past_level"] = sum(any(not r[h] < level for h in hs) for r in runs.values())
            if model != baseline:
                eb = {s: endpoint(r, hs, level) for s, r in base.items() if all(h in r for h in hs)}
                pairs, ratios, ci = paired_ratio(e, eb, reps=reps, seed=seed)
                row["n_pairs"] = len(pairs)
                row["n_data_sets"] = len({d for d, _ in pairs})
                row.update(zip(RATIO, ci))
                row[P_EXACT] = sign_flip_p(np.log(ratios))
                p = p_improvement_ci(vals, np.array(list(eb.values()))[:, None], reps=reps, seed=seed)
                row["p_improvement"], row["p_improvement_ci_low"], row["p_improvement_ci_high"] = (
                    float(v[0]) for v in p
                )
            out.append(row)
    tested = [i for i, r in enumerate(out) if P_EXACT in r]
    missing = set(family) - {(out[i]["env"], out[i]["model"]) for i in tested}
    for i, p in zip(tested, holm([out[i][P_EXACT] for i in tested] + [1.0] * len(missing))):
        r = out[i]
        r[P_HOLM] = p
        r["verdict"] = _verdict(r[RATIO[0]], p)
        r["ci_exact_note"] = ci_exact_note(r[RATIO[1]], r[RATIO[2]], 1.0, r[P_EXACT])
    return out


def per_data_set_rows(
    rows: Iterable[Mapping[str, Any]], levels: Mapping[str, tuple[float, str]]
) -> list[dict[str, Any]]:
    """The primary endpoint (:func:`primary_rows`) of each data set alone: its own
    tracking horizons and pairs, no correction (the 3-data-set study's secondary)."""
    rows = list(rows)
    out = []
    for d in sorted({int(r["data_seed"]) for r in rows}):
        subset = [r for r in rows if int(r["data_seed"]) == d]
        out += [{"data_seed": d, **r} for r in primary_rows(subset, levels)]
    return out


def versus_rows(
    rows: Iterable[Mapping[str, Any]],
    comparisons: Sequence[tuple[str, str]],
    levels: Mapping[str, tuple[float, str]] | None = None,
    *,
    reps: int = REPS,
    seed: int = 0,
) -> list[dict[str, Any]]:
    """Secondary: per env and (model, versus) of ``comparisons`` (e.g. ``("gem-se", "gem")``), the per-run ratio
    model / versus of the primary endpoint, both at the baseline's tracking horizons and clipped at the same level
    (so each is the primary endpoint's own value), paired by (data seed, seed): IQM [CI] (two-level with several
    data sets), the exact sign-flip p of the mean log ratio (no Holm: not a primary test) and how many pairs the
    model is lower in (:data:`VERSUS_COLUMNS`). Envs without both arms or without a tracking horizon are left out."""
    levels = dict(levels or {})
    out = []
    for env, models in _errors(rows).items():
        level = levels.get(env, (DEFAULT_LEVEL, DEFAULT_SOURCE))[0]
        hs = tracking_horizons(models.get(BASELINE, {}), level) if BASELINE in models else []
        for model, versus in comparisons:
            if not hs or model not in models or versus not in models:
                continue
            e, ev = ({r: endpoint(v, hs, level) for r, v in models[m].items() if all(h in v for h in hs)}
                     for m in (model, versus))  # fmt: skip
            pairs, ratios, ci = paired_ratio(e, ev, reps=reps, seed=seed)
            out.append(
                {
                    "env": env,
                    "model": model,
                    "versus": versus,
                    "tracking_horizons": " ".join(map(str, hs)),
                    "n_pairs": len(pairs),
                    **dict(zip(("ratio", "ratio_ci_low", "ratio_ci_high"), ci)),
                    P_EXACT: sign_flip_p(np.log(ratios)),
                    "n_lower": int((ratios < 1).sum()),
                }
            )
    return out


def past_level_rows(rows: Iterable[Mapping[str, Any]], levels: Mapping[str, tuple[float, str]] | None = None):
    """How models fail: per env, model and horizon the runs whose ``standardized_error`` is at or past the
    env's level (non-finite included) and the median error (:data:`PAST_LEVEL_COLUMNS`)."""
    levels = dict(levels or {})
    out = []
    for env, models in _errors(rows).items():
        level = levels.get(env, (DEFAULT_LEVEL, ""))[0]
        for model, runs in models.items():
            for h in sorted({h for r in runs.values() for h in r}):
                errs = [r[h] for r in runs.values() if h in r]
                past = sum(not v < level for v in errs)
                out.append(
                    {
                        "env": env,
                        "model": model,
                        "horizon": h,
                        "n_runs": len(errs),
                        "n_past_level": past,
                        "fraction_past_level": past / len(errs),
                        "median_error": median_inf(errs),
                    }
                )
    return out


def write_primary_files(
    rows: Sequence[Mapping[str, Any]],
    out: str | Path,
    levels: Mapping[str, tuple[float, str]] | None = None,
    comparisons: Sequence[tuple[str, str]] = (),
    past_level: str | Path | None = None,
    versus: str | Path | None = None,
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Write ``OUT.csv`` (:func:`primary_rows`), the past-level file (:func:`past_level_rows`; default
    ``OUT_past_level.csv``) and, with ``comparisons`` (MODEL, OTHER), the versus file (:func:`versus_rows`, at the
    default level as ``docs/scripts/offline_primary.py`` has always computed it; default ``OUT_versus.csv``).
    Returns ``(primary rows, versus rows)``. What ``offline_primary.py`` and ``pets.compare report`` both call."""
    from pets.experiments.report import write_csv

    primary = primary_rows(rows, levels)
    write_csv(Path(f"{out}.csv"), primary, PRIMARY_COLUMNS)
    write_csv(Path(past_level or f"{out}_past_level.csv"), past_level_rows(rows, levels), PAST_LEVEL_COLUMNS)
    versus_out = versus_rows(rows, comparisons) if comparisons else []
    if comparisons:
        write_csv(Path(versus or f"{out}_versus.csv"), versus_out, VERSUS_COLUMNS)
    return primary, versus_out


def _fmt(x: Any, digits: int = 3) -> str:
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.{digits}g}"


def read_primary(path: Path) -> list[dict[str, Any]]:
    """The rows of a ``primary.csv`` (a study's, or ``docs/scripts/offline_primary.py``'s) with numbers as floats
    (empty: None), as :func:`primary_markdown` takes them; ValueError (what is wrong) if it is not one."""
    if not path.is_file():
        raise ValueError(f"{path}: no such file (give a primary.csv of pets.compare offline or offline_primary.py)")
    rows = read_csv_rows(path)  # ValueError for a binary file
    if not rows or not {"env", "model", "level", "tracking_horizons", P_HOLM, "verdict"} <= set(rows[0]):
        raise ValueError(f"{path}: not a primary.csv (env, model, level, tracking_horizons, ..., verdict)")
    text = {"env", "model", "level_source", "tracking_horizons", "verdict", "ci_exact_note"}

    def number(key: str, value: str) -> float | int | None:
        return None if value in ("", None) else int(float(value)) if key.startswith("n_") else float(value)

    return [{k: v if k in text else number(k, v) for k, v in r.items()} for r in rows]


def primary_markdown(rows: Sequence[Mapping[str, Any]], source: str | None = None) -> list[str]:
    """prediction.md's first section: the primary endpoint table of :func:`primary_rows`; ``source`` (the file the
    rows come from) goes into the heading, so that the families of several studies stay apart."""
    if not rows:
        return []
    table = [
        [
            r["env"],
            r["model"],
            f"{r['level']:.3g} ({r['level_source']})",
            r["tracking_horizons"] or "-",
            f"{_fmt(r.get('endpoint_iqm'))} [{_fmt(r.get('endpoint_ci_low'))}, {_fmt(r.get('endpoint_ci_high'))}]",
            "-"
            if r["model"] == BASELINE
            else f"{_fmt(r.get('ratio_to_delta'))} [{_fmt(r.get('ratio_ci_low'))}, {_fmt(r.get('ratio_ci_high'))}]",
            _fmt(r.get(P_EXACT)),
            _fmt(r.get(P_HOLM)),
            str(r.get("n_past_level", "-")),
            r.get("verdict", "-") if r["model"] != BASELINE else "-",
        ]
        for r in rows
    ]
    from pets.experiments.report import disagreement_lines, md_table

    return [
        "## Primary endpoint (pre-registered, docs/experiments.md)" + (f": `{source}`" if source else ""),
        "",
        "Per run: the standardized error averaged over the tracking horizons (those at which the baseline's median "
        "is below the no-information level, the error of predicting a random training observation), each value "
        f"clipped at that level (a diverged run scores the level). Per arm: IQM [95 % CI] over seeds; ratio to "
        f"{BASELINE}: IQM [CI] of the per-seed ratios; p: the exact paired sign-flip p-value of the mean log "
        f"ratio, and Holm's adjustment over every (env, arm) test here; verdict at family-wise {ALPHA:g}. "
        "past level: runs at or past the level at some tracking horizon.",
        "",
        md_table(
            [
                "env",
                "model",
                "level",
                "tracking horizons",
                "endpoint",
                f"ratio to {BASELINE}",
                "p (exact)",
                "p (Holm)",
                "past level",
                "verdict",
            ],
            table,
        ),
        "",
        *disagreement_lines(rows),
    ]
