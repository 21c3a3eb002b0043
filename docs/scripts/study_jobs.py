"""The running studies' jobs still to do, from their committed rows, as lines of two queue files for
``docs/scripts/run_queue.sh`` (one per core), in each study's registered order: what a new sitting on a replaced
machine (its run directories gone) starts from.

    python docs/scripts/study_jobs.py --runs /work/runs --gate-worktree WT --composition-worktree WT [--write]

Core 1: the locomotion gate's ablation (docs/studies/locomotion_gate.md: `delta` on HalfCheetah, seeds 100-102
seed-major, the full preset, `value.enabled=false`, `model.iterations=0`), then the online locomotion study's seeds
upwards (docs/studies/online_locomotion.md: per seed `gem-se`, `gem`, `delta`; on a planar env `delta-groupfeat` is
`gem`'s run). Core 2: the composition study's data sets (docs/studies/composition.md: Ant 1-2, then Humanoid 0-2,
each data set's seeds 0-4 with its four arms), then the online study's seeds downwards from 9. A run is done when its
row is complete (100k env steps; a composition run: its rows at every horizon); an online seed is taken by one core
only. Prints both files; ``--write`` writes RUNS/next_core1.jobs and RUNS/next_core2.jobs (refused where one exists:
a running queue reads its file as it goes).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pets.experiments.gate import BUDGET
from pets.experiments.report import read_csv_rows

RESULTS = Path(__file__).resolve().parents[2] / "docs" / "results"
ABLATION = {"v2": "", "novalue": "value.enabled=false", "epochs": "model.iterations=0"}
ONLINE_ARMS = ("gem-se", "gem", "delta")
COMPOSITION = [("ant", 1), ("ant", 2), ("humanoid", 0), ("humanoid", 1), ("humanoid", 2)]
COMPOSITION_ARMS = ("delta-groupfeat", "gem", "gem-se", "delta")


def ablation_left() -> list[tuple[str, int]]:
    """(arm, seed) of the ablation not yet at the budget, seed-major."""
    done = {r["run"] for r in read_csv_rows(RESULTS / "locomotion_pilots.csv") if float(r["env_steps"] or 0) >= BUDGET}
    return [(arm, s) for s in (100, 101, 102) for arm in ABLATION if f"halfcheetah-{arm}-s{s}" not in done]


def online_left() -> list[tuple[str, int]]:
    """(arm, seed) of the online study on HalfCheetah not yet complete, seed by seed."""
    done = {
        (r["model"], int(r["seed"]))
        for r in read_csv_rows(RESULTS / "online_locomotion_runs.csv")
        if r["status"] == "complete"
    }
    return [(arm, s) for s in range(10) for arm in ONLINE_ARMS if (arm, s) not in done]


def composition_left() -> list[tuple[str, int, int]]:
    """(env, data set, seed) of every data set of the composition study with an arm not yet evaluated: all its seeds,
    since a data set is made and run on one machine (the study's amendment of 2026-11-28; on the same machine the
    finished runs are reused, on a replaced one they run again with the data set)."""
    name = {0: "{env}-test.npz", 1: "{env}-d1-test.npz", 2: "{env}-d2-test.npz"}
    done = {(r["env"], r["model"], r["data"], int(r["seed"])) for r in read_csv_rows(RESULTS / "composition_runs.csv")}
    left = [
        (env, d)
        for env, d in COMPOSITION
        if any((env, m, name[d].format(env=env), s) not in done for m in COMPOSITION_ARMS for s in range(5))
    ]
    return [(env, d, s) for env, d in left for s in range(5)]  # fmt: skip


def queues(runs: Path, gate_wt: Path, comp_wt: Path) -> tuple[list[str], list[str]]:
    """The two queue files' lines."""
    online = online_left()
    seeds = sorted({s for _, s in online})
    up, down = seeds[: (len(seeds) + 1) // 2], seeds[(len(seeds) + 1) // 2 :][::-1]
    core1 = [f"# core 1: the gate's ablation (issue 56), then the online study's seeds {up} (issue 52)"]
    for arm, s in ablation_left():
        extra = f" {ABLATION[arm]}" if ABLATION[arm] else ""
        core1.append(f"{gate_wt}|{runs}/pilots/halfcheetah-{arm}-s{s}|pets|--env halfcheetah --model delta "
                     f"--preset locomotion --seed {s} threads=1{extra}")  # fmt: skip
    core2 = [f"# core 2: the composition study (issue 53), then the online study's seeds {down} (issue 52)"]
    for env, d, s in composition_left():
        core2.append(f"{comp_wt}|{runs}/composition/{env}-d{d}-s{s}|cmd|python -m pets.compare offline --envs {env} "
                     f"--models delta-groupfeat,gem,gem-se,delta --seeds {s} --data-seeds {d} --policy sac "
                     f"--protocol paper --workers 1 --threads 1 --out {runs}/composition/results")  # fmt: skip
    for lines, order in ((core1, up), (core2, down)):
        for s in order:
            for arm in (a for a, seed in online if seed == s):
                lines.append(f"{gate_wt}|{runs}/online/halfcheetah-{arm}-s{s}|pets|--env halfcheetah --model {arm} "
                             f"--preset locomotion --seed {s} threads=1")  # fmt: skip
    return core1, core2


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=Path, default=Path("/work/runs"))
    parser.add_argument("--gate-worktree", type=Path, required=True, help="a worktree at the gate's commit 1f6591b")
    parser.add_argument("--composition-worktree", type=Path, required=True, help="a worktree at 975e50e")
    parser.add_argument("--write", action="store_true", help="write RUNS/next_core{1,2}.jobs")
    args = parser.parse_args(argv)
    files = [args.runs / f"next_core{i}.jobs" for i in (1, 2)]
    existing = [str(path) for path in files if path.exists()]
    if args.write and existing:
        sys.exit(f"study_jobs.py: {', '.join(existing)} exists (a queue may be reading it); move it away first")
    for path, lines in zip(files, queues(args.runs, args.gate_worktree, args.composition_worktree)):
        text = "\n".join(lines) + "\n"
        if args.write:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
        print(f"== {path}\n{text}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
