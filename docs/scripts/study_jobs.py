"""The running studies' jobs still to do, from their committed rows, as lines of two queue files for
``docs/scripts/run_queue.sh`` (one per core), in each study's registered order: what a new sitting on a replaced
machine (its run directories gone) starts from.

    python docs/scripts/study_jobs.py --runs /work/runs --gate-worktree WT --composition-worktree WT [--write]

Core 1: the locomotion gate's ablation, then the online locomotion study's seeds upwards; core 2: the composition
study, then the online study's seeds downwards from 9 (an online seed is taken by one core only, its arms one after
another). What each study runs, in what order and from which commit is its ``DESIGN`` (:mod:`pets.experiments.design`;
``python -m pets.compare design`` lists it): this script only splits what the committed rows lack over the two
cores, and refuses a worktree that is not at its study's commit. Prints both files; ``--write`` writes
RUNS/next_core1.jobs and RUNS/next_core2.jobs (refused where one exists: a running queue reads its file as it goes).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

from pets.experiments.design import Design, Job
from pets.experiments.gate_published import DESIGN as ABLATION
from pets.experiments.studies.composition import DESIGN as COMPOSITION
from pets.experiments.studies.locomotion import DESIGN as ONLINE

ROOT = Path(__file__).resolve().parents[2]
KIND = {"pets": "pets", "compare": "cmd"}  # a job's kind -> its kind in a queue line (docs/scripts/run_queue.sh)


def line(job: Job, worktree: Path, runs: Path) -> str:
    """One queue line: the worktree it runs from, its directory, its kind and its command."""
    return f"{worktree}|{runs}/{job.folder}/{job.name}|{KIND[job.kind]}|{job.command(runs)}"


def check_pinned(design: Design, worktree: Path) -> None:
    """Exit with one line unless ``worktree`` is checked out at the design's commit."""
    head = subprocess.run(["git", "-C", str(worktree), "rev-parse", "HEAD"], capture_output=True, text=True)
    if head.returncode != 0 or not head.stdout.startswith(design.commit):
        found = head.stdout.strip()[:7] or "not a git worktree"
        sys.exit(f"study_jobs.py: {worktree} is at {found}, not at {design.name}'s commit {design.commit}: "
                 f"git worktree add --detach {worktree} {design.commit}")  # fmt: skip


def queues(runs: Path, gate_wt: Path, comp_wt: Path) -> tuple[list[str], list[str]]:
    """The two queue files' lines."""
    online = ONLINE.left(ROOT)
    seeds = sorted({job.seed for job in online})
    up, down = seeds[: (len(seeds) + 1) // 2], seeds[(len(seeds) + 1) // 2 :][::-1]
    core1 = [f"# core 1: the gate's ablation (issue {ABLATION.issue}), then the online study's seeds {up} "
             f"(issue {ONLINE.issue})"]  # fmt: skip
    core1 += [line(job, gate_wt, runs) for job in ABLATION.left(ROOT)]
    core2 = [f"# core 2: the composition study (issue {COMPOSITION.issue}), then the online study's seeds {down} "
             f"(issue {ONLINE.issue})"]  # fmt: skip
    core2 += [line(job, comp_wt, runs) for job in COMPOSITION.left(ROOT)]
    for lines, order in ((core1, up), (core2, down)):
        lines += [line(job, gate_wt, runs) for seed in order for job in online if job.seed == seed]
    return core1, core2


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=Path, default=Path("/work/runs"))
    parser.add_argument("--gate-worktree", type=Path, required=True, help=f"a worktree at {ABLATION.commit}")
    parser.add_argument("--composition-worktree", type=Path, required=True, help=f"a worktree at {COMPOSITION.commit}")
    parser.add_argument("--write", action="store_true", help="write RUNS/next_core{1,2}.jobs")
    args = parser.parse_args(argv)
    files = [args.runs / f"next_core{i}.jobs" for i in (1, 2)]
    existing = [str(path) for path in files if path.exists()]
    if args.write and existing:
        sys.exit(f"study_jobs.py: {', '.join(existing)} exists (a queue may be reading it); move it away first")
    for design, worktree in (
        (ABLATION, args.gate_worktree),
        (ONLINE, args.gate_worktree),
        (COMPOSITION, args.composition_worktree),
    ):
        check_pinned(design, worktree)
    for path, lines in zip(files, queues(args.runs, args.gate_worktree, args.composition_worktree)):
        text = "\n".join(lines) + "\n"
        if args.write:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
        print(f"== {path}\n{text}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
