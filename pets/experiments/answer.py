"""The one-screen answer (the ``answer`` block of README.md and docs/results.md): per env, gem against delta in the
three primary comparisons, each cell rendered from a generated or committed file, never typed:

- offline: the pre-registered endpoint's ratio gem / delta (``offline_primary_gem.csv``, Holm over its 8 envs);
- planning with a frozen pre-trained model, closed loop: the total-reward difference (``headline_planning.csv``,
  Holm over the 8 envs);
- online: the final-reward difference of the env's online study, recomputed from its committed per-run rows
  (:func:`pets.experiments.studies.online.summary_from_runs`, Holm over that study's arms); on an env where the
  online locomotion study has every pre-registered pair, its endpoint instead (its generated summary, Holm over
  its (env, arm) tests): that study is the one whose baseline passed the locomotion gate.

Under the table, the line "inputs or composition" on the 3D bodies, from the composition study's primary family
(:func:`pets.experiments.studies.composition.answer_line`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pets.experiments.published import NOT_GENERATED, ONLINE, ORIGINAL, PRODUCTS, RAW, RESULTS
from pets.experiments.report import csv_number, fmt, md_table, read_csv_rows
from pets.experiments.statistics import ALPHA
from pets.experiments.studies.base import P_EXACT, P_HOLM, RATIO

MODEL = "gem"
#: The online study of each env the answer reads (the first of :data:`pets.experiments.published.ONLINE`'s).
ONLINE_STUDIES = ONLINE[:5]


def _p(x: float) -> str:
    return "n/a" if not math.isfinite(x) else fmt(x, 3)


def _cell(value: float, low: float, high: float, n: Any, p: float, holm: float, verdict: str, unit: str) -> str:
    """``value [low, high], N unit, p P, Holm H: verdict`` (3 significant digits)."""
    ci = f"{fmt(value, 3)} [{fmt(low, 3)}, {fmt(high, 3)}]"
    n_text = f"{int(float(n))} {unit}" if n not in (None, "") else "n/a"
    return f"{ci}, {n_text}, p {_p(p)}, Holm {_p(holm)}: {verdict}"


def _difference_verdict(diff: float, holm: float) -> str:
    """Higher reward is better: a win or loss where Holm's p is below :data:`ALPHA`."""
    if not math.isfinite(holm) or holm >= ALPHA:
        return "no difference shown"
    return "**win**" if diff > 0 else "**loss**"


def _primary_cell(r: Mapping[str, str]) -> str:
    """The cell of a ``primary.csv`` row: its ratio to delta, pairs, exact and Holm p and verdict."""
    num = [csv_number(r[k]) for k in RATIO]
    p, holm = csv_number(r[P_EXACT]), csv_number(r[P_HOLM])
    verdict = r["verdict"].replace("(win)", "(**win**)").replace("(loss)", "(**loss**)")
    return _cell(*num, r["n_pairs"], p, holm, verdict, "pairs")


def _offline(tree: Path) -> dict[str, str]:
    rows = read_csv_rows(tree / RESULTS / "offline_primary_gem.csv")
    return {r["env"]: _primary_cell(r) for r in rows if r["model"] == MODEL}


def _planning(tree: Path) -> dict[str, str]:
    cells = {}
    for r in read_csv_rows(tree / RESULTS / "headline" / "headline_planning.csv"):
        if r["loop"] == "closed" and r["model"] == MODEL:
            diff, holm = csv_number(r["diff_to_delta"]), csv_number(r[P_HOLM])
            num = (diff, csv_number(r["diff_ci_low"]), csv_number(r["diff_ci_high"]))
            verdict = _difference_verdict(diff, holm)
            cells[r["env"]] = _cell(*num, r["n_pairs"], csv_number(r[P_EXACT]), holm, verdict, "pairs")
    return cells


def _difference_cell(r: Mapping[str, Any], study: str) -> str:
    """The cell of an online summary row (numbers, or their CSV text): its paired difference to delta."""
    keys = ("diff_to_delta", "diff_ci_low", "diff_ci_high", "diff_p_signflip", "diff_p_holm")
    diff, low, high, p, holm = (r[k] if isinstance(r[k], float | int) else csv_number(r[k]) for k in keys)
    text = _cell(diff, low, high, r["n_pairs"], p, holm, _difference_verdict(diff, holm), "pairs")
    return f"{text} ({study})"


def _online(tree: Path) -> dict[str, str]:
    from pets.experiments.studies.online import summary_from_runs

    cells = {}
    for study in ONLINE_STUDIES:
        for r in summary_from_runs(read_csv_rows(tree / RESULTS / f"{study}_runs.csv")):
            if r["model"] == MODEL and not r["planner"]:
                cells[r["env"]] = _difference_cell(r, study)
    return cells


def _locomotion(tree: Path) -> dict[str, str]:
    """The online locomotion study's cell per env where every arm has every pre-registered pair (its design reads
    nothing from a partial table, and Holm's family is then whole), from its generated summary."""
    from pets.experiments.studies import locomotion

    rows = read_csv_rows(tree / RESULTS / locomotion.SUMMARY)
    pairs = {(r["env"], r["model"]): csv_number(r["n_pairs"]) for r in rows}
    whole = {env for env, _ in pairs if all(pairs.get((env, arm)) == len(locomotion.SEEDS) for arm in locomotion.ARMS)}
    return {
        r["env"]: _difference_cell(r, "online_locomotion") for r in rows if r["model"] == MODEL and r["env"] in whole
    }


def answer_table(tree: Path) -> str:
    """The answer table (module docstring) from the files under ``tree``."""
    offline, planning, locomotion = _offline(tree), _planning(tree), _locomotion(tree)
    online = _online(tree) | locomotion
    header = [
        "env",
        "offline: error gem / delta [95 % CI]",
        "planning, closed loop: total reward gem - delta [95 % CI]",
        "online: final reward gem - delta [95 % CI]",
    ]
    rows = [[env, offline[env], planning.get(env, "not run"), online.get(env, "not run")] for env in offline]
    table = md_table(header, rows) + "\n\n" + LEGEND + (LOCOMOTION_LEGEND if locomotion else "")
    return table + "\n\n" + _inputs_or_composition(tree)


def _inputs_or_composition(tree: Path) -> str:
    """The line "inputs or composition" (issue 53) from the composition study's generated primary family."""
    from pets.experiments.studies import composition

    return composition.answer_line(read_csv_rows(tree / RESULTS / composition.OUTPUTS[1]))


#: What a cell says (the legend under the answer table).
LEGEND = (
    "Each cell: value [95 % CI], pairs (same seed, same data), the exact paired sign-flip p and Holm's adjustment over "
    "the family (offline and planning: the 8 envs; online: the arms of that study), then the verdict at family-wise "
    f"{ALPHA}. Offline: IQM of the per-pair ratios of the pre-registered endpoint (the standardized error averaged "
    "over the tracking horizons; below 1: gem predicts better); planning: mean paired difference of the total reward "
    "of 300 MPC steps with the frozen model; online: IQM of the paired differences of the final reward."
)
#: Added to the legend once a cell is the online locomotion study's.
LOCOMOTION_LEGEND = (
    " The online locomotion study's cells (online_locomotion; docs/studies/online_locomotion.md): the locomotion "
    "preset, whose delta passed the locomotion gate there; IQM of the paired differences of its endpoint, the mean "
    "return of the last 5 episodes at 100k env steps, Holm over that study's (env, arm) tests."
)
#: The later offline studies (new data sets, more seeds) whose primary endpoint the second table shows.
LATER_STUDIES = ("paper_data3_primary", "paper_gemse_primary", "paper_50k_primary")


def later_offline_table(tree: Path) -> str:
    """The primary endpoint of the later offline studies (:data:`LATER_STUDIES`), every arm against delta, Holm
    over each study's own tests."""
    rows = [
        [r["env"], r["model"], study.removesuffix("_primary"), _primary_cell(r)]
        for study in LATER_STUDIES
        for r in read_csv_rows(tree / RESULTS / f"{study}.csv")
        if r["model"] != "delta"
    ]
    return md_table(["env", "arm", "study", "offline: error arm / delta [95 % CI]"], rows)


def coverage_table(tree: Path) -> str:
    """What ``pets.compare report`` makes (each product, its outputs and inputs) and the committed summaries it does
    not make, with why: docs/experiments.md's "What report covers", rendered from the declarations (``tree`` unused:
    the declarations are the source)."""
    made = md_table(
        ["product", "generated (compared by --check)", "from"],
        [[p.name, ", ".join(Path(o).name for o in p.outputs), f"{len(p.inputs)} committed file(s)"] for p in PRODUCTS],
    )
    reasons: dict[str, list[str]] = {}
    for path, why in NOT_GENERATED.items():
        reasons.setdefault(why, []).append(Path(path).name)
    header = ["not generated (excluded from --check)", "why"]
    excluded = md_table(header, [[", ".join(names), why] for why, names in reasons.items()])
    raw = f"Per-seed or per-trial data, the inputs (nothing to regenerate): {len(RAW)} files and folders of {RESULTS}."
    return f"{made}\n\n{excluded}\n\n{raw}"


def _seeds(rows: list[dict[str, str]]) -> str:
    """``arm (N seeds), ...`` of per-run rows, arms in the order the rows give them."""
    seeds: dict[str, set[str]] = {}
    for r in rows:
        seeds.setdefault(r["model"], set()).add(r["seed"])
    return ", ".join(f"{arm} ({len(s)})" for arm, s in seeds.items())


def runs_coverage_table(tree: Path) -> str:
    """What ran, per env: the arms of the paper-protocol study with their seeds, and of each online study of the
    fast preset with their seeds and trials, counted from the committed per-run rows."""
    online: dict[str, list[str]] = {}
    for study in ONLINE_STUDIES:
        rows = read_csv_rows(tree / RESULTS / f"{study}_runs.csv")
        for env in dict.fromkeys(r["env"] for r in rows):
            mine = [r for r in rows if r["env"] == env]
            online.setdefault(env, []).append(f"{_seeds(mine)}; {mine[0]['trials']} trials ({study})")
    table = []
    for study in ORIGINAL:
        rows = read_csv_rows(tree / RESULTS / f"paper_{study}_runs.csv")
        env = rows[0]["env"]
        table.append([env, _seeds(rows), "; ".join(online.get(env, ["not run at the fast preset"]))])
    header = [
        "env",
        "offline, the paper's protocol: arm (seeds)",
        "online, the fast preset: arm (seeds); trials (at most)",
    ]
    return md_table(header, table)
