"""``pets.compare online --estimate``: the sweep's CPU-hours projected on this machine before anything runs.

Per arm of each env (the seeds cost alike) one short measurement with the run's own config, at the sweep's
threads: the planning step's process-CPU seconds (:func:`pets.tools.bench.time_rows`, the median of
:data:`PLAN_STEPS` steps of a briefly fitted model) and, for a fixed training schedule (``model.iterations`` > 0),
one gradient step's (two trainings of :data:`TRAIN_STEPS` steps, eager). Projection per run still to do (a resumed one
counts what is left of it): planned env steps (the budget, or trials x episode length: episodes that end early
cost less) x the step, plus the trainings the schedule makes x ``model.iterations`` x the gradient step. Training by
epochs with early stopping (``model.iterations=0``) grows with the data and is not projected. Not counted: the
terminal value's fit, the simulator, start-up (a few % at the locomotion preset: docs/planning.md).
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig

from pets.experiments.studies.online import online_rows

PLAN_STEPS, TRAIN_STEPS = 3, 20


def plan_seconds(cfg: DictConfig, parts: Mapping[str, Any]) -> float:
    """Median process-CPU seconds of one planning step of ``cfg``'s agent on ``parts``' model."""
    from pets.tools.bench import time_rows

    (row,) = time_rows(cfg, [("estimate", {})], repeats=PLAN_STEPS, parts=dict(parts))
    return float(row["cpu_seconds_per_step"])


def train_step_seconds(cfg: DictConfig, parts: Mapping[str, Any]) -> float:
    """Median process-CPU seconds of one gradient step of ``cfg``'s trainer on ``parts``' random transitions."""
    from pets import builder

    trainer = builder.make_trainer(cfg, parts["model"])
    trainer.compile, trainer.iterations = False, TRAIN_STEPS
    obs, act, nxt = parts["data"]
    gen = torch.Generator(device=obs.device).manual_seed(cfg.seed)
    times = []
    for _ in range(3):  # the first one warms up; each call also evaluates its holdout, as a real training does
        c0 = time.process_time()
        trainer.train(obs, act, nxt, gen)
        times.append((time.process_time() - c0) / TRAIN_STEPS)
    parts["model"].eval()
    return statistics.median(times[1:])


def prepare(cfg: DictConfig) -> dict[str, Any]:
    """:func:`pets.tools.bench.prepare` with its random transitions kept for the training measurement."""
    from pets.data.rollout import collect_random
    from pets.tools.bench import prepare as bench_prepare

    parts = bench_prepare(cfg)
    data = collect_random(parts["spec"], 400, cfg.seed)
    parts["data"] = tuple(torch.as_tensor(x, device=parts["device"]) for x in data)
    return parts


def run_shape(cfg: DictConfig, episode_length: int, steps_done: int = 0) -> tuple[int, int | None]:
    """``(planned env steps left, gradient steps left or None)`` of a run that has ``steps_done`` env steps
    (seed data included); None: training by epochs, not projected."""
    planned = cfg.trials * episode_length
    if cfg.max_env_steps is not None:
        planned = min(planned, cfg.max_env_steps - cfg.seed_steps)
    left = max(0, planned - max(0, steps_done - cfg.seed_steps))
    if cfg.model.iterations == 0:
        return left, None
    trainings = (left // cfg.train_every if cfg.train_every else 0) + (
        -(-left // episode_length) if cfg.train_after_trial else 0
    )
    return left, trainings * cfg.model.iterations


def estimate(
    configs: Mapping[str, DictConfig],
    actions: Mapping[str, str],
    out: Path,
    workers: int | None,
    measure: Callable[[DictConfig], tuple[float, float | None]] | None = None,
) -> str:
    """The projection's table and total, for the runs of ``actions`` that are not reused; the wall time on
    ``workers`` local workers (None: a Ray cluster, whose parallelism the driver does not know). ``measure(cfg)`` gives
    ``(planning CPU-s per step, CPU-s per gradient step or None)`` (default: measured now, once per env and arm)."""
    import envs
    from pets.experiments.report import fmt, md_table

    measured: dict[str, tuple[float, float | None]] = {}
    rows: dict[str, list[Any]] = {}
    for name, cfg in configs.items():
        if actions.get(name, "start") == "reuse":
            continue
        key = name.rsplit("-s", 1)[0]  # the run's env and arm (pets.experiments.rundirs.run_name)
        if key not in measured:
            measured[key] = (measure or _measure)(cfg)
        plan_s, grad_s = measured[key]
        length = cfg.episode_length or envs.get(cfg.env).episode_length
        run_dir = out / "runs" / name
        done = int(online_rows(run_dir)[-1]["env_steps"]) if actions.get(name) == "resume" else 0
        steps, grads = run_shape(cfg, length, done)
        train_h = None if grads is None or grad_s is None else grads * grad_s / 3600
        acc = rows.setdefault(key, [0, 0, 0.0, 0.0, grads is None])
        acc[0] += 1
        acc[1] += steps
        acc[2] += steps * plan_s / 3600
        acc[3] += train_h or 0.0
    if not rows:
        return "nothing to run: every run of the sweep is complete (reused)"
    header = ["env and arm", "runs to do", "planned env steps", "planning CPU-h", "training CPU-h", "CPU-h"]
    body, total = [], 0.0
    for key, (n, steps, plan_h, train_h, epochs) in rows.items():
        total += plan_h + train_h
        plan_s, grad_s = measured[key]
        body.append([key, str(n), f"{steps:,}", f"{fmt(plan_h, 3)} ({fmt(plan_s, 3)} s a step)",
                     "not projected (epochs)" if epochs else f"{fmt(train_h, 3)} ({fmt(grad_s, 3)} s a step)",
                     fmt(plan_h + train_h, 3)])  # fmt: skip
    runs = sum(r[0] for r in rows.values())
    wall = "" if workers is None else f" ({fmt(total / min(workers, runs), 3)} h of wall time on {workers} worker(s))"
    unprojected = "; training by epochs not included" if any(r[4] for r in rows.values()) else ""
    return (
        f"{md_table(header, body)}\n\n{runs} runs, about {fmt(total, 3)} CPU-hours{wall}, measured on this machine "
        f"now{unprojected}; training measured eager (model.compile makes it faster); the value fit, the simulator "
        "and start-up not counted; episodes that end early cost less"
    )


def _measure(cfg: DictConfig) -> tuple[float, float | None]:
    parts = prepare(cfg)
    plan_s = plan_seconds(cfg, parts)
    return plan_s, (train_step_seconds(cfg, parts) if cfg.model.iterations > 0 else None)
