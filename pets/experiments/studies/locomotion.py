"""The online locomotion study (docs/studies/online_locomotion.md): each arm against ``delta`` at the locomotion
preset, paired by seed, on the envs where the locomotion gate passed. Its metric table (:data:`STUDY`), one row per
run directory (:func:`run_row`), the summary from the committed rows (:func:`summary_from_runs`), the secondary
comparisons between two GEM arms (:func:`versus_rows`) and the generated markdown.

    python -m pets.experiments.studies.locomotion RUN_DIR [RUN_DIR ...] --out docs/results/online_locomotion_runs.csv \
        --curves docs/results/online_locomotion_curves.csv

Per run (pre-registered): ``endpoint``, the gate's endpoint at the budget (the mean return of the last 5 complete
episodes); secondary: ``auc``, the mean of that moving window at every 1,000 env steps from 10k to the budget (the
area under the reward curve over its span); ``steps_to_threshold``, the first env step at which the window reaches
the gate's threshold (NaN if never). A run short of the budget is ``partial`` (still running; left out of the
summary); a run the study gave up on (``--crashed RUN``) is recorded with an endpoint and AUC of 0 and counts as
the worst outcome: the lower of 0 and the lowest value of any other run on its env (:func:`_runs`).
``--identical``: on a planar env ``delta-groupfeat`` is ``gem`` bit for bit, so a seed of it that was not run takes
``gem``'s row, marked so (:func:`identical_rows`).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pets.experiments import curves, gate, gate_published, publication
from pets.experiments.design import Design, Job
from pets.experiments.publication import Product, Publication, results_path
from pets.experiments.report import (
    cell_text,
    csv_number,
    fmt,
    fmt_interval,
    md_table,
    merge_committed,
    write_rounded_csv,
)
from pets.experiments.statistics import ALPHA, BASELINE, REPS, iqm_ci, paired_differences, sign_flip_p
from pets.experiments.studies.base import (
    HIGHER,
    LOWER,
    Group,
    Metric,
    Study,
    arm_statistics,
    env_tables,
    holm_over_summary,
)

OUTCOME = Group("outcome")
REACHED = Group("reached", reached=True, missing="-")
STUDY = Study(
    name="online-locomotion",
    keys=("env", "model"),
    context=("env_steps",),
    metrics=(
        Metric("endpoint", "endpoint", HIGHER, OUTCOME, "p_improvement", f"P(endpoint > {BASELINE}'s)", "diff",
               "endpoint (last 5 at the budget)"),
        Metric("auc", "auc", HIGHER, OUTCOME, label="AUC"),
        Metric("steps_to_threshold", "steps_to_threshold", LOWER, REACHED, label="env steps to it"),
        Metric("cpu_hours", "cpu_hours", label="CPU h"),
    ),
)  # fmt: skip
#: One row per run: the study's columns, then the checkpoints, the falls and whether the run is complete.
RUN_COLUMNS = [*STUDY.run_columns(), "reward_25k", "reward_50k", "fall_fraction", "status"]
SUMMARY_COLUMNS = STUDY.summary_columns()
#: The secondary comparisons between arms (pre-registered): composition alone, then SE(n) against GEM's groups.
COMPARISONS = (("gem", "delta-groupfeat"), ("gem-se", "gem"))
VERSUS_COLUMNS = ["env", "model", "versus", "n_pairs", "diff", "diff_ci_low", "diff_ci_high", "p_signflip", "n_higher"]
#: The AUC's grid (amendment of 2026-11-28 09:35 UTC), the committed curves' too.
AUC_FROM, AUC_EVERY = curves.GRID_FROM, curves.GRID_EVERY


def auc(rows: Sequence[Mapping[str, Any]], length: int, budget: int = gate.BUDGET) -> float:
    """Mean of the gate's moving window at every :data:`AUC_EVERY` env steps from :data:`AUC_FROM` to ``budget``
    (NaN if the run has not got to the budget or has fewer than 5 complete episodes at 10k)."""
    if not rows or int(float(rows[-1]["env_steps"])) < budget:
        return math.nan
    points = curves.window_points(lambda n: gate.endpoint(rows, n, length), budget, AUC_FROM, AUC_EVERY)
    return float(np.mean([reward for _, reward in points]))


def steps_to_threshold(rows: Sequence[Mapping[str, Any]], length: int, threshold: float) -> float:
    """The first env step at which the moving window reaches ``threshold`` (NaN if never or no threshold)."""
    steps, values = gate.curve(rows, length)
    hit = np.flatnonzero(values >= threshold) if math.isfinite(threshold) else []
    return float(steps[hit[0]]) if len(hit) else math.nan


def run_row(run_dir: Path, crashed: bool = False) -> dict[str, Any]:
    """The :data:`RUN_COLUMNS` row of one run directory of the study (``crashed``: recorded as 0; :func:`_runs` makes
    it the worst outcome)."""
    cfg, rows = gate.read_run(run_dir)
    base = gate.config_row(cfg, rows)
    length, budget = gate.full_length(cfg), int(cfg.get("max_env_steps") or gate.BUDGET)
    row = {"env": cfg["env"], "model": cfg["head"], "seed": int(cfg["seed"]), "env_steps": base["env_steps"]}
    row |= {"diverged": "crashed" if crashed else ""}
    row |= {"endpoint": base[f"reward_{gate.BUDGET // 1000}k"], "auc": auc(rows, length, budget)}
    row |= {"steps_to_threshold": steps_to_threshold(rows, length, gate.THRESHOLDS.get(cfg["env"], math.nan))}
    row |= {"cpu_hours": base["cpu_hours"], "reward_25k": base["reward_25k"], "reward_50k": base["reward_50k"]}
    row |= {"fall_fraction": base["fall_fraction"], "status": "crashed" if crashed else base["status"]}
    return row | ({"endpoint": 0.0, "auc": 0.0} if crashed else {})


#: On an env whose every group is ``Rn`` or ``SO2_angle`` (a planar body) ``delta-groupfeat`` is ``gem`` bit for bit:
#: the same inputs, targets, training and plans (tests/test_models.py, ``test_groupfeat_equals_gem_on_a_planar_env``).
IDENTICAL = ("delta-groupfeat", "gem")
IDENTICAL_STATUS = "not run: gem's run (identical)"
_COMPARED = ("endpoint", "auc", "reward_25k", "reward_50k", "steps_to_threshold", "fall_fraction")


def planar(env: str) -> bool:
    """Whether every group of ``env``'s layout composes by addition (its codec is ``additive``: ``Rn``,
    ``SO2_angle``)."""
    import envs
    from gem_head.codecs import CODECS

    return all(CODECS[g.kind].additive for g in envs.get(env).layout.groups)


def identical_rows(rows: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """The rows of :data:`IDENTICAL`'s first arm for the seeds of a planar env that it has no row of: each the
    complete row of the second arm with the first's name, no CPU-hours (not run) and :data:`IDENTICAL_STATUS`.
    Where both arms have complete rows their learning results must agree, else ``ValueError`` (they are not
    identical: run the arm)."""
    arm, same = IDENTICAL
    have = {(r["env"], r["seed"]): r for r in rows if r["model"] == arm}
    out = []
    for r in rows:
        if r["model"] != same or r["status"] != "complete" or not planar(r["env"]):
            continue
        mine = have.get((r["env"], r["seed"]))
        if mine is None:
            out.append({**r, "model": arm, "cpu_hours": math.nan, "status": IDENTICAL_STATUS})
        elif mine["status"] == "complete":
            differ = [k for k in _COMPARED if cell_text(mine[k]) != cell_text(r[k])]
            if differ:
                raise ValueError(f"{r['env']} seed {r['seed']}: {arm} and {same} differ in {', '.join(differ)}: "
                                 f"not identical, so {arm} must be run")  # fmt: skip
    return out


#: The metrics a crashed run gets the worst outcome of (:func:`_runs`); its other metrics are what it reached.
WORST_OUTCOME = ("endpoint", "auc")


def _runs(rows: Sequence[Mapping[str, str]]) -> list[dict[str, Any]]:
    """The runs the summary counts (complete, crashed, or identical by construction to one that is complete), numbers
    parsed; a crashed run is not ``diverged`` for the statistics: it enters every one with the worst outcome of each
    of :data:`WORST_OUTCOME`, the lower of 0 (as registered) and the lowest value of any other run counted on its
    env (HalfCheetah's returns can be negative; the amendment of 2026-11-30, 12:30 UTC)."""
    counted = [r for r in rows if r["status"] in ("complete", "crashed", IDENTICAL_STATUS)]
    out = [{**{m.name: csv_number(r[m.name]) for m in STUDY.metrics}, "env": r["env"], "model": r["model"],
            "seed": int(r["seed"]), "diverged": None, "crashed": r["status"] == "crashed"}
           for r in counted]  # fmt: skip
    for run in (r for r in out if r["crashed"]):
        others = [r for r in out if r["env"] == run["env"] and not r["crashed"]]
        run |= {k: min([0.0, *(r[k] for r in others if math.isfinite(r[k]))]) for k in WORST_OUTCOME}
    return out


def summary_from_runs(rows: Sequence[Mapping[str, str]], *, reps: int = REPS) -> list[dict[str, Any]]:
    """:data:`SUMMARY_COLUMNS` rows per (env, arm) from the committed run rows: the IQM [CI] of each metric and,
    against ``delta`` (paired by seed), the IQM [CI] of the endpoint's differences, its exact sign-flip p and
    Holm's adjustment over every (env, arm) test."""
    runs, summary = _runs(rows), []
    for env in dict.fromkeys(r["env"] for r in runs):
        arms: dict[str, list[dict[str, Any]]] = {}
        for r in runs:
            if r["env"] == env:
                arms.setdefault(r["model"], []).append(r)
        order = sorted(arms, key=lambda m: m != BASELINE)
        baselines = {m: BASELINE if m != BASELINE and BASELINE in arms else None for m in order}
        threshold = gate.THRESHOLDS.get(env)
        stats = arm_statistics(STUDY, arms, baselines, reps=reps, threshold=threshold is not None)
        steps = max(int(csv_number(r["env_steps"])) for r in rows if r["env"] == env)
        summary += [{"env": env, "model": m, "env_steps": steps, **stats[m], "threshold": threshold} for m in order]
    holm_over_summary(STUDY, summary)
    return summary


def versus_rows(rows: Sequence[Mapping[str, str]], *, reps: int = REPS) -> list[dict[str, Any]]:
    """Secondary (no Holm): per env and pair of :data:`COMPARISONS` both of whose arms have runs, the endpoint's
    paired differences model - versus: IQM [CI], exact sign-flip p and the pairs where the model is higher."""
    runs, out = _runs(rows), []
    for env in dict.fromkeys(r["env"] for r in runs):
        by = {}
        for r in runs:
            if r["env"] == env:
                by.setdefault(r["model"], {})[r["seed"]] = r["endpoint"]
        for model, versus in COMPARISONS:
            seeds, d = paired_differences(by.get(model, {}), by.get(versus, {}))
            if not seeds:
                continue
            (mid,), (low,), (high,) = iqm_ci(d, reps=reps)
            out.append({"env": env, "model": model, "versus": versus, "n_pairs": len(seeds), "diff": float(mid),
                        "diff_ci_low": float(low), "diff_ci_high": float(high),
                        "p_signflip": sign_flip_p(d[:, 0]), "n_higher": int((d[:, 0] > 0).sum())})  # fmt: skip
    return out


def summary_markdown(summary: Sequence[Mapping[str, str]], versus: Sequence[Mapping[str, str]]) -> str:
    """The ``online-locomotion`` block: per env the summary table, then the secondary comparisons."""
    parts = env_tables(STUDY, [{k: _value(k, v) for k, v in r.items()} for r in summary])
    if versus:
        header = ["env", "model", "versus", "pairs", "paired diff", "p (sign-flip)", "model higher in"]
        body = [[r["env"], r["model"], r["versus"], r["n_pairs"],
                 fmt_interval(*(csv_number(r[k]) for k in ("diff", "diff_ci_low", "diff_ci_high"))),
                 fmt(csv_number(r["p_signflip"]), 3), r["n_higher"]] for r in versus]  # fmt: skip
        parts.append(md_table(header, body))
    return "\n\n".join(parts) if parts else "No seed is complete in every arm yet."


#: The pre-registered arms paired to delta and seeds of every arm (docs/studies/online_locomotion.md, Design).
ARMS, SEEDS = ("delta-groupfeat", "gem", "gem-se"), tuple(range(10))
#: The design's envs: Ant and Hopper, and HalfCheetah (its amendment of 2026-11-28, 07:50 UTC).
ENVS = ("halfcheetah", "ant", "hopper")
#: The paper's claim the study tests, and the arm that is the paper's GEM.
CLAIM, PAPER_ARM = "GEM+PETS consistently achieves higher rewards on complex environments", "gem"


#: A seed's runs, in their registered order (docs/studies/online_locomotion.md, amendment of 2026-11-28 07:50 UTC).
RUN_ORDER = ("gem-se", "gem", "delta-groupfeat", "delta")


def design_jobs(tree: Path) -> list[Job]:
    """The study's runs, seed-major, on the envs of :data:`ENVS` where the gate passed (its committed summary): per
    seed the arms of :data:`RUN_ORDER`, ``delta-groupfeat`` left out on a planar env (it takes ``gem``'s run)."""
    from pets.experiments.report import read_csv_rows

    gates = tree / RESULTS / GATE_SUMMARY
    verdicts = {(r["env"], r["agent"]): r["verdict"] for r in (read_csv_rows(gates) if gates.is_file() else [])}
    passed = [env for env in ENVS if verdicts.get((env, BASELINE)) == "passed"]
    return [
        Job(f"{env}-{arm}-s{seed}", seed, "online", "pets",
            ("--env", env, "--model", arm, "--preset", "locomotion", "--seed", str(seed), "threads=1"))
        for seed in SEEDS
        for env in passed
        for arm in RUN_ORDER
        if not (arm == IDENTICAL[0] and planar(env))
    ]  # fmt: skip


def design_done(tree: Path) -> set[str]:
    """The runs with a complete committed row."""
    from pets.experiments.report import read_csv_rows

    rows = read_csv_rows(tree / RESULTS / RUNS)
    return {f"{r['env']}-{r['model']}-s{r['seed']}" for r in rows if r["status"] == "complete"}


#: The study's registered runs (:mod:`pets.experiments.design`), made from the gate's pinned commit.
DESIGN = Design("online-locomotion", 52, gate_published.DESIGN.commit, design_jobs, design_done)


def _verdict(row: Mapping[str, str]) -> str:
    holm, diff = csv_number(row["diff_p_holm"]), csv_number(row["diff_to_delta"])
    if not math.isfinite(holm) or holm >= ALPHA:
        return "no difference shown"
    return "higher" if diff > 0 else "lower"


def claim_lines(summary: Sequence[Mapping[str, str]], gate_summary: Sequence[Mapping[str, str]]) -> list[str]:
    """The paper's claim per env of the design, worded by its rule (docs/studies/online_locomotion.md, amendment of
    2026-11-30): *reproduced* where the paper's GEM (``gem``) ends higher than ``delta`` at family-wise
    :data:`ALPHA` (Holm over the study's tests); *not reproduced* where every arm has its pre-registered pairs and
    it does not (no difference shown, or lower); *not shown* where the gate did not pass (``delta`` below
    competence: the study does not run there); *not yet* while pairs are missing or the gate is still running.
    Each names the other arms' outcomes beside it."""
    gate_verdicts = {r["env"]: r["verdict"] for r in gate_summary if r["agent"] == BASELINE}
    rows = {(r["env"], r["model"]): r for r in summary}
    lines = []
    for env in ENVS:
        gate_verdict = gate_verdicts.get(env, "not run")
        if gate_verdict == "partial":  # the gate still runs there: the study may yet start
            lines.append(f"- {env}: not yet (the gate: partial; the study runs there once it passes)")
            continue
        if gate_verdict != "passed":
            lines.append(f"- {env}: **not shown** (the gate: {gate_verdict}; delta is not shown competent there, so "
                         "the study does not run)")  # fmt: skip
            continue
        pairs = {arm: int(csv_number(rows[env, arm]["n_pairs"])) if (env, arm) in rows else 0 for arm in ARMS}
        if any(n < len(SEEDS) for n in pairs.values()):
            counts = ", ".join(f"{arm} {n}" for arm, n in pairs.items())
            lines.append(f"- {env}: not yet (pairs of {len(SEEDS)} per arm: {counts}; no verdict is read before)")
            continue
        verdicts = {arm: _verdict(rows[env, arm]) for arm in ARMS}
        word = "reproduced" if verdicts[PAPER_ARM] == "higher" else "not reproduced"
        others = "; ".join(f"{arm}: {verdicts[arm]}" for arm in ARMS if arm != PAPER_ARM)
        body = " (a planar body: gem is GEM's inputs alone, nothing composes)" if planar(env) else ""
        lines.append(f"- {env}: **{word}** (gem's endpoint against delta's: {verdicts[PAPER_ARM]}, Holm p "
                     f"{fmt(csv_number(rows[env, PAPER_ARM]['diff_p_holm']), 3)}; {others}){body}")  # fmt: skip
    return [f'The paper\'s claim, "{CLAIM}", per env of the design (at family-wise {ALPHA:g}):', "", *lines]


RESULTS = Path(publication.RESULTS)
RUNS, SUMMARY, VERSUS, CURVES = (f"online_locomotion_{kind}.csv" for kind in ("runs", "summary", "versus", "curves"))
GATE_SUMMARY = "locomotion_gate_summary.csv"
FIGURE = Path("docs") / "figures" / "online_locomotion.png"
CURVE_COLUMNS = ["env", "model", "seed", "env_steps", "reward"]


def curve_rows(run_dir: Path) -> list[dict[str, Any]]:
    """A run's learning curve (:func:`pets.experiments.gate.run_curve`), keyed by env, model and seed."""
    return gate.run_curve(run_dir, head="model")


def plot_curves(results: Path, figure: Path) -> None:
    """Reward (the moving window) against env steps per env, one line per arm: the mean over its complete runs
    with a 95 % bootstrap band (seeds resampled as whole curves), the gate's threshold dashed, the ceiling (the
    true-dynamics MPC of the preset's planner, ``locomotion_oracle.csv``) dotted and SAC's mean curve at the same
    budget (the gate's reference runs, ``locomotion_gate_curves.csv``) dash-dotted. On a planar env
    ``delta-groupfeat`` is not drawn: its curve is ``gem``'s (:data:`IDENTICAL`), which is drawn. Every arm of an
    env is drawn over the seeds complete in all of its arms (:func:`pets.experiments.curves.paired_members`), so
    the lines of a study still running compare the same seeds."""
    arms = curves.complete_curves(results / RUNS, results / CURVES, "model")
    for env, lines in arms.items():
        if planar(env):
            lines.pop(IDENTICAL[0], None)
    arms = curves.paired_members(arms)
    curves.plot_curves(figure, arms, thresholds=gate.THRESHOLDS,
                       ceiling=gate_published.committed_ceiling(results / "locomotion_oracle.csv"), first=BASELINE,
                       ylabel=f"return, last {gate.WINDOW} episodes (95 % CI)",
                       references=gate_published.committed_curves(results, agents={"sac"}))  # fmt: skip


def write_summary(results: Path) -> None:
    """Write :data:`SUMMARY` and :data:`VERSUS` in ``results`` from its :data:`RUNS` (``pets.compare report``)."""
    from pets.experiments.report import read_csv_rows

    rows = read_csv_rows(results / RUNS)
    write_rounded_csv(results / SUMMARY, summary_from_runs(rows), SUMMARY_COLUMNS)
    write_rounded_csv(results / VERSUS, versus_rows(rows), VERSUS_COLUMNS)
    plot_curves(results, results.parent / "figures" / FIGURE.name)


def runs_table(tree: Path) -> str:
    """The ``online-locomotion-runs`` block: one row per run (complete, partial or crashed) of :data:`RUNS`."""
    columns = {"env": "env", "model": "arm", "seed": "seed", "env_steps": "env steps", "reward_25k": "25k"}
    columns |= {"reward_50k": "50k", "endpoint": "100k (endpoint)", "cpu_hours": "CPU-hours", "status": "status"}
    return gate_published.csv_table(tree / RESULTS / RUNS, columns)


def summary_table(tree: Path) -> str:
    """The ``online-locomotion`` block: :func:`summary_markdown` of the generated summary and versus files, then
    :func:`claim_lines` (the gate's verdicts from its generated summary)."""
    from pets.experiments.report import read_csv_rows

    summary, versus = (read_csv_rows(tree / RESULTS / name) for name in (SUMMARY, VERSUS))
    gates = read_csv_rows(tree / RESULTS / GATE_SUMMARY) if (tree / RESULTS / GATE_SUMMARY).is_file() else []
    return summary_markdown(summary, versus) + "\n\n" + "\n".join(claim_lines(summary, gates))


def _value(key: str, text: str) -> Any:
    if key in ("env", "model", "ci_exact_note"):
        return text
    value = csv_number(text)
    if key.startswith("n_"):
        return None if math.isnan(value) else int(value)
    return None if math.isnan(value) else value


#: What the study publishes (:mod:`pets.experiments.publication`): its summary, secondary comparisons and figure
#: from its committed run rows and curves, and the two blocks of its page.
PUBLICATION = Publication(
    "online locomotion",
    raw=(results_path(RUNS), results_path(CURVES)),
    products=(
        Product(
            "online locomotion summary",
            (results_path(SUMMARY), results_path(VERSUS), str(FIGURE)),
            (results_path(RUNS), results_path(CURVES), results_path("locomotion_oracle.csv")),
            lambda: write_summary(RESULTS),
        ),
    ),
    blocks={
        "online-locomotion-runs": runs_table,
        "online-locomotion": summary_table,
        "online-locomotion-progress": DESIGN.progress,
    },
    pages=("docs/studies/online_locomotion.md",),
)


def main(argv: list[str] | None = None) -> int:
    from pets.tools.cli import OneLineParser

    p = OneLineParser(prog="pets.experiments.studies.locomotion", description=__doc__.splitlines()[0])
    p.add_argument("run_dirs", nargs="+", type=Path, help="the study's run directories (run_pets.py --out)")
    p.add_argument("--out", type=Path, required=True, help="the runs CSV to write (one row per run)")
    p.add_argument("--curves", type=Path, help="also write every run's learning curve to this CSV")
    p.add_argument("--crashed", nargs="*", type=Path, default=[], help="runs given up on: the worst outcome")
    same = "on a planar env, a delta-groupfeat seed not run takes gem's row (identical by construction)"
    p.add_argument("--identical", action="store_true", help=same)
    p.add_argument("--replace", action="store_true", help=gate.REPLACE_HELP)
    args = p.parse_args(argv)
    missing = [str(d) for d in args.run_dirs if not (d / "config.yaml").is_file()]
    if missing:
        p.error(f"not run directories (no config.yaml): {', '.join(missing)}")
    unknown = [str(d) for d in args.crashed if d not in args.run_dirs]
    if unknown:
        p.error(f"--crashed names runs not given: {', '.join(unknown)}")
    keep = () if args.replace else ("env", "model", "seed")
    try:  # every run read before anything is written
        rows = [run_row(d, crashed=d in args.crashed) for d in args.run_dirs]
        curves = [c for d in args.run_dirs for c in curve_rows(d)] if args.curves else []
    except ValueError as e:  # not an online run's directory (gate.read_run)
        p.error(str(e))
    text = [{c: cell_text(r[c]) for c in RUN_COLUMNS} for r in rows]
    if keep:
        merged = merge_committed(args.out, text, keep, "env_steps")[0]
        text = [r for r in merged if r["status"] != IDENTICAL_STATUS]  # derived below
    if args.identical:
        try:
            text += identical_rows(text)
        except ValueError as e:
            p.error(str(e))
    write_rounded_csv(args.out, text, RUN_COLUMNS)
    if args.curves:
        write_rounded_csv(args.curves, curves, CURVE_COLUMNS, keep)
    for r in rows:
        print("  ".join(f"{k}={cell_text(v)}" for k, v in r.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
