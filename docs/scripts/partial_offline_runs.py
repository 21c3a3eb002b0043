"""Snapshot of an offline study still running: one row per finished run and horizon, from each run's eval.json.

    python docs/scripts/partial_offline_runs.py OUT_DIR SNAPSHOT.csv

Not a summary (no statistics: a study's numbers are read only when it is complete); it keeps the finished runs'
errors in the repository while the study runs. Columns: run, env, model, data (its test file name, which names
the data set), seed, horizon and the eval.json errors of that horizon.
"""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

METRICS = ("standardized_error", "translation_error", "rotation_error", "velocity_error", "nonfinite_fraction")


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print(__doc__.split("\n\n")[1].strip(), file=sys.stderr)
        return 2
    out, snapshot = Path(argv[0]), Path(argv[1])
    rows = []
    for path in sorted((out / "runs").glob("*/eval.json")):
        e = json.loads(path.read_text())
        for h, errors in e["horizons"].items():
            base = {"run": path.parent.name, "env": e["env"], "model": e["model"], "data": Path(e["data"]).name}
            rows.append({**base, "seed": e["seed"], "horizon": int(h), **{m: errors.get(m) for m in METRICS}})
    with open(snapshot, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["run", "env", "model", "data", "seed", "horizon", *METRICS])
        writer.writeheader()
        writer.writerows(rows)
    print(f"{snapshot}: {len({r['run'] for r in rows})} finished runs")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
