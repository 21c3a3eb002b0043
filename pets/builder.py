"""Build the parts of a PETS run from a resolved config: model, trainer, planner, agent."""

from __future__ import annotations

import re
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from torch import Tensor

from dynamics.model import DynamicsModel
from envs import EnvSpec
from pets.agent import MPCAgent
from pets.config import ConfigError
from pets.learning.trainer import ModelTrainer
from pets.models import make_model
from pets.planning.feedback import LinearFeedback
from pets.planning.particles import CANDIDATE_TABLE, OpenLoop
from pets.planning.planners import PLANNER_CLASSES, Planner
from pets.planning.propagation import TrajectoryEvaluator, retain_freed_memory
from pets.planning.value import ValueFunction
from pets.runs.hardware import emulated_bf16_warning


def resolve_device(name: str) -> torch.device:
    """``auto`` picks CUDA when available; asking for CUDA without one, or for another device, is a clear error."""
    from pets.config import DEVICES

    if not isinstance(name, str) or not (name in DEVICES or re.fullmatch(r"cuda:\d+", name)):
        raise ConfigError(f"device must be one of {', '.join(DEVICES)} (or cuda:N), got {name!r}")
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError("device=cuda was asked for but torch sees no CUDA device; use --device cpu or auto")
    return torch.device(name)


def check_memory(
    cfg: DictConfig, spec: EnvSpec, steps: int | None = None, beside: tuple[int, float] = (0, 0.0)
) -> None:
    """ConfigError (one line) where the config's estimated memory exceeds what this machine can still allocate
    (:func:`pets.limits.memory_problem`; ``beside``: other runs at the same time), before anything is allocated."""
    from pets.limits import memory_problem

    device = str(resolve_device(cfg.device))
    problem = memory_problem(cfg, spec.obs_dim, spec.act_dim, spec.episode_length, device, steps, beside)
    if problem:
        raise ConfigError(problem)


def warn_if_emulated(key: str, precision: str, device: str | torch.device) -> None:
    """RuntimeWarning where ``precision`` is bf16 on a CPU without native bf16 (emulated there, ~35x slower)."""
    message = emulated_bf16_warning(key, precision, str(device))
    if message:
        warnings.warn(message, RuntimeWarning, 3)


def make_trainer(cfg: DictConfig, model: DynamicsModel) -> ModelTrainer:
    m = cfg.model
    warn_if_emulated("model.precision", m.precision, next(model.parameters()).device)
    return ModelTrainer(
        model,
        lr=m.lr,
        batch_size=m.batch_size,
        max_epochs=m.max_epochs,
        patience=m.patience,
        holdout_ratio=m.holdout_ratio,
        max_holdout=m.max_holdout,
        num_elites=m.num_elites,
        iterations=m.iterations,
        bootstrap=m.bootstrap,
        precision=m.precision,
        compile=m.compile,
        curve_every=m.curve_every,
    )


def make_agent(
    cfg: DictConfig,
    spec: EnvSpec,
    model: DynamicsModel,
    device: torch.device,
    generator: torch.Generator,
    value: Callable[[Tensor], Tensor] | None = None,
) -> MPCAgent:
    """The MPC agent of the config; ``value``: the terminal value of ``value.enabled`` (``pets.planning.value``)."""
    p = cfg.planner
    warn_if_emulated("planner.precision", p.precision, device)
    if device.type == "cpu":
        retain_freed_memory()
    candidates = make_candidates(cfg, spec, device)
    feedback = candidates.law
    evaluator = TrajectoryEvaluator(
        model,
        spec.reward,
        spec.terminated,
        particles=p.particles,
        propagation=p.propagation,
        precision=p.precision,
        compile=p.compile,
        terminal_value=value,
        termination_penalty=p.termination_penalty,
        risk_aversion=p.risk_aversion,
        candidates=candidates,
    )
    planner = make_planner(cfg, spec, device, feedback)
    return MPCAgent(
        planner,
        evaluator,
        replan_every=p.replan_every,
        action_low=spec.action_low,
        action_high=spec.action_high,
        device=device,
        generator=generator,
        feedback=feedback,
    )


def make_feedback(cfg: DictConfig, spec: EnvSpec, device: torch.device) -> LinearFeedback | None:
    """The law of the config's candidate kind (``planner.candidates=feedback``: pets.planning.feedback), else None."""
    return make_candidates(cfg, spec, device).law


def make_candidates(cfg: DictConfig, spec: EnvSpec, device: torch.device) -> OpenLoop:
    """The strategy of the config's candidate kind (``planner.candidates``, ``pets.planning.particles``; one of
    ``register_candidates`` too: its ``build``) with its law (None for action sequences), for the evaluator."""
    kind = cfg.planner.candidates
    try:
        return CANDIDATE_TABLE[kind].build(cfg.planner, spec, device)
    except ValueError as err:
        raise ConfigError(f"planner.{kind}: {err} ({spec.name} has {spec.obs_dim} observations)") from None


def make_planner(
    cfg: DictConfig, spec: EnvSpec, device: torch.device, feedback: LinearFeedback | None = None
) -> Planner:
    """The planner named by ``planner.name`` (``pets.planning.planners.PLANNER_CLASSES``) with the config's settings.
    With feedback candidates it searches the gains (pets.planning.feedback): a (rows, act_dim) box of +-``gain_bound``
    sampled with std ``gain_std`` at every plan (the planner's ``gain_options``). ``feedback``: the law already built
    for the config (else built here)."""
    p = cfg.planner
    planner_class = PLANNER_CLASSES[p.name]  # the name is validated by the config
    kwargs = dict(horizon=p.horizon, population=p.population, iterations=p.iterations, alpha=p.alpha, device=device)
    if planner_class.uses_elites:
        kwargs["elites"] = p.elites if p.elites < 1 else int(p.elites)
    if planner_class.section is not None:  # the planner's own section, planner.<name>.*: its constructor's arguments
        kwargs.update(OmegaConf.to_container(p[p.name]))
    low, high = spec.action_low, spec.action_high
    if feedback is None:
        feedback = make_feedback(cfg, spec, device)
    if feedback is not None:
        f = p.feedback
        kwargs["horizon"] = feedback.shape[0]
        low, high = np.full(spec.act_dim, -f.gain_bound), np.full(spec.act_dim, f.gain_bound)
        kwargs.update(planner_class.gain_options(f.gain_bound, f.gain_std))  # validated: it searches gains
    return planner_class(low, high, **kwargs)


def load_model(run_dir: str | Path, device: str | torch.device = "cpu") -> tuple[DictConfig, EnvSpec, DynamicsModel]:
    """The trained model of a run directory (online or offline): ``(cfg, spec, model)``, in eval mode."""
    from pets.config import load_run_config
    from pets.runs import rundir

    run_dir = Path(run_dir)
    cfg = load_run_config(run_dir)
    state = rundir.load_checkpoint(run_dir)
    if state is None:
        raise ConfigError(f"{run_dir} has no {rundir.CHECKPOINT_FILE} yet (no trial completed)")
    import envs

    spec = envs.get(cfg.env)
    model = make_model(cfg, spec, device if isinstance(device, torch.device) else resolve_device(device))
    rundir.load_model_state(model, state)
    model.eval()
    return cfg, spec, model


def load_value(
    run_dir: str | Path, cfg: DictConfig, spec: EnvSpec, device: str | torch.device = "cpu"
) -> ValueFunction | None:
    """The terminal value a run planned with (``value.enabled``; ``pets.planning.value``), or None when it had none."""
    from pets.runs import rundir

    if not cfg.value.enabled:
        return None
    state = rundir.load_checkpoint(Path(run_dir))
    if state is None or "value" not in state:
        raise ConfigError(f"{run_dir}: value.enabled is set but the checkpoint holds no value")
    value = make_value(cfg, spec, torch.device(device))
    value.load_state_dict(state["value"])
    return value


def make_value(cfg: DictConfig, spec: EnvSpec, device: torch.device) -> ValueFunction:
    """An unfitted terminal value of the config's ``value.*`` settings."""
    return ValueFunction(spec.obs_dim, hidden_size=cfg.value.hidden_size, discount=cfg.value.discount).to(device)
