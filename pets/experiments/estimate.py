"""``pets.compare online --estimate``: the sweep's CPU-hours projected on this machine before anything runs.

Per arm of each env (the seeds cost alike) one short measurement with the run's own config, at the sweep's
threads: the process-CPU seconds (on CUDA the wall seconds) of a planning step (:func:`pets.tools.bench.time_rows`,
the median of :data:`PLAN_STEPS` steps of a briefly fitted model) and, for a fixed training schedule
(``model.iterations`` > 0), of a gradient step (two trainings of :data:`TRAIN_STEPS` steps, eager). Projection per
run still to do (a resumed one counts what is left of it): planned env steps (the budget, or trials x episode
length: episodes that end early cost less) / ``planner.replan_every`` x the step, plus the trainings the schedule
makes x ``model.iterations`` x the gradient step. Training by epochs with early stopping (``model.iterations=0``) grows
with the data and is not projected. Not counted: the terminal value's fit, the simulator, start-up (a few % at the
locomotion preset: docs/planning.md).
"""

from __future__ import annotations

import statistics
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig

from pets.experiments.arguments import PROG
from pets.experiments.report import fmt, md_table
from pets.experiments.studies.online import online_rows

PLAN_STEPS, TRAIN_STEPS = 3, 20


def plan_seconds(cfg: DictConfig, parts: Mapping[str, Any]) -> float:
    """Median seconds of one planning step of ``cfg``'s agent on ``parts``' model: process CPU on a CPU, wall
    (synchronised) on CUDA, where the device does the work."""
    from pets.tools.bench import time_rows

    (row,) = time_rows(cfg, [("estimate", {})], repeats=PLAN_STEPS, parts=dict(parts))
    return float(row["cpu_seconds_per_step" if parts["device"].type == "cpu" else "seconds_per_step"])


def train_step_seconds(cfg: DictConfig, parts: Mapping[str, Any]) -> float:
    """Median seconds (as :func:`plan_seconds` counts them) of one gradient step of ``cfg``'s trainer on ``parts``'
    random transitions (``data``)."""
    from pets import builder
    from pets.tools.measure import sync

    device = parts["device"]
    clock = time.process_time if device.type == "cpu" else time.perf_counter
    trainer = builder.make_trainer(cfg, parts["model"])
    trainer.compile, trainer.iterations = False, TRAIN_STEPS
    obs, act, nxt = parts["data"]
    gen = torch.Generator(device=device).manual_seed(cfg.seed)
    times = []
    for _ in range(3):  # the first one warms up; each call also evaluates its holdout, as a real training does
        sync(device)
        t0 = clock()
        trainer.train(obs, act, nxt, gen)
        sync(device)
        times.append((clock() - t0) / TRAIN_STEPS)
    parts["model"].eval()
    return statistics.median(times[1:])


def run_shape(
    cfg: DictConfig, episode_length: int, steps_done: int = 0, trials_done: int = 0
) -> tuple[int, int | None]:
    """``(planned env steps left, gradient steps left or None)`` of a run that has ``trials_done`` trials and
    ``steps_done`` env steps (seed data included); None: training by epochs, not projected. What is left is its
    trials to do at ``episode_length`` each (episodes that ended early do not make the next ones longer), within
    its env-step budget if it has one."""
    left = max(0, cfg.trials - trials_done) * episode_length
    if cfg.max_env_steps is not None:
        left = min(left, max(0, cfg.max_env_steps - max(steps_done, cfg.seed_steps)))
    if cfg.model.iterations == 0:
        return left, None
    trainings = (left // cfg.train_every if cfg.train_every else 0) + (
        -(-left // episode_length) if cfg.train_after_trial else 0
    )
    return left, trainings * cfg.model.iterations


@dataclass
class ArmCost:
    """The projection of one env and arm: the measured seconds per step and what its runs still do."""

    plan_s: float
    grad_s: float | None
    runs: int = 0
    steps: int = 0
    grads: int | None = 0  # None: training by epochs (not projected)
    replan_every: int = 1  # the agent plans once per this many env steps

    @property
    def plan_h(self) -> float:
        return -(-self.steps // self.replan_every) * self.plan_s / 3600

    @property
    def train_h(self) -> float:
        return 0.0 if self.grads is None or self.grad_s is None else self.grads * self.grad_s / 3600

    def row(self, key: str) -> list[str]:
        train = (
            "not projected (epochs)"
            if self.grads is None
            else f"{fmt(self.train_h, 3)} ({fmt(self.grad_s, 3)} s a step)"
        )
        return [key, str(self.runs), f"{self.steps:,}", f"{fmt(self.plan_h, 3)} ({fmt(self.plan_s, 3)} s a step)",
                train, fmt(self.plan_h + self.train_h, 3)]  # fmt: skip


def estimate(
    configs: Mapping[str, DictConfig],
    actions: Mapping[str, str],
    out: Path,
    workers: int | None,
    measure: Callable[[DictConfig], tuple[float, float | None]] | None = None,
) -> str:
    """The projection's table and total, for the runs of ``actions`` that are not reused; the wall time on
    ``workers`` local workers (None: a Ray cluster, whose parallelism the driver does not know). ``measure(cfg)`` gives
    ``(seconds per planning step, per gradient step or None)`` (default: measured now, once per env and arm)."""
    import envs
    from pets import builder

    arms: dict[str, ArmCost] = {}
    unit = "CPU-h"
    for name, cfg in configs.items():
        if actions.get(name, "start") == "reuse":
            continue
        key = name.rsplit("-s", 1)[0]  # the run's env and arm (pets.experiments.rundirs.run_name)
        if key not in arms:
            print(f"{PROG} --estimate: measuring {key} (a few planning and gradient steps)", file=sys.stderr)
            arms[key] = ArmCost(*(measure or _measure)(cfg), replan_every=cfg.planner.replan_every)
        if builder.resolve_device(cfg.device).type == "cuda":
            unit = "hours"  # the device's wall time, as measured there
        length = cfg.episode_length or envs.get(cfg.env).episode_length
        rows = online_rows(out / "runs" / name) if actions.get(name) == "resume" else []
        steps, grads = run_shape(cfg, length, int(rows[-1]["env_steps"]) if rows else 0, len(rows))
        arm = arms[key]
        arm.runs, arm.steps = arm.runs + 1, arm.steps + steps
        arm.grads = None if grads is None or arm.grads is None else arm.grads + grads
    if not arms:
        return "nothing to run: every run of the sweep is complete (reused)"
    long_unit = "CPU-hours" if unit == "CPU-h" else "hours (on CUDA: wall time)"
    header = ["env and arm", "runs to do", "planned env steps", f"planning {unit}", f"training {unit}", unit]
    total = sum(a.plan_h + a.train_h for a in arms.values())
    runs = sum(a.runs for a in arms.values())
    wall = "" if workers is None else f" ({fmt(total / min(workers, runs), 3)} h of wall time on {workers} worker(s))"
    notes = ["training by epochs not included"] if any(a.grads is None for a in arms.values()) else []
    if any(a.grads is not None for a in arms.values()):
        notes.append("training measured eager (model.compile makes it faster)")
    table = md_table(header, [a.row(k) for k, a in arms.items()])
    return (
        f"{table}\n\n{runs} run{'' if runs == 1 else 's'}, about {fmt(total, 3)} {long_unit}{wall}, "
        f"measured on this machine now; {'; '.join(notes)}; the value fit, the simulator and start-up not counted; "
        "episodes that end early cost less"
    )


def _measure(cfg: DictConfig) -> tuple[float, float | None]:
    from pets.tools.bench import prepare

    parts = prepare(cfg)  # its model fitted on random transitions, which the training measurement reuses
    plan_s = plan_seconds(cfg, parts)
    return plan_s, (train_step_seconds(cfg, parts) if cfg.model.iterations > 0 else None)
