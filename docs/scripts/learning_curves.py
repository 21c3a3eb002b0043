"""Learning curves of offline runs: the holdout error against gradient steps, one panel per env.

    python docs/scripts/learning_curves.py STUDY_DIR/runs [MORE_DIR/runs ... CURVES.csv ...] --out FIGURE.png \
        [--csv CURVES.csv]

Reads every ``RUN/learning_curve.csv`` (offline runs trained with ``model.curve_every=N``) and keeps, per run,
the curve of the architecture the run selected (its ``config.yaml``); a ``.csv`` input is an earlier ``--csv``
output (the kept points of runs whose directories are gone), taken as it is. Plots one line per run, coloured by model;
``--csv`` writes the kept points (env, model, run, step, holdout_error) and prints, per env and model, the median
over runs of the last point's error relative to the error at 80 % of the steps: a value near 1 means the
validation error had stopped falling by the end of training.
"""

from __future__ import annotations

import argparse
import csv
import statistics
import sys
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

CURVE_FILE = "learning_curve.csv"


def run_curve(run: Path, cfg: DictConfig) -> list[tuple[int, float]]:
    """The ``(step, holdout_error)`` points of one run, of the architecture its config ``cfg`` selected."""
    arch = (int(cfg.model.hidden_size), int(cfg.model.num_layers))
    with open(run / CURVE_FILE) as f:
        rows = [r for r in csv.DictReader(f) if (int(r["hidden_size"]), int(r["num_layers"])) == arch]
    return [(int(r["step"]), float(r["holdout_error"])) for r in rows]


def collect(sources: list[Path]) -> list[dict]:
    """One entry per run with a learning curve: env, model (the config's head), run name, points; from runs/
    directories and from earlier ``--csv`` outputs (``.csv`` files)."""
    found = [c for src in sources if src.suffix == ".csv" for c in read_kept(src)]
    runs_dirs = [src for src in sources if src.suffix != ".csv"]
    for run in sorted(p.parent for runs_dir in runs_dirs for p in runs_dir.glob(f"*/{CURVE_FILE}")):
        cfg = OmegaConf.load(run / "config.yaml")
        found.append({"env": str(cfg.env), "model": str(cfg.head), "run": run.name, "points": run_curve(run, cfg)})
    return found


def read_kept(path: Path) -> list[dict]:
    """The curves of an earlier ``--csv`` output (env, model, run, step, holdout_error), one entry per run."""
    curves: dict[str, dict] = {}
    with open(path) as f:
        for r in csv.DictReader(f):
            c = curves.setdefault(r["run"], {"env": r["env"], "model": r["model"], "run": r["run"], "points": []})
            c["points"].append((int(r["step"]), float(r["holdout_error"])))
    return list(curves.values())


def late_ratio(points: list[tuple[int, float]]) -> float:
    """The last point's error over the error at the first point at or after 80 % of the steps."""
    last_step = points[-1][0]
    late = next(error for step, error in points if step >= 0.8 * last_step)
    return points[-1][1] / late


def plot(curves: list[dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    env_names = sorted({c["env"] for c in curves})
    models = sorted({c["model"] for c in curves})
    colours = {m: matplotlib.colormaps["tab10"](i) for i, m in enumerate(models)}
    ncols = min(4, len(env_names))  # rows of at most 4 panels
    nrows = -(-len(env_names) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(4.5 * ncols, 3.6 * nrows), squeeze=False)
    for ax in axes.flat[len(env_names) :]:
        ax.set_visible(False)
    for ax, env in zip(axes.flat, env_names):
        for c in (c for c in curves if c["env"] == env):
            steps, errors = zip(*c["points"])
            ax.plot(steps, errors, color=colours[c["model"]], alpha=0.7, lw=1)
        ax.set(title=env, xlabel="gradient steps", ylabel="holdout error (standardized, one step)", yscale="log")
    handles = [plt.Line2D([], [], color=colours[m], label=m) for m in models]
    axes[0][0].legend(handles=handles)
    fig.tight_layout()
    fig.savefig(out, dpi=120)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", type=Path, nargs="+", help="studies' runs/ directories or earlier --csv outputs")
    p.add_argument("--out", type=Path, required=True, help="the figure (PNG)")
    p.add_argument("--csv", type=Path, help="also write the points kept")
    args = p.parse_args(argv)
    curves = collect(args.runs)
    if not curves:
        where = ", ".join(map(str, args.runs))
        print(f"learning_curves: no {CURVE_FILE} under {where} (train with model.curve_every=N)", file=sys.stderr)
        return 2
    plot(curves, args.out)
    if args.csv:
        with open(args.csv, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["env", "model", "run", "step", "holdout_error"])
            for c in curves:
                w.writerows([c["env"], c["model"], c["run"], s, e] for s, e in c["points"])
    for env, model in sorted({(c["env"], c["model"]) for c in curves}):
        ratios = [late_ratio(c["points"]) for c in curves if (c["env"], c["model"]) == (env, model)]
        print(f"{env} {model}: {len(ratios)} runs, last / 80 % error, median {statistics.median(ratios):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
