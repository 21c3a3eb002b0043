"""Paired comparison of two arms of an online study on any per-run column, from its ``summary_runs.csv``.

The online summary compares every arm with ``delta`` on the final reward; this prints, for the columns asked
(``final_reward``, ``auc``, ...), the IQM of the per-seed difference ARM - BASELINE with its 95 %
stratified-bootstrap CI, P(ARM's value > BASELINE's) with its CI, and how many seeds have the arm higher, from
the same rliable functions the summaries use (`pets.experiments.statistics`). Diverged runs are left out of the
difference and count as the worst value in P.

    python docs/scripts/online_paired.py docs/results/activation_reacher_fast_5seeds_runs.csv delta-relu delta \
        final_reward auc
"""

import csv
import math
import sys

import numpy as np

from pets.experiments.statistics import iqm_ci, p_improvement_ci


def main(path: str, arm: str, baseline: str, *columns: str) -> None:
    with open(path, newline="") as f:
        rows = [r for r in csv.DictReader(f) if r["model"] in (arm, baseline)]
    missing = [c for c in columns if not rows or c not in rows[0]]
    if missing:
        sys.exit(f"{path}: no rows of {arm}/{baseline} with the column(s) {', '.join(missing)}")
    value = {(r["model"], int(r["seed"])): r for r in rows}
    seeds = sorted({s for m, s in value if m == arm} & {s for m, s in value if m == baseline})
    print(f"{path}: {arm} - {baseline}, {len(seeds)} paired seeds")
    print("| column | difference IQM [95 % CI] | seeds' min-max | P(higher) [CI] | seeds higher |")
    print("|---|---|---|---|---|")
    for column in columns:

        def get(model: str, seed: int, col: str = column) -> float:
            r = value[model, seed]
            return -math.inf if r["diverged"] or not r[col] else float(r[col])

        x = np.array([get(arm, s) for s in seeds])
        y = np.array([get(baseline, s) for s in seeds])
        both = np.isfinite(x) & np.isfinite(y)
        diff = (x - y)[both]
        d, d_low, d_high = iqm_ci(diff[:, None])
        p, p_low, p_high = p_improvement_ci(x, y, higher_is_better=True)
        print(
            f"| {column} | {d[0]:+.3g} [{d_low[0]:+.3g}, {d_high[0]:+.3g}] | {diff.min():+.3g} to {diff.max():+.3g} "
            f"| {p[0]:.2f} [{p_low[0]:.2f}, {p_high[0]:.2f}] | {int((diff > 0).sum())} of {diff.size} |"
        )


if __name__ == "__main__":
    if len(sys.argv) < 5:
        sys.exit(__doc__)
    main(*sys.argv[1:])
