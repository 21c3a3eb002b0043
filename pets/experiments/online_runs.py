"""An online run's numbers from its metrics.csv: final reward, AUC, divergence, time to its env's reward threshold,
cost (:mod:`pets.experiments.online_summary` gathers them into the statistics over seeds).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

#: Reward thresholds of the time-to-threshold columns (``docs/performance.md``): InvertedPendulum's maximum
#: (1000 = balanced for the whole 1000-step episode), Reacher -5 (near the target for most of the episode)
#: and HalfCheetah 1000 at the fast preset (a steady forward gait; PETS' research config reaches ~10x that).
THRESHOLDS: dict[str, float] = {
    "invertedpendulum": 1000.0,
    "inverteddoublependulum": 9000.0,  # issue 16's mark; a full 1000-step episode earns about 9,350
    "reacher": -5.0,
    "halfcheetah": 1000.0,
    # The Ant study's mark (docs/results.md, fixed before its runs): 500 in a 300-step episode, about 1 m/s of
    # forward speed on top of the healthy reward; the true-dynamics planner reaches ~2,300 there.
    "ant": 500.0,
}
#: The time-to-threshold columns of a run (:func:`time_to_threshold`).
THRESHOLD_KEYS = ("minutes_to_threshold", "steps_to_threshold", "cpu_minutes_to_threshold")
#: Cost columns of a run: their mean over the complete runs of an arm (``KEY_mean``).
COST_KEYS = ("env_steps", "wall_time_s", "cpu_time_s", "plan_seconds_per_step")


def online_rows(run_dir: Path) -> list[dict[str, float]]:
    """The metrics rows of a run directory (empty if it has none yet)."""
    from pets.runs import rundir

    path = run_dir / rundir.METRICS_FILE
    return rundir.read_metrics(path) if path.is_file() else []


def reward_divergence(rows: Sequence[Mapping[str, float]]) -> str | None:
    """Why a run counts as diverged (its first non-finite episode reward), or None."""
    for i, r in enumerate(rows):
        v = float(r["episode_reward"])
        if not math.isfinite(v):
            return f"episode_reward {v} at trial {int(r.get('trial', i))}"
    return None


def time_to_threshold(rows: Sequence[Mapping[str, float]], threshold: float | None) -> dict[str, float]:
    """{:data:`THRESHOLD_KEYS`: value} at the end of the first trial whose episode reward is >= ``threshold``:
    ``wall_time_s`` / 60, ``env_steps`` and ``cpu_time_s`` / 60 of that row (NaN for a run without the CPU
    column); NaN for all when no trial reaches it or there is no threshold."""
    if threshold is not None:
        for r in rows:
            if float(r["episode_reward"]) >= threshold:
                cpu = float(r.get("cpu_time_s", math.nan))
                return dict(zip(THRESHOLD_KEYS, (float(r["wall_time_s"]) / 60.0, float(r["env_steps"]), cpu / 60.0)))
    return dict.fromkeys(THRESHOLD_KEYS, math.nan)


def online_run_stats(
    rows: Sequence[Mapping[str, float]], trials: int, final_window: int, threshold: float | None = None
) -> dict[str, Any]:
    """Per-run numbers from the first ``trials`` metrics rows: diverged (:func:`reward_divergence`: None or
    why), final (mean of the last ``final_window`` episode rewards), auc (mean episode reward over all
    trials), the :data:`THRESHOLD_KEYS` (:func:`time_to_threshold`), env_steps, wall_time_s (the run's
    wall-clock seconds: planning, simulation and model training), cpu_time_s (its process CPU seconds; NaN for a
    run without the column) and
    plan_seconds_per_step (median over the planned trials; 0 if every trial was random)."""
    use = list(rows)[:trials]
    to_threshold = time_to_threshold(use, threshold)
    rewards = np.array([r["episode_reward"] for r in use], dtype=np.float64)
    w = min(final_window, len(use))
    planned = [r["plan_seconds_per_step"] for r in use if r.get("plan_seconds_per_step", 0.0) > 0]
    with np.errstate(invalid="ignore"):  # inf - inf in a diverged run: NaN, reported as such
        final, auc = float(rewards[-w:].mean()), float(rewards.mean())
    return {
        "diverged": reward_divergence(use),
        "final_reward": final,
        "auc": auc,
        **to_threshold,
        "env_steps": float(use[-1]["env_steps"]),
        "wall_time_s": float(use[-1]["wall_time_s"]),
        "cpu_time_s": float(use[-1].get("cpu_time_s", math.nan)),
        "plan_seconds_per_step": float(np.median(planned)) if planned else 0.0,
    }
