"""The A/B intervals' cost: rliable's ``get_interval_estimates`` against :mod:`pets.stats.stratified`, same numbers.

Times both on the shapes the studies use (an IQM over 5 seeds of one column, as the gate's and online
summaries take it; over 5, 10 and 15 seeds of 40 columns, as an offline summary's horizons and metrics; a
probability of improvement of 5 runs against 5), :data:`pets.experiments.statistics.REPS` replications, process
CPU seconds, the median of ``--repeat`` runs each, and checks that the two give the same numbers bit for bit::

    python docs/scripts/bench_bootstrap.py [--repeat 3]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
from rliable import library

from pets.experiments.statistics import REPS, p_lower_columns
from pets.runs.hardware import cpu_name
from pets.stats.bootstrap import iqm_columns
from pets.stats.stratified import stratified_percentile_ci


def _cpu(call, *args, **kwargs) -> tuple[float, object]:
    start = time.process_time()
    out = call(*args, **kwargs)
    return time.process_time() - start, out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    cases = {"IQM, 5 runs x 1 column": ([rng.gamma(2.0, 1.0, size=(5, 1))], iqm_columns)}
    for n in (5, 10, 15):
        cases[f"IQM, {n} runs x 40 columns"] = ([rng.gamma(2.0, 1.0, size=(n, 40))], iqm_columns)
    cases["P(improvement), 5 vs 5 runs x 40 columns"] = (
        [rng.normal(size=(5, 40)), rng.normal(size=(5, 40))],
        p_lower_columns,
    )
    print(f"{cpu_name()}, {REPS} replications, median of {args.repeat} (process CPU s)")
    for name, (arrays, func) in cases.items():
        theirs, ours = [], []
        for _ in range(args.repeat):
            np.random.seed(0)
            scores = arrays[0] if len(arrays) == 1 else arrays
            t, (point, interval) = _cpu(library.get_interval_estimates, {"k": scores}, func, reps=REPS)
            theirs.append(t)
            np.random.seed(0)
            t, mine = _cpu(stratified_percentile_ci, arrays, func, reps=REPS, confidence=0.95)
            ours.append(t)
            same = all(np.array_equal(a, b) for a, b in zip(mine, (point["k"], *interval["k"])))
        a, b = statistics.median(theirs), statistics.median(ours)
        print(f"{name}: rliable {a:.3f}, all at once {b:.4f}, {a / b:.0f}x; the same numbers: {same}")


if __name__ == "__main__":
    main()
