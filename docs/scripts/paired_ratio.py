"""Paired comparison of any two models of an offline study, from its per-run CSV (``prediction_runs.csv``).

The study summaries compare every model with ``delta``; the paper compares GEM's models with the baseline's of
the same kind (single deterministic ``gem2-x1`` vs ``delta-det-x1``, the 5-member averages ``gem2`` vs
``delta-det``). This prints, per horizon, the IQM of the per-seed ratio MODEL / BASELINE with its 95 %
stratified-bootstrap CI and P(MODEL's error < BASELINE's) with its CI, from the same rliable functions the
summaries use (`pets.experiments.statistics`), plus the seeds' min-max ratio. Diverged runs (per horizon, the
summaries' rule) are left out of the ratio and count as the worst error in P.

    python docs/scripts/paired_ratio.py docs/results/paper_ant_runs.csv gem2-x1 delta-det-x1 rotation_error
"""

import csv
import math
import sys

import numpy as np

from pets.experiments.statistics import iqm_ci_finite, p_improvement_ci


def main(path: str, model: str, baseline: str, metric: str) -> None:
    with open(path, newline="") as f:
        rows = [r for r in csv.DictReader(f) if r["model"] in (model, baseline)]
    if not rows or metric not in rows[0]:
        sys.exit(f"{path}: no rows of {model}/{baseline} with a {metric} column")
    value = {}
    for r in rows:
        v = float(r[metric]) if r[metric] and not r["diverged"] else math.inf
        value[r["model"], int(r["seed"]), int(r["horizon"])] = v
    horizons = sorted({h for _, _, h in value})
    seeds = sorted({s for m, s, _ in value if m == model} & {s for m, s, _ in value if m == baseline})
    x = np.array([[value[model, s, h] for h in horizons] for s in seeds])
    y = np.array([[value[baseline, s, h] for h in horizons] for s in seeds])
    both = np.isfinite(x) & np.isfinite(y)
    ratio = np.where(both, x / np.where(both, y, 1.0), np.nan)
    r_iqm, r_low, r_high = iqm_ci_finite(ratio)
    p, p_low, p_high = p_improvement_ci(x, y)
    print(f"{path}: {model} / {baseline}, {metric}, {len(seeds)} paired seeds")
    print("| h | ratio IQM [95 % CI] | seeds' min-max | P(lower) [CI] | diverged (model, baseline) |")
    print("|---|---|---|---|---|")
    for j, h in enumerate(horizons):
        col = ratio[:, j][np.isfinite(ratio[:, j])]
        span = f"{col.min():.3g}-{col.max():.3g}" if col.size else "-"
        div = f"{int((~np.isfinite(x[:, j])).sum())}, {int((~np.isfinite(y[:, j])).sum())}"
        print(
            f"| {h} | {r_iqm[j]:.3g} [{r_low[j]:.3g}, {r_high[j]:.3g}] | {span} "
            f"| {p[j]:.2f} [{p_low[j]:.2f}, {p_high[j]:.2f}] | {div} |"
        )


if __name__ == "__main__":
    if len(sys.argv) != 5:
        sys.exit(__doc__)
    main(*sys.argv[1:])
