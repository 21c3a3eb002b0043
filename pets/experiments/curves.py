"""Learning curves as committed rows, and figures drawn from those rows only.

A curve is the gate's moving window (the mean return of the last 5 complete episodes,
:func:`pets.experiments.gate.endpoint`) on a grid of env steps: one CSV row per point, so a figure of the locomotion
gate or of the online locomotion study regenerates from ``docs/results`` without the run directories.
"""

from __future__ import annotations

from collections.abc import Callable, Container, Iterable, Mapping
from pathlib import Path

import numpy as np

#: The grid: every ``GRID_EVERY`` env steps from ``GRID_FROM`` (the online study's AUC is the mean over it).
GRID_FROM, GRID_EVERY = 10_000, 1_000

#: ``{env: {label: {member: [(env steps, reward), ...]}}}``: a label is one line of a figure (an arm or a run),
#: its members the seeds averaged into it.
Curves = dict[str, dict[str, dict[str, list[tuple[int, float]]]]]


def window_points(
    value: Callable[[int], float], until: int, start: int = GRID_FROM, every: int = GRID_EVERY
) -> list[tuple[int, float]]:
    """``(n, value(n))`` every ``every`` env steps ``n`` from ``start`` to ``until``; ``value``: a run's moving window
    at ``n`` env steps (:func:`pets.experiments.gate.endpoint`)."""
    return [(n, value(n)) for n in range(start, until + 1, every)]


def group_curves(rows: Iterable[Mapping[str, str]], label: str, member: str) -> Curves:
    """Committed curve rows (``env``, ``env_steps``, ``reward`` and the columns ``label`` and ``member``) grouped
    as :data:`Curves`, in the rows' order."""
    from pets.experiments.report import csv_number

    out: Curves = {}
    for r in rows:
        points = out.setdefault(r["env"], {}).setdefault(r[label], {}).setdefault(r[member], [])
        points.append((int(r["env_steps"]), csv_number(r["reward"])))
    return out


def complete_curves(runs: Path, points: Path, label: str, keep: Container[str] | None = None) -> Curves:
    """The committed curve rows ``points`` of the runs that ``runs`` (one row per run: ``env``, ``label``, ``seed``,
    ``status``) marks complete, of the labels in ``keep`` if given, as :data:`Curves` by ``label`` and seed."""
    from pets.experiments.report import read_csv_rows

    def key(r: Mapping[str, str]) -> tuple[str, str, str]:
        return r["env"], r[label], r["seed"]

    wanted = [r for r in read_csv_rows(runs) if keep is None or r[label] in keep]
    done = {key(r) for r in wanted if r["status"] == "complete"}
    return group_curves((r for r in read_csv_rows(points) if key(r) in done), label, "seed")


def paired_members(curves: Curves) -> Curves:
    """``curves`` with each env's lines cut to the members (seeds) that every line of the env has: while a paired
    study runs, its arms are drawn over the same seeds."""
    out: Curves = {}
    for env, lines in curves.items():
        common = set.intersection(*(set(members) for members in lines.values())) if lines else set()
        out[env] = {label: {m: p for m, p in members.items() if m in common} for label, members in lines.items()}
    return out


def plot_curves(
    path: Path,
    curves: Curves,
    *,
    thresholds: Mapping[str, float],
    ceiling: Mapping[str, float],
    first: str = "",
    ylabel: str = "return, last 5 episodes",
    references: Curves | None = None,
) -> None:
    """One panel per env, one line per label: the mean over its members with a 95 % bootstrap band (members
    resampled as whole curves; a single member's band is its own line), ``thresholds`` dashed and ``ceiling``
    (the true-dynamics MPC) dotted. ``first``: the label drawn first (the baseline). ``references``: other agents'
    curves (e.g. SAC's from the gate) drawn as the mean over their members, thin and dash-dotted, in the panels of
    ``curves``' envs only."""
    from pets.experiments.plots import figure_bytes, model_colors, pyplot
    from pets.experiments.report import BOOT_SEED
    from pets.runs.fileio import atomic_write_bytes
    from pets.stats.bootstrap import bootstrap_band

    plt = pyplot()
    n = max(len(curves), 1)
    fig, axes = plt.subplots(1, n, figsize=(6 * n, 4), squeeze=False)
    for ax, (env, lines) in zip(axes[0], curves.items()):
        colors = model_colors(list(lines))
        for label in sorted(lines, key=lambda name: name != first):
            members = lines[label]
            steps, values = _curve_matrix(members)
            low, high = bootstrap_band(values, seed=BOOT_SEED)
            ax.plot(steps / 1000, values.mean(axis=0), color=colors[label], label=f"{label} (n={len(values)})")
            ax.fill_between(steps / 1000, low, high, color=colors[label], alpha=0.2, lw=0)
        for label, members in (references or {}).get(env, {}).items():
            steps, values = _curve_matrix(members)
            ax.plot(steps / 1000, values.mean(axis=0), color="k", ls="-.", lw=1, label=f"{label} (n={len(members)})")
        if env in thresholds:
            ax.axhline(thresholds[env], color="k", ls="--", lw=1, label="gate threshold")
        if env in ceiling:
            ax.axhline(ceiling[env], color="tab:gray", ls=":", lw=1, label="true-dynamics MPC (no value)")
        ax.set(title=env, xlabel="env steps (thousands)", ylabel=ylabel)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    atomic_write_bytes(path, figure_bytes(fig))


def _curve_matrix(members: Mapping[str, list[tuple[int, float]]]) -> tuple[np.ndarray, np.ndarray]:
    """``(env steps, values (members, points))`` over the steps every member reached (runs cut at different steps:
    the common part)."""
    length = min(len(points) for points in members.values())
    steps = np.array([n for n, _ in next(iter(members.values()))[:length]])
    return steps, np.array([[v for _, v in points[:length]] for points in members.values()])
