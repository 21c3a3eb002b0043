"""An honest cost: the run's remaining time estimated from its first planning steps, one line when it is long.

:class:`CostEstimate` watches the planning time of the first trial planned in a session. After
:data:`WARMUP_STEPS` steps (the first includes any ``torch.compile``) and :data:`MEASURED_STEPS` more, it
estimates the planning time of the rest of the run (seconds per step x episode length x trials left) and,
when that exceeds :data:`LONG_RUN_HOURS`, gives one line naming faster settings. Planning is nearly all of
a PETS run's time at the research config (docs/performance.md); model training adds to it, episodes that
terminate early take less.
"""

from __future__ import annotations

from omegaconf import DictConfig

from pets.config import PRESETS
from pets.planning.particles import CANDIDATE_TABLE
from pets.planning.planners import PLANNER_CLASSES
from pets.runs.hardware import resolve_precision

#: Steps before the measurement (the first planning step compiles when ``planner.compile``).
WARMUP_STEPS = 2
#: Planning steps the estimate is measured over.
MEASURED_STEPS = 5
#: A run whose planning alone is estimated above this gets the line.
LONG_RUN_HOURS = 3.0


def faster_options(cfg: DictConfig) -> list[str]:
    """Settings that make planning faster and that ``cfg`` does not use yet."""
    p, fast = cfg.planner, PRESETS["fast"]["planner"]
    feedback = not CANDIDATE_TABLE[p.candidates].searches_actions  # gains: a horizon of their own, no iCEM
    options = []
    if not feedback and p.population * p.particles * p.horizon * p.iterations > (
        fast["population"] * fast["particles"] * fast["horizon"] * fast["iterations"]
    ):
        options.append("--preset fast (about 20x fewer model evaluations per step)")
    faster = PLANNER_CLASSES[p.name].faster  # a faster planner, for action sequences (CEM: iCEM)
    if faster and not feedback:
        options.append(faster)
    if p.precision == "fp32" and resolve_precision("auto", cfg.device) == "bf16":  # where bf16 was measured to pay
        options.append("planner.precision=bf16")
    if not p.compile:
        options.append("planner.compile=true")
    return options


def compile_line(cfg: DictConfig) -> str | None:
    """The one-off cost of the run's compiled paths, for its start (None when it compiles nothing)."""
    parts = []
    if cfg.model.compile:
        parts.append("the first training compiles the training step (6-15 CPU-s; 30-50 s wall, cold inductor cache)")
    if cfg.planner.compile:
        parts.append("the first planning step compiles the rollout step (5-30 s)")
    if not parts:
        return None
    return (
        f"compiling once per run: {'; '.join(parts)}; paid back by faster steps after (docs/performance.md); "
        "model.compile=false planner.compile=false run eagerly"
    )


def format_duration(seconds: float) -> str:
    """``2 h 05 min``, ``3 d 4 h`` or ``12 min``."""
    minutes = int(round(seconds / 60))
    if minutes >= 48 * 60:
        return f"{minutes // 1440} d {minutes % 1440 // 60} h"
    if minutes >= 60:
        return f"{minutes // 60} h {minutes % 60:02d} min"
    return f"{minutes} min"


def long_run_line(
    cfg: DictConfig, seconds_per_step: float, steps_per_trial: int, trials_left: int, steps_left: int | None = None
) -> str | None:
    """The one line for a run whose planning is estimated above :data:`LONG_RUN_HOURS`, else None; ``steps_left``:
    the env steps left of the run's budget (``max_env_steps``), which caps the trials' steps."""
    if steps_left is not None and steps_left < steps_per_trial * trials_left:
        estimate, left = seconds_per_step * steps_left, f"{steps_left} env steps left of the budget"
    else:
        estimate, left = seconds_per_step * steps_per_trial * trials_left, f"{trials_left} trials left"
    if estimate <= LONG_RUN_HOURS * 3600:
        return None
    options = faster_options(cfg)
    return (
        f"estimated time: about {format_duration(estimate)} of planning for the {left} "
        f"({seconds_per_step:.2f} s per planning step x up to {steps_per_trial} steps per trial; model training "
        "not counted)" + (f"; faster: {', '.join(options)}" if options else "")
    )


class CostEstimate:
    """Feeds on the cumulative planning seconds after each step of the first planned trial of a session."""

    def __init__(self, cfg: DictConfig, steps_per_trial: int, trials_left: int, steps_left: int | None = None) -> None:
        self.cfg = cfg
        self.steps_per_trial = steps_per_trial
        self.trials_left = trials_left
        self.steps_left = steps_left
        self.done = False
        self._start = 0.0

    def step(self, steps: int, plan_seconds: float) -> str | None:
        """After step ``steps`` (1-based) with ``plan_seconds`` of planning so far: the line once, when due."""
        if self.done:
            return None
        if steps == WARMUP_STEPS:
            self._start = plan_seconds
        elif steps == WARMUP_STEPS + MEASURED_STEPS:
            self.done = True
            per_step = (plan_seconds - self._start) / MEASURED_STEPS
            return long_run_line(self.cfg, per_step, self.steps_per_trial, self.trials_left, self.steps_left)
        return None
