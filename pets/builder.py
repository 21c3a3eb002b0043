"""Build the parts of a PETS run from a resolved config: head, ensemble, trainer, planner, agent."""

from __future__ import annotations

from pathlib import Path

import torch
from omegaconf import DictConfig

from envs import EnvSpec
from pets.agent import MPCAgent
from pets.config import ConfigError
from pets.ensemble import GaussianEnsemble, MemberEnsemble
from pets.heads import DeltaHead, DynamicsHead
from pets.planners import CEMPlanner, ICEMPlanner, MPPIPlanner, Planner
from pets.propagation import TrajectoryEvaluator, retain_freed_memory
from pets.training import ModelTrainer


def resolve_device(name: str) -> torch.device:
    """``auto`` picks CUDA when available; asking for CUDA without one is a clear error."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError("device=cuda was asked for but torch sees no CUDA device; use --device cpu or auto")
    return torch.device(name)


def make_head(cfg: DictConfig, spec: EnvSpec) -> DynamicsHead:
    """The dynamics head of ``cfg.head`` (the ``--model`` value; ``pets.models`` describes each)."""
    if cfg.head == "delta":
        return DeltaHead(spec.layout, spec.act_dim)
    if cfg.head == "gem":
        from gem_head.head import GemHead

        return GemHead(
            spec.layout,
            spec.act_dim,
            compose=cfg.gem.compose,
            loss=cfg.gem.loss,
            frobenius_weight=cfg.gem.frobenius_weight,
        )
    if cfg.head == "delta-det":
        from pets.models import DeterministicDeltaHead

        return DeterministicDeltaHead(spec.layout, spec.act_dim)
    if cfg.head == "gem2":
        from gem_head.two_stage import TwoStageGemHead

        return TwoStageGemHead(spec.layout, spec.act_dim, compose=cfg.gem.compose)
    if cfg.head == "delta-groupfeat":
        from pets.models import GroupFeatureDeltaHead

        return GroupFeatureDeltaHead(spec.layout, spec.act_dim)
    raise ConfigError(f"unknown head {cfg.head!r}; accepted: delta, gem, delta-det, gem2, delta-groupfeat")


def make_ensemble(cfg: DictConfig, head: DynamicsHead, device: torch.device) -> MemberEnsemble:
    """The model of ``cfg.head``: a Gaussian ensemble (delta, gem, delta-groupfeat), deterministic MLPs
    (delta-det) or two-stage GEMs (gem2); ``model.*`` sets the sizes of all of them."""
    m = cfg.model
    if cfg.head == "gem2":
        from gem_head.two_stage import TwoStageGemEnsemble

        return TwoStageGemEnsemble(
            head.input_dim,
            head.target_dim,
            head.group_slots,
            head.velocity_slots,
            ensemble_size=m.ensemble_size,
            hidden_size=m.hidden_size,
            num_layers=m.num_layers,
            num_elites=m.num_elites,
        ).to(device)
    if head.deterministic:
        from pets.models import DeterministicEnsemble

        return DeterministicEnsemble(
            head.input_dim,
            head.target_dim,
            ensemble_size=m.ensemble_size,
            hidden_size=m.hidden_size,
            num_layers=m.num_layers,
            num_elites=m.num_elites,
        ).to(device)
    return GaussianEnsemble(
        head.input_dim,
        head.target_dim,
        ensemble_size=m.ensemble_size,
        hidden_size=m.hidden_size,
        num_layers=m.num_layers,
        learn_logvar_bounds=m.learn_logvar_bounds,
        num_elites=m.num_elites,
    ).to(device)


def make_trainer(cfg: DictConfig, ensemble: MemberEnsemble, head: DynamicsHead) -> ModelTrainer:
    m = cfg.model
    return ModelTrainer(
        ensemble,
        head,
        lr=m.lr,
        batch_size=m.batch_size,
        max_epochs=m.max_epochs,
        patience=m.patience,
        holdout_ratio=m.holdout_ratio,
        max_holdout=m.max_holdout,
        num_elites=m.num_elites,
    )


def make_agent(
    cfg: DictConfig,
    spec: EnvSpec,
    ensemble: GaussianEnsemble,
    head: DynamicsHead,
    device: torch.device,
    generator: torch.Generator,
) -> MPCAgent:
    p = cfg.planner
    if device.type == "cpu":
        retain_freed_memory()
    evaluator = TrajectoryEvaluator(
        ensemble,
        head,
        spec.reward,
        spec.terminated,
        particles=p.particles,
        propagation=p.propagation,
        precision=p.precision,
        compile=p.compile,
    )
    planner = make_planner(cfg, spec, device)
    return MPCAgent(
        planner,
        evaluator,
        replan_every=p.replan_every,
        action_low=spec.action_low,
        action_high=spec.action_high,
        device=device,
        generator=generator,
    )


def make_planner(cfg: DictConfig, spec: EnvSpec, device: torch.device) -> Planner:
    """The planner named by ``planner.name`` (cem, icem, mppi) with the config's settings."""
    p = cfg.planner
    common = dict(horizon=p.horizon, population=p.population, iterations=p.iterations, alpha=p.alpha, device=device)
    elites = p.elites if p.elites < 1 else int(p.elites)
    if p.name == "cem":
        return CEMPlanner(spec.action_low, spec.action_high, elites=elites, **common)
    if p.name == "icem":
        return ICEMPlanner(
            spec.action_low,
            spec.action_high,
            elites=elites,
            noise_beta=p.noise_beta,
            population_decay=p.icem_population_decay,
            keep_elites=p.icem_keep_elites,
            **common,
        )
    if p.name == "mppi":
        return MPPIPlanner(
            spec.action_low,
            spec.action_high,
            sigma=p.mppi_sigma,
            temperature=p.mppi_temperature,
            smoothing=p.mppi_smoothing,
            **common,
        )
    raise ConfigError(f"unknown planner {p.name!r}; accepted: cem, icem, mppi")


def load_model(run_dir: str | Path, device: str | torch.device = "cpu"):
    """The trained model of a run directory (online or offline): ``(cfg, spec, head, ensemble)``."""
    from pets import rundir
    from pets.config import load_config

    run_dir = Path(run_dir)
    if not (run_dir / rundir.CONFIG_FILE).exists():
        raise ConfigError(f"{run_dir} is not a run directory (no {rundir.CONFIG_FILE})")
    cfg = load_config(str(run_dir / rundir.CONFIG_FILE))
    state = rundir.load_checkpoint(run_dir)
    if state is None:
        raise ConfigError(f"{run_dir} has no {rundir.CHECKPOINT_FILE} yet (no trial completed)")
    import envs

    spec = envs.get(cfg.env)
    device = torch.device(device)
    head = make_head(cfg, spec)
    ensemble = make_ensemble(cfg, head, device)
    ensemble.load_state_dict(state["ensemble"])
    ensemble.eval()
    return cfg, spec, head, ensemble
