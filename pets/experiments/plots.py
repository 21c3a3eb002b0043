"""The comparison figures: reward curves, prediction error per horizon, relative error bars, open-loop rewards."""

from __future__ import annotations

import io
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pets.experiments.report import BOOT_SEED
from pets.experiments.statistics import bootstrap_band
from pets.fileio import atomic_write_bytes


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


def _figure_bytes(fig: Any) -> bytes:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()


def _pyplot() -> Any:
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
) -> None:
    """Episode reward vs env steps (or wall-clock time) per arm: mean over seeds on a common grid, bootstrap
    band (the grid: :mod:`pets.experiments.online_summary`)."""
    x_label, x_scale = ONLINE_X[x_key]
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for arm, seed_rows in runs.items():
        c = colors[arm]
        xs = [np.array([r[x_key] for r in rows]) * x_scale for rows in seed_rows]
        ys = [np.array([r["episode_reward"] for r in rows]) for rows in seed_rows]
        for x, y in zip(xs, ys):
            ax.plot(x, y, color=c, alpha=0.2, lw=0.8)
        lo, hi = max(x[0] for x in xs), min(x[-1] for x in xs)
        label = f"{arm} (n={len(seed_rows)})"
        if hi > lo:
            grid = np.linspace(lo, hi, 200)
            curves = np.stack([np.interp(grid, x, y) for x, y in zip(xs, ys)])
            band_low, band_high = bootstrap_band(curves, seed=BOOT_SEED)
            ax.plot(grid, curves.mean(axis=0), color=c, lw=2, label=label)
            ax.fill_between(grid, band_low, band_high, color=c, alpha=0.25, lw=0)
        else:  # one trial, or seeds whose ranges do not overlap: the final points only
            finals = np.array([y[-1] for y in ys])
            ax.errorbar(
                [np.mean([x[-1] for x in xs])],
                [finals.mean()],
                yerr=[[finals.mean() - finals.min()], [finals.max() - finals.mean()]],
                color=c,
                marker="o",
                capsize=4,
                label=label,
            )
    ax.set_xlabel(x_label)
    ax.set_ylabel("episode reward")
    ax.set_title(f"{env}: episode reward (mean over seeds, 95 % bootstrap CI)", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    atomic_write_bytes(path, _figure_bytes(fig))


def plot_absolute(path: Path, env: str, curves: Mapping[str, tuple[Sequence[int], Mapping[int, Mapping]]]) -> None:
    """Fig. 3: mean step-wise error vs horizon per model with CI bands (log y if it spans a factor >= 10)."""
    plt = _pyplot()
    colors = model_colors(list(curves))
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    values = []
    for model, (hs, st) in curves.items():
        mean = np.array([st[h]["mean"] for h in hs])
        low, high = np.array([st[h]["ci_low"] for h in hs]), np.array([st[h]["ci_high"] for h in hs])
        n = st[hs[0]]["n"] if hs else 0
        ax.plot(hs, mean, marker="o", color=colors[model], label=f"{model} (n={n})")
        ax.fill_between(hs, low, high, color=colors[model], alpha=0.25, lw=0)
        values += [v for v in np.concatenate([mean, low, high]) if math.isfinite(v) and v > 0]
    if values and max(values) / min(values) >= 10:
        ax.set_yscale("log")
    ax.set_xlabel("prediction horizon (steps)")
    ax.set_ylabel("mean step-wise error")
    ax.set_title(f"{env}: prediction error (mean over seeds, 95 % bootstrap CI)", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend()
    fig.tight_layout()
    atomic_write_bytes(path, _figure_bytes(fig))


def plot_relative(path: Path, relative: Mapping[str, Mapping[str, Mapping[str, float]]]) -> None:
    """Fig. 2: per env a group of bars (one per model), normalised by the env's largest mean error."""
    plt = _pyplot()
    env_list = list(relative)
    models = list(dict.fromkeys(m for vals in relative.values() for m in vals))
    colors = model_colors(models)
    width = 0.8 / max(len(models), 1)
    fig, ax = plt.subplots(figsize=(max(5.0, 1.6 * len(env_list) + 2), 4.5))
    for j, model in enumerate(models):
        xs, heights, errs = [], [], [[], []]
        for i, env in enumerate(env_list):
            vals = relative[env]
            if model not in vals:
                continue
            finite = [v["mean"] for v in vals.values() if math.isfinite(v["mean"])]
            top = max(finite) if finite else math.nan
            s = vals[model]
            h = s["mean"] / top if math.isfinite(s["mean"]) else math.nan
            xs.append(i - 0.4 + width * (j + 0.5))
            heights.append(h)
            lo, hi = s["ci_low"] / top, s["ci_high"] / top
            errs[0].append(max(h - lo, 0.0) if math.isfinite(lo) else 0.0)
            errs[1].append(max(hi - h, 0.0) if math.isfinite(hi) else 0.0)
        ax.bar(xs, heights, width, yerr=errs, capsize=3, color=colors[model], label=model)
    ax.set_xticks(range(len(env_list)), env_list)
    ax.axhline(1.0, color="grey", lw=0.8, ls="--")
    ax.set_ylabel("relative step-wise error (worst model = 1)")
    ax.set_title("Prediction error averaged over horizons, relative to the worst model", fontsize=10)
    ax.legend()
    fig.tight_layout()
    atomic_write_bytes(path, _figure_bytes(fig))


def plot_openloop(
    path: Path, env: str, panels: Mapping[str, Mapping[str, np.ndarray]], colors: Mapping[str, Any]
) -> None:
    """Open-loop reward per step, one panel per planner: per model the mean over seeds (rows of each
    ``(n_seeds, steps)`` array) with the bootstrap band."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4), squeeze=False)
    for ax, (planner, by_model) in zip(axes[0], panels.items()):
        for model, curves in by_model.items():
            steps = np.arange(1, curves.shape[1] + 1)
            low, high = bootstrap_band(curves, seed=BOOT_SEED)
            ax.plot(steps, curves.mean(axis=0), color=colors[model], label=f"{model} (n={len(curves)})")
            ax.fill_between(steps, low, high, color=colors[model], alpha=0.25, lw=0)
        ax.set_title(f"{env}, {planner}: open-loop reward per step", fontsize=10)
        ax.set_xlabel("step")
        ax.set_ylabel("reward (mean over seeds, 95 % CI)")
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    atomic_write_bytes(path, _figure_bytes(fig))
