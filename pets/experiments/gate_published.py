"""The locomotion gate's published blocks and figures, made by ``pets.compare report`` from its committed rows only:
the tables of its runs, pilots and true-dynamics episodes (:func:`gate_table`, :func:`pilots_table`,
:func:`oracle_table`), its figures (:func:`write_figures`: the runs' and the pilots' learning curves,
``locomotion_gate_curves.csv`` and ``locomotion_pilots_curves.csv``, with the true-dynamics ceiling,
``locomotion_oracle.csv``), and the diagnosis blocks (docs/studies/locomotion_gate.md, "Pilots"): how the Ant pilots'
episodes ended and what a pilot's learned model, frozen, does (``docs/scripts/episode_ends.py`` and
``docs/scripts/frozen_model_checks.py`` write the committed CSVs these render); and what the locomotion work cost
(docs/results.md)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

import envs
from pets.experiments import gate, publication
from pets.experiments.curves import Curves, complete_curves, group_curves, plot_curves
from pets.experiments.design import Design, Job
from pets.experiments.publication import FIGURES, Product, Publication, results_path
from pets.experiments.report import csv_number, fmt, md_table, read_csv_rows, write_rounded_csv
from pets.experiments.statistics import sign_flip_p
from pets.presets import PRESETS

RESULTS = Path(publication.RESULTS)
SEED_STEPS = PRESETS["locomotion"]["seed_steps"]  # the random episodes before the first planned one
ANT_TOP = 1.0  # the top of gymnasium Ant-v5's healthy_z_range [0.2, 1.0]: a torso above it fell by jumping


def episode_ends_table(tree: Path) -> str:
    """The ``locomotion-episode-ends`` block: per Ant run of ``locomotion_episode_ends.csv`` (docs/scripts/
    episode_ends.py; its replay buffer's episodes, the seed data's included), how its episodes ended, and the mean
    squared action norm per step of its planned episodes (after the preset's 1,000 random seed steps) that lasted the
    full 1,000 steps."""
    counts: dict[str, list[int]] = {}
    action_sq: dict[str, list[float]] = {}
    start: dict[str, int] = {}
    full = envs.get("ant").episode_length
    for r in read_csv_rows(tree / RESULTS / "locomotion_episode_ends.csv"):
        begun = start.get(r["run"], 0)
        start[r["run"]] = begun + int(r["steps"])
        fell, height, up = int(r["fell"]), float(r["height"]), float(r["up_cos"])
        c = counts.setdefault(r["run"], [0, 0, 0, 0])
        c[0] += 1
        c[1] += fell
        c[2] += fell and height > ANT_TOP
        c[3] += not fell and up < 0
        if int(r["steps"]) == full and begun >= SEED_STEPS:
            action_sq.setdefault(r["run"], []).append(float(r["action_sq"]))
    header = ["run", "episodes", "fell", f"fell by jumping (torso above {ANT_TOP})", "did not fall, ended on its back"]
    header += ["planned 1,000-step episodes", "their squared action per step"]
    body = []
    for run, c in counts.items():
        planned = action_sq.get(run, [])
        body.append([run, *map(str, c), str(len(planned)), fmt(float(np.mean(planned))) if planned else "-"])
    return md_table(header, body)


def frozen_planning_table(tree: Path) -> str:
    """The ``locomotion-frozen-planning`` block: per run and planner variant of ``locomotion_frozen_planning.csv``,
    the episodes, how many fell, their mean length and mean return."""
    groups: dict[tuple[str, str], list[dict[str, str]]] = {}
    for r in read_csv_rows(tree / RESULTS / "locomotion_frozen_planning.csv"):
        groups.setdefault((r["run"], r["variant"]), []).append(r)
    header = ["run", "planner variant", "episodes", "fell", "mean steps", "mean return"]

    def mean(rs: list[dict[str, str]], key: str) -> str:
        return fmt(float(np.mean([float(r[key]) for r in rs])))

    body = [
        [run, variant, str(len(rs)), str(sum(int(r["fell"]) for r in rs)), mean(rs, "steps"), mean(rs, "reward")]
        for (run, variant), rs in groups.items()
    ]
    return md_table(header, body)


def fall_prediction_table(tree: Path) -> str:
    """The ``locomotion-fall-prediction`` block: ``locomotion_fall_prediction.csv`` as it is."""
    columns = {"run": "run", "horizon": "H steps before the fall", "falls": "falls", "foreseen": "foreseen"}
    return csv_table(tree / RESULTS / "locomotion_fall_prediction.csv", columns | {"recall": "fraction foreseen"})


def reward_prediction_table(tree: Path) -> str:
    """The ``locomotion-reward-prediction`` block: ``locomotion_reward_prediction.csv`` as it is."""
    columns = {"run": "run", "horizon": "H", "true_mean": "true sum (mean)", "true_sd": "true sum (sd)"}
    columns |= {"pred_mean": "predicted (mean)", "corr": "correlation", "mean_abs_error": "mean abs error"}
    return csv_table(tree / RESULTS / "locomotion_reward_prediction.csv", columns)


#: The ablation's arms (docs/studies/locomotion_gate.md, amendment of 2026-11-28 06:35 UTC), `delta` on HalfCheetah,
#: pilot seeds 100-102: each its runs' name, its overrides on the command line and as a pilot row records them (a
#: row's overrides name its arm), and its label.
ABLATION_ARMS = (
    ("v2", "", "", "full preset"),
    ("novalue", "value.enabled=false", "value.enabled=False", "without the value"),
    ("epochs", "model.iterations=0", "model.iterations=0", "epoch training"),
)
ABLATION = {recorded: label for _, _, recorded, label in ABLATION_ARMS}
ABLATION_SEEDS = ("100", "101", "102")


def _is_ablation(r: dict[str, str]) -> bool:
    """Whether a pilot row is a run of the ablation (its full preset's seed 100 is HalfCheetah's pilot v2)."""
    return r["env"] == "halfcheetah" and r["overrides"] in ABLATION and r["seed"] in ABLATION_SEEDS


def ablation_table(tree: Path) -> str:
    """The ``locomotion-ablation`` block: per arm the endpoint at the budget of each seed (or how far a partial run
    got), the mean over its complete seeds, and over the seeds both it and the full preset have complete: the mean
    paired difference, in how many pairs the arm ends below, and the exact sign-flip p (3 pairs at most, whose
    smallest p is 0.25: a direction, never significance)."""
    done: dict[str, dict[str, float]] = {arm: {} for arm in ABLATION}
    cells: dict[str, dict[str, str]] = {arm: {} for arm in ABLATION}
    for r in read_csv_rows(tree / RESULTS / "locomotion_pilots.csv"):
        if _is_ablation(r):
            final, reached = r["reward_100k"], int(r["env_steps"]) // 1000
            cells[r["overrides"]][r["seed"]] = fmt(float(final)) if final else f"partial ({reached}k)"
            if final:
                done[r["overrides"]][r["seed"]] = float(final)
    body = []
    for arm, label in ABLATION.items():
        pairs = sorted(set(done[arm]) & set(done[""]))
        differences = [done[arm][s] - done[""][s] for s in pairs]
        diff = fmt(float(np.mean(differences))) if pairs and arm else "-"
        mean = fmt(float(np.mean(list(done[arm].values())))) if done[arm] else "-"
        seeds = [cells[arm].get(s, "not run") for s in ABLATION_SEEDS]
        pairs_text = f"{len(pairs)} pair" + ("" if len(pairs) == 1 else "s")
        lower = f"{sum(d < 0 for d in differences)} of {len(pairs)}" if pairs and arm else "-"
        p = fmt(sign_flip_p(differences), 3) if pairs and arm else "-"
        body.append([label, *seeds, mean, f"{diff} ({pairs_text})" if arm else "-", lower, p])
    header = ["arm", *(f"seed {s}" for s in ABLATION_SEEDS), "mean (complete)", "minus the full preset"]
    return md_table([*header, "pairs below the full preset", "exact sign-flip p"], body)


def compute_table(tree: Path) -> str:
    """The ``locomotion-compute`` block: the CPU-hours (process CPU, one thread per run) recorded in the committed rows
    of the locomotion work, per part and env: the gate's runs, its pilots and ablation runs (whose full preset's seed
    100 is HalfCheetah's pilot v2), the frozen-model planning checks, and the online study's own runs (the gate's
    ``delta`` runs it reuses counted once, as the gate's; rows of arms not run, none)."""
    parts: dict[tuple[str, str], list[float]] = {}

    def add(part: str, env: str, hours: float) -> None:
        if np.isfinite(hours):  # an empty cell (not recorded, or not run) is NaN
            parts.setdefault((part, env), []).append(hours)

    gate_runs = read_csv_rows(tree / RESULTS / "locomotion_gate_runs.csv")
    for r in gate_runs:
        add("the gate's runs", r["env"], csv_number(r["cpu_hours"]))
    for r in read_csv_rows(tree / RESULTS / "locomotion_pilots.csv"):
        part = "the gate's ablation (with pilot v2)" if _is_ablation(r) else "the gate's pilots"
        add(part, r["env"], csv_number(r["cpu_hours"]))
    for r in read_csv_rows(tree / RESULTS / "locomotion_frozen_planning.csv"):
        add("frozen-model planning checks", r["run"].split("-")[0], csv_number(r["cpu_s"]) / 3600)
    reused = {(r["env"], r["agent"], r["seed"]) for r in gate_runs}
    for r in read_csv_rows(tree / RESULTS / "online_locomotion_runs.csv"):
        if (r["env"], r["model"], r["seed"]) not in reused:
            add("the online study's runs", r["env"], csv_number(r["cpu_hours"]))
    body = [[part, env, str(len(v)), fmt(float(np.sum(v)))] for (part, env), v in parts.items()]
    every = [h for v in parts.values() for h in v]
    body.append(["all of the above", "", str(len(every)), fmt(float(np.sum(every)))])
    return md_table(["part", "env", "runs (or episodes)", "CPU-hours"], body)


def csv_table(path: Path, columns: Mapping[str, str]) -> str:
    """The committed CSV ``path`` as a markdown table of ``columns`` (CSV column -> header), numbers to 4 digits."""

    def cell(text: str) -> str:
        try:
            return fmt(csv_number(text)) if text else ""
        except ValueError:
            return text

    return md_table(list(columns.values()), ([cell(r[c]) for c in columns] for r in read_csv_rows(path)))


def oracle_table(tree: Path) -> str:
    """The ``locomotion-oracle`` block: every true-dynamics episode of ``locomotion_oracle.csv``."""
    columns = {"source": "file", "candidates": "candidates", "population": "population", "horizon": "horizon"}
    columns |= {"iterations": "iterations"}
    columns |= {"termination_penalty": "termination penalty", "terminal_value": "terminal value of"}
    columns |= {"steps": "steps", "reward": "reward", "fell": "fell"}
    return csv_table(tree / RESULTS / "locomotion_oracle.csv", columns)


def pilots_table(tree: Path) -> str:
    """The ``locomotion-pilots`` block: one row per pilot run of ``locomotion_pilots.csv``."""
    columns = {"run": "run", "overrides": "overrides", "env_steps": "env steps", "reward_last5": "last-5 mean"}
    columns |= {"fall_fraction": "episodes that fell", "cpu_hours": "CPU-hours"}
    return csv_table(tree / RESULTS / "locomotion_pilots.csv", columns)


def gate_table(tree: Path) -> str:
    """The ``locomotion-gate`` block: every run of ``locomotion_gate_runs.csv``, then the verdict per env."""
    runs = {"env": "env", "agent": "agent", "seed": "seed", "env_steps": "env steps", "reward_25k": "25k"}
    runs |= {"reward_50k": "50k", "reward_100k": "100k (endpoint)", "fall_fraction": "fell", "cpu_hours": "CPU-h"}
    runs |= {"plan_cpu_hours": "of it planning", "status": "status"}
    summary = {"env": "env", "agent": "agent", "n_runs": "runs", "endpoint_at": "endpoint at (env steps)"}
    summary |= {"mean": "mean", "iqm": "IQM", "ci_low": "CI low"}
    summary |= {"ci_high": "CI high", "threshold": "threshold", "verdict": "verdict"}
    parts = (("runs", runs), ("summary", summary))
    return "\n\n".join(csv_table(tree / RESULTS / f"locomotion_gate_{part}.csv", cols) for part, cols in parts)


#: The env steps at which the gate's agents are set side by side (mbrl-lib's budget: the amendment of 2026-11-28,
#: 21:45 UTC), and the unit of the cost column.
PEER_STEPS, COST_STEPS = 50_000, 10_000


def peer_table(tree: Path) -> str:
    """The ``locomotion-peer`` block: on each env where mbrl-lib ran, every agent's complete gate runs side by side
    at :data:`PEER_STEPS` env steps: the reward there (mean [min, max] over runs), the CPU-hours per
    :data:`COST_STEPS` env steps (each run's CPU-hours over its own budget), and the reward there per CPU-hour spent
    to reach it (a run's CPU-hours pro rata to :data:`PEER_STEPS`; for runs whose budget is larger the per-step
    cost is constant by their design, a fixed planner and a fixed number of gradient steps per env step)."""
    runs = [r for r in read_csv_rows(tree / RESULTS / "locomotion_gate_runs.csv") if r["status"] == "complete"]
    body = []
    for env in dict.fromkeys(r["env"] for r in runs if r["agent"] == "mbrl-lib"):
        for agent in dict.fromkeys(r["agent"] for r in runs if r["env"] == env):
            mine = [r for r in runs if (r["env"], r["agent"]) == (env, agent)]
            reward = np.array([csv_number(r[f"reward_{PEER_STEPS // 1000}k"]) for r in mine])
            per_step = np.array([csv_number(r["cpu_hours"]) / int(r["env_steps"]) for r in mine])
            per_hour = reward / (per_step * PEER_STEPS)
            cost, rate = (
                fmt(float(np.mean(v))) if np.isfinite(v).all() else "not recorded"
                for v in (per_step * COST_STEPS, per_hour)
            )
            budgets = "/".join(sorted({r["env_steps"] for r in mine}))
            spread = f"{fmt(float(np.mean(reward)))} [{fmt(float(reward.min()))}, {fmt(float(reward.max()))}]"
            body.append([env, agent, str(len(mine)), budgets, spread, cost, rate])
    header = ["env", "agent", "complete runs", "budget (env steps)", f"reward at {PEER_STEPS // 1000}k env steps"]
    header += [f"CPU-h per {COST_STEPS // 1000}k env steps", f"reward at {PEER_STEPS // 1000}k per CPU-h to it"]
    return md_table(header, body)


#: The parts of a run's process CPU in ``locomotion_cost_breakdown.csv`` (docs/scripts/cost_breakdown.py), by column.
COST_PARTS = {"plan_cpu_s": "planning", "train_cpu_s": "model training", "value_cpu_s": "value fit"}


def cost_table(tree: Path) -> str:
    """The ``locomotion-cost`` block: per run of ``locomotion_cost_breakdown.csv``, its process CPU over all its
    trials (the seed data's and the first compiles included) per :data:`COST_PARTS`, the rest (the simulator and the
    run's bookkeeping) apart, as shares, and all of it projected pro rata to the gate's budget."""
    runs: dict[str, list[dict[str, str]]] = {}
    for r in read_csv_rows(tree / RESULTS / "locomotion_cost_breakdown.csv"):
        runs.setdefault(r["run"], []).append(r)
    body = []
    for run, rows in runs.items():
        total = sum(float(r["cpu_s"]) for r in rows)
        parts = [sum(float(r[k]) for r in rows) for k in COST_PARTS]
        steps = int(rows[-1]["env_steps"])
        shares = [f"{100 * v / total:.0f} %" for v in (*parts, total - sum(parts))]
        body.append([run, str(steps), fmt(total / 3600 * gate.BUDGET / steps), *shares])
    header = ["run", "env steps", f"CPU-h per {gate.BUDGET // 1000}k env steps", *COST_PARTS.values()]
    return md_table([*header, "simulator and the rest"], body)


def committed_ceiling(path: Path) -> dict[str, float]:
    """:func:`pets.experiments.gate.ceiling` of the committed ``locomotion_oracle.csv`` (empty without it)."""
    numbers = ("reward", "population", "horizon", "iterations", "termination_penalty")
    rows = read_csv_rows(path) if path.is_file() else []
    return gate.ceiling([dict(r, **{k: csv_number(r[k]) for k in numbers}) for r in rows])


def committed_curves(results: Path, agents: set[str] | None = None) -> Curves:
    """The gate's committed curves of its complete runs (``locomotion_gate_{runs,curves}.csv`` in ``results``; of
    ``agents`` only, if given) as :data:`pets.experiments.curves.Curves` by agent and seed; empty without them."""
    runs, points = results / "locomotion_gate_runs.csv", results / "locomotion_gate_curves.csv"
    return complete_curves(runs, points, "agent", agents) if runs.is_file() and points.is_file() else {}


def write_figures(results: Path, figures: Path) -> None:
    """``locomotion_gate.png`` (per env, each agent's complete runs: mean and 95 % band) and
    ``locomotion_pilots.png`` (one line per pilot) from the committed curve rows (``pets.compare report``)."""
    ceil = committed_ceiling(results / "locomotion_oracle.csv")
    ylabel = f"return, last {gate.WINDOW} episodes (95 % CI)"
    plot_curves(figures / "locomotion_gate.png", committed_curves(results), thresholds=gate.THRESHOLDS, ceiling=ceil,
                first="delta", ylabel=ylabel)  # fmt: skip
    pilots = group_curves(read_csv_rows(results / "locomotion_pilots_curves.csv"), "run", "run")
    plot_curves(figures / "locomotion_pilots.png", pilots, thresholds=gate.THRESHOLDS, ceiling=ceil,
                ylabel=f"return, last {gate.WINDOW} episodes")  # fmt: skip


def write_summary(results: Path, figures: Path) -> None:
    """``locomotion_gate_summary.csv`` (the verdict per env) from ``locomotion_gate_runs.csv`` (one row per run,
    ``python -m pets.experiments.gate RUN_DIR ... --out docs/results/locomotion_gate``), and the figures."""
    rows = read_csv_rows(results / "locomotion_gate_runs.csv")
    write_rounded_csv(results / "locomotion_gate_summary.csv", gate.summary_rows(rows), gate.SUMMARY_COLUMNS)
    write_figures(results, figures)


def ablation_jobs(tree: Path) -> list[Job]:
    """The ablation's runs, seed-major (every arm of seed 100, then 101, 102)."""
    base = ("--env", "halfcheetah", "--model", "delta", "--preset", "locomotion")
    return [
        Job(f"halfcheetah-{name}-s{s}", int(s), "pilots", "pets", (*base, "--seed", s, "threads=1", *overrides.split()))
        for s in ABLATION_SEEDS
        for name, overrides, _, _ in ABLATION_ARMS
    ]


def ablation_done(tree: Path) -> set[str]:
    """The runs whose committed pilot row is at the gate's budget."""
    rows = read_csv_rows(tree / RESULTS / "locomotion_pilots.csv")
    return {r["run"] for r in rows if float(r["env_steps"] or 0) >= gate.BUDGET}


#: The ablation's registered runs (:mod:`pets.experiments.design`), made from the gate's pinned commit.
DESIGN = Design("locomotion-gate-ablation", 56, "1f6591b", ablation_jobs, ablation_done)

#: The gate's committed rows: its runs and curves, the pilots (and the ablation's runs among them), the
#: true-dynamics episodes, mbrl-lib's runs beside it and the diagnosis files (docs/studies/locomotion_gate.md).
RAW = tuple(
    results_path(name)
    for name in (
        *("locomotion_pilots.csv", "locomotion_oracle.csv", "locomotion_episode_ends.csv"),
        *("locomotion_gate_runs.csv", "locomotion_gate_curves.csv"),
        *(f"peer_gate_halfcheetah_s{seed}.csv" for seed in range(3)),
        *("locomotion_pilots_curves.csv", "locomotion_cost_breakdown.csv", "locomotion_frozen_planning.csv"),
        *("locomotion_reward_prediction.csv", "locomotion_fall_prediction.csv"),
    )
)
#: What the gate publishes (:mod:`pets.experiments.publication`).
PUBLICATION = Publication(
    "locomotion gate",
    raw=RAW,
    products=(
        Product(
            "locomotion gate summary and figures",
            (
                results_path("locomotion_gate_summary.csv"),
                f"{FIGURES}/locomotion_gate.png",
                f"{FIGURES}/locomotion_pilots.png",
            ),
            tuple(
                results_path(n)
                for n in (
                    "locomotion_gate_runs.csv",
                    "locomotion_gate_curves.csv",
                    "locomotion_pilots_curves.csv",
                    "locomotion_oracle.csv",
                )
            ),
            lambda: write_summary(RESULTS, Path(FIGURES)),
        ),
    ),
    blocks={
        "locomotion-oracle": oracle_table,
        "locomotion-pilots": pilots_table,
        "locomotion-episode-ends": episode_ends_table,
        "locomotion-frozen-planning": frozen_planning_table,
        "locomotion-fall-prediction": fall_prediction_table,
        "locomotion-reward-prediction": reward_prediction_table,
        "locomotion-gate": gate_table,
        "locomotion-ablation": ablation_table,
        "locomotion-ablation-progress": DESIGN.progress,
        "locomotion-peer": peer_table,
        "locomotion-compute": compute_table,
        "locomotion-cost": cost_table,
    },
    pages=("docs/studies/locomotion_gate.md",),
)
