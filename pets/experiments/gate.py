"""The locomotion gate (docs/studies/locomotion_gate.md): does PETS at ``--preset locomotion`` learn to run and
walk within 100k env steps? The endpoint of one online run, the per-run and summary rows, the verdict.

    python -m pets.experiments.gate RUN_DIR [RUN_DIR ...] [--crashed RUN_DIR ...] [--sac SAC_DATA ...] \
        [--peer PEER_CSV ...] --out docs/results/locomotion_gate
    python -m pets.experiments.gate --pilots RUN_DIR [RUN_DIR ...] --out docs/results/locomotion_pilots

Writes the runs' rows and their learning curves (``OUT_runs.csv`` and ``OUT_curves.csv``; pilots: ``OUT.csv`` and
``OUT_curves.csv``); ``python -m pets.compare report`` makes the summary and the figures from those rows.

The endpoint of a run at ``n`` env steps: the mean return of the last :data:`WINDOW` complete episodes (ended by
a fall or by the episode's step limit, not by the budget) whose last step is at or before ``n`` (the seed data's
random episodes are not trials and do not count). Reads each run directory's ``config.yaml`` and ``metrics.csv``.
A run the gate gave up on (``--crashed``: it crashed or diverged and cannot go on) counts as the worst outcome, as
registered: an endpoint of 0 at every checkpoint it did not reach.
"""

from __future__ import annotations

import csv
import math
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pets.experiments.curves import window_points
from pets.experiments.gate_references import Reference, peer_runs, sac_run
from pets.experiments.report import cell_text, write_rounded_csv

#: The pre-registered thresholds (Wang et al. 2019, PETS-CEM at 200k env steps), per catalogue env.
THRESHOLDS = {"halfcheetah": 2800.0, "ant": 1170.0, "hopper": 1130.0}
BUDGET = 100_000
CHECKPOINTS = (25_000, 50_000, 100_000)
WINDOW = 5
#: The status of a run the gate gave up on (``--crashed``): in the verdict with the worst outcome, 0.
CRASHED = "crashed"
RUN_COLUMNS = [
    "env",
    "agent",
    "seed",
    "env_steps",
    *[f"reward_{n // 1000}k" for n in CHECKPOINTS],
    "episodes",
    "fall_fraction",
    "cpu_hours",
    "plan_cpu_hours",
    "status",
]
SUMMARY_COLUMNS = ["env", "agent", "n_runs", "endpoint_at", "mean", "iqm", "ci_low", "ci_high", "threshold", "verdict"]


def complete(row: Mapping[str, Any], full_length: int) -> bool:
    """Whether a metrics row's episode ended by itself: a fall (``terminated``) or the episode's step limit."""
    return int(float(row["terminated"])) == 1 or int(float(row["episode_length"])) >= full_length


def endpoint(rows: Sequence[Mapping[str, Any]], at: int, full_length: int, window: int = WINDOW) -> float:
    """Mean return of the last ``window`` complete episodes ending at or before ``at`` env steps; NaN if fewer
    than ``window`` exist by then (the run has not got there)."""
    done = [r for r in rows if int(float(r["env_steps"])) <= at and complete(r, full_length)]
    if len(done) < window:
        return math.nan
    return float(np.mean([float(r["episode_reward"]) for r in done[-window:]]))


def curve(rows: Sequence[Mapping[str, Any]], full_length: int, window: int = WINDOW) -> tuple[np.ndarray, np.ndarray]:
    """``(env_steps, endpoint)`` after every complete episode from the ``window``-th on: the run's learning curve."""
    steps, values, done = [], [], []
    for r in rows:
        if complete(r, full_length):
            done.append(float(r["episode_reward"]))
            if len(done) >= window:
                steps.append(int(float(r["env_steps"])))
                values.append(float(np.mean(done[-window:])))
    return np.array(steps, dtype=np.int64), np.array(values)


def read_run(run_dir: Path) -> tuple[dict[str, Any], list[dict[str, str]]]:
    """A run directory's config and metrics rows; ValueError (one line) for one that is not an online run's."""
    import yaml

    try:
        cfg = yaml.safe_load((run_dir / "config.yaml").read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as err:
        raise ValueError(f"{run_dir}/config.yaml is not readable YAML ({type(err).__name__})") from None
    metrics = run_dir / "metrics.csv"
    rows = list(csv.DictReader(open(metrics, newline=""))) if metrics.is_file() else []
    episodes = ("env_steps", "episode_reward", "episode_length", "terminated")
    if not isinstance(cfg, dict) or not {"env", "head", "seed"} <= set(cfg):
        raise ValueError(f"{run_dir}/config.yaml is not a run's config (no env, head and seed)")
    if rows and any(r.get(k) in (None, "", "nan") for r in rows for k in episodes):
        raise ValueError(f"{run_dir} is not an online run (run_pets.py): its metrics.csv has no episode in every row")
    return cfg, rows


def full_length(cfg: Mapping[str, Any]) -> int:
    """The episode step limit of a run's config (its ``episode_length``, else the env's own)."""
    if cfg.get("episode_length"):
        return int(cfg["episode_length"])
    import envs

    return envs.get(cfg["env"]).episode_length


def run_row(run_dir: Path, agent: str | None = None) -> dict[str, Any]:
    """The :data:`RUN_COLUMNS` row of one run directory (``agent``: default the run's head)."""
    return config_row(*read_run(run_dir), agent=agent)


def crashed_row(run_dir: Path) -> dict[str, Any]:
    """:func:`run_row` of a run the gate gave up on: status ``crashed``, 0 at every checkpoint it did not reach."""
    row = run_row(run_dir)
    return row | {k: 0.0 for k in row if k.startswith("reward_") and not math.isfinite(row[k])} | {"status": CRASHED}


def config_row(cfg: Mapping[str, Any], rows: Sequence[Mapping[str, Any]], agent: str | None = None) -> dict[str, Any]:
    """:func:`run_row` of a run's config and metrics rows (:func:`read_run`)."""
    cpu = float(rows[-1]["cpu_time_s"]) if rows else 0.0
    plan = sum(float(r.get("plan_cpu_s", "nan")) for r in rows)
    budget = cfg.get("max_env_steps") or BUDGET
    return episodes_row(cfg["env"], agent or cfg["head"], int(cfg["seed"]), rows, full_length(cfg), budget, cpu, plan)


def episodes_row(
    env: str,
    agent: str,
    seed: int,
    rows: Sequence[Mapping[str, Any]],
    length: int,
    budget: int,
    cpu_s: float,
    plan_cpu_s: float,
) -> dict[str, Any]:
    """The :data:`RUN_COLUMNS` row of one run's episodes (metrics rows: ``env_steps`` cumulative,
    ``episode_reward``, ``episode_length``, ``terminated``)."""
    steps = int(float(rows[-1]["env_steps"])) if rows else 0
    falls = [int(float(r["terminated"])) for r in rows]
    row = {
        "env": env,
        "agent": agent,
        "seed": seed,
        "env_steps": steps,
        "episodes": len(rows),
        "fall_fraction": round(float(np.mean(falls)), 4) if falls else math.nan,
        "cpu_hours": round(cpu_s / 3600, 4),
        "plan_cpu_hours": round(plan_cpu_s / 3600, 4),
        "status": "complete" if steps >= budget else "partial",
    }
    for n in CHECKPOINTS:
        row[f"reward_{n // 1000}k"] = endpoint(rows, n, length) if steps >= n else math.nan
    return row


def reference_row(ref: Reference) -> dict[str, Any]:
    """The :data:`RUN_COLUMNS` row of a reference run (SAC, mbrl-lib: :mod:`pets.experiments.gate_references`),
    complete at its own budget where it has one."""
    import envs

    length = envs.get(ref.env).episode_length
    return episodes_row(ref.env, ref.agent, ref.seed, ref.rows, length, ref.budget or BUDGET, ref.cpu_s, ref.plan_cpu_s)


def reference_curve(ref: Reference) -> list[dict[str, Any]]:
    """:func:`curve_rows` of a reference run, keyed by env, agent and seed."""
    import envs

    key = {"env": ref.env, "agent": ref.agent, "seed": ref.seed}
    return curve_rows(key, ref.rows, envs.get(ref.env).episode_length)


def endpoint_budget(runs: Sequence[Mapping[str, Any]]) -> int:
    """Where an agent's endpoint is read: the gate's budget, or for a reference whose every run is complete at a
    smaller registered budget (mbrl-lib: 50k env steps) the last checkpoint all of them reached."""
    if not all(r["status"] == "complete" for r in runs):
        return BUDGET
    steps = [int(float(r["env_steps"])) for r in runs]
    if min(steps) >= BUDGET:
        return BUDGET
    reached = [n for n in CHECKPOINTS if n <= min(steps)]
    return reached[-1] if reached else BUDGET


def summary_rows(runs: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Per (env, agent): the endpoint at its budget (:func:`endpoint_budget`) over its runs (mean, IQM with a
    bootstrap CI) and, for the gate's agent ``delta``, the verdict by the pre-registered rule (the mean over the
    seeds reaches the threshold; a run with no endpoint or crashed counts as 0, the worst outcome). ``partial``
    while a run is short of the budget."""
    from pets.experiments.report import csv_number
    from pets.experiments.statistics import iqm_ci

    out = []
    for env, agent in dict.fromkeys((r["env"], r["agent"]) for r in runs):
        mine = [r for r in runs if r["env"] == env and r["agent"] == agent]
        at = endpoint_budget(mine)
        final = np.array([csv_number(r[f"reward_{at // 1000}k"]) for r in mine], dtype=np.float64)
        partial = any(r["status"] not in ("complete", CRASHED) for r in mine)
        scores = np.where(np.isfinite(final), final, 0.0)  # a complete run without an endpoint: the worst
        point, low, high = iqm_ci(scores[:, None]) if not partial else ([math.nan],) * 3
        threshold = THRESHOLDS.get(env, math.nan)
        if partial:
            verdict = "partial"
        elif agent != "delta" or math.isnan(threshold):
            verdict = ""
        else:
            verdict = "passed" if scores.mean() >= threshold else "not passed"
        out.append(
            {
                "env": env,
                "agent": agent,
                "n_runs": len(mine),
                "endpoint_at": at,
                "mean": float(scores.mean()) if not partial else math.nan,
                "iqm": float(point[0]),
                "ci_low": float(low[0]),
                "ci_high": float(high[0]),
                "threshold": threshold,
                "verdict": verdict,
            }
        )
    return out


_ABSENT = object()


def pilot_row(run_dir: Path) -> dict[str, Any]:
    """A pilot's row: its name, the keys where its config differs from the locomotion preset's (at the pilot's own
    env and head), the endpoint at the env steps it reached and at each checkpoint, its CPU-hours."""
    from pets.config import all_keys, make_config

    cfg, rows = read_run(run_dir)
    preset = make_config(cfg["env"], cfg["head"], "locomotion")
    differs = []
    for key in all_keys(preset):
        if key in ("seed", "threads", "device") or key.endswith("precision") or key.endswith("compile"):
            continue
        mine: Any = cfg
        for part in key.split("."):
            mine = mine.get(part, _ABSENT) if isinstance(mine, dict) else _ABSENT
        theirs = preset
        for part in key.split("."):
            theirs = theirs[part]
        if mine is not _ABSENT and mine != theirs:  # absent: a key added to the code after the run (its default)
            differs.append(f"{key}={mine}")
    base = run_row(run_dir)
    steps = base["env_steps"]
    return {
        "run": run_dir.name,
        "env": base["env"],
        "head": base["agent"],
        "seed": base["seed"],
        "overrides": " ".join(differs),
        "env_steps": steps,
        "reward_last5": endpoint(rows, steps, full_length(cfg)) if rows else math.nan,
        **{k: base[k] for k in RUN_COLUMNS if k.startswith("reward_")},
        "fall_fraction": base["fall_fraction"],
        "cpu_hours": base["cpu_hours"],
        "plan_cpu_hours": base["plan_cpu_hours"],
    }


ORACLE_COLUMNS = [
    "env",
    "source",
    "planner",
    "candidates",
    "population",
    "horizon",
    "iterations",
    "termination_penalty",
    "terminal_value",
    "episode",
    "steps",
    "reward",
    "fell",
]


def oracle_rows(path: Path) -> list[dict[str, Any]]:
    """The episodes of one ``pets.oracle --json`` file (MPC with the true simulator): the gate's ceiling and the
    evidence its planner settings were chosen on. The env is in the file's name (``ENV_...json``)."""
    import json

    try:
        data = json.loads(path.read_text())
        p, episodes = data["planner"], data["episodes"]
    except (ValueError, KeyError, TypeError):  # not JSON, another JSON, not text (UnicodeDecodeError is a ValueError)
        raise ValueError(f"{path} is not a pets.oracle --json file (its planner and episodes)") from None
    return [
        {
            "env": path.stem.split("_")[0],
            "source": path.stem,
            "planner": p["name"],
            "candidates": p.get("candidates", "open_loop"),
            "population": p["population"],
            "horizon": p["horizon"],
            "iterations": p["iterations"],
            "termination_penalty": float(p.get("termination_penalty", 0.0)),  # absent: written before the setting
            "terminal_value": Path(data["value_from"]).name if data.get("value_from") else "",  # --value-from RUN
            "episode": i,
            "steps": e["steps"],
            "reward": float(e["reward"]),
            "fell": int(bool(e["terminated"])),
        }
        for i, e in enumerate(episodes)
    ]


def ceiling(rows: Sequence[Mapping[str, Any]]) -> dict[str, float]:
    """Per env, the mean reward of the true-dynamics episodes run with the locomotion preset's planner settings
    (the env's own entries of the preset included), termination penalty included; never with a run's learned
    terminal value (``pets.oracle --value-from``: the value is not the simulator's)."""
    from pets.config import make_config

    out: dict[str, list[float]] = {}
    planners = {env: make_config(env, "delta", "locomotion").planner for env in {r["env"] for r in rows}}
    for r in rows:
        p = planners[r["env"]]
        setting = (r["planner"], r.get("candidates", "open_loop"), r["population"], r["horizon"], r["iterations"],
                   r["termination_penalty"])  # fmt: skip
        if not r.get("terminal_value") and setting == (p.name, p.candidates, p.population, p.horizon, p.iterations,
                                                      p.termination_penalty):  # fmt: skip
            out.setdefault(r["env"], []).append(float(r["reward"]))
    return {env: float(np.mean(values)) for env, values in out.items()}


CURVE_COLUMNS = ["env", "agent", "seed", "env_steps", "reward"]
PILOT_CURVE_COLUMNS = ["run", "env", "env_steps", "reward"]


def curve_rows(key: Mapping[str, Any], rows: Sequence[Mapping[str, Any]], length: int) -> list[dict[str, Any]]:
    """One run's learning curve (its :func:`endpoint` on :mod:`pets.experiments.curves`' grid up to the budget or
    the steps it reached), each point a row that starts with ``key`` (the run's columns)."""
    reached = min(int(float(rows[-1]["env_steps"])) if rows else 0, BUDGET)
    points = window_points(lambda n: endpoint(rows, n, length), reached)
    return [dict(key, env_steps=n, reward=r) for n, r in points]


def run_curve(run_dir: Path, pilot: bool = False, head: str = "agent") -> list[dict[str, Any]]:
    """:func:`curve_rows` of a run directory: keyed by env, its head (under the column ``head``) and seed, or
    (``pilot``) by its name."""
    cfg, rows = read_run(run_dir)
    key = {"run": run_dir.name, "env": cfg["env"]} if pilot else {"env": cfg["env"], head: cfg["head"],
                                                                 "seed": int(cfg["seed"])}  # fmt: skip
    return curve_rows(key, rows, full_length(cfg))


#: The ``--replace`` help of the commands that write a study's runs tables from run directories.
REPLACE_HELP = (
    "write only the runs given (default: merge them into the committed tables, keeping the rows of runs whose "
    "directories are not given, e.g. finished on a machine since replaced, and a run's committed rows while its "
    "directory given has fewer env steps, e.g. started again under its name)"
)


#: One file :func:`main` writes: ``(path, rows, columns, the key columns whose committed rows it replaces)``.
Write = tuple[Path, list[dict[str, Any]], list[str], Sequence[str]]


def _outputs(args: Any, keep: Sequence[str]) -> tuple[list[Write], list[dict[str, Any]]]:
    """What :func:`main` writes, read from every input first, and the rows it prints; ValueError (one line) for an
    input that is not what its option takes."""
    writes: list[Write] = []
    if args.oracle:
        oracle = [row for path in args.oracle for row in oracle_rows(path)]
        writes.append(
            (Path(f"{args.out}_oracle.csv"), oracle, ORACLE_COLUMNS, () if args.replace else ("env", "source"))
        )
    if not (args.run_dirs or args.crashed or args.sac or args.peer):
        return writes, []
    if args.pilots:
        rows = [pilot_row(d) for d in args.run_dirs]
        curves = [c for d in args.run_dirs for c in run_curve(d, pilot=True)]
        writes.append((args.out.with_suffix(".csv"), rows, list(rows[0]), keep))
        return [*writes, (Path(f"{args.out}_curves.csv"), curves, PILOT_CURVE_COLUMNS, keep)], rows
    refs = [sac_run(path) for path in args.sac] + [r for path in args.peer for r in peer_runs(path)]
    rows = [run_row(d) for d in args.run_dirs] + [crashed_row(d) for d in args.crashed]
    rows += [reference_row(r) for r in refs]
    runs = [*args.run_dirs, *args.crashed]
    curves = [c for d in runs for c in run_curve(d)] + [c for r in refs for c in reference_curve(r)]
    writes.append((Path(f"{args.out}_runs.csv"), rows, RUN_COLUMNS, keep))
    return [*writes, (Path(f"{args.out}_curves.csv"), curves, CURVE_COLUMNS, keep)], rows


def main(argv: list[str] | None = None) -> int:
    from pets.tools.cli import OneLineParser

    p = OneLineParser(prog="pets.experiments.gate", description=__doc__.splitlines()[0])
    p.add_argument("run_dirs", nargs="*", type=Path, help="online run directories (run_pets.py --out)")
    crashed = "runs given up on (crashed or diverged, cannot go on): the worst outcome, 0"
    p.add_argument("--crashed", nargs="*", type=Path, default=[], help=crashed)
    p.add_argument("--sac", nargs="*", type=Path, default=[], help="SAC data sets (pets.collect --policy sac:STEPS)")
    p.add_argument("--peer", nargs="*", type=Path, default=[], help="mbrl-lib runs (peer_mbrl.py learn CSVs)")
    p.add_argument("--out", type=Path, required=True, help="output prefix (see above)")
    p.add_argument("--oracle", nargs="*", type=Path, default=[], help="pets.oracle --json files: OUT_oracle.csv")
    p.add_argument("--pilots", action="store_true", help="pilot runs: one OUT.csv row per run with its overrides")
    p.add_argument("--replace", action="store_true", help=REPLACE_HELP + "; likewise the rows of --oracle files")
    args = p.parse_args(argv)
    keep = () if args.replace else ("run",) if args.pilots else ("env", "agent", "seed")
    if not (args.run_dirs or args.crashed or args.sac or args.peer or args.oracle):
        p.error("give run directories, --sac data sets, --peer CSVs or --oracle files")
    if args.pilots and args.crashed:
        p.error("--crashed is for the gate's runs, not --pilots")
    if set(args.run_dirs) & set(args.crashed):
        p.error("a run directory is given both as a run and as --crashed; give it once")
    missing = [str(d) for d in [*args.run_dirs, *args.crashed] if not (d / "config.yaml").is_file()]
    missing += [str(path) for path in [*args.sac, *args.peer, *args.oracle] if not path.is_file()]
    if missing:
        p.error(f"not run directories (no config.yaml) or files: {', '.join(missing)}")
    try:  # every input read before anything is written: a bad one is one line and leaves the files as they were
        writes, rows = _outputs(args, keep)
    except ValueError as err:
        p.error(str(err))
    for path, out_rows, columns, keys in writes:
        write_rounded_csv(path, out_rows, columns, keys)
    for r in rows:
        print("  ".join(f"{k}={cell_text(v)}" for k, v in r.items()), file=sys.stdout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
