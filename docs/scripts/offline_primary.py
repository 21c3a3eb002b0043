"""The pre-registered offline primary endpoint (docs/experiments.md) of committed runs CSVs.

    python docs/scripts/offline_primary.py docs/results/paper_*_runs.csv --out docs/results/offline_primary

Reads per-run rows (``prediction_runs.csv`` of ``pets.compare offline``, committed as
``docs/results/paper_ENV_runs.csv``) and writes ``OUT.csv`` (:data:`pets.experiments.studies.primary.PRIMARY_COLUMNS`,
Holm over every (env, arm) test of the call) and ``OUT_past_level.csv`` (how models fail, per horizon), and prints
the table. ``--versus gem-se:gem`` adds ``OUT_versus.csv``: one arm against another on the same endpoint
(``pets.experiments.studies.primary.versus_rows``, secondary). The data sets are not in the repository, so the level is
sqrt(2) (``level_source`` says so); a fresh ``pets.compare offline`` computes it from its data, and
``--levels PRIMARY.csv ...`` takes each env's level from such a study's own ``primary.csv`` (its delta row), so
that runs of studies summarised apart get one Holm step with the levels their studies computed.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

from pets.experiments.studies.primary import read_primary, write_primary_files


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", type=Path, help="per-run CSVs (env, model, seed, horizon, standardized_error)")
    p.add_argument("--out", type=Path, required=True, help="output prefix: OUT.csv and OUT_past_level.csv")
    p.add_argument("--models", help="comma-separated models to keep (default: all; delta is always kept)")
    p.add_argument(
        "--versus",
        action="append",
        default=[],
        metavar="MODEL:OTHER",
        help="secondary: MODEL against OTHER on the primary endpoint (e.g. gem-se:gem), into OUT_versus.csv",
    )
    p.add_argument(
        "--levels",
        nargs="+",
        type=Path,
        default=[],
        metavar="PRIMARY.csv",
        help="primary.csv files whose delta rows give each env's no-information level (default: sqrt(2))",
    )
    args = p.parse_args(argv)
    comparisons = [tuple(v.split(":")) for v in args.versus]
    if any(len(c) != 2 or not all(c) for c in comparisons):
        p.error(f"--versus takes MODEL:OTHER such as gem-se:gem, got {args.versus}")
    keep = None if args.models is None else {"delta", *args.models.split(",")}
    rows = []
    for path in args.runs:
        if not path.is_file():
            p.error(f"{path} does not exist")
        rows += [r for r in csv.DictReader(open(path)) if keep is None or r["model"] in keep]
    levels = {}
    for path in args.levels:
        try:
            primary_file = read_primary(path)
        except ValueError as e:
            p.error(str(e))
        for r in primary_file:
            if r["model"] == "delta":
                levels[r["env"]] = (r["level"], r["level_source"])
    primary, versus = write_primary_files(rows, args.out, levels, comparisons)
    if comparisons:
        for r in versus:
            print(
                f"{r['env']:>18} {r['model']:>10} / {r['versus']:<10} ratio {r['ratio']:.3f} "
                f"[{r['ratio_ci_low']:.3f}, {r['ratio_ci_high']:.3f}] n={r['n_pairs']} lower in {r['n_lower']} "
                f"p={r['p_value_exact']:.4f} (secondary, no Holm)"
            )
    for r in primary:
        if r["model"] != "delta":
            print(
                f"{r['env']:>18} {r['model']:>16} h={r['tracking_horizons']:<12} "
                f"ratio {r.get('ratio_to_delta', float('nan')):.3f} "
                f"[{r.get('ratio_ci_low', float('nan')):.3f}, {r.get('ratio_ci_high', float('nan')):.3f}] "
                f"n={r.get('n_pairs', 0):<3} p={r.get('p_value_exact', float('nan')):.4f} "
                f"holm={r.get('p_value_holm', float('nan')):.4f} {r['verdict']}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
