"""Snapshot of an offline study still running: one row per finished run and horizon, from each run's eval.json.

    python docs/scripts/partial_offline_runs.py OUT_DIR SNAPSHOT.csv
    python docs/scripts/partial_offline_runs.py OUT_DIR SNAPSHOT.csv --summary DIR --envs E --models M --seeds S \
        [--data-seeds D]
    python docs/scripts/partial_offline_runs.py OUT_DIR SNAPSHOT.csv --levels LEVELS.csv

SNAPSHOT.csv keeps the rows it holds of data sets not under OUT_DIR (a study whose earlier data sets and runs
were made on a machine since replaced); the rows of a data set under OUT_DIR come from its runs there alone.
Columns of SNAPSHOT.csv: run, env, model (the run's head; an arm's label is in the run name), data (its test file
name, which names the data set), seed (the model's), horizon and
the eval.json errors of that horizon. With ``--summary DIR``: also the study's summary of the finished runs
(``pets.experiments.offline_summary.summarise_offline``: summary.csv, primary.csv, prediction.md, ...) written to
DIR, which links to OUT_DIR's runs and data and is the only place written; runs not finished yet are simply
absent, so a partial summary is labelled as such wherever it is quoted. It reads the runs and never trains, so it
also re-summarises a finished study with this checkout's code without risking its runs.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from omegaconf import OmegaConf

from pets.experiments.report import read_csv_rows, write_csv

METRICS = ("standardized_error", "translation_error", "rotation_error", "velocity_error", "nonfinite_fraction")


def write_runs(out: Path, snapshot: Path) -> tuple[list[dict], list[dict]]:
    """SNAPSHOT.csv from every finished run's eval.json, merged into the rows it holds: a committed row is kept
    where its data set (its test file) is not under OUT_DIR/data (made on a machine since replaced; a data set made
    here again replaces all of its rows, a withdrawn data set's runs with the new ones). Returns the rows of the
    runs under OUT_DIR and their eval.json contents."""
    rows, evals = [], []
    for path in sorted((out / "runs").glob("*/eval.json")):
        e = json.loads(path.read_text())
        evals.append(e)
        seed = OmegaConf.load(path.parent / "config.yaml").seed  # the model's seed (eval.json's is the evaluation's)
        for h, errors in e["horizons"].items():
            base = {"run": path.parent.name, "env": e["env"], "model": e["model"], "data": Path(e["data"]).name}
            rows.append({**base, "seed": seed, "horizon": int(h), **{m: errors.get(m) for m in METRICS}})
    kept = []
    if snapshot.is_file():
        kept = [r for r in read_csv_rows(snapshot) if not (out / "data" / r["data"]).is_file()]
    merged = sorted(kept + rows, key=lambda r: (r["run"], int(r["horizon"])))
    write_csv(snapshot, merged, ["run", "env", "model", "data", "seed", "horizon", *METRICS])  # atomic
    print(f"{snapshot}: {len({r['run'] for r in rows})} finished runs here, {len({r['run'] for r in kept})} kept")
    return rows, evals


def write_levels(out: Path, runs: list[dict], levels: Path) -> None:
    """LEVELS.csv (env, data_seed, level): the no-information level of every data set the finished runs were
    evaluated on (``pets.experiments.studies.primary.no_information_level``); rows of data sets not under OUT_DIR
    (made on a machine since replaced) are kept as they were."""
    import envs
    from pets.data.datasets import load_dataset
    from pets.experiments.studies.composition import LEVEL_COLUMNS, data_seed
    from pets.experiments.studies.primary import no_information_level

    kept = {}
    if levels.is_file():
        kept = {(r["env"], int(r["data_seed"])): r for r in read_csv_rows(levels)}
    for env, test in sorted({(r["env"], r["data"]) for r in runs}):
        train = out / "data" / test.replace("-test.npz", "-train.npz")
        layout = envs.get(env).layout
        level = no_information_level(load_dataset(train), load_dataset(out / "data" / test), layout)
        kept[(env, data_seed(test))] = {"env": env, "data_seed": data_seed(test), "level": level}
    write_csv(levels, [kept[k] for k in sorted(kept)], LEVEL_COLUMNS)  # atomic
    print(f"{levels}: {len(kept)} data sets")


def write_summary(
    out: Path, summary: Path, evals: list[dict], envs: str, models: str, seeds: str, data_seeds: str = "0"
) -> None:
    """The study's summary of its finished runs in ``summary`` (links to OUT_DIR's runs and data)."""
    from pets.experiments.offline_summary import summarise_offline

    if not evals:
        raise SystemExit(f"{out}: no finished run to summarise")
    summary.mkdir(parents=True, exist_ok=True)
    for part in ("runs", "data"):
        link = summary / part
        if not link.is_symlink():
            link.symlink_to((out / part).resolve(), target_is_directory=True)
    request = {k: v for k, v in evals[0]["request"].items() if k != "data"}  # the study's own evaluation request
    seed_list = [int(s) for s in seeds.split(",")]
    data_list = [int(d) for d in data_seeds.split(",")]
    summarise_offline(summary, envs.split(","), models.split(","), seed_list, request, data_seeds=data_list)
    print(f"{summary}: summary of the finished runs")


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="output directory of the running pets.compare offline")
    parser.add_argument("snapshot", type=Path, help="CSV to write: one row per finished run and horizon")
    parser.add_argument("--summary", type=Path, help="also write the summary of the finished runs here")
    parser.add_argument("--envs", help="with --summary: comma-separated envs")
    parser.add_argument("--models", help="with --summary: comma-separated models (arms)")
    parser.add_argument("--seeds", help="with --summary: comma-separated seeds")
    parser.add_argument("--data-seeds", default="0", help="with --summary: comma-separated data seeds (default 0)")
    parser.add_argument("--levels", type=Path, help="also write the no-information level of each data set here")
    args = parser.parse_args(argv)
    if args.summary and not (args.envs and args.models and args.seeds):
        parser.error("--summary needs --envs, --models and --seeds")
    rows, evals = write_runs(args.out, args.snapshot)
    if args.levels:
        write_levels(args.out, rows, args.levels)
    if args.summary:
        write_summary(args.out, args.summary, evals, args.envs, args.models, args.seeds, args.data_seeds)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
