"""The comparison figures: reward curves, prediction error per horizon, relative error bars, open-loop rewards."""

from __future__ import annotations

import io
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pets.experiments.report import BOOT_SEED, csv_number
from pets.experiments.statistics import BASELINE, REPS, iqm_ci
from pets.experiments.studies.base import RATIO
from pets.runs.fileio import atomic_write_bytes
from pets.stats.bootstrap import bootstrap_band


def model_colors(models: Sequence[str]) -> dict[str, Any]:
    """A fixed colour per model (its index in ``pets.config.HEADS``), so that every figure agrees."""
    import matplotlib

    from pets import config

    cmap = matplotlib.colormaps["tab10"]
    order = list(config.HEADS) + [m for m in models if m not in config.HEADS]
    return {m: cmap(order.index(m) % 10) for m in models}


def arm_colors(labels: Sequence[str]) -> dict[str, Any]:
    """A colour per compared arm, in order (``tab10``)."""
    import matplotlib

    cmap = matplotlib.colormaps["tab10"]
    return {label: cmap(i % 10) for i, label in enumerate(labels)}


def figure_bytes(fig: Any) -> bytes:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()


def pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


#: x axis of the online plots: metrics column -> (axis label, scale applied to the column).
ONLINE_X = {"env_steps": ("environment steps", 1.0), "wall_time_s": ("wall-clock hours of the run", 1 / 3600)}


def plot_online(
    path: Path,
    env: str,
    runs: Mapping[str, Sequence[Sequence[Mapping[str, float]]]],
    colors: Mapping[str, Any],
    x_key: str = "env_steps",
    diverged: Mapping[str, int] | None = None,
    *,
    reps: int = REPS,
) -> None:
    """Episode reward vs env steps (or wall-clock time) per arm: the IQM over seeds at each point of a common
    grid with its 95 % stratified-bootstrap CI band (:func:`pets.experiments.statistics.iqm_ci`, one call
    per arm with the 200 grid points as columns, all :data:`~pets.experiments.statistics.REPS`
    replications: about 0.2 s per arm and figure for 5 seeds on 2 busy CPU cores; the grid:
    :mod:`pets.experiments.studies.online`), each seed's raw curve faintly behind. ``runs``: {arm: the
    metrics rows of each seed that did not diverge} (an empty list: every run diverged); ``diverged``:
    {arm: diverged runs}, counted in the legend, never plotted."""
    x_label, x_scale = ONLINE_X[x_key]
    diverged = diverged or {}
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for arm, seed_rows in runs.items():
        c = colors[arm]
        label = _n_label(arm, len(seed_rows), diverged.get(arm, 0))
        if not seed_rows:
            ax.plot([], [], color=c, label=f"{label}: no curve")
            continue
        xs = [np.array([r[x_key] for r in rows]) * x_scale for rows in seed_rows]
        ys = [np.array([r["episode_reward"] for r in rows]) for rows in seed_rows]
        for x, y in zip(xs, ys):
            ax.plot(x, y, color=c, alpha=0.2, lw=0.8)
        lo, hi = max(x[0] for x in xs), min(x[-1] for x in xs)
        if hi > lo:
            grid = np.linspace(lo, hi, 200)
            curves = np.stack([np.interp(grid, x, y) for x, y in zip(xs, ys)])
            mid, band_low, band_high = iqm_ci(curves, reps=reps, seed=BOOT_SEED)
            ax.plot(grid, mid, color=c, lw=2, label=label)
            ax.fill_between(grid, band_low, band_high, color=c, alpha=0.25, lw=0)
        else:  # one trial, or seeds whose ranges do not overlap: the final points only
            (mid,), (low,), (high,) = iqm_ci(np.array([[y[-1]] for y in ys]), reps=reps, seed=BOOT_SEED)
            ax.errorbar(
                [np.mean([x[-1] for x in xs])],
                [mid],
                yerr=[[max(mid - low, 0.0)], [max(high - mid, 0.0)]],
                color=c,
                marker="o",
                capsize=4,
                label=label,
            )
    ax.set_xlabel(x_label)
    ax.set_ylabel("episode reward")
    ax.set_title(f"{env}: episode reward (IQM over seeds, 95 % stratified-bootstrap CI)", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    atomic_write_bytes(path, figure_bytes(fig))


def _n_label(model: str, n_seeds: int, n_diverged: int) -> str:
    """Legend label: the model with its seeds, and the diverged ones when there are any."""
    return f"{model} (n={n_seeds}{f', {n_diverged} diverged' if n_diverged else ''})"


def _nan(values: Sequence[float | None]) -> np.ndarray:
    return np.array([math.nan if v is None else v for v in values], dtype=np.float64)


def plot_absolute(path: Path, env: str, curves: Mapping[str, Mapping[str, Any]]) -> None:
    """Fig. 3: per model the IQM of the mean step-wise error vs horizon with its CI band (log y if the values
    span a factor >= 10). ``curves``: {model: {"horizons", "iqm", "ci_low", "ci_high", "n_runs", "n_diverged"}},
    ``n_diverged`` per horizon (the runs left out there, named in the legend)."""
    plt = pyplot()
    colors = model_colors(list(curves))
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    values = []
    for model, c in curves.items():
        hs, mid, low, high = c["horizons"], _nan(c["iqm"]), _nan(c["ci_low"]), _nan(c["ci_high"])
        diverged = [f"{k} at h={h}" for h, k in zip(hs, c["n_diverged"]) if k]
        label = f"{model} (n={c['n_runs']}{'; diverged: ' + ', '.join(diverged) if diverged else ''})"
        if not np.isfinite(mid).any():
            ax.plot([], [], color=colors[model], label=f"{label}: no value")
            continue
        ax.plot(hs, mid, marker="o", color=colors[model], label=label)
        ax.fill_between(hs, low, high, color=colors[model], alpha=0.25, lw=0)
        values += [v for v in np.concatenate([mid, low, high]) if math.isfinite(v) and v > 0]
    if values and max(values) / min(values) >= 10:
        ax.set_yscale("log")
    ax.set_xlabel("prediction horizon (steps)")
    ax.set_ylabel("mean step-wise error")
    ax.set_title(f"{env}: prediction error (IQM over seeds, 95 % stratified-bootstrap CI)", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    atomic_write_bytes(path, figure_bytes(fig))


def _grouped_points(
    ax: Any,
    rows: Mapping[str, Mapping[str, Mapping[str, Any]]],
    models: Sequence[str],
    keys: tuple[str, str, str],
    bars: bool,
) -> list[float]:
    """Per env a group with one bar (or point) per model at ``rows[env][model][keys[0]]`` with the CI
    ``keys[1:]`` as error bar; a model without a value gets a note instead. Returns the plotted values."""
    colors = model_colors(models)
    width = 0.8 / max(len(models), 1)
    plotted = []
    for j, model in enumerate(models):
        xs, mids, errs = [], [], [[], []]
        for i, env in enumerate(rows):
            r = rows[env].get(model)
            if r is None:
                continue
            x = i - 0.4 + width * (j + 0.5)
            mid, low, high = (r[k] for k in keys)
            if mid is None:
                why = "all diverged" if r["n_seeds"] == 0 else "n/a"
                ax.annotate(why, (x, 0.02), xycoords=("data", "axes fraction"), rotation=90, ha="center", fontsize=7)
                continue
            xs.append(x)
            mids.append(mid)
            errs[0].append(max(mid - low, 0.0) if low is not None else 0.0)
            errs[1].append(max(high - mid, 0.0) if high is not None else 0.0)
            plotted += [v for v in (mid, low, high) if v is not None]
            if r["n_diverged"]:
                top = high if high is not None else mid
                ax.annotate(
                    f"{r['n_diverged']} div.",
                    (x, top),
                    textcoords="offset points",
                    xytext=(0, 3),
                    ha="center",
                    fontsize=7,
                )
        label = model
        if bars:
            ax.bar(xs, mids, width, yerr=errs, capsize=3, color=colors[model], label=label)
        else:
            ax.errorbar(xs, mids, yerr=errs, fmt="o", capsize=4, color=colors[model], label=label)
    ax.set_xticks(range(len(rows)), list(rows))
    ax.set_xlim(-0.5, len(rows) - 0.5)  # every env's group inside the axes, notes ("all diverged") included
    return plotted


def _group_figsize(n_envs: int, n_models: int) -> tuple[float, float]:
    """Figure size of a grouped plot: about 0.3 inch per bar plus room for the legend; 6.5 to 16 inches wide."""
    return min(16.0, max(6.5, 3.5 + 0.3 * n_envs * max(n_models, 2))), 4.8


def _legend_outside(ax: Any) -> None:
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)


def plot_relative(path: Path, rows: Mapping[str, Mapping[str, Mapping[str, Any]]]) -> None:
    """Fig. 2 as the paper normalises it: per env one bar per model, the IQM over seeds of the error averaged
    over the env's tracking horizons divided by the env's largest model IQM (``rows[env][model]``:
    relative_error.csv rows), with the CI divided alike; diverged seeds are left out and counted above the bar."""
    plt = pyplot()
    models = list(dict.fromkeys(m for vals in rows.values() for m in vals))
    fig, ax = plt.subplots(figsize=_group_figsize(len(rows), len(models)))
    _grouped_points(ax, rows, models, ("relative", "relative_ci_low", "relative_ci_high"), bars=True)
    ax.axhline(1.0, color="grey", lw=0.8, ls="--")
    ax.set_ylabel("error / largest model's error")
    ax.set_title(
        "Prediction error averaged over the tracking horizons, relative to the worst model\n"
        "(IQM over seeds, 95 % CI; diverged seeds left out and counted)",
        fontsize=10,
    )
    _legend_outside(ax)
    fig.tight_layout()
    atomic_write_bytes(path, figure_bytes(fig))


def plot_ratio(path: Path, rows: Mapping[str, Mapping[str, Mapping[str, Any]]], baseline: str = "delta") -> None:
    """Fig. 2 as a paired ratio: per env and model (``baseline`` aside) the IQM over seeds of the per-seed ratio
    of the error averaged over the env's tracking horizons to ``baseline``'s, with its CI; a line at 1 (log y if
    the values span a factor >= 4)."""
    plt = pyplot()
    models = [m for m in dict.fromkeys(m for vals in rows.values() for m in vals) if m != baseline]
    fig, ax = plt.subplots(figsize=_group_figsize(len(rows), len(models)))
    values = _grouped_points(ax, rows, models, RATIO, bars=False)
    ax.axhline(1.0, color="grey", lw=1.0, ls="--")
    positive = [v for v in values if v > 0]
    if positive and max(positive) / min(positive) >= 4:
        ax.set_yscale("log")
    ax.set_ylabel(f"error / {baseline}'s error (paired by seed)")
    ax.set_title(
        f"Prediction error averaged over the tracking horizons, ratio to {baseline}\n"
        "(IQM over seeds of the per-seed ratio, 95 % CI; below 1: lower error)",
        fontsize=10,
    )
    ax.grid(alpha=0.3, axis="y", which="both")
    _legend_outside(ax)
    fig.tight_layout()
    atomic_write_bytes(path, figure_bytes(fig))


def plot_openloop(
    path: Path,
    env: str,
    panels: Mapping[str, Mapping[str, np.ndarray]],
    colors: Mapping[str, Any],
    kind: str = "open-loop",
) -> None:
    """Open-loop reward per step, one panel per planner: per model the mean over seeds (rows of each
    ``(n_seeds, steps)`` array) with the bootstrap band."""
    plt = pyplot()
    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4), squeeze=False)
    for ax, (planner, by_model) in zip(axes[0], panels.items()):
        for model, curves in by_model.items():
            steps = np.arange(1, curves.shape[1] + 1)
            low, high = bootstrap_band(curves, seed=BOOT_SEED)
            ax.plot(steps, curves.mean(axis=0), color=colors[model], label=f"{model} (n={len(curves)})")
            ax.fill_between(steps, low, high, color=colors[model], alpha=0.25, lw=0)
        ax.set_title(f"{env}, {planner}: {kind} reward per step", fontsize=10)
        ax.set_xlabel("step")
        ax.set_ylabel("reward (mean over seeds, 95 % CI)")
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    atomic_write_bytes(path, figure_bytes(fig))


def plot_headline_ratios(
    path: Path,
    offline: Mapping[str, Sequence[Mapping[str, str]]],
    model: str,
    metrics: Sequence[str],
    caption: str = "",
) -> None:
    """The paired ratio ``model`` / delta against the horizon, one line per env, one panel per metric of
    ``metrics``, from offline summary.csv rows (``{source: rows}``); ``caption`` under the panels (say where the runs
    were made)."""
    plt = pyplot()
    from matplotlib.ticker import NullFormatter, ScalarFormatter

    fig, axes = plt.subplots(1, len(metrics), figsize=(5.2 * len(metrics), 3.8), squeeze=False)
    for ax, metric in zip(axes[0], metrics):
        for rows in offline.values():
            for env in dict.fromkeys(r["env"] for r in rows):
                pts = sorted(
                    (
                        int(r["horizon"]),
                        *(csv_number(r[k]) for k in RATIO),
                    )
                    for r in rows
                    if r["env"] == env and r["model"] == model and r["metric"] == metric and r[RATIO[0]]
                )
                if not pts:
                    continue
                h, v, lo, hi = (list(x) for x in zip(*pts))
                yerr = [[a - b for a, b in zip(v, lo)], [b - a for a, b in zip(v, hi)]]
                ax.errorbar(h, v, yerr=yerr, marker="o", capsize=3, label=env)
        ax.axhline(1.0, color="grey", lw=0.8, ls="--")
        ax.set_xscale("log")
        ax.set_yscale("log")
        for axis in (ax.xaxis, ax.yaxis):
            axis.set_major_formatter(ScalarFormatter())
            axis.set_minor_formatter(NullFormatter())
        low, high = ax.get_ylim()
        ax.set_yticks([t for t in (0.1, 0.2, 0.3, 0.5, 0.7, 1, 1.5, 2, 3, 5, 10, 30, 100) if low <= t <= high])
        ax.set_ylim(low, high)
        ax.set_xticks(sorted({int(r["horizon"]) for rows in offline.values() for r in rows}))
        ax.set_xlabel("horizon (steps)")
        ax.set_ylabel(f"{model} / {BASELINE}, paired (IQM, 95 % CI)")
        ax.set_title(metric)
        ax.legend(fontsize=8)
    if caption:
        fig.text(0.01, 0.01, caption, fontsize=7, color="dimgrey")
    fig.tight_layout(rect=(0, 0.04 if caption else 0, 1, 1))
    atomic_write_bytes(path, figure_bytes(fig))
