"""The table of models (``--model``): each name -> how to build its head and its network (docs/models.md).

The classes are imported when a model is built, so reading the table (``--help``, config validation) is cheap.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch
    from omegaconf import DictConfig

    from dynamics.heads import DynamicsHead
    from dynamics.model import DynamicsModel
    from dynamics.networks import MemberEnsemble
    from envs import EnvSpec


@dataclass(frozen=True)
class ModelEntry:
    """One ``--model``: a one-line summary, whether it is deterministic, its two builders, and whether it needs a
    floating root in the env's layout (``ObsLayout.root``)."""

    summary: str
    deterministic: bool
    make_head: Callable[[DictConfig, EnvSpec], DynamicsHead]
    make_network: Callable[[DictConfig, DynamicsHead], MemberEnsemble]
    needs_root: bool = False


def _delta_head(cfg: DictConfig, spec: EnvSpec) -> DynamicsHead:
    from dynamics.heads import DeltaHead

    return DeltaHead(spec.layout, spec.act_dim)


def _gem_head(cfg: DictConfig, spec: EnvSpec) -> DynamicsHead:
    from gem_head.head import GemHead

    g = cfg.gem
    return GemHead(spec.layout, spec.act_dim, compose=g.compose, loss=g.loss, frobenius_weight=g.frobenius_weight)


def _gem_se_head(cfg: DictConfig, spec: EnvSpec) -> DynamicsHead:
    from gem_head.se_root import GemSEHead

    g = cfg.gem
    return GemSEHead(spec.layout, spec.act_dim, compose=g.compose, loss=g.loss, frobenius_weight=g.frobenius_weight)


def _delta_det_head(cfg: DictConfig, spec: EnvSpec) -> DynamicsHead:
    from dynamics.heads import DeterministicDeltaHead

    return DeterministicDeltaHead(spec.layout, spec.act_dim)


def _gem2_head(cfg: DictConfig, spec: EnvSpec) -> DynamicsHead:
    from gem_head.two_stage import TwoStageGemHead

    return TwoStageGemHead(spec.layout, spec.act_dim, compose=cfg.gem.compose)


def _groupfeat_head(cfg: DictConfig, spec: EnvSpec) -> DynamicsHead:
    from gem_head.ablation import GroupFeatureDeltaHead

    return GroupFeatureDeltaHead(spec.layout, spec.act_dim)


def _sizes(cfg: DictConfig) -> dict[str, int]:
    """The ``model.*`` sizes (and the activation) every network takes."""
    m = cfg.model
    return dict(
        ensemble_size=m.ensemble_size,
        hidden_size=m.hidden_size,
        num_layers=m.num_layers,
        num_elites=m.num_elites,
        activation=m.activation,
    )


def gaussian_ensemble(cfg: DictConfig, head: DynamicsHead) -> MemberEnsemble:
    """PETS' probabilistic ensemble (mean and log-variance per target) sized by ``cfg.model``, for ``head``."""
    from dynamics.networks import GaussianEnsemble

    learn = cfg.model.learn_logvar_bounds
    return GaussianEnsemble(head.input_dim, head.target_dim, learn_logvar_bounds=learn, **_sizes(cfg))


def deterministic_ensemble(cfg: DictConfig, head: DynamicsHead) -> MemberEnsemble:
    """An ensemble of deterministic networks (MSE training, no variance) sized by ``cfg.model``, for ``head``."""
    from dynamics.networks import DeterministicEnsemble

    return DeterministicEnsemble(head.input_dim, head.target_dim, **_sizes(cfg))


def _two_stage(cfg: DictConfig, head: DynamicsHead) -> MemberEnsemble:
    from gem_head.two_stage import TwoStageGemEnsemble

    slots = (head.group_slots, head.velocity_slots)
    return TwoStageGemEnsemble(head.input_dim, head.target_dim, *slots, **_sizes(cfg))


MODELS: dict[str, ModelEntry] = {
    "delta": ModelEntry("PETS: Gaussian ensemble predicting next_obs - obs", False, _delta_head, gaussian_ensemble),
    "gem": ModelEntry(
        "Gaussian ensemble predicting Lie-algebra coefficients + deltas", False, _gem_head, gaussian_ensemble
    ),
    "delta-det": ModelEntry("the paper's deterministic baseline (MSE)", True, _delta_det_head, deterministic_ensemble),
    "gem2": ModelEntry("the paper's two-stage GEM (Algorithm 1), deterministic", True, _gem2_head, _two_stage),
    "delta-groupfeat": ModelEntry(
        "ablation: GEM's input features, delta targets", False, _groupfeat_head, gaussian_ensemble
    ),
    "gem-se": ModelEntry(
        "gem with the floating root on SE(2)/SE(3), body-frame twist",
        False,
        _gem_se_head,
        gaussian_ensemble,
        needs_root=True,
    ),
}


def register_model(name: str, entry: ModelEntry) -> ModelEntry:
    """Add a model of your own to :data:`MODELS` under ``name`` (the ``--model`` / ``model=`` value from then on, in
    this process); returns ``entry``. ValueError (one line) for a name that is not a non-empty string without
    spaces, ``=``, ``,``, ``:``, ``/`` or ``\\`` (the command line and run directories carry it), or that another
    entry holds (a built-in model is never replaced behind the config's back), and for an ``entry`` that is not a
    :class:`ModelEntry`."""
    if not isinstance(name, str) or not name or any(c.isspace() or c in "=,:/\\" for c in name):
        raise ValueError(
            f"a model name must be a non-empty string without spaces, '=', ',', ':', '/' or '\\', got {name!r}"
        )
    if not isinstance(entry, ModelEntry):
        raise ValueError(f"model {name!r}: entry must be a pets.models.ModelEntry, got {type(entry).__name__}")
    taken = MODELS.get(name)
    if taken is not None and taken is not entry:
        raise ValueError(f"model name {name!r} is taken ({taken.summary}); give yours another name")
    MODELS[name] = entry
    return entry


#: What an unknown ``head`` (``--model``) may be: a model of one's own, registered by a module not imported here.
UNREGISTERED = (
    " (a model of your own is known where the module that calls register_model is imported: name that module in "
    "the config key imports, e.g. imports=[my_model]; in a run's config.yaml: imports: [my_model]; docs/models.md)"
)


def unknown_model(name: str, option: str = "--model") -> str | None:
    """The one line refusing ``name`` given as ``option`` where it is not a model of the table (with
    :data:`UNREGISTERED`); None for a known one."""
    if name in MODELS:
        return None
    return f"{option} must be one of {', '.join(MODELS)}, got {name!r}{UNREGISTERED}"


def check_model(head: str, env: str, compose: str) -> None:
    """``head`` a model of the table (a model of one's own: see :data:`UNREGISTERED`); a model that composes the
    floating root (``gem-se``) needs an env with one, and the body-frame composition
    (:func:`gem_head.se_root.check_gem_se`, the one place of that rule); a one-line ValueError otherwise (an unknown
    env is reported where it is built)."""
    import envs
    from gem_head.se_root import check_gem_se

    if problem := unknown_model(head, "head"):
        raise ValueError(problem)
    if not MODELS[head].needs_root:
        return
    try:
        layout = envs.get(env).layout
    except ValueError:
        return
    check_gem_se(layout, compose, env)


def models_for(spec: EnvSpec) -> list[str]:
    """The ``--model`` names that apply to the env ``spec`` (``gem-se`` only where its layout has a root)."""
    return [name for name, entry in MODELS.items() if not entry.needs_root or spec.layout.root is not None]


def probe_observation(spec: EnvSpec) -> torch.Tensor:
    """A valid observation of ``spec``'s layout, (obs_dim,): zeros, each rotation the identity (``SO2_cossin``:
    cos 1; ``SO3_quat``: w = 1, quaternions being (w, x, y, z)), so that normalisations and decompositions of it
    are defined."""
    import torch

    obs = torch.zeros(spec.obs_dim)
    for group in spec.layout.groups:
        if group.kind in ("SO2_cossin", "SO3_quat"):
            obs[group.indices[0]] = 1.0
    return obs


def check_head(name: str, head: DynamicsHead, spec: EnvSpec) -> None:
    """ConfigError (one line) where ``head``'s maps raise or return other shapes than its declared ``input_dim`` and
    ``target_dim`` and the env's observation, on a probe batch of 2 (:func:`probe_observation`; a model of one's own:
    caught when it is built, not in training after the seed episodes)."""
    import torch

    from pets.errors import ConfigError

    obs, act = probe_observation(spec).expand(2, spec.obs_dim), torch.zeros(2, spec.act_dim)
    maps = (("inputs", lambda: head.inputs(obs, act), head.input_dim),
            ("targets", lambda: head.targets(obs, obs), head.target_dim),
            ("next_obs", lambda: head.next_obs(obs, torch.zeros(2, head.target_dim)), spec.obs_dim))  # fmt: skip
    for what, call, width in maps:
        try:
            out = call()
        except Exception as err:
            line = (str(err).strip().splitlines() or ["no message"])[0]
            raise ConfigError(
                f"model {name!r}: its head's {what} raised {type(err).__name__} on a probe batch: {line}"
            ) from None
        if not isinstance(out, torch.Tensor) or tuple(out.shape) != (2, width):
            got = tuple(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
            raise ConfigError(
                f"model {name!r}: its head's {what} returned {got} for a probe batch of 2, not (2, {width})"
            )


def make_model(cfg: DictConfig, spec: EnvSpec, device: torch.device) -> DynamicsModel:
    """The model ``cfg.head`` for env ``spec`` on ``device`` (``cfg`` is validated: the name is in :data:`MODELS`)."""
    from dynamics.heads import DynamicsHead
    from dynamics.model import DynamicsModel
    from pets.errors import ConfigError

    entry, name = MODELS[cfg.head], cfg.head
    head = entry.make_head(cfg, spec)
    if not isinstance(head, DynamicsHead):  # a model of one's own: one line, not an AttributeError in the probe
        raise ConfigError(
            f"model {name!r}: make_head returned {type(head).__name__}, not a dynamics.heads.DynamicsHead"
        )
    check_head(name, head, spec)
    try:
        model = DynamicsModel(head, entry.make_network(cfg, head), name=name)  # checks that head and network agree
    except ValueError as err:
        raise ConfigError(f"model {name!r}: {err}") from None
    if model.deterministic != entry.deterministic:  # the table's flag (read without building) is the model's
        raise ConfigError(
            f"model {name!r}: its ModelEntry says deterministic={entry.deterministic}, but its head and network are "
            f"{'not ' * entry.deterministic}deterministic"
        )
    return model.to(device)
