"""The locomotion gate's figures, drawn from its committed rows only (``pets.compare report``): the gate's runs and
the pilots' learning curves (``locomotion_gate_curves.csv``, ``locomotion_pilots_curves.csv``) and the true-dynamics
ceiling (``locomotion_oracle.csv``)."""

from __future__ import annotations

from pathlib import Path

from pets.experiments import gate
from pets.experiments.curves import Curves, complete_curves, group_curves, plot_curves
from pets.experiments.report import csv_number, read_csv_rows


def committed_ceiling(path: Path) -> dict[str, float]:
    """:func:`pets.experiments.gate.ceiling` of the committed ``locomotion_oracle.csv`` (empty without it)."""
    numbers = ("reward", "population", "horizon", "iterations", "termination_penalty")
    rows = read_csv_rows(path) if path.is_file() else []
    return gate.ceiling([dict(r, **{k: csv_number(r[k]) for k in numbers}) for r in rows])


def committed_curves(results: Path, agents: set[str] | None = None) -> Curves:
    """The gate's committed curves of its complete runs (``locomotion_gate_{runs,curves}.csv`` in ``results``; of
    ``agents`` only, if given) as :data:`pets.experiments.curves.Curves` by agent and seed; empty without them."""
    runs, points = results / "locomotion_gate_runs.csv", results / "locomotion_gate_curves.csv"
    return complete_curves(runs, points, "agent", agents) if runs.is_file() and points.is_file() else {}


def write_figures(results: Path, figures: Path) -> None:
    """``locomotion_gate.png`` (per env, each agent's complete runs: mean and 95 % band) and
    ``locomotion_pilots.png`` (one line per pilot) from the committed curve rows (``pets.compare report``)."""
    ceil = committed_ceiling(results / "locomotion_oracle.csv")
    ylabel = f"return, last {gate.WINDOW} episodes (95 % CI)"
    plot_curves(figures / "locomotion_gate.png", committed_curves(results), thresholds=gate.THRESHOLDS, ceiling=ceil,
                first="delta", ylabel=ylabel)  # fmt: skip
    pilots = group_curves(read_csv_rows(results / "locomotion_pilots_curves.csv"), "run", "run")
    plot_curves(figures / "locomotion_pilots.png", pilots, thresholds=gate.THRESHOLDS, ceiling=ceil,
                ylabel=f"return, last {gate.WINDOW} episodes")  # fmt: skip
