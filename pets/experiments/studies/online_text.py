"""The text of an online comparison's summary.md around its tables: what the columns mean, and the lists of the
diverged and of the missing runs (:func:`pets.experiments.studies.online.summarise_online`)."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path

from pets.experiments.report import machine_label, provenance_lines
from pets.experiments.statistics import BASELINE


def summary_header(
    trials: int, w: int, compared: bool, with_planner: bool, until_threshold: bool, budget: bool
) -> list[str]:
    """The top of summary.md: what the columns mean (``budget``: some run has an env-step budget)."""
    base_name = BASELINE if not with_planner else f"{BASELINE} with the same planner"
    if until_threshold:
        runs_line = f"# Online comparison (runs to the threshold, at most {trials} trials each)"
        span = "the trials up to the one that reached the threshold (or all, if none did)"
    elif budget:
        runs_line, span = f"# Online comparison (runs to their env-step budget, at most {trials} trials)", "all trials"
    else:
        runs_line, span = f"# Online comparison ({trials} trials per run)", f"all {trials} trials"
    cut = " An episode cut by a run's env-step budget (max_env_steps) is in neither." if budget else ""
    return [
        runs_line,
        "",
        f"final = mean episode reward of the last {w} trial{'s' if w > 1 else ''} of each run; "
        f"AUC = mean episode reward over {span}.{cut} Per arm: the interquartile mean (IQM) over seeds "
        "with its 95 % stratified-bootstrap CI in brackets (rliable)."
        + (
            f" P(final > {BASELINE}'s): the probability that a random seed of the arm ends with a higher final "
            f"reward than a random seed of {base_name} (ties count half), with its CI. final - {BASELINE}: IQM "
            "[CI] of the per-seed difference of the final rewards over the seeds both arms have (same seed: "
            "the same random seed data and env reset seeds). p (sign-flip): the exact two-sided paired permutation "
            f"p-value of the mean final - {BASELINE} over the seeds both arms ran (each pair's sign flipped), a "
            "diverged run entered as the env's lowest final reward (at 5 pairs it cannot go below 0.0625); p (Holm): "
            "Holm's adjustment over every arm-vs-baseline test of this summary (envs x arms)."
            if compared
            else ""
        )
        + " A run with a non-finite episode reward, or one that stopped because its model training diverged or no "
        "plan had a finite return (its diverged.txt), is diverged: counted, left out of the IQMs, CIs and "
        "differences, and the worst final reward in P. Plan s/step: median seconds per planning step of "
        "a run; wall h: the run's wall-clock hours (planning, simulation, model training); CPU h: its process "
        "CPU hours (what other jobs on the machine do not inflate; - for runs made before the column existed); "
        "each the mean over the complete runs, diverged ones included (not a run that stopped diverged: it ran part of "
        "its trials). To threshold: how many of the runs that "
        "did not diverge reached the env's reward threshold, and over those that did the IQM [CI] of the "
        "wall-clock minutes, env steps and process CPU minutes until the end of the first trial that reached it "
        "(the others counted, not averaged in).",
        "",
    ]


def runs_sections(diverged_runs: Sequence[str], missing: Sequence[str]) -> list[str]:
    """Markdown of the diverged runs and of the missing or incomplete ones."""
    text = []
    if diverged_runs:
        text += ["## Diverged runs (counted, not in the IQMs)", ""] + [f"- {d}" for d in diverged_runs] + [""]
    if missing:
        text += ["## Missing or incomplete runs (not in the statistics)", ""] + [f"- {m}" for m in missing] + [""]
    return text


def online_provenance(seeds: Sequence[int], run_dirs: Iterable[Path], command: str | None = None) -> list[str]:
    """:func:`pets.experiments.report.provenance_lines` of an online comparison: the machines from each run's
    history.csv (its ``host`` and ``cpu``: a run resumed on another machine counts on each)."""
    from pets.runs.rundir import read_history

    return provenance_lines(
        f"{', '.join(str(s) for s in seeds)} ({len(seeds)}; an arm's run is paired with {BASELINE}'s run of the same "
        "seed)",
        command,
        "each run's resolved config in runs/RUN/config.yaml, its run_pets.py command on the first line of logs/RUN.log",
        ([machine_label(h.get("host"), h.get("cpu")) for h in read_history(run_dir)] for run_dir in run_dirs),
        "runs/RUN/history.csv",
    )
