"""An offline study's summary recomputed from its committed per-run CSV, for studies whose run directories are gone.

    python docs/scripts/resummarise_offline.py docs/results/paper_ENV_runs.csv --out docs/results/paper_ENV \
        [--level 1.4142135623730951]

Writes ``OUT_summary.csv`` and ``OUT_relative_error.csv`` with today's columns (the exact sign-flip p and the note
where the bootstrap CI and the exact test disagree among them) by
``pets.experiments.studies.offline.summary_from_runs``, the statistics ``pets.compare offline`` computes from the
runs' eval.json files. The data sets are not in the repository, so the divergence rule's no-information level is
sqrt(2) unless given (a fresh ``pets.compare offline`` computes it from its data). Prints, per column both files
have, how many values changed against an existing ``OUT_summary.csv`` (the check that nothing else moved).
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from pathlib import Path

from pets.experiments.report import write_csv
from pets.experiments.studies.offline import RELATIVE_COLUMNS, SUMMARY_COLUMNS, summary_from_runs


def changed_columns(old: list[dict[str, str]], new: list[dict[str, str]]) -> dict[str, int]:
    """{column: values that differ (relative 1e-9; both empty is equal)} over the rows both files have."""
    key = ("env", "model", "horizon", "metric")
    before = {tuple(r[k] for k in key): r for r in old}
    counts: dict[str, int] = {}
    for r in new:
        o = before.get(tuple(str(r[k]) for k in key))
        if o is None:
            continue
        for col in set(o) & set(r):
            a, b = o[col], r[col]
            try:
                same = (a == b) or math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=1e-15)
            except ValueError:
                same = False
            counts[col] = counts.get(col, 0) + (not same)
    return counts


def read_rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", type=Path, help="per-run CSV (env, model, seed, horizon, starts, the error metrics)")
    p.add_argument("--out", type=Path, required=True, help="output prefix: OUT_summary.csv, OUT_relative_error.csv")
    p.add_argument("--level", type=float, default=math.sqrt(2), help="no-information level (default sqrt(2))")
    args = p.parse_args(argv)
    if not args.runs.is_file():
        p.error(f"{args.runs} does not exist")
    summary, relative = summary_from_runs(read_rows(args.runs), args.level)
    target = Path(f"{args.out}_summary.csv")
    old = read_rows(target) if target.is_file() else []
    write_csv(target, summary, SUMMARY_COLUMNS)
    write_csv(Path(f"{args.out}_relative_error.csv"), relative, RELATIVE_COLUMNS)
    new = read_rows(target)
    if old:
        moved = {c: n for c, n in sorted(changed_columns(old, new).items()) if n}
        print(f"{target}: {len(new)} rows; values changed against the file before: {moved or 'none'}")
    else:
        print(f"{target}: {len(new)} rows")
    return 0


if __name__ == "__main__":
    sys.exit(main())
